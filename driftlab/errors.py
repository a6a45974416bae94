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


class NotFoundError(DriftlabError):
    """A machine, campaign, model version or job that does not exist."""

    http_status = 404


class ConflictError(DriftlabError):
    """An operation that would duplicate or contradict stored data (e.g. importing a bundle twice)."""

    http_status = 409


class InstrumentError(DriftlabError):
    """An instrument timed out or replied with something that failed validation."""

    http_status = 503


class KinematicsError(DriftlabError):
    """A pose the kinematic model cannot solve (e.g. the A = 90 deg singularity)."""

    http_status = 422
