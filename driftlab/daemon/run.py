"""The daemon: a campaign plan opened (or resumed) in the store and run on the real or simulated rig."""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from driftlab.campaigns.acquisition import Batch, StoreSink, open_campaign
from driftlab.campaigns.db import store_engine, write_transaction
from driftlab.campaigns.plan import Cursor, Plan
from driftlab.daemon.loop import RunStats, Scheduler
from driftlab.daemon.rig import build_real_rig
from driftlab.daemon.simrig import build_sim_rig, scenario_meta, sim_meta

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
    from driftlab.errors import ValidationError

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


def sim_clock(plan: Plan, cursor: Cursor = Cursor(), speed: float = 3600.0) -> Any:
    """Return the simulated clock for running `plan` from `cursor`: it starts at the cursor's first step.

    Build it before the simulated rig: the servers take their starting time from it.
    """
    from driftlab.campaigns.clock import SimClock
    from driftlab.campaigns.plan import cursor_time

    return SimClock(speed=speed, start_s=cursor_time(plan, plan.sweep_points(), cursor))


def run_daemon(
    plan: Plan,
    *,
    db_url: str | None = None,
    scenario_path: Path | str | None = None,
    speed: float = 3600.0,
    resume: bool = False,
    stop: threading.Event | None = None,
    max_batch: int = 200,
    flush_s: float = 0.05,
    stop_after_commits: int | None = None,
    engine: Any | None = None,
    world: Any | None = None,
    rig_path: Path | str | None = None,
    export_readers: Any | None = None,
    sim_laser: str = "attocube-ids3010",
) -> DaemonResult:
    """Open (or resume) the plan's campaign in the store and run it on the simulated rig, a rig file's
    instruments (``rig_path``), or the instruments named in the plan; ``sim_laser`` picks the simulated
    rig's laser (``thesis-laser``: the legacy head, a benchmark baseline)."""
    from driftlab.campaigns.clock import WallClock
    from driftlab.progress import progress

    check_rig_can_run(plan)
    log.info(
        "plan %s measures %d of the 30 motion-error terms%s",
        plan.name,
        30 - len(plan.missing_terms()),
        f"; the model will lack {', '.join(plan.missing_terms())}" if plan.missing_terms() else "",
    )
    engine = engine if engine is not None else store_engine(db_url)
    stop = stop or threading.Event()
    scenario = None
    if scenario_path is not None:
        from driftlab.daq.sim.scenario import load_scenario

        scenario = load_scenario(scenario_path)
    rig_spec = None
    if rig_path is not None:
        from driftlab.daemon.rigfile import load_rig
        from driftlab.errors import ValidationError

        if scenario is not None:
            raise ValidationError("give either --sim (the virtual machine's rig) or --rig, not both")
        rig_spec = load_rig(rig_path)
    channels, rooms = resolve_channels(plan, scenario, rig_spec)
    origin = {
        "mode": "sim" if scenario is not None else "real",
        "scenario": str(scenario_path) if scenario_path is not None else None,
        "rig": rig_spec.name if rig_spec is not None else None,
        "speed": None if math.isinf(speed) else speed,
    }
    points = plan.sweep_points()
    if scenario is None:
        # open the instruments before touching the store: an unreachable instrument leaves no campaign behind
        clock: Any = WallClock()
        if rig_spec is not None:
            from driftlab.daemon.rig import build_file_rig

            rig = build_file_rig(plan, rig_spec, list(channels), clock, export_readers)
        else:
            rig = build_real_rig(plan, list(channels), clock)
    extra = sim_meta(plan, scenario) if scenario is not None else None
    try:
        handle = open_campaign(engine, plan, channels, rooms, resume=resume, origin=origin, extra_meta=extra)
    except BaseException:
        if scenario is None:
            rig.close()
        raise
    cursor = handle.cursor
    if scenario is not None:
        clock = sim_clock(plan, cursor, speed)
        rig = build_sim_rig(
            plan,
            scenario,
            clock,
            list(channels),
            datum=handle.progress.get("datum"),
            world=world,
            cursor=cursor,
            laser=sim_laser,
        )
    else:
        clock.started_epoch_s = _campaign_started_epoch(engine, handle.campaign_id)
        if handle.resumed:
            cursor, ns, np_ = skip_missed(plan, cursor, clock.now())
            if ns or np_:
                log.warning("skipped %d scans and %d sweep points missed while the daemon was down", ns, np_)
    sink = StoreSink(engine, plan, handle)
    total = plan.n_scans + len(points)
    commits = [0]
    try:
        with progress(f"{plan.name}", total=total) as bar:
            bar.advance(cursor.next_scan + cursor.next_point)

            def on_commit(batch: Batch, stats: RunStats) -> None:
                """Advance the progress bar; stop after the requested number of commits."""
                bar.advance(len(batch.scans) + len(batch.points))
                commits[0] += 1
                if stop_after_commits is not None and commits[0] >= stop_after_commits:
                    stop.set()

            sched = Scheduler(
                plan, rig, sink, clock, cursor, max_batch=max_batch, flush_s=flush_s, on_commit=on_commit, stop=stop
            )
            stats = sched.run()
    finally:
        rig.close()
    if stats.finished:
        _summarise_finished(engine, handle.campaign_id)
    return DaemonResult(handle.campaign_id, sched.cursor, stats, handle.resumed)


def _summarise_finished(engine: Any, campaign_id: int) -> None:
    """Build the per-minute temperature rollups of a campaign that has just finished.

    Live campaigns are written scan by scan without rollups; once complete, the wide-bucket
    history queries (API, `driftlab drift`) read the rollups instead of every raw reading.
    """
    from driftlab.campaigns import ingest

    with write_transaction(engine) as conn:
        ingest.refresh_rollups(conn, campaign_id)


def _campaign_started_epoch(engine: Any, campaign_id: int) -> float:
    """Return the campaign's start as a Unix epoch (the origin of a real campaign's time_s)."""
    from sqlalchemy import select

    from driftlab.campaigns import schema as sc

    with engine.connect() as conn:
        started = conn.execute(select(sc.Campaign.started_at).where(sc.Campaign.id == campaign_id)).scalar_one()
    return started.timestamp()


def resolve_channels(
    plan: Plan, scenario: Any | None, rig: Any | None = None
) -> tuple[dict[str, dict[str, str]], list[str]]:
    """Return the channel map (name -> location, structure) and room channels of the plan, scenario or rig.

    A plan whose channels are 'from scenario' run on a rig file takes the rig's thermocouple names,
    with the locations of the thesis' sites (Table 5.1) where the names are theirs.
    """
    from driftlab.errors import ValidationError

    if rig is not None and not isinstance(plan.machine.channels, dict):
        from driftlab.daemon.rigfile import thermocouple_channels

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
