"""The campaign store on SQLite and PostgreSQL: drift and history queries, model registry, jobs, progress."""

from __future__ import annotations

import io
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from sqlalchemy import insert, select, update
from sqlalchemy.exc import IntegrityError

from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import load_bundle, write_bundle
from driftlab.campaigns.store import Store, connect
from driftlab.cli import main
from driftlab.errors import NotFoundError, ValidationError


@pytest.fixture
def store(store_url: str):
    s = connect(store_url)
    yield s
    s.close()


# ----------------------------------------------------------------------------- drift


def _two_campaigns(store: Store, bundle_factory) -> tuple[int, int]:
    a = store.campaigns.import_bundle(load_bundle(bundle_factory(seed=1, started_at="2026-03-02T08:00:00Z")))
    b = store.campaigns.import_bundle(load_bundle(bundle_factory(seed=2, started_at="2026-03-05T09:30:00+01:00")))
    return a, b


def test_drift_nearest_position_across_campaigns_in_wall_clock(store: Store, bundle_factory) -> None:
    a, b = _two_campaigns(store, bundle_factory)
    d = store.readings.drift("vmc-test-01", "Z", "dz", position=130.0, direction=1)
    # measured positions are 0, 100, 200, 300, 400: nearest to 130 is 100
    assert set(d["position"]) == {100.0}
    assert list(d["campaign_id"]) == [a] * 4 + [b] * 4
    assert (d["direction"] == 1).all()
    errors_a = load_bundle(bundle_factory(seed=1)).errors
    want = errors_a[(errors_a.term == "dz") & (errors_a.position == 100.0) & (errors_a.direction == 1)]
    assert d["value"].iloc[:4].tolist() == want["value"].tolist()
    assert d["time"].iloc[0] == pd.Timestamp("2026-03-02T08:00:00Z") + pd.Timedelta(seconds=want["time_s"].iloc[0])
    assert d["time"].iloc[4] == pd.Timestamp("2026-03-05T08:30:00Z") + pd.Timedelta(seconds=want["time_s"].iloc[0])
    assert d["time"].is_monotonic_increasing
    both = store.readings.drift("vmc-test-01", "Z", "dz", position=100.0)
    assert set(both["direction"]) == {1, -1} and len(both) == 16


def test_drift_time_window_and_all_positions(store: Store, bundle_factory) -> None:
    a, b = _two_campaigns(store, bundle_factory)
    start = datetime(2026, 3, 2, 8, 5, tzinfo=UTC)
    end = datetime(2026, 3, 2, 8, 10, tzinfo=UTC)
    d = store.readings.drift("vmc-test-01", "Z", "dx", start=start, end=end)
    assert set(d["campaign_id"]) == {a}
    assert d["time_s"].between(300.0, 600.0).all() and len(d) == 11  # sweep at 300 s (10 points) + 600 s start
    assert set(d["position"]) == {0.0, 100.0, 200.0, 300.0, 400.0}
    late = store.readings.drift("vmc-test-01", "Z", "dx", start=datetime(2026, 3, 4, tzinfo=UTC))
    assert set(late["campaign_id"]) == {b}
    empty = store.readings.drift("vmc-test-01", "Z", "dy")
    assert empty.empty and list(empty.columns) == [
        "campaign_id",
        "time",
        "time_s",
        "position",
        "direction",
        "sweep",
        "value",
    ]


def test_drift_interpolates_along_position_within_each_sweep(store: Store, bundle_factory) -> None:
    cid = store.campaigns.import_bundle(load_bundle(bundle_factory(seed=3)))
    errors = store.campaigns.load(cid).errors
    d = store.readings.drift("vmc-test-01", "Z", "dx", position=250.0, direction=-1, interpolate=True)
    assert len(d) == 4 and (d["position"] == 250.0).all()
    sel = errors[(errors.term == "dx") & (errors.direction == -1)]
    for k, (_, row) in enumerate(d.iterrows()):
        sweep = sel.iloc[5 * k : 5 * k + 5].sort_values("position")
        lo, hi = sweep[sweep.position == 200.0].iloc[0], sweep[sweep.position == 300.0].iloc[0]
        assert row["value"] == pytest.approx(lo.value + 0.5 * (hi.value - lo.value), rel=1e-12, abs=1e-18)
        assert row["time_s"] == pytest.approx(lo.time_s + 0.5 * (hi.time_s - lo.time_s))
    exact = store.readings.drift("vmc-test-01", "Z", "dx", position=400.0, direction=1, interpolate=True)
    want = errors[(errors.term == "dx") & (errors.direction == 1) & (errors.position == 400.0)]
    assert exact["value"].tolist() == want["value"].tolist()
    assert store.readings.drift("vmc-test-01", "Z", "dx", position=900.0, interpolate=True).empty


def test_drift_refuses_bad_requests(store: Store, bundle_dir: Path) -> None:
    store.campaigns.import_bundle(load_bundle(bundle_dir))
    with pytest.raises(ValidationError, match="unknown axis"):
        store.readings.drift("vmc-test-01", "W", "dz")
    with pytest.raises(ValidationError, match="unknown term"):
        store.readings.drift("vmc-test-01", "Z", "dw")
    with pytest.raises(NotFoundError, match="no machine"):
        store.readings.drift("nope", "Z", "dz")
    with pytest.raises(ValidationError, match="needs a position"):
        store.readings.drift("vmc-test-01", "Z", "dz", interpolate=True)


def test_drift_cli_csv_is_exact(store_url: str, bundle_dir: Path, capsys) -> None:
    assert main(["import", str(bundle_dir), "--db", store_url]) == 0
    capsys.readouterr()
    assert (
        main(
            [
                "drift",
                "--machine",
                "vmc-test-01",
                "--axis",
                "Z",
                "--term",
                "gamma",
                "--position",
                "0",
                "--direction",
                "+1",
                "--csv",
                "--db",
                store_url,
            ]
        )
        == 0
    )
    got = pd.read_csv(io.StringIO(capsys.readouterr().out))
    errors = load_bundle(bundle_dir).errors
    want = errors[(errors.term == "gamma") & (errors.position == 0.0) & (errors.direction == 1)]
    assert got["value"].tolist() == want["value"].tolist()
    assert got["time"].iloc[0] == "2026-03-02T08:00:00Z"
    assert main(["drift", "--machine", "vmc-test-01", "--axis", "Z", "--term", "dz", "--db", store_url]) == 0
    assert "campaign_id" in capsys.readouterr().out
    assert (
        main(
            [
                "drift",
                "--machine",
                "vmc-test-01",
                "--axis",
                "Z",
                "--term",
                "dx",
                "--position",
                "260",
                "--interpolate",
                "--direction",
                "-1",
                "--from",
                "2026-03-02T08:04:00",
                "--to",
                "2026-03-02T08:30:00Z",
                "--csv",
                "--db",
                store_url,
            ]
        )
        == 0
    )
    got = pd.read_csv(io.StringIO(capsys.readouterr().out))
    assert len(got) == 3 and set(got["direction"]) == {-1} and set(got["position"]) == {260.0}
    with pytest.raises(SystemExit) as usage:
        main(
            ["drift", "--machine", "vmc-test-01", "--axis", "Z", "--term", "dx", "--direction", "0", "--db", store_url]
        )
    assert usage.value.code == 2
    assert (
        main(
            [
                "drift",
                "--machine",
                "vmc-test-01",
                "--axis",
                "Z",
                "--term",
                "dx",
                "--from",
                "2026-03-03",
                "--to",
                "2026-03-02",
                "--db",
                store_url,
            ]
        )
        == 2
    )
    assert "--to is before --from" in capsys.readouterr().err


# ----------------------------------------------------------------------------- histories


def test_temperature_history_buckets_match_numpy(store: Store, bundle_dir: Path) -> None:
    b = load_bundle(bundle_dir)
    cid = store.campaigns.import_bundle(b)
    t = b.temperatures["time_s"].to_numpy()
    v = b.temperatures["T2"].to_numpy()
    h = store.readings.temperature_history(cid, "T2", buckets=6, rollups=False)
    edges = np.linspace(t[0], t[-1], 7)
    w = (t[-1] - t[0]) / 6
    idx = np.array([min(int(np.searchsorted(t[0] + w * np.arange(1, 6), x, side="right")), 5) for x in t])
    assert len(h) == 6
    for k in range(6):
        sel = v[idx == k]
        sel = sel[~np.isnan(sel)]
        assert h["value_min"][k] == sel.min() and h["value_max"][k] == sel.max()
        assert h["value_mean"][k] == pytest.approx(sel.mean(), rel=1e-12)
        assert h["time_s"][k] == pytest.approx(edges[k])
    assert h["n"].sum() == len(t)
    window = store.readings.temperature_history(cid, "T2", start_s=300.0, end_s=600.0)
    assert window["time_s"].tolist() == [float(x) for x in range(300, 601, 30)]
    with pytest.raises(NotFoundError, match="no channel 'T9'"):
        store.readings.temperature_history(cid, "T9")


def _rollups(store: Store) -> list:
    """Return the stored rollup rows in channel and minute order."""
    with store.engine.connect() as conn:
        return conn.execute(
            select(sc.TemperatureRollup.__table__).order_by(
                sc.TemperatureRollup.channel_id, sc.TemperatureRollup.minute
            )
        ).all()


def test_temperature_history_from_minute_rollups(store: Store, bundle_dir: Path) -> None:
    b = load_bundle(bundle_dir)
    cid = store.campaigns.import_bundle(b)
    t = b.temperatures["time_s"].to_numpy()
    v = b.temperatures["T2"].to_numpy()
    h = store.readings.temperature_history(cid, "T2", buckets=3)  # 390 s wide: snapped out to 7 minutes
    k = (np.floor(t / 60) // 7).astype(int)
    assert h["time_s"].tolist() == [0.0, 420.0, 840.0] and h["t_end_s"].tolist() == [420.0, 840.0, 1260.0]
    for j in range(3):
        sel = v[(k == j) & ~np.isnan(v)]
        assert h["value_min"][j] == sel.min() and h["value_max"][j] == sel.max()
        assert h["value_mean"][j] == pytest.approx(sel.mean(), rel=1e-12)
        assert h["n"][j] == (k == j).sum()
    # narrow buckets are never taken from rollups
    narrow = store.readings.temperature_history(cid, "T2", buckets=20)
    assert narrow.equals(store.readings.temperature_history(cid, "T2", buckets=20, rollups=False))

    # recomputing the rollups in SQL gives the rows the import wrote
    written = _rollups(store)
    assert len(written) == 4 * 20
    assert store.campaigns.refresh_rollups(cid) == len(written)
    again = _rollups(store)
    assert [r[:5] for r in again] == [r[:5] for r in written]
    for a, w in zip(again, written, strict=True):
        assert a[5] == w[5] and a[7] == w[7] and a[6] == pytest.approx(w[6], rel=1e-12)
    # a campaign without complete rollups (written live) is aggregated from the readings
    with store.engine.begin() as conn:
        conn.execute(update(sc.Campaign).where(sc.Campaign.id == cid).values(rollups_complete=False))
    assert store.readings.temperature_history(cid, "T2", buckets=3).equals(
        store.readings.temperature_history(cid, "T2", buckets=3, rollups=False)
    )
    with pytest.raises(NotFoundError):
        store.campaigns.refresh_rollups(99)


def test_rollups_of_minutes_without_a_reading_are_null(store: Store, bundle_dir: Path, tmp_path: Path) -> None:
    """A minute whose readings of a channel are all missing is written as a rollup with a count and no
    value (NULL min, sum, max), between minutes with values, exactly as SQL's aggregates make it."""
    b = load_bundle(bundle_dir)
    temps = b.temperatures.copy()
    t = temps["time_s"].to_numpy()
    temps.loc[(t >= 120) & (t < 300), "T2"] = np.nan  # minutes 2, 3 and 4 of T2: no reading
    temps.loc[t < 60, "T49"] = np.nan  # T49's first minute
    cid = store.campaigns.import_bundle(
        load_bundle(write_bundle(tmp_path / "gaps", b.meta, temps, b.conditions, b.errors))
    )

    written = _rollups(store)
    empty = [(r.minute, r.n, r.n_values, r.vmin, r.vsum, r.vmax) for r in written if r.n_values == 0]  # T2, then T49
    assert [e[0] for e in empty] == [2, 3, 4, 0] and all(e[1] > 0 and e[3:] == (None, None, None) for e in empty)
    store.campaigns.refresh_rollups(cid)
    again = _rollups(store)
    assert [r[:6] for r in again] == [r[:6] for r in written] and [r[7] for r in again] == [r[7] for r in written]
    assert all((a[6] is None) == (w[6] is None) for a, w in zip(again, written, strict=True))


def test_condition_history(store: Store, bundle_dir: Path) -> None:
    cid = store.campaigns.import_bundle(load_bundle(bundle_dir))
    h = store.readings.condition_history(cid, ["spindle_rpm", "z"], buckets=2)
    assert h["spindle_rpm_max"].tolist() == [8000.0, 0.0]
    assert h["spindle_rpm_min"].tolist() == [8000.0, 0.0]
    assert h["z_mean"].isna().all()
    raw = store.readings.condition_history(cid, ["feed_mm_min"], end_s=60.0)
    assert raw.shape == (3, 2)
    with pytest.raises(ValidationError, match="unknown condition"):
        store.readings.condition_history(cid, ["torque"])


# ----------------------------------------------------------------------------- registry, jobs, progress


def test_model_registry_keeps_exactly_one_current(store: Store, bundle_dir: Path) -> None:
    cid = store.campaigns.import_bundle(load_bundle(bundle_dir))
    assert store.models.current("vmc-test-01") is None
    v1 = store.models.register("vmc-test-01", {"kind": "standard", "coef": [1.5, 2.0]}, [cid])
    v2 = store.models.register("vmc-test-01", {"kind": "extended", "nested": {"a": [1, None]}}, [cid])
    assert (v1.version, v2.version) == (1, 2)
    current = store.models.current("vmc-test-01")
    assert current is not None and current.version == 2 and current.document["nested"] == {"a": [1, None]}
    assert [m.status for m in store.models.versions("vmc-test-01")] == ["retired", "current"]
    with pytest.raises(IntegrityError), store.engine.begin() as conn:
        conn.execute(
            insert(sc.ModelVersion),
            {
                "machine_id": "vmc-test-01",
                "version": 9,
                "document": {},
                "source_campaigns": [],
                "status": "current",
                "created_at": datetime.now(UTC),
            },
        )
    with pytest.raises(NotFoundError):
        store.models.register("nope", {})


def test_job_records_lifecycle(store: Store) -> None:
    """A job record: queued, running (one attempt more each start), queued again for a retry, then done or failed."""
    a = store.jobs.record("diagnose", {"campaigns": [1]})
    b = store.jobs.record("fit", {"campaigns": [1]})
    assert [store.jobs.get(j).state for j in (a, b)] == ["queued", "queued"]
    assert store.jobs.in_state("queued") == [a, b] and store.jobs.in_state("queued", ["fit"]) == [b]
    job = store.jobs.start(b, "w1", only_if_queued=True)
    assert job is not None and job.state == "running" and job.attempts == 1 and job.worker == "w1"
    assert store.jobs.start(b, "w2", only_if_queued=True) is None  # another process has it
    store.jobs.fail(b, "database\ngone away", retry=True)
    job = store.jobs.get(b)
    assert job.state == "queued" and job.error == "database gone away" and job.finished_at is None
    assert store.jobs.start(b, "w2").attempts == 2
    store.jobs.finish(b, {"model_version": 3})
    job = store.jobs.get(b)
    assert job.state == "done" and job.result == {"model_version": 3} and job.error is None and job.finished_at
    store.jobs.start(a, "w1")
    store.jobs.fail(a, "singular\nmatrix")
    assert store.jobs.get(a).state == "failed" and store.jobs.get(a).error == "singular matrix"
    assert store.jobs.get(a).queue_status is None  # never queued on procrastinate
    store.jobs.delete(a)
    with pytest.raises(NotFoundError):
        store.jobs.get(a)
    with pytest.raises(NotFoundError):
        store.jobs.start(999, "w1")
    with pytest.raises(ValidationError):
        store.jobs.record("")


def test_acquisition_progress_upsert(store: Store, bundle_dir: Path) -> None:
    cid = store.campaigns.import_bundle(load_bundle(bundle_dir))
    assert store.campaigns.progress(cid) is None
    store.campaigns.save_progress(cid, 0, 1, 30.0, {"next_scan": 2})
    store.campaigns.save_progress(cid, 1, 4, 90.0, {"next_scan": 4})
    p = store.campaigns.progress(cid)
    assert p is not None and (p.stage_ordinal, p.sweep, p.last_sample_time_s, p.cursor) == (
        1,
        4,
        90.0,
        {"next_scan": 4},
    )
    assert p.updated_at.tzinfo is not None


def test_delete_campaign_removes_everything(store: Store, bundle_factory) -> None:
    empty = store.table_counts()
    cid = store.campaigns.import_bundle(load_bundle(bundle_factory(seed=1)))
    store.campaigns.save_progress(cid, 0, 0, None)
    store.campaigns.delete(cid)
    after = store.table_counts()
    assert {k: v for k, v in after.items() if k != "machines"} == {k: v for k, v in empty.items() if k != "machines"}
    with pytest.raises(NotFoundError):
        store.campaigns.delete(cid)


def test_default_url_comes_from_environment(tmp_path: Path, monkeypatch, bundle_dir: Path) -> None:
    path = tmp_path / "env" / "store.sqlite"
    monkeypatch.setenv("DRIFTLAB_DB_URL", f"sqlite:///{path}")
    assert main(["import", str(bundle_dir)]) == 0
    assert path.exists()
    s = connect()
    try:
        assert [c.id for c in s.campaigns.summaries()] == [1]
    finally:
        s.close()


def test_unsupported_url_is_a_user_error() -> None:
    with pytest.raises(ValidationError, match="unsupported database"):
        connect("mysql://x@localhost/db")


def test_timestamps_are_utc_aware(store: Store, bundle_factory) -> None:
    cid = store.campaigns.import_bundle(load_bundle(bundle_factory(started_at="2026-03-05T09:30:00+01:00")))
    [c] = store.campaigns.summaries()
    assert c.id == cid and c.started_at == datetime(2026, 3, 5, 8, 30, tzinfo=UTC)
    assert c.started_at.utcoffset() == timedelta(0)
