"""`driftlab health [--daemon | --worker]`: a container healthcheck for the services that hold no port.

Exit 0 with one line when healthy, 1 with one line saying what is wrong:

* always: the store's database answers;
* ``--daemon``: no campaign the daemon runs has stopped beating (its heartbeat is younger than the
  staleness threshold, ``campaigns.status``); a daemon between campaigns is healthy;
* ``--worker``: *this container's* worker is alive and working, from the pulse file it writes every
  5 s (``jobs.queue.Pulse``; ``--pulse-file``, default as `driftlab worker`'s): the file is younger
  than ``--max-age-s``, its process still exists, it has not been reconnecting to the database for
  longer than ``--max-age-s``, and its own row of ``procrastinate_workers`` (its event loop's
  heartbeat, every 10 s) is younger than ``--max-age-s``. Another worker's heartbeat does not
  make this one healthy.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from driftlab.commands.db import add_db_option
from driftlab.errors import ServiceError


def register(sub: argparse._SubParsersAction) -> None:
    """Register `health`."""
    p = sub.add_parser(
        "health", help="healthcheck for containers: the database answers (and the daemon or a worker beats)"
    )
    add_db_option(p)
    who = p.add_mutually_exclusive_group()
    who.add_argument("--daemon", action="store_true", help="also require the running campaigns' daemon heartbeat")
    who.add_argument(
        "--worker", action="store_true", help="also require this container's worker to be alive and beating"
    )
    p.add_argument("--max-age-s", type=float, default=60.0, metavar="S", help="with --worker: oldest pulse accepted")
    p.add_argument(
        "--pulse-file",
        default=None,
        metavar="PATH",
        help="with --worker: the worker's pulse file (as `driftlab worker`)",
    )
    p.set_defaults(func=_health)


def _health(args: argparse.Namespace) -> int:
    """Print one line and return 0 when healthy, 1 otherwise (a database that does not answer: 1 too)."""
    # lazy: this function's imports would add 0.6 s to `driftlab --help` (measured)
    from sqlalchemy import text

    from driftlab.campaigns.db import make_engine
    from driftlab.config import get_settings

    pulse = _worker_pulse(args.pulse_file, args.max_age_s) if args.worker else None
    # no migration from a healthcheck: the `migrate` service owns the schema
    engine = make_engine(args.db or get_settings().resolved_db_url())
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
            if pulse is not None:
                if engine.dialect.name != "postgresql":
                    raise ServiceError("health: workers run on the PostgreSQL store only")
                age = conn.execute(
                    text("SELECT EXTRACT(EPOCH FROM now() - last_heartbeat) FROM procrastinate_workers WHERE id = :id"),
                    {"id": int(pulse["worker_id"])},
                ).scalar()
                who = f"worker {pulse['name']} (pid {pulse['pid']}, queue id {pulse['worker_id']})"
                if age is None:
                    raise ServiceError(f"health: {who} is no longer registered in the job queue")
                if float(age) > args.max_age_s:
                    raise ServiceError(
                        f"health: {who} last beat in the job queue {float(age):.0f} s ago (limit {args.max_age_s:g} s)"
                    )
        if args.daemon:
            # lazy, as above: kept off the `driftlab --help` path
            from driftlab.campaigns.status import campaign_status

            stale = [r for r in campaign_status(engine) if r.get("stale_since")]
            if stale:
                names = ", ".join(f"{r['name']} (stale since {r['stale_since']})" for r in stale)
                raise ServiceError(f"health: the daemon stopped beating: {names}")
    finally:
        engine.dispose()
    print("healthy")
    return 0


def _worker_pulse(path: str | None, max_age_s: float) -> dict:
    """Return this container's worker pulse (``jobs.queue.Pulse``); ServiceError saying what is wrong with it."""
    # lazy: this function's imports would add 0.7 s to `driftlab --help` (measured)
    from driftlab.jobs.queue import default_pulse_file

    path = path or default_pulse_file()
    try:
        with open(path, encoding="utf-8") as fh:
            pulse = json.load(fh)
        pid, name, written = int(pulse["pid"]), str(pulse["name"]), float(pulse["written_at"])
    except FileNotFoundError:
        raise ServiceError(f"health: no worker pulse at {path} (no `driftlab worker` runs here)") from None
    except (OSError, ValueError, KeyError, TypeError):
        raise ServiceError(f"health: the worker pulse {path} is unreadable") from None
    now = time.time()
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        raise ServiceError(f"health: worker {name} (pid {pid}) is gone") from None
    except PermissionError:
        pass  # it exists, under another user
    if now - written > max_age_s:
        raise ServiceError(f"health: worker {name} (pid {pid}) wrote no pulse for {now - written:.0f} s (hung?)")
    lost = pulse.get("lost_since")
    if lost is not None:
        gone = now - float(lost)
        if gone > max_age_s:
            raise ServiceError(f"health: worker {name} (pid {pid}) has been without its database for {gone:.0f} s")
        raise ServiceError(f"health: worker {name} (pid {pid}) is reconnecting to its database ({gone:.0f} s)")
    if pulse.get("worker_id") is None:
        raise ServiceError(f"health: worker {name} (pid {pid}) is not connected to the job queue yet")
    return dict(pulse)
