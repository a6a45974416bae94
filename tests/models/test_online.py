"""RLS with forgetting factor (eqs. 6.10-6.13): equals batch LS at lambda=1, stays stable, tracks drift."""

import json
from datetime import UTC

import numpy as np
import pytest

from driftlab.errors import ValidationError
from driftlab.models.online import RLSState, online_regressors, rls_init, rls_run, rls_update


def test_rls_without_forgetting_equals_batch_least_squares():
    rng = np.random.default_rng(0)
    Phi = np.column_stack([np.ones(400), rng.standard_normal((400, 2))])
    y = Phi @ [0.01, -0.002, 0.005] + 1e-4 * rng.standard_normal(400)
    run = rls_run(rls_init(3, lam=1.0, p0=1e8), Phi, y)
    batch, *_ = np.linalg.lstsq(Phi, y, rcond=None)
    np.testing.assert_allclose(run.state.theta, batch, rtol=1e-5, atol=1e-9)


def test_rls_stays_symmetric_and_bounded_over_long_runs():
    rng = np.random.default_rng(1)
    n = 6000
    Phi = np.column_stack([np.ones(n), 0.5 + 0.01 * rng.standard_normal(n)])  # poorly excited: P grows
    y = Phi @ [0.003, 0.002] + 1e-4 * rng.standard_normal(n)
    run = rls_run(rls_init(2, lam=0.98), Phi, y)
    P = run.state.P
    assert np.array_equal(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    assert np.all(np.isfinite(run.theta_history))
    assert run.rmse_prior < 5e-4


def test_rls_tracks_a_slow_drift_that_a_frozen_fit_misses():
    days = np.linspace(0, 30, 600)
    drift = 0.0004 * days  # mm/day: wear
    rng = np.random.default_rng(2)
    y = drift + 0.0003 * rng.standard_normal(days.size)
    run = rls_run(rls_init(1, lam=0.95), online_regressors(days.size), y)
    late = days > 20
    assert np.sqrt(np.mean((y[late] - run.prior_prediction[late]) ** 2)) < 0.0006
    frozen = np.mean(y[days < 3])
    assert np.sqrt(np.mean((y[late] - frozen) ** 2)) > 0.007


def test_state_round_trip_and_errors():
    st, err = rls_update(rls_init(2), np.array([1.0, 2.0]), 3.0)
    assert err == 3.0 and st.n_updates == 1
    back = RLSState.from_dict(st.to_dict())
    np.testing.assert_array_equal(back.P, st.P)
    with pytest.raises(ValidationError):
        rls_init(2, lam=1.5)
    with pytest.raises(ValidationError):
        rls_run(rls_init(2), np.ones((3, 3)), np.ones(3))
    with pytest.raises(ValidationError):
        online_regressors(3, {"A": np.ones(3)}, ["B"])


def _probe_from_campaign(sim, positions=(0.0, 254.0)):
    """Probe measurements at the X extremes from a simulated campaign (dx, dy, dz with the readings)."""
    import pandas as pd

    e = sim.errors[(sim.errors.axis == "X") & (sim.errors.position.isin(positions)) & (sim.errors.direction == 1)]
    wide = e.pivot_table(index=["time_s", "position"], columns="term", values="value").reset_index()
    t = wide["time_s"].to_numpy()
    temps = sim.temperatures
    cols = {c: np.interp(t, temps.time_s, temps[c]) for c in temps.columns if c != "time_s"}
    return pd.DataFrame(
        {
            "time_s": t,
            "x": wide["position"],
            "y": 0.0,
            "z": 0.0,
            "a": 0.0,
            "b": 0.0,
            "dx": wide["dx"],
            "dy": wide["dy"],
            "dz": wide["dz"],
            **cols,
        }
    )


def test_virtual_machine_rls_tracks_a_drift_the_offline_model_misses(tmp_path, capsys):
    from driftlab.campaigns.bundle import Bundle, CampaignMeta
    from driftlab.campaigns.store import connect
    from driftlab.cli import main
    from driftlab.daq.sim.campaign import simulate_campaign
    from driftlab.daq.sim.scenario import HiddenEffect, Scenario
    from driftlab.jobs.tasks import fit_campaigns
    from driftlab.models.fitting import FitOptions
    from driftlab.models.online import online_update_document

    clean = simulate_campaign(Scenario(name="clean", hours=12, seed=7))
    rate = 0.01  # mm/day of wear on X (ch. 6.4.3)
    worn = simulate_campaign(
        Scenario(
            name="worn",
            hours=36,
            seed=8,
            hidden=[HiddenEffect(kind="drift", axis="X", term="dx", params={"rate_per_day": rate})],
        )
    )
    url = f"sqlite:///{tmp_path / 'online.sqlite'}"
    store = connect(url)
    cid = store.campaigns.import_bundle(
        Bundle("clean", CampaignMeta.model_validate(clean.meta), clean.temperatures, clean.conditions, clean.errors)
    )
    _, doc = fit_campaigns(store, [cid], FitOptions(network=False, virtual_sensors=False))
    probe = _probe_from_campaign(worn)
    report, pred = online_update_document(doc, probe, lam=0.98)
    from driftlab.models.online import online_residuals

    t, resid = online_residuals(doc, probe)
    late = t > 24 * 3600
    offline = np.sqrt(np.mean(resid[late, 0] ** 2))
    online = np.sqrt(np.mean((resid[late, 0] - pred["dx"][late]) ** 2))
    assert offline > 0.006  # the off-line model cannot know the wear
    assert online < 0.2 * offline
    assert report.terms["dx"]["correction_mm"] == pytest.approx(rate * 36 / 24, abs=0.003)
    # through the store and the command line: the state is kept and continued
    path = tmp_path / "probe.csv"
    probe.iloc[: len(probe) // 2].to_csv(path, index=False)
    assert main(["online", "--machine", doc.machine, "--probe", str(path), "--db", url, "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    probe.iloc[len(probe) // 2 :].to_csv(path, index=False)
    assert main(["online", "--machine", doc.machine, "--probe", str(path), "--db", url, "--json"]) == 0
    second = json.loads(capsys.readouterr().out)
    assert second["states"]["dx"]["n_updates"] == first["states"]["dx"]["n_updates"] + second["n"]
    assert second["terms"]["dx"]["correction_mm"] > first["terms"]["dx"]["correction_mm"]
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,x\n0,1\n")
    assert main(["online", "--machine", doc.machine, "--probe", str(bad), "--db", url]) == 2
    store.close()


def test_concurrent_updates_queue_for_the_machine_lock(store_url):
    """Four threads update one machine's on-line state at once: they hold the state one after the other
    (never two inside the hold), each computed once, and all four updates and probe rows are kept."""
    import tempfile
    import threading
    from contextlib import contextmanager
    from datetime import datetime, timedelta

    import pandas as pd

    from driftlab.campaigns.bundle import load_bundle, write_bundle
    from driftlab.campaigns.online_repo import OnlineStateRepository
    from driftlab.campaigns.store import connect
    from driftlab.jobs import registry as model_registry
    from driftlab.jobs.online import latest_online_states, store_update
    from tests.api.helpers import MACHINE, model_document, small_frames, small_meta

    with tempfile.TemporaryDirectory() as tmp, connect(store_url) as store:
        temps, cond, errors = small_frames()
        store.campaigns.import_bundle(load_bundle(write_bundle(f"{tmp}/b", small_meta(), temps, cond, errors)))
        doc = model_registry.register_model(store, model_document())
    t0 = datetime(2026, 3, 3, 8, tzinfo=UTC)
    n = 4
    errors_seen: list[BaseException] = []
    barrier = threading.Barrier(n)
    count = threading.Lock()
    inside = [0, 0]  # holders now, most holders at once
    second_holder = threading.Event()
    hold = OnlineStateRepository.hold

    @contextmanager
    def watched_hold(self, machine_id):
        with hold(self, machine_id) as held:
            with count:
                inside[0] += 1
                inside[1] = max(inside[1], inside[0])
                if inside[0] > 1:
                    second_holder.set()
            second_holder.wait(1.0)  # a broken lock lets another thread in meanwhile
            try:
                yield held
            finally:
                with count:
                    inside[0] -= 1

    def worker(k: int) -> None:
        try:
            with connect(store_url) as s:
                row = {"time_s": 0.0, "x": 0.0, "y": 0.0, "z": 0.0, "a": 0.0, "b": 0.0, "dy": 0.0, "dz": 0.0}
                probe = pd.DataFrame([{**row, "dx": 0.001 * (k + 1), "T1": 21.0, "T2": 22.0}])
                barrier.wait(timeout=60)
                store_update(s, MACHINE, probe, [t0 + timedelta(minutes=k)])
        except BaseException as exc:  # reported below
            errors_seen.append(exc)

    OnlineStateRepository.hold = watched_hold  # type: ignore[method-assign]
    try:
        threads = [threading.Thread(target=worker, args=(k,)) for k in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        OnlineStateRepository.hold = hold  # type: ignore[method-assign]
    assert not errors_seen, errors_seen
    assert inside[1] == 1 and not second_holder.is_set()
    with connect(store_url) as store:
        states = latest_online_states(store, MACHINE, doc.version)
        assert states["dx"].n_updates == n and states["dz"].n_updates == n
        row = store.online.get(MACHINE)
        assert row.version == n and row.n_updates == n
        assert store.table_counts()["probe_measurements"] == n
        # a stale writer is refused and writes nothing
        from driftlab.campaigns.store import OnlineUpdate, StaleOnlineState

        with pytest.raises(StaleOnlineState):
            store.online.save(
                MACHINE,
                1,
                OnlineUpdate(
                    model_version_id=None, model_version=doc.version, lam=0.98, n_updates=9, theta=row.theta, p=row.p
                ),
                [
                    {
                        "measured_at": t0 + timedelta(hours=5),
                        "x": 0,
                        "y": 0,
                        "z": 0,
                        "a_deg": 0,
                        "b_deg": 0,
                        "dx": 0,
                        "dy": 0,
                        "dz": 0,
                    }
                ],
            )
        assert store.table_counts()["probe_measurements"] == n


def test_a_state_kept_the_old_way_is_continued_once_into_the_table(tmp_path):
    from datetime import datetime

    import pandas as pd

    from driftlab.campaigns.bundle import load_bundle, write_bundle
    from driftlab.campaigns.store import connect
    from driftlab.jobs import registry as model_registry
    from driftlab.jobs.online import online_update
    from driftlab.models.online import ONLINE_JOB
    from tests.api.helpers import MACHINE, model_document, small_frames, small_meta

    with connect(f"sqlite:///{tmp_path / 's.sqlite'}") as store:
        temps, cond, errors = small_frames()
        store.campaigns.import_bundle(load_bundle(write_bundle(tmp_path / "b", small_meta(), temps, cond, errors)))
        doc = model_registry.register_model(store, model_document())
        old = {t: RLSState(np.array([0.001]), np.array([[0.5]]), 0.95, 7).to_dict() for t in ("dx", "dy", "dz")}
        job = store.jobs.record(ONLINE_JOB, {}, machine_id=MACHINE)
        store.jobs.start(job, "w")
        store.jobs.finish(job, {"model_version": doc.version, "states": old})
        probe = pd.DataFrame(
            [
                {
                    "time_s": 0.0,
                    "x": 0.0,
                    "y": 0.0,
                    "z": 0.0,
                    "a": 0.0,
                    "b": 0.0,
                    "dx": 0.0,
                    "dy": 0.0,
                    "dz": 0.0,
                    "T1": 21.0,
                    "T2": 22.0,
                }
            ]
        )
        rep = online_update(store, MACHINE, probe, start=datetime(2026, 3, 3, tzinfo=UTC))
        assert rep.states["dx"].n_updates == 8 and rep.states["dx"].lam == 0.95
        assert store.online.get(MACHINE).n_updates == 8
        assert store.table_counts()["probe_measurements"] == 1


def test_a_fresh_on_line_model_takes_the_first_cycle_whole():
    """A diffuse P(0) (``ONLINE_P0``): a 30 um residual seen by the first probe cycle's four spheres is
    the correction after that cycle; with P(0) = 1 (theta0 = 0 weighing as one probe) it was 80% of it."""
    r = np.full(4, 0.030)
    diffuse = rls_run(rls_init(1, lam=0.98), online_regressors(4), r).state.theta[0]
    assert abs(diffuse - 0.030) < 1e-5
    small = rls_run(rls_init(1, lam=0.98, p0=1.0), online_regressors(4), r).state.theta[0]
    assert 0.75 * 0.030 < small < 0.85 * 0.030
