"""Retry with exponential backoff for instrument exchanges, then one clear InstrumentError.

A transient fault (a timeout, a garbled or invalid reply) is retried a few times with
a growing pause; if every attempt fails the caller gets a one-line
:class:`driftlab.errors.InstrumentError` and never a value: nothing built from a reply
that failed validation leaves this module.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TypeVar

from driftlab.errors import InstrumentError

log = logging.getLogger(__name__)

T = TypeVar("T")


class TransientError(Exception):
    """A fault worth retrying: the instrument may answer properly next time."""


class TransportTimeout(TransientError):
    """No complete reply arrived within the transport's timeout."""


class GarbledReply(TransientError):
    """A reply arrived but failed validation (undecodable, wrong shape, out of range)."""


@dataclass(frozen=True)
class RetryPolicy:
    """How often and how patiently a failed exchange is retried."""

    attempts: int = 3
    base_delay_s: float = 0.05
    factor: float = 2.0
    max_delay_s: float = 2.0

    def __post_init__(self) -> None:
        if self.attempts < 1:
            raise ValueError("RetryPolicy.attempts must be at least 1")
        if self.base_delay_s < 0 or self.factor < 1 or self.max_delay_s < 0:
            raise ValueError("RetryPolicy delays must be non-negative and factor >= 1")

    def delays(self) -> Iterator[float]:
        """Return the pauses (s) taken between consecutive attempts (attempts - 1 of them)."""
        delay = self.base_delay_s
        for _ in range(self.attempts - 1):
            yield min(delay, self.max_delay_s)
            delay *= self.factor


def call_with_retry(
    fn: Callable[[], T],
    what: str,
    policy: RetryPolicy | None = None,
    sleep: Callable[[float], None] = time.sleep,
    before_retry: Callable[[], None] | None = None,
) -> T:
    """Return ``fn()``, retrying TransientError with backoff; raise InstrumentError when all fail."""
    policy = policy or RetryPolicy()
    delays = policy.delays()
    attempt = 0
    while True:
        attempt += 1
        try:
            return fn()
        except TransientError as exc:
            reason = " ".join(str(exc).split()) or type(exc).__name__
            delay = next(delays, None)
            if delay is None:
                raise InstrumentError(
                    f"{what}: {reason} (gave up after {attempt} attempt{'s' if attempt > 1 else ''})"
                ) from exc
            log.warning("%s: %s; retry %d in %.3f s", what, reason, attempt, delay)
            sleep(delay)
            if before_retry is not None:
                before_retry()
