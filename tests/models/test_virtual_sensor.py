"""Virtual sensors: a detached or broken thermocouple is flagged with its start and replaced."""

import numpy as np
import pandas as pd
import pytest

from driftlab.errors import ValidationError
from driftlab.models.virtual_sensor import VirtualSensor, check_sensors, fit_virtual_sensors


def _record(hours=30.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, hours * 3600, 60.0)
    room = 20 + 1.5 * np.sin(2 * np.pi * t / 86400)
    heat = 6 * (1 - np.exp(-t / 9000)) * (t < 15 * 3600) + 6 * (1 - np.exp(-15 * 3600 / 9000)) * np.exp(
        -(t - 15 * 3600) / 9000
    ) * (t >= 15 * 3600)
    heat2 = 3 * (np.sin(2 * np.pi * t / 40000) + 1)
    df = pd.DataFrame({"time_s": t, "T49": room, "T50": room - 0.5})
    df["T32"] = room + 0.6 * heat + 0.2 * heat2
    df["T34"] = room + 1.0 * heat + 0.1 * heat2
    df["T24"] = room + 0.3 * heat + 0.8 * heat2
    df["T26"] = room + 0.25 * heat + 0.9 * heat2
    for c in df.columns[1:]:
        df[c] = df[c] + 0.02 * rng.standard_normal(t.size)
    return df


def test_healthy_record_has_no_fault_and_estimates_track():
    df = _record()
    sensors = fit_virtual_sensors(df.iloc[: len(df) // 2], ["T24", "T26", "T32", "T34", "T49", "T50"])
    chk = check_sensors(sensors, df)
    assert chk.faults == []
    assert not chk.replaced.to_numpy().any()
    s = sensors["T34"]
    assert np.sqrt(np.mean((s.estimate(df) - df["T34"]) ** 2)) < 0.1
    assert VirtualSensor.from_dict(s.to_dict()).estimate(df.iloc[[0]].to_dict("records")[0]) == pytest.approx(
        s.estimate(df.iloc[[0]])
    )


def test_detached_thermocouple_is_flagged_since_its_start_and_replaced():
    df = _record()
    train = df[df.time_s < 12 * 3600]
    sensors = fit_virtual_sensors(train, ["T24", "T26", "T32", "T34", "T49", "T50"])
    t0 = 18 * 3600.0
    bad = df.copy()
    after = bad.time_s >= t0
    truth = bad.loc[after, "T34"].to_numpy()
    # the junction dangles in the air: it relaxes to room temperature within minutes
    air = bad.loc[after, "T49"].to_numpy()
    bad.loc[after, "T34"] = air + (truth - air) * np.exp(-(bad.time_s[after].to_numpy() - t0) / 300)
    chk = check_sensors(sensors, bad)
    assert [f.channel for f in chk.faults] == ["T34"]
    f = chk.faults[0]
    assert t0 <= f.since_s <= t0 + 1800
    assert "T34" in f.message() and "since" in f.message()
    late = bad.time_s > t0 + 1800
    err_fixed = np.abs(chk.corrected.loc[late, "T34"].to_numpy() - df.loc[late, "T34"].to_numpy())
    err_raw = np.abs(bad.loc[late, "T34"].to_numpy() - df.loc[late, "T34"].to_numpy())
    assert err_fixed.max() < 0.5 < err_raw.mean()
    assert chk.replaced.loc[late, "T34"].all() and not chk.replaced["T32"].any()


def test_broken_lead_error_signal_is_open_fault():
    df = _record()
    sensors = fit_virtual_sensors(df.iloc[:900], ["T24", "T26", "T32", "T34", "T49", "T50"])
    bad = df.copy()
    bad.loc[1200:, "T24"] = np.nan
    chk = check_sensors(sensors, bad)
    assert [(f.channel, f.mode) for f in chk.faults] == [("T24", "open")]
    assert chk.faults[0].since_s == df.time_s.iloc[1200]
    assert np.isfinite(chk.corrected["T24"]).all()


def test_virtual_machine_detached_thermocouple_is_replaced():
    from driftlab.daq.sim.campaign import simulate_campaign
    from driftlab.daq.sim.machine import VirtualMachine
    from driftlab.daq.sim.scenario import HiddenEffect, Scenario
    from driftlab.daq.sim.sites import CHANNELS

    t0 = 9 * 3600.0
    sc = Scenario(
        name="fault",
        hours=14,
        seed=5,
        hidden=[HiddenEffect(kind="sensor_fault", channels=["T34"], params={"start_s": t0, "mode": "detached"})],
    )
    sim = simulate_campaign(sc)
    temps = sim.temperatures
    chans = ["T24", "T26", "T30", "T32", "T34", "T35", "T37", "T49", "T50"]
    clean = simulate_campaign(Scenario(name="clean", hours=14, seed=6)).temperatures  # the training campaign
    sensors = fit_virtual_sensors(clean, chans)
    chk = check_sensors(sensors, temps)
    assert [f.channel for f in chk.faults] == ["T34"]
    since = chk.faults[0].since_s
    assert t0 <= since <= t0 + 2 * 3600
    true = VirtualMachine(sc).true_temperatures_array(temps.time_s.to_numpy())[:, CHANNELS.index("T34")]
    # flagged as soon as the loose junction reads measurably wrong: before that it was within the band
    quiet = ((temps.time_s >= t0) & (temps.time_s < since - 600)).to_numpy()
    assert np.all(np.abs(temps["T34"].to_numpy()[quiet] - true[quiet]) < sensors["T34"].band)
    late = (temps.time_s > t0 + 3600).to_numpy()
    fixed = np.abs(chk.corrected["T34"].to_numpy()[late] - true[late])
    raw = np.abs(temps["T34"].to_numpy()[late] - true[late])
    assert fixed.mean() < 0.25 * raw.mean() and fixed.mean() < 0.5


def test_sensors_round_trip_through_a_model_document():
    from driftlab.models.virtual_sensor import check_live, sensors_from_document

    df = _record()
    sensors = fit_virtual_sensors(df, ["T24", "T26", "T32", "T34", "T49", "T50"])
    doc = {"virtual_sensors": [s.to_dict() for s in sensors.values()]}
    assert set(sensors_from_document(doc)) == set(sensors)
    bad = df.copy()
    bad.loc[1000:, "T26"] = 150.5  # the card's rail value for a broken lead
    chk = check_live(doc, bad)
    assert [(f.channel, f.mode) for f in chk.faults] == [("T26", "open")]
    with pytest.raises(ValidationError, match="no virtual sensors"):
        check_live({"virtual_sensors": []}, df)
