"""`driftlab worker`: run the fit, diagnose and refit jobs of the PostgreSQL job queue (procrastinate).

Exit status 0 after SIGINT/SIGTERM (running jobs end first) or, with ``--until-idle``, once nothing
is runnable; 1 when the database stayed away longer than ``--reconnect-s`` (the worker reconnects
by itself before that), so that ``restart: on-failure`` brings it back.
"""

from __future__ import annotations

import argparse
import logging

from driftlab.commands.db import add_db_option
from driftlab.errors import ValidationError


def register(sub: argparse._SubParsersAction) -> None:
    """Register `worker [--db URL] [--concurrency N] [--until-idle] [--name N] [--reconnect-s S] [--pulse-file P]`."""
    p = sub.add_parser(
        "worker", help="run queued fit/diagnose/refit jobs (PostgreSQL store; start as many as you like)"
    )
    add_db_option(p)
    p.add_argument(
        "--concurrency",
        type=int,
        default=1,
        metavar="N",
        help="jobs run at once by this process, each in a thread (default 1; fits are CPU-bound: "
        "prefer more worker processes)",
    )
    p.add_argument("--until-idle", action="store_true", help="exit once no job is runnable instead of waiting for more")
    p.add_argument("--name", default=None, help="the worker's name in the job records (default host:pid)")
    p.add_argument(
        "--reconnect-s",
        type=float,
        default=300.0,
        metavar="S",
        help="when the database goes away, keep trying to reconnect this long, then exit with status 1 "
        "so that a supervisor restarts the worker (default 300)",
    )
    p.add_argument(
        "--pulse-file",
        default=None,
        metavar="PATH",
        help="where this worker writes its liveness every 5 s for `driftlab health --worker` "
        "(default $DRIFTLAB_WORKER_PULSE, else driftlab-worker.pulse.json in the temporary directory: "
        "one per container; give each worker its own when several share a host)",
    )
    p.set_defaults(func=_worker)


def _worker(args: argparse.Namespace) -> int:
    """Run a procrastinate worker on the store's database until SIGINT/SIGTERM (running jobs end first)."""
    # lazy: this function's imports would add 2.8 s to `driftlab --help` (measured)
    from driftlab.campaigns.store import connect
    from driftlab.jobs.queue import default_pulse_file, run_worker

    if args.concurrency < 1:
        raise ValidationError(f"--concurrency must be at least 1, got {args.concurrency}")
    if not args.reconnect_s >= 0:
        raise ValidationError(f"--reconnect-s must be at least 0, got {args.reconnect_s}")
    with connect(args.db) as store:
        if store.dialect != "postgresql":
            raise ValidationError(
                "driftlab worker needs the PostgreSQL store "
                "(DRIFTLAB_DB_URL=postgresql+psycopg://...): "
                "on the embedded SQLite store jobs run inside `driftlab serve` and `driftlab fit`"
            )
        store.ensure_schema()  # brings the queue's schema too (revision 0006)
        logging.getLogger(__name__).info("worker on %s, concurrency %d", store.url, args.concurrency)
        run_worker(
            store,
            concurrency=args.concurrency,
            wait=not args.until_idle,
            name=args.name,
            reconnect_s=args.reconnect_s,
            pulse_file=args.pulse_file or default_pulse_file(),
        )
    # only a stop asked for (SIGINT/SIGTERM) or --until-idle gets here: a lost database raises ServiceError (1)
    return 0
