"""The scheduler's store side and engine: atomic batches with their cursor, resume, status, sim runs."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from sqlalchemy import func, select

from driftlab.campaigns import schema as sc
from driftlab.campaigns.acquisition import Batch, Fault, StoreSink, open_campaign
from driftlab.campaigns.db import store_engine
from driftlab.campaigns.plan import Cursor, load_plan, parse_plan
from driftlab.campaigns.status import campaign_status, format_status
from driftlab.daemon.loop import Scheduler, SchedulerOptions
from driftlab.daemon.run import skip_missed
from driftlab.daemon.simrig import plan_scenario, scenario_meta, scenario_stages
from driftlab.daq.protocols import FLAG_BEAM_BREAK, FLAG_OPEN, Reading, TemperatureScan
from driftlab.errors import ConflictError, ValidationError
from tests.daemon.sim_helpers import plant_reading, sim_run

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "examples" / "plans" / "z-axis-demo.yaml"
CHANNELS = {
    "T1": {"location": "X axis front left corner", "structure": "x_table"},
    "T49": {"location": "room top", "structure": "room"},
}


def _plan():
    """Return a small plan with a sweep in its first stage."""
    return parse_plan(
        {
            "name": "unit",
            "machine": {"id": "m-unit", "channels": {k: dict(v) for k, v in CHANNELS.items()}},
            "scan_interval_s": 10,
            "stages": [
                {
                    "name": "sp",
                    "axis": "Z",
                    "duration_s": 100,
                    "heat": [{"kind": "spindle", "rpm": 8000}],
                    "sweep": {"positions": [0, 50], "interval_s": 50, "point_s": 5},
                },
                {"name": "cool", "axis": "Z", "duration_s": 50},
            ],
        }
    )


def _scan(t: float, base: float = 20.0) -> TemperatureScan:
    return TemperatureScan(t_s=t, values={"T1": base + t / 100, "T49": base})


def _count(engine, table) -> int:
    with engine.connect() as conn:
        return conn.execute(select(func.count()).select_from(table)).scalar_one()


def test_batches_commit_with_their_cursor_and_resume_from_it(store_url: str) -> None:
    """Readings and cursor land together; a resumed open returns that cursor; stages and status follow."""
    engine = store_engine(store_url)
    plan = _plan()
    h = open_campaign(engine, plan, CHANNELS, ["T49"], resume=False, origin={"mode": "test"})
    assert h.cursor == Cursor() and not h.resumed and set(h.channel_ids) == {"T1", "T49"}
    sink = StoreSink(engine, plan, h)
    pts = plan.sweep_points()
    b = Batch(
        scans=[(0, _scan(0.0)), (1, _scan(10.0))],
        states=[(0.0, {"spindle_rpm": 8000.0, "z": 0.0})],
        points=[(pts[0], 0.0, {"dz": Reading(0.001)}), (pts[1], 5.0, {"dz": Reading.missing(FLAG_BEAM_BREAK)})],
        cursor=Cursor(2, 2),
        stage=0,
        t_s=10.0,
    )
    sink.commit(b)
    assert _count(engine, sc.TemperatureSample.__table__) == 4
    assert _count(engine, sc.ErrorSample.__table__) == 1  # the broken-beam term is a fault, not a row
    with pytest.raises(ConflictError, match="--resume"):
        open_campaign(engine, plan, CHANNELS, ["T49"], resume=False, origin={})
    again = open_campaign(engine, plan, CHANNELS, ["T49"], resume=True, origin={})
    assert again.resumed and again.campaign_id == h.campaign_id and again.cursor == Cursor(2, 2)
    (st,) = campaign_status(engine, "unit")
    assert st["status"] == "running" and st["stage"]["name"] == "sp" and st["stage"]["status"] == "running"
    assert st["progress"]["scans"] == 2 and st["progress"]["n_scans"] == 15
    assert st["faults"]["count"] == 1 and FLAG_BEAM_BREAK in st["faults"]["recent"][0]["message"]
    assert st["last_point"]["values"] == {"dz": None} and st["last_point"]["position"] == 50
    assert "unit" in format_status([st]) and "faults 1" in format_status([st])


def test_a_failing_batch_stores_nothing_and_keeps_the_cursor(store_url: str) -> None:
    """A batch whose insert fails (a reading already stored) rolls back whole: no row, no cursor move."""
    engine = store_engine(store_url)
    plan = _plan()
    h = open_campaign(engine, plan, CHANNELS, [], resume=False, origin={})
    sink = StoreSink(engine, plan, h)
    sink.commit(Batch(scans=[(0, _scan(0.0))], cursor=Cursor(1, 0)))
    before = _count(engine, sc.TemperatureSample.__table__)
    dup = Batch(scans=[(1, _scan(10.0)), (0, _scan(0.0, base=99.0))], cursor=Cursor(2, 0), t_s=10.0)
    with pytest.raises(ConflictError):
        sink.commit(dup)
    assert _count(engine, sc.TemperatureSample.__table__) == before == 2
    assert open_campaign(engine, plan, CHANNELS, [], resume=True, origin={}).cursor == Cursor(1, 0)


def test_open_thermocouple_is_stored_as_missing_and_the_last_batch_closes_the_campaign(store_url: str) -> None:
    """A flagged channel becomes NULL; the batch reaching the end marks stages and campaign done."""
    engine = store_engine(store_url)
    plan = _plan()
    h = open_campaign(engine, plan, CHANNELS, [], resume=False, origin={})
    sink = StoreSink(engine, plan, h)
    scan = TemperatureScan(0.0, {"T1": math.nan, "T49": 20.0}, {"T1": FLAG_OPEN})
    sink.commit(
        Batch(
            scans=[(0, scan)],
            faults=[Fault(0.0, "scan 0", "thermocouple", "x")],
            cursor=Cursor(plan.n_scans, len(plan.sweep_points())),
            stage=1,
            t_s=140.0,
        )
    )
    with engine.connect() as conn:
        vals = dict(
            conn.execute(
                select(sc.Channel.name, sc.TemperatureSample.value).join(
                    sc.Channel, sc.Channel.id == sc.TemperatureSample.channel_id
                )
            ).all()
        )
        statuses = conn.execute(select(sc.Stage.status).order_by(sc.Stage.ordinal)).scalars().all()
        camp = conn.execute(select(sc.Campaign.status)).scalar_one()
    assert vals == {"T1": None, "T49": 20.0}
    assert statuses == ["done", "done"] and camp == "done"
    # resuming a complete campaign finds nothing left to do; a new run of the same plan is a new campaign
    done = open_campaign(engine, plan, CHANNELS, [], resume=True, origin={})
    assert done.campaign_id == h.campaign_id and done.cursor == Cursor(plan.n_scans, len(plan.sweep_points()))
    assert open_campaign(engine, plan, CHANNELS, [], resume=False, origin={}).campaign_id != h.campaign_id


def test_resume_refuses_a_changed_plan(tmp_path: Path) -> None:
    """Resuming with a plan whose timeline changed is a one-line conflict, not silent corruption."""
    engine = store_engine(f"sqlite:///{tmp_path / 'd.sqlite'}")
    plan = _plan()
    open_campaign(engine, plan, CHANNELS, [], resume=False, origin={})
    doc = plan.model_dump(mode="json")
    doc["stages"][1]["duration_s"] = 60
    with pytest.raises(ConflictError, match="different plan timeline"):
        open_campaign(engine, parse_plan(doc), CHANNELS, [], resume=True, origin={})


def test_real_clock_resume_skips_what_was_missed() -> None:
    """On a real clock the scans and points that fell in the downtime are skipped, not faked."""
    plan = _plan()
    cur, ns, np_ = skip_missed(plan, Cursor(2, 1), now_s=52.0)
    assert cur.next_scan == 6 and ns == 4
    assert plan.sweep_points()[cur.next_point].t_s >= 52.0 and np_ == cur.next_point - 1


def test_plan_drives_the_virtual_machine_stages() -> None:
    """The demo plan maps onto scenario stages: idle, spindle, feed, combined, back to back."""
    from driftlab.daq.sim.scenario import Scenario

    plan = load_plan(DEMO)
    stages = scenario_stages(plan)
    assert [s["heat_source"] for s in stages] == ["idle", "spindle", "idle", "feed", "idle", "combined"]
    sc_ = plan_scenario(plan, Scenario(hours=1.0))
    assert sc_.hours * 3600 >= plan.total_s and sc_.stages[-1].end_s == plan.total_s
    hold = plan.model_dump(mode="json")
    hold["stages"][1]["heat"] = [{"kind": "motor_hold", "axis": "Y", "position": 0}]
    hold["staged_order"] = False
    with pytest.raises(ValidationError, match="motor_hold"):
        scenario_stages(parse_plan(hold))
    far = plan.model_dump(mode="json")
    far["stages"][0]["sweep"]["positions"] = [0, 400]
    with pytest.raises(ValidationError, match=r"stages\[0\].sweep.positions: 400 outside .* Z travel -254..0"):
        plan_scenario(parse_plan(far), Scenario())


def test_channel_maps_from_scenario_or_plan() -> None:
    """'from scenario' takes the virtual machine's 50 sites; a plan's own map must name sites it has."""
    from driftlab.daemon.run import resolve_channels
    from driftlab.daq.sim.scenario import Scenario

    chans, rooms = resolve_channels(load_plan(DEMO), Scenario())
    assert len(chans) == 50 and rooms == ["T49", "T50"] and chans["T37"]["location"]
    own = _plan()
    assert list(resolve_channels(own, Scenario())[0]) == ["T1", "T49"]
    bad = own.model_dump(mode="json")
    bad["machine"]["channels"]["T99"] = {"location": "nowhere"}
    with pytest.raises(ValidationError, match="T99 not on the virtual machine"):
        resolve_channels(parse_plan(bad), Scenario())
    with pytest.raises(ValidationError, match="no --sim scenario"):
        resolve_channels(load_plan(DEMO), None)


def test_instrument_faults_are_logged_and_the_campaign_goes_on(tmp_path: Path) -> None:
    """A card that keeps garbling and a broken laser beam become faults; every other reading is stored."""
    plan = parse_plan(
        {
            "name": "faulty",
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 60,
            "stages": [
                {
                    "name": "sp",
                    "axis": "Z",
                    "duration_s": 600,
                    "heat": [{"kind": "spindle", "rpm": 9000}],
                    "sweep": {"positions": [-100, 0], "interval_s": 300, "point_s": 5},
                }
            ],
        }
    )
    run = sim_run(plan, f"sqlite:///{tmp_path / 'f.sqlite'}")
    engine, handle, rig = run.engine, run.handle, run.rig
    rig.servers["thermocouple"].inject("garble", "garble", "garble", on="READ?")  # every attempt of the first scan
    rig.servers["laser"].break_beam()
    try:
        stats = Scheduler(plan, rig, run.sink, run.clock, options=SchedulerOptions(max_batch=1)).run()  # scan by scan
    finally:
        rig.close()
    assert stats.finished
    assert _count(engine, sc.TemperatureSample.__table__) == (plan.n_scans - 1) * 50
    assert _count(engine, sc.ErrorSample.__table__) == 0
    (st,) = campaign_status(engine, handle.campaign_id)
    assert st["status"] == "done"
    assert st["faults"]["count"] == 1 + len(plan.sweep_points())
    messages = " ".join(f["message"] for f in st["faults"]["recent"])
    with engine.connect() as conn:
        first = conn.execute(select(func.min(sc.TemperatureSample.time_s))).scalar_one()
    assert first == 60.0  # scan 0 is the card's fault: missing, not invented
    assert "IDS3010 resetAxes" in messages and "beam interrupted" in messages  # the head's own error text


def test_real_mode_opens_the_instruments_named_in_the_plan(tmp_path: Path) -> None:
    """Without --sim the daemon opens the plan's instrument addresses (here: servers on loopback) on the wall clock."""
    from driftlab.daemon.run import run_daemon
    from driftlab.daq.sim.instruments import (
        SimController,
        SimLaser,
        SimThermocoupleCard,
        WallClock,
        serial_url,
        visa_address,
    )
    from driftlab.testing.tinyworld import TinyWorld

    world, clock = TinyWorld(channels=4), WallClock(acceleration=1.0)
    card = SimThermocoupleCard(world, clock, {0: "T1", 1: "T2", 2: "T3", 3: "T4"}).start()
    ctrl = SimController(world, clock).start()
    head = SimLaser(world, clock, ctrl).start()
    try:
        plan = parse_plan(
            {
                "name": "bench-top",
                "machine": {"id": "rig-1", "channels": {f"T{i}": {"location": f"site {i}"} for i in range(1, 5)}},
                "scan_interval_s": 0.1,
                "instruments": {
                    "thermocouple": visa_address(card),
                    "laser": visa_address(head),
                    "machine_link": serial_url(ctrl),
                },
                "stages": [
                    {
                        "name": "idle",
                        "axis": "X",
                        "duration_s": 0.6,
                        "sweep": {"positions": [0, 0.01], "directions": [1], "interval_s": 0.5, "point_s": 0.25},
                    }
                ],
            }
        )
        result = run_daemon(plan, db_url=f"sqlite:///{tmp_path / 'r.sqlite'}")
    finally:
        for server in (card, ctrl, head):
            server.close()
    assert result.stats.finished and not result.resumed
    engine = store_engine(f"sqlite:///{tmp_path / 'r.sqlite'}")
    with engine.connect() as conn:
        times = (
            conn.execute(select(sc.TemperatureSample.time_s).distinct().order_by(sc.TemperatureSample.time_s))
            .scalars()
            .all()
        )
        errs = conn.execute(select(func.count()).select_from(sc.ErrorSample.__table__)).scalar_one()
    assert len(times) == plan.n_scans == 6
    assert all(b > a for a, b in zip(times, times[1:])) and times[0] >= 0.0  # real, increasing times
    assert errs == 2 and result.stats.faults == 0
    with engine.connect() as conn:  # a finished live campaign gets its per-minute rollups
        complete = conn.execute(select(sc.Campaign.rollups_complete)).scalar_one()
        rolled = conn.execute(select(func.sum(sc.TemperatureRollup.n))).scalar_one()
        readings = conn.execute(select(func.count()).select_from(sc.TemperatureSample.__table__)).scalar_one()
    assert complete and rolled == readings
    (st,) = campaign_status(engine)
    assert st["mode"] == "real" and st["status"] == "done"


def test_a_reading_already_stored_stops_the_run_with_a_conflict(tmp_path: Path) -> None:
    """If the store already holds a reading the cursor says is still to do, the run stops: never a double row."""
    plan = parse_plan(
        {
            "name": "dup",
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 60,
            "stages": [{"name": "idle", "axis": "Z", "duration_s": 300}],
        }
    )
    run = sim_run(plan, f"sqlite:///{tmp_path / 'dup.sqlite'}")
    engine = run.engine
    plant_reading(run, 0.0)
    try:
        with pytest.raises(ConflictError, match="already holds a reading"):
            Scheduler(plan, run.rig, run.sink, run.clock, run.handle.cursor).run()
    finally:
        run.rig.close()
    assert _count(engine, sc.TemperatureSample.__table__) == 1
    channels = scenario_meta(None)["channels"]
    assert open_campaign(engine, plan, channels, [], resume=True, origin={}).cursor == Cursor()


@pytest.mark.postgres
def test_a_lost_database_connection_is_retried_without_losing_or_doubling_rows(pg_cluster) -> None:
    """PostgreSQL drops the daemon's connections mid-run: the same batch is committed again, once."""
    from sqlalchemy import create_engine, text

    url = pg_cluster.create_database()
    plan = parse_plan(
        {
            "name": "blip",
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 60,
            "stages": [
                {
                    "name": "idle",
                    "axis": "Z",
                    "duration_s": 1800,
                    "sweep": {"positions": [-200, 0], "interval_s": 600, "point_s": 5},
                }
            ],
        }
    )
    run = sim_run(plan, url)
    engine, rig = run.engine, run.rig
    admin = create_engine(url.rsplit("/", 1)[0] + "/postgres", isolation_level="AUTOCOMMIT")
    dbname = url.rsplit("/", 1)[1]
    dropped = []

    def drop_connections(batch, stats) -> None:
        if stats.commits in (2, 5):
            with admin.connect() as conn:
                n = conn.execute(
                    text(
                        "SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
                        "WHERE datname = :d AND pid <> pg_backend_pid()"
                    ),
                    {"d": dbname},
                ).scalar_one()
            dropped.append(n)

    try:
        stats = Scheduler(
            plan, rig, run.sink, run.clock, run.handle.cursor, SchedulerOptions(on_commit=drop_connections)
        ).run()
    finally:
        rig.close()
        admin.dispose()
    assert stats.finished and dropped and all(n >= 1 for n in dropped), campaign_status(engine)[0]["faults"]
    assert stats.faults == 0, campaign_status(engine)[0]["faults"]
    assert _count(engine, sc.TemperatureSample.__table__) == plan.n_scans * 50
    assert _count(engine, sc.ErrorSample.__table__) == len(plan.sweep_points())


def test_block_reads_store_the_rows_of_scan_by_scan_reads(tmp_path: Path) -> None:
    """Buffered block reads and one scan per exchange store the same readings (and the same states)."""

    plan = parse_plan(
        {
            "name": "blocks",
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 10,
            "state_every": 3,
            "stages": [
                {
                    "name": "sp",
                    "axis": "Z",
                    "duration_s": 900,
                    "heat": [{"kind": "spindle", "rpm": 9000}],
                    "sweep": {"positions": [-100, 0], "interval_s": 300, "point_s": 5},
                }
            ],
        }
    )
    rows = {}
    for mode, max_batch in (("single", 1), ("blocks", 40)):
        run = sim_run(plan, f"sqlite:///{tmp_path / (mode + '.sqlite')}")
        engine, rig = run.engine, run.rig
        try:
            sched = Scheduler(plan, rig, run.sink, run.clock, options=SchedulerOptions(max_batch=max_batch))
            assert sched.block_scans() == max_batch
            stats = sched.run()
            received = list(rig.servers["thermocouple"].received)
        finally:
            rig.close()
        if mode == "blocks":
            # the scans between a sweep's moves and points wait in the card's buffer: one block read per commit
            removes = [c for c in received if c.startswith("DATA:REM?")]
            assert 0 < len(removes) <= stats.commits
        assert stats.finished and stats.faults == 0 and stats.scans == plan.n_scans
        with engine.connect() as conn:
            rows[mode] = (
                conn.execute(
                    select(
                        sc.TemperatureSample.channel_id, sc.TemperatureSample.time_s, sc.TemperatureSample.value
                    ).order_by(sc.TemperatureSample.channel_id, sc.TemperatureSample.time_s)
                ).all(),
                conn.execute(select(sc.ConditionSample.__table__).order_by(sc.ConditionSample.time_s)).all(),
                conn.execute(select(sc.ErrorSample.time_s, sc.ErrorSample.value).order_by(sc.ErrorSample.seq)).all(),
            )
        assert stats.commits < plan.n_scans if mode == "blocks" else True
    (t1, c1, e1), (t2, c2, e2) = rows["single"], rows["blocks"]
    assert len(t1) == len(t2) == plan.n_scans * 50
    assert [r[:2] for r in t1] == [r[:2] for r in t2]
    # the single-scan reply carries 10 significant digits, the block the card's full float64
    assert max(abs(a[2] - b[2]) for a, b in zip(t1, t2)) < 1e-6
    assert [tuple(r) for r in c1] == [tuple(r) for r in c2] and len(c1) == plan.n_scans // 3
    assert e1 == e2
