"""`driftlab serve`: the REST API (FastAPI) under uvicorn, one process; jobs also run in it unless --no-jobs."""

from __future__ import annotations

import argparse
import logging

from driftlab.commands.db import add_db_option
from driftlab.errors import ValidationError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Register `serve [--host H] [--port P] [--db URL] [--no-jobs]`."""
    p = sub.add_parser("serve", help="serve the REST API (campaigns, drift, models, jobs, on-line update)")
    p.add_argument("--host", default=None, help="bind address (default: DRIFTLAB_API_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="port (default: DRIFTLAB_API_PORT or 8765)")
    add_db_option(p)
    p.add_argument(
        "--no-jobs",
        action="store_true",
        help="do not run fit/diagnosis jobs in this process: leave them to `driftlab worker` processes "
        "(PostgreSQL; on SQLite they then wait for a server that runs jobs)",
    )
    p.add_argument(
        "--log-level",
        default="info",
        choices=["critical", "error", "warning", "info", "debug"],
        help="uvicorn log level (default info)",
    )
    p.set_defaults(func=_serve)


def _serve(args: argparse.Namespace) -> int:
    """Build the app and run it under uvicorn until interrupted; 0 on a clean shutdown."""
    # lazy: this function's imports would add 2.5 s to `driftlab --help` (measured)
    import uvicorn
    from sqlalchemy.exc import SQLAlchemyError

    from driftlab.api.app import create_app
    from driftlab.api.connections import ConnectionLimits, server_config
    from driftlab.campaigns.db import StoreError
    from driftlab.config import Settings

    settings = Settings()
    host = args.host or settings.api_host
    port = settings.api_port if args.port is None else args.port
    if not 0 <= port <= 65535:
        raise ValidationError(f"--port must be 0..65535, got {port}")
    if not settings.api_token:
        log.warning("DRIFTLAB_API_TOKEN is not set: the API is read-only (every write is refused)")
    if host not in ("127.0.0.1", "localhost", "::1"):
        log.warning("serving on %s: reads are open to anyone who can reach this address", host)
    app = create_app(args.db, run_jobs=not args.no_jobs)
    try:
        app.state.driftlab.store.ensure_schema()  # an unreachable database fails here, in one line
    except SQLAlchemyError as exc:
        cause = getattr(exc, "orig", None) or exc  # DBAPIError carries the driver's own message
        raise StoreError(f"cannot open the database: {' '.join(str(cause).split())[:200]}") from None
    limits = ConnectionLimits(settings.api_header_timeout_s, settings.api_body_timeout_s, settings.api_keep_alive_s)
    uvicorn.Server(server_config(app, host, port, args.log_level, limits)).run()
    return 0
