"""The daemon: a campaign plan opened (or resumed) in the store and run on the real or simulated rig."""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict, Unpack

from sqlalchemy import select

from driftlab.campaigns import ingest
from driftlab.campaigns import schema as sc
from driftlab.campaigns.acquisition import Batch, CampaignHandle, StoreSink, open_campaign
from driftlab.campaigns.clock import SimClock, WallClock
from driftlab.campaigns.db import store_engine, write_transaction
from driftlab.campaigns.plan import Cursor, Plan, cursor_time
from driftlab.daemon.clocks import LoopClock
from driftlab.daemon.loop import RunStats, Scheduler, SchedulerOptions
from driftlab.daemon.rig import InstrumentRig, build_file_rig, build_real_rig
from driftlab.daemon.rigfile import RigSpec, load_rig, thermocouple_channels
from driftlab.daemon.simrig import build_sim_rig, scenario_meta, sim_meta
from driftlab.daq.sim.scenario import Scenario, load_scenario
from driftlab.errors import ValidationError
from driftlab.progress import progress

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine

log = logging.getLogger(__name__)


@dataclass
class DaemonResult:
    """The outcome of one daemon run."""

    campaign_id: int
    cursor: Cursor
    stats: RunStats
    resumed: bool


def check_rig_can_run(plan: Plan) -> None:
    """Refuse, before anything starts, a plan whose setups this daemon cannot drive (one line naming the stage)."""
    for i, stage in enumerate(plan.stages):
        got = plan.stage_setup(i)
        if got is not None and got[1].instrument == "probe":
            raise ValidationError(
                f"plan {plan.name}: stages[{i}] ({stage.name}): setup {got[0]!r} is a probe setup, which the daemon "
                "does not drive (run it with the touch-probe cycle of the on-line model)"
            )


def skip_missed(plan: Plan, cursor: Cursor, now_s: float) -> tuple[Cursor, int, int]:
    """Return the cursor moved past steps already in the past on a real clock, and how many were skipped."""
    points = plan.sweep_points()
    k = cursor.next_scan
    while k < plan.n_scans and plan.scan_time(k) < now_s:
        k += 1
    j = cursor.next_point
    while j < len(points) and points[j].t_s < now_s:
        j += 1
    return Cursor(k, j), k - cursor.next_scan, j - cursor.next_point


def sim_clock(plan: Plan, cursor: Cursor = Cursor(), speed: float = 3600.0) -> SimClock:
    """Return the simulated clock for running `plan` from `cursor`: it starts at the cursor's first step.

    Build it before the simulated rig: the servers take their starting time from it.
    """
    return SimClock(speed=speed, start_s=cursor_time(plan, plan.sweep_points(), cursor))


@dataclass(frozen=True)
class DaemonOptions:
    """What `run_daemon` is told besides the plan (the keywords it takes, with the same defaults).

    ``scenario_path``: run on the virtual machine (``--sim``); ``rig_path``: a rig file's
    instruments (``--rig``); neither: the instruments named in the plan. ``engine`` or ``db_url``:
    the store. ``sim_laser`` picks the simulated rig's laser (``thesis-laser``: the legacy head, a
    benchmark baseline); ``world`` replaces the virtual machine behind the simulated instruments.
    """

    db_url: str | None = None
    scenario_path: Path | str | None = None
    speed: float = 3600.0
    resume: bool = False
    stop: threading.Event | None = None
    max_batch: int = 200
    flush_s: float = 0.05
    stop_after_commits: int | None = None
    engine: Engine | None = None
    world: object | None = None
    rig_path: Path | str | None = None
    export_readers: Mapping[str, Callable[..., Any]] | None = None
    sim_laser: str = "attocube-ids3010"


class DaemonKeywords(TypedDict, total=False):
    """`DaemonOptions` given as keywords to `run_daemon` (how every caller passes them)."""

    db_url: str | None
    scenario_path: Path | str | None
    speed: float
    resume: bool
    stop: threading.Event | None
    max_batch: int
    flush_s: float
    stop_after_commits: int | None
    engine: Engine | None
    world: object | None
    rig_path: Path | str | None
    export_readers: Mapping[str, Callable[..., Any]] | None
    sim_laser: str


@dataclass
class _Opened:
    """A campaign opened in the store with the rig and clock it runs on."""

    handle: CampaignHandle
    rig: InstrumentRig
    clock: LoopClock
    cursor: Cursor


def run_daemon(plan: Plan, options: DaemonOptions | None = None, /, **keywords: Unpack[DaemonKeywords]) -> DaemonResult:
    """Open (or resume) the plan's campaign in the store and run it on the simulated rig, a rig file's
    instruments (``rig_path``), or the instruments named in the plan (see `DaemonOptions`)."""
    opts = options if options is not None else DaemonOptions(**keywords)
    check_rig_can_run(plan)
    log.info(
        "plan %s measures %d of the 30 motion-error terms%s",
        plan.name,
        30 - len(plan.missing_terms()),
        f"; the model will lack {', '.join(plan.missing_terms())}" if plan.missing_terms() else "",
    )
    engine = opts.engine if opts.engine is not None else store_engine(opts.db_url)
    stop = opts.stop or threading.Event()
    scenario, rig_spec = _sources(opts)
    channels, rooms = resolve_channels(plan, scenario, rig_spec)
    opened = _open(plan, engine, opts, (scenario, rig_spec), (channels, rooms))
    try:
        stats, cursor = _run(plan, opened, StoreSink(engine, plan, opened.handle), stop, opts)
    finally:
        opened.rig.close()
    if stats.finished:
        _summarise_finished(engine, opened.handle.campaign_id)
    return DaemonResult(opened.handle.campaign_id, cursor, stats, opened.handle.resumed)


def _sources(opts: DaemonOptions) -> tuple[Scenario | None, RigSpec | None]:
    """Return the virtual machine's scenario (``--sim``) or the rig file (``--rig``), refusing both at once."""
    scenario = load_scenario(opts.scenario_path) if opts.scenario_path is not None else None
    if opts.rig_path is None:
        return scenario, None
    if scenario is not None:
        raise ValidationError("give either --sim (the virtual machine's rig) or --rig, not both")
    return None, load_rig(opts.rig_path)


def _open(
    plan: Plan,
    engine: Engine,
    opts: DaemonOptions,
    sources: tuple[Scenario | None, RigSpec | None],
    chans: tuple[dict[str, dict[str, str]], list[str]],
) -> _Opened:
    """Open the campaign and its rig: real instruments before the store (an unreachable one leaves no
    campaign behind), the simulated ones after it (they start where its cursor is)."""
    scenario, rig_spec = sources
    channels, rooms = chans
    origin = {
        "mode": "sim" if scenario is not None else "real",
        "scenario": str(opts.scenario_path) if opts.scenario_path is not None else None,
        "rig": rig_spec.name if rig_spec is not None else None,
        "speed": None if math.isinf(opts.speed) else opts.speed,
    }
    if scenario is not None:
        handle = open_campaign(
            engine, plan, channels, rooms, resume=opts.resume, origin=origin, extra_meta=sim_meta(plan, scenario)
        )
        clock = sim_clock(plan, handle.cursor, opts.speed)
        rig = build_sim_rig(
            plan,
            scenario,
            clock,
            list(channels),
            datum=handle.progress.get("datum"),
            world=opts.world,
            cursor=handle.cursor,
            laser=opts.sim_laser,
        )
        return _Opened(handle, rig, clock, handle.cursor)
    wall = WallClock()
    if rig_spec is not None:
        rig = build_file_rig(plan, rig_spec, list(channels), wall, opts.export_readers)
    else:
        rig = build_real_rig(plan, list(channels), wall)
    try:
        handle = open_campaign(engine, plan, channels, rooms, resume=opts.resume, origin=origin)
    except BaseException:
        rig.close()
        raise
    wall.started_epoch_s = _campaign_started_epoch(engine, handle.campaign_id)
    cursor = handle.cursor
    if handle.resumed:
        cursor, ns, np_ = skip_missed(plan, cursor, wall.now())
        if ns or np_:
            log.warning("skipped %d scans and %d sweep points missed while the daemon was down", ns, np_)
    return _Opened(handle, rig, wall, cursor)


def _run(
    plan: Plan, opened: _Opened, sink: StoreSink, stop: threading.Event, opts: DaemonOptions
) -> tuple[RunStats, Cursor]:
    """Run the scheduler on the opened campaign with a progress bar; return its statistics and final cursor."""
    cursor = opened.cursor
    commits = [0]
    with progress(f"{plan.name}", total=plan.n_scans + len(plan.sweep_points())) as bar:
        bar.advance(cursor.next_scan + cursor.next_point)

        def on_commit(batch: Batch, stats: RunStats) -> None:
            """Advance the progress bar; stop after the requested number of commits."""
            bar.advance(len(batch.scans) + len(batch.points))
            commits[0] += 1
            if opts.stop_after_commits is not None and commits[0] >= opts.stop_after_commits:
                stop.set()

        sched = Scheduler(
            plan,
            opened.rig,
            sink,
            opened.clock,
            cursor,
            SchedulerOptions(
                max_batch=opts.max_batch,
                flush_s=opts.flush_s,
                on_commit=on_commit,
                stop=stop,
                # stopping after a count of commits stops there: no batches read ahead of the writer
                pipeline_depth=1 if opts.stop_after_commits is not None else SchedulerOptions.pipeline_depth,
            ),
        )
        stats = sched.run()
    return stats, sched.cursor


def _summarise_finished(engine: Engine, campaign_id: int) -> None:
    """Build the per-minute temperature rollups of a campaign that has just finished.

    Live campaigns are written scan by scan without rollups; once complete, the wide-bucket
    history queries (API, `driftlab drift`) read the rollups instead of every raw reading.
    """
    with write_transaction(engine) as conn:
        ingest.refresh_rollups(conn, campaign_id)


def _campaign_started_epoch(engine: Engine, campaign_id: int) -> float:
    """Return the campaign's start as a Unix epoch (the origin of a real campaign's time_s)."""
    with engine.connect() as conn:
        started = conn.execute(select(sc.Campaign.started_at).where(sc.Campaign.id == campaign_id)).scalar_one()
    return started.timestamp()


def resolve_channels(
    plan: Plan, scenario: Scenario | None, rig: RigSpec | None = None
) -> tuple[dict[str, dict[str, str]], list[str]]:
    """Return the channel map (name -> location, structure) and room channels of the plan, scenario or rig.

    A plan whose channels are 'from scenario' run on a rig file takes the rig's thermocouple names,
    with the locations of the thesis' sites (Table 5.1) where the names are theirs.
    """
    if rig is not None and not isinstance(plan.machine.channels, dict):
        names = thermocouple_channels(rig)
        if not names:
            raise ValidationError(f"rig {rig.name}: no thermocouples role: the plan's channels come from it")
        sites = scenario_meta(None)
        table = sites["channels"]
        chans = {
            n: {"location": table.get(n, {}).get("location", ""), "structure": table.get(n, {}).get("structure", "")}
            for n in names
        }
        rooms = list(plan.machine.room_channels or [c for c in sites.get("room_channels", []) if c in chans])
        return chans, rooms

    if isinstance(plan.machine.channels, dict):
        chans = {k: {"location": v.location, "structure": v.structure} for k, v in plan.machine.channels.items()}
        if scenario is not None:
            known = scenario_meta(scenario)["channels"]
            unknown = [k for k in chans if k not in known]
            if unknown:
                raise ValidationError(
                    f"plan {plan.name}: machine.channels: {', '.join(unknown[:5])} not on the virtual machine "
                    f"(it has {', '.join(list(known)[:3])} ... {list(known)[-1]})"
                )
        return chans, list(plan.machine.room_channels)
    if scenario is None:
        raise ValidationError(f"plan {plan.name}: machine.channels is 'from scenario' but no --sim scenario was given")
    meta = scenario_meta(scenario)
    chans = {
        k: {"location": v.get("location", ""), "structure": v.get("structure", "")} for k, v in meta["channels"].items()
    }
    return chans, list(plan.machine.room_channels or meta.get("room_channels", []))
