"""Neural comparison: eq. 6.3 scaling; interpolates well; extrapolates worse than physical regression."""

from datetime import UTC, datetime, timedelta
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from driftlab.errors import ValidationError
from driftlab.models.neural import (
    compare_models,
    comparison_data,
    extrapolation_errors,
    fit_linear,
    fit_network,
    neural_comparisons,
    scale_inputs,
)


def test_scaling_maps_training_range_to_plus_minus_0_9():
    X = np.array([[1.0, 10.0], [3.0, 30.0], [2.0, 20.0]])
    Z = scale_inputs(X, X.min(0), X.max(0))
    np.testing.assert_allclose(Z, [[-0.9, -0.9], [0.9, 0.9], [0.0, 0.0]])


def _frame(room, rng):
    n = room.size
    heat = rng.uniform(0, 6, n)
    return pd.DataFrame({"room": room, "heat": heat, "T34": room + heat})


def test_network_interpolates_but_drifts_when_the_room_leaves_its_range():
    rng = np.random.default_rng(0)
    train = _frame(rng.uniform(19.0, 22.0, 3000), rng)
    y = 0.0121 * (train["T34"] - 20) + 0.004 * (train["room"] - 20)
    net = fit_network(train, y.to_numpy(), hidden=(12, 6), max_iter=300)
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones(len(train)), train.to_numpy()]), y, rcond=None)
    test_in = _frame(rng.uniform(19.0, 22.0, 500), rng)
    test_out = _frame(rng.uniform(23.5, 24.5, 500), rng)  # two degrees beyond the training range

    def reg(df):
        return coef[0] + df.to_numpy() @ coef[1:]

    def truth(df):
        return (0.0121 * (df["T34"] - 20) + 0.004 * (df["room"] - 20)).to_numpy()

    assert net.outside_training_range(test_out).all() and net.outside_training_range(test_in).mean() < 0.02
    res = extrapolation_errors(
        truth(test_in), reg(test_in), net.predict(test_in), truth(test_out), reg(test_out), net.predict(test_out), 2.0
    )
    assert res.network_in_range_mm < 0.001
    assert res.network_mm > 3 * max(res.regression_mm, res.network_in_range_mm)
    assert res.to_dict()["n"] == 500


def test_network_needs_data():
    with pytest.raises(ValidationError):
        fit_network(pd.DataFrame({"a": [1.0, 2.0]}), np.array([1.0, 2.0]))


# ----------------------------------------------------------------------------- the fair comparison (ch. 6.6)

T0 = datetime(2026, 3, 2, 8, tzinfo=UTC)
COEF = {"T1": 0.012, "T2": -0.004}  # mm/degC: the truth is linear in the two channels


def _campaign(name, start_h, room, heat, *, datum=None, hours=24.0, seed=0, zeroed_at_start=False):
    """A bundle-like campaign: T1 follows the room and a heat source, T2 the room; Z/dz linear in both."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, hours * 3600 + 1, 300.0)
    h = t / 3600
    T2 = room + 0.5 * np.sin(2 * np.pi * h / 24)
    T1 = T2 + heat * (1 - np.exp(-h / 3)) + 0.2 * np.sin(2 * np.pi * h / 7)
    temps = pd.DataFrame({"time_s": t, "T1": T1, "T2": T2})
    pos = np.tile([-200.0, -100.0, 0.0], t.size)
    tt = np.repeat(t, 3)
    ref = (T1[0], T2[0]) if zeroed_at_start else (20.0, 20.0)
    value = (
        COEF["T1"] * (np.repeat(T1, 3) - ref[0])
        + COEF["T2"] * (np.repeat(T2, 3) - ref[1])
        + 1e-5 * pos
        + 0.0005 * rng.standard_normal(tt.size)
    )
    errors = pd.DataFrame({"time_s": tt, "axis": "Z", "term": "dz", "position": pos, "direction": 1, "value": value})
    meta = SimpleNamespace(started_at=T0 + timedelta(hours=start_h), setups=None)
    if datum is not None:
        errors["setup"] = "z-pos"
        meta.setups = {"z-pos": SimpleNamespace(datum=datum)}
    return SimpleNamespace(name=name, meta=meta, temperatures=temps, errors=errors)


def test_both_models_are_given_the_very_same_matrix_in_both_directions():
    seen = {"regression": [], "network": []}

    def rec_linear(X, y):
        seen["regression"].append((X.copy(), np.array(y)))
        return fit_linear(X, y)

    def rec_net(X, y):
        seen["network"].append((X.copy(), np.array(y)))
        return fit_network(X, y, hidden=(8, 4), max_iter=100)

    data = comparison_data(
        [_campaign("a", 0, 20.0, 4.0, datum="absolute"), _campaign("b", 48, 23.0, 6.0, datum="absolute", seed=1)],
        "Z/dz",
        ["T1", "T2"],
    )
    res = compare_models(data, fit_regression=rec_linear, fit_net=rec_net)
    assert [d.direction for d in res.directions] == ["earlier -> later", "later -> earlier"]
    assert res.split == "campaign" and [(d.train, d.test) for d in res.directions] == [("a", "b"), ("b", "a")]
    assert len(seen["regression"]) == len(seen["network"]) == 2
    for (Xr, yr), (Xn, yn), d in zip(seen["regression"], seen["network"], res.directions):
        pd.testing.assert_frame_equal(Xr, Xn)
        np.testing.assert_array_equal(yr, yn)
        assert list(Xr.columns) == d.inputs == ["position", "position^2", "position^3", "dT[T1]", "dT[T2]"]
    # one temperature reference for both campaigns (eq. 3.1): the warm campaign's inputs are not zeroed
    assert data.reference == pytest.approx({"T1": 20.0, "T2": 20.0})
    assert data.X.loc[data.campaign == 1, "dT[T2]"].min() > 2.0
    assert res.directions[0].max_excess_degC > 1.0 and res.directions[0].beyond_range > 0.5


def test_both_directions_are_scored_and_the_network_fails_beyond_its_range_either_way():
    res = compare_models(
        comparison_data(
            [
                _campaign("cold", 0, 20.0, 3.0, datum="absolute"),
                _campaign("warm", 48, 23.5, 3.0, datum="absolute", seed=1),
            ],
            "Z/dz",
            ["T1", "T2"],
        ),
        hidden=(12, 6),
        max_iter=300,
    )
    assert res.status == "compared" and len(res.directions) == 2
    for d in res.directions:  # train on one room, test on the other: up then down
        assert d.regression_test < 0.002, d  # the linear truth extrapolates (noise 0.5 um)
        assert d.network_train < 0.002, d  # the network fits its own range
        assert d.network_test > 3 * d.regression_test, d
    out = res.to_dict()
    assert [d["direction"] for d in out["directions"]] == ["earlier -> later", "later -> earlier"]


def test_a_zeroed_campaign_is_refused_as_absolute_target():
    laser = [
        _campaign("a", 0, 20.0, 4.0, datum="session"),
        _campaign("b", 48, 23.0, 6.0, datum="session", seed=1, zeroed_at_start=True),
    ]
    data = comparison_data(laser, "Z/dz", ["T1", "T2"])
    with pytest.raises(ValidationError, match="zeroed campaign is not an absolute target"):
        compare_models(data, split="campaign")
    # the project's v1 convention: a campaign counts from its start, so it is zeroed too
    v1 = [_campaign("a", 0, 20.0, 4.0), _campaign("b", 48, 23.0, 6.0, seed=1, zeroed_at_start=True)]
    with pytest.raises(ValidationError, match="v1: zeroed at its start"):
        compare_models(comparison_data(v1, "Z/dz", ["T1", "T2"]), split="campaign")
    [refused] = neural_comparisons(laser, ["Z/dz"], ["T1", "T2"], split="campaign", hidden=(4,), max_iter=20)
    assert refused.status == "refused" and "zeroed" in refused.note and not refused.directions
    # by time each datum keeps its offset: one column for it, given to both models alike
    res = compare_models(comparison_data(v1, "Z/dz", ["T1", "T2"]), split="auto", hidden=(8, 4), max_iter=100)
    assert res.split == "time" and res.offsets == ["b"] and res.excluded == {}
    assert all("datum[b]" in d.inputs for d in res.directions)
    assert all(d.regression_test < 0.002 for d in res.directions)
    # an absolute campaign pair beside a zeroed one: the zeroed readings are excluded and listed
    mixed = [
        _campaign("a", 0, 20.0, 4.0, datum="absolute"),
        _campaign("z", 24, 21.0, 4.0, datum="session", seed=2),
        _campaign("b", 48, 23.0, 6.0, datum="absolute", seed=1),
    ]
    res = compare_models(comparison_data(mixed, "Z/dz", ["T1", "T2"]), hidden=(8, 4), max_iter=100)
    assert res.split == "campaign" and list(res.excluded) == ["z/z-pos#0"]
    assert all(d.n_test == 289 * 3 for d in res.directions)  # a whole absolute campaign, never the zeroed one


def test_the_target_is_a_parameter_never_chosen_from_results():
    camps = [_campaign("a", 0, 20.0, 4.0, datum="absolute")]
    for c in camps:  # a second term that both models could fit better does not move the target
        extra = c.errors.copy()
        extra["term"], extra["value"] = "dx", 0.0
        c.errors = pd.concat([c.errors, extra], ignore_index=True)
    [res] = neural_comparisons(camps, ["Z/dz"], ["T1", "T2"], hidden=(4,), max_iter=30)
    assert res.target == "Z/dz" and res.split == "time"
    assert [r.target for r in neural_comparisons(camps, ["all"], ["T1", "T2"], hidden=(4,), max_iter=30)] == [
        "Z/dx",
        "Z/dz",
    ]
    [bad] = neural_comparisons(camps, ["Q/dz"], ["T1"], hidden=(4,), max_iter=30)
    assert bad.status == "refused" and "AXIS/term" in bad.note
