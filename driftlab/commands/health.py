"""`driftlab health [--daemon | --worker]`: a container healthcheck for the services that hold no port.

Exit 0 with one line when healthy, 1 with one line saying what is wrong:

* always: the store's database answers;
* ``--daemon``: no campaign the daemon runs has stopped beating (its heartbeat is younger than the
  staleness threshold, ``campaigns.status``); a daemon between campaigns is healthy;
* ``--worker``: some job-queue worker has beaten within ``--max-age-s`` (procrastinate's heartbeat,
  every 10 s while a worker runs).
"""

from __future__ import annotations

import argparse

from driftlab.commands.db import add_db_option


def register(sub: argparse._SubParsersAction) -> None:
    """Register `health`."""
    p = sub.add_parser(
        "health", help="healthcheck for containers: the database answers (and the daemon or a worker beats)"
    )
    add_db_option(p)
    who = p.add_mutually_exclusive_group()
    who.add_argument("--daemon", action="store_true", help="also require the running campaigns' daemon heartbeat")
    who.add_argument("--worker", action="store_true", help="also require a job-queue worker's recent heartbeat")
    p.add_argument("--max-age-s", type=float, default=60.0, metavar="S", help="with --worker: newest heartbeat age")
    p.set_defaults(func=_health)


def _health(args: argparse.Namespace) -> int:
    """Print one line and return 0 when healthy, 1 otherwise (a database that does not answer: 1 too)."""
    from sqlalchemy import text

    from driftlab.campaigns.db import make_engine
    from driftlab.config import get_settings
    from driftlab.errors import ServiceError

    # no migration from a healthcheck: the `migrate` service owns the schema
    engine = make_engine(args.db or get_settings().resolved_db_url())
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
            if args.worker:
                if engine.dialect.name != "postgresql":
                    raise ServiceError("health: workers run on the PostgreSQL store only")
                age = conn.execute(
                    text("SELECT EXTRACT(EPOCH FROM now() - max(last_heartbeat)) FROM procrastinate_workers")
                ).scalar()
                if age is None or float(age) > args.max_age_s:
                    seen = (
                        "no worker is registered" if age is None else f"the newest heartbeat is {float(age):.0f} s old"
                    )
                    raise ServiceError(f"health: {seen} (limit {args.max_age_s:g} s)")
        if args.daemon:
            from driftlab.campaigns.status import campaign_status

            stale = [r for r in campaign_status(engine) if r.get("stale_since")]
            if stale:
                names = ", ".join(f"{r['name']} (stale since {r['stale_since']})" for r in stale)
                raise ServiceError(f"health: the daemon stopped beating: {names}")
    finally:
        engine.dispose()
    print("healthy")
    return 0
