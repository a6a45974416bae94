"""`driftlab serve`: the REST API (FastAPI) under uvicorn, one process; jobs also run in it unless --no-jobs."""

from __future__ import annotations

import argparse
import errno
import logging
import socket

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
    sock = bind(host, port)  # a busy port fails here, in one line, before the app or the database is opened
    app = create_app(args.db, run_jobs=not args.no_jobs)
    try:
        app.state.driftlab.store.ensure_schema()  # an unreachable database fails here, in one line
    except SQLAlchemyError as exc:
        sock.close()
        cause = getattr(exc, "orig", None) or exc  # DBAPIError carries the driver's own message
        raise StoreError(f"cannot open the database: {' '.join(str(cause).split())[:200]}") from None
    limits = ConnectionLimits(settings.api_header_timeout_s, settings.api_body_timeout_s, settings.api_keep_alive_s)
    try:
        uvicorn.Server(server_config(app, host, port, args.log_level, limits)).run(sockets=[sock])
    finally:
        sock.close()
    return 0


def bind(host: str, port: int) -> socket.socket:
    """Return a listening-ready TCP socket bound to ``host:port``; ValidationError in one line when it cannot be.

    Bound here rather than by uvicorn, whose failure is five log lines and an exit status of 1: the
    socket is then handed to uvicorn (``Server.run(sockets=...)``), so there is no gap between the
    check and the server's bind. SO_REUSEADDR as uvicorn sets it (a restart does not wait out TIME_WAIT).
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ValidationError(f"cannot serve on {host}:{port}: unknown host ({exc.strerror})") from None
    family, kind, proto, _, address = infos[0]
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            reason = "the port is already in use (another server is listening there; give another --port)"
        elif exc.errno == errno.EACCES:
            reason = "permission denied (ports below 1024 need privileges; give another --port)"
        else:
            reason = exc.strerror or type(exc).__name__
        raise ValidationError(f"cannot serve on {host}:{port}: {reason}") from None
    sock.set_inheritable(True)
    return sock
