"""`driftlab daemon`: run a campaign plan end to end, storing every reading as it arrives (resumable).

`driftlab daemon --plan PLAN.yaml [--sim SCENARIO.yaml --speed 3600 | --rig RIG.yaml] [--resume] [--db URL]`

With --rig the instruments of a rig file are opened (examples/rigs/: a Keysight 34970A for the
thermocouples, LinuxCNC through linuxcncrsh, ...; `driftlab rig check RIG` first). With --sim a
virtual machine built from the scenario answers as those same instruments (34970A SCPI,
linuxcncrsh) and the same drivers talk to it. With neither, the thesis' instruments named in
the plan's `instruments:` section are opened (legacy protocols). SIGINT/SIGTERM stop it between
two commits; `kill -9` at any moment loses nothing either: `--resume` continues from the last
committed cursor.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from driftlab.commands.db import add_db_option
from driftlab.commands.rig import export_readers
from driftlab.errors import NotFoundError, ValidationError

log = logging.getLogger(__name__)

EXIT_STOPPED = 3  # stopped before the end of the plan; resumable


def register(sub: argparse._SubParsersAction) -> None:
    """Register `daemon`."""
    p = sub.add_parser("daemon", help="run a campaign plan against the instruments, resumable")
    p.add_argument("--plan", type=Path, required=True, help="campaign plan YAML (examples/plans/)")
    p.add_argument("--sim", type=Path, default=None, metavar="SCENARIO", help="run on the virtual machine")
    p.add_argument(
        "--rig", type=Path, default=None, metavar="RIG", help="run on the instruments of a rig file (examples/rigs/)"
    )
    p.add_argument(
        "--speed",
        type=float,
        default=3600.0,
        help="simulated seconds per wall-clock second with --sim (0 = as fast as possible)",
    )
    p.add_argument("--resume", action="store_true", help="continue the unfinished campaign of this plan")
    add_db_option(p)
    p.add_argument("--max-batch", type=int, default=200, help="most scans committed in one transaction")
    p.add_argument(
        "--stop-after",
        type=int,
        default=None,
        metavar="N",
        help="stop after N commits (testing and staged runs; resumable)",
    )
    p.add_argument("--stats-json", type=Path, default=None, help="write run statistics here")
    p.set_defaults(func=_daemon)


def _export_readers() -> dict[str, Any]:
    """Return the export formats a laser-export follower reads (the importers, wired in here above both layers)."""
    return dict(export_readers())


def _daemon(args: argparse.Namespace) -> int:
    """Run (or resume) the plan's campaign and return 0 when it completed, 3 when stopped early."""
    # lazy: this function's imports would add 0.9 s to `driftlab --help` (measured)
    from driftlab.campaigns.plan import load_plan
    from driftlab.daemon.run import run_daemon

    plan = load_plan(args.plan)
    if args.max_batch < 1:
        raise ValidationError("--max-batch must be at least 1")
    if args.speed < 0 or (args.speed == 0 and args.sim is None):
        raise ValidationError("--speed must be positive (0 = as fast as possible, only with --sim)")
    speed = math.inf if args.speed == 0 else args.speed
    # lazy, as above: kept off the `driftlab --help` path
    from driftlab.campaigns.store import connect

    with connect(args.db) as store:  # a read-only or unreachable store: one line now, not a traceback later
        store.check_writable()
    stop = threading.Event()

    def _on_signal(signum: int, _frame: Any) -> None:
        """Ask the scheduler to stop after its current commit; a second signal stops it at once."""
        if stop.is_set():
            # at once: an open transaction rolls back, so the stored cursor still matches the rows
            raise KeyboardInterrupt
        log.warning("signal %d: stopping after the current commit (again to stop at once)", signum)
        stop.set()

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        result = run_daemon(
            plan,
            db_url=args.db,
            scenario_path=args.sim,
            rig_path=args.rig,
            export_readers=_export_readers(),
            speed=speed,
            resume=args.resume,
            stop=stop,
            max_batch=args.max_batch,
            stop_after_commits=args.stop_after,
        )
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    stats = result.stats
    summary = {
        "campaign_id": result.campaign_id,
        "finished": stats.finished,
        "scans": stats.scans,
        "points": stats.points,
        "faults": stats.faults,
        "commits": stats.commits,
        "wall_s": round(stats.wall_s, 3),
        "scans_per_s": round(stats.scans_per_s(), 1),
        "p99_commit_ms": round(stats.p99_commit_s() * 1e3, 3),
        "p99_reading_to_commit_ms": round(stats.p99_latency_s() * 1e3, 3),
        "max_lag_s": round(stats.max_lag_s, 3),
        "next_scan": result.cursor.next_scan,
        "next_point": result.cursor.next_point,
    }
    if args.stats_json is not None:
        args.stats_json.write_text(json.dumps(summary) + "\n")
    if stats.finished:
        print(
            f"campaign {plan.name} (id {result.campaign_id}) complete: {stats.scans} scans, "
            f"{stats.points} sweep points stored in this run, {stats.faults} faults"
        )
        return 0
    sys.stderr.write(
        f"driftlab: campaign {plan.name} (id {result.campaign_id}) stopped at scan {result.cursor.next_scan}/"
        f"{plan.n_scans}, point {result.cursor.next_point}; continue with --resume\n"
    )
    return EXIT_STOPPED


def register_status(campsub: argparse._SubParsersAction) -> None:
    """Register `campaign status` on the `campaign` command's subparsers."""
    st = campsub.add_parser("status", help="daemon campaigns: stage, progress, last readings, faults")
    st.add_argument("campaign", nargs="?", default=None, help="campaign id or name (default: all)")
    st.add_argument("--json", action="store_true", help="one JSON array instead of text")
    add_db_option(st)
    st.set_defaults(func=_status)


def _status(args: argparse.Namespace) -> int:
    """Print the status of the daemon's campaigns (text, or JSON with --json)."""
    # lazy: this function's imports would add 0.2 s to `driftlab --help` (measured)
    from driftlab.campaigns.db import store_engine
    from driftlab.campaigns.status import campaign_status, format_status

    rows = campaign_status(store_engine(args.db), args.campaign)
    if args.campaign is not None and not rows:
        raise NotFoundError(f"no daemon campaign {args.campaign!r}")
    print(json.dumps(rows) if args.json else format_status(rows))
    return 0
