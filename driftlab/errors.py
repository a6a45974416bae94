"""One exception hierarchy, mapped to one-line CLI messages and HTTP problem responses."""

from __future__ import annotations


class DriftlabError(Exception):
    """Base of every error driftlab reports to a user (never shown as a traceback)."""

    exit_code = 2
    http_status = 400

    def one_line(self) -> str:
        """Return the message squeezed onto a single line."""
        return " ".join(str(self).split())


class ValidationError(DriftlabError):
    """Input (bundle, plan, scenario, motion code, request) that does not meet its contract."""

    http_status = 422


class BadRequestError(ValidationError):
    """A malformed request parameter (query, path or cursor): HTTP 400, a CLI usage error."""

    http_status = 400


class NotFoundError(DriftlabError):
    """A machine, campaign, model version or job that does not exist."""

    http_status = 404


class ConflictError(DriftlabError):
    """An operation that would duplicate or contradict stored data (e.g. importing a bundle twice)."""

    http_status = 409


class InstrumentError(DriftlabError):
    """An instrument timed out or replied with something that failed validation."""

    http_status = 503


class ServiceError(DriftlabError):
    """A service a long-running command depends on (the database) went away and did not come back.

    Exit status 1, so that a supervisor (docker-compose ``restart: on-failure``, systemd) restarts it.
    """

    exit_code = 1
    http_status = 503


class KinematicsError(DriftlabError):
    """A pose the kinematic model cannot solve (e.g. the A = 90 deg singularity)."""

    http_status = 422


def environment_error(exc: BaseException) -> str | None:
    """Return a one-line description of a database, file or permission failure (None for anything else).

    These are not user errors in the input but in the surroundings (an unreachable or read-only
    database, an unreadable file): the CLI reports them in one line, with the traceback under -v.
    """
    # lazy: errors is on the `driftlab --help` path; sqlalchemy would add 0.15 s there (measured)
    from sqlalchemy.exc import DBAPIError, SQLAlchemyError

    if isinstance(exc, DBAPIError):
        orig = exc.orig if exc.orig is not None else exc
        first = next((line.strip() for line in str(orig).splitlines() if line.strip()), type(orig).__name__)
        return f"database: {first[:300]}"
    if isinstance(exc, SQLAlchemyError):
        return f"database: {' '.join(str(exc).split())[:300]}"
    if isinstance(exc, OSError):
        reason = exc.strerror or " ".join(str(exc).split())[:300] or type(exc).__name__
        where = exc.filename if exc.filename is not None else None
        return f"{where}: {reason}" if where else reason
    return None
