"""An ``expected_protocol`` helper in the manner of pymeasure's: exact bytes, every pair used.

A :class:`ProtocolPort` stands in for the byte port under a driver.  It is given the
conversation as (bytes the driver must write, bytes the instrument replies) pairs; a
write that differs from the next expected one fails at once, and leaving the ``with``
block with pairs unused fails too.  A reply of :data:`TIMEOUT` makes the read time out,
``None`` means the instrument sends nothing for that write.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TypeVar

from driftlab.daq.retry import RetryPolicy, TransportTimeout
from driftlab.daq.transport import LineChannel

T = TypeVar("T")

TIMEOUT = object()


class ProtocolPort:
    """A RawPort that checks every byte written against an expected conversation."""

    def __init__(self, pairs: Sequence[tuple[bytes | None, object]]) -> None:
        self.pairs = list(pairs)
        self.index = 0
        self._reply: object = None
        self._awaiting_read = False
        self.discards = 0
        self.closed = False

    def write(self, data: bytes) -> None:
        """Check ``data`` against the next expected write."""
        assert not self._awaiting_read, "driver wrote again before reading the previous reply"
        assert self.index < len(self.pairs), f"unexpected write {data!r}: conversation already finished"
        expected, reply = self.pairs[self.index]
        assert data == expected, f"pair {self.index}: wrote {data!r}, expected {expected!r}"
        self.index += 1
        self._reply = reply
        self._awaiting_read = reply is not None

    def read_line(self) -> bytes:
        """Return the scripted reply to the last write (or time out)."""
        if not self._awaiting_read:
            # a read with no scripted reply: either a pair with write None (unsolicited) or a bug
            assert self.index < len(self.pairs) and self.pairs[self.index][0] is None, "read with no reply pending"
            self._reply = self.pairs[self.index][1]
            self.index += 1
        self._awaiting_read = False
        if self._reply is TIMEOUT:
            raise TransportTimeout("timeout waiting for reply")
        assert isinstance(self._reply, bytes)
        return self._reply

    def discard_input(self) -> None:
        """Count input flushes (they exchange no bytes)."""
        self.discards += 1

    def close(self) -> None:
        """Mark the port closed."""
        self.closed = True


@contextmanager
def expected_protocol(
    factory: Callable[[LineChannel], T],
    pairs: Sequence[tuple[bytes | None, object]],
    policy: RetryPolicy | None = None,
    sleeps: list[float] | None = None,
) -> Iterator[T]:
    """Yield ``factory(channel)`` on a ProtocolPort; on exit assert every pair was used."""
    port = ProtocolPort(pairs)
    recorded = sleeps if sleeps is not None else []
    channel = LineChannel(
        port, name="dut", policy=policy or RetryPolicy(attempts=3, base_delay_s=0.01), sleep=recorded.append
    )
    yield factory(channel)
    assert not port._awaiting_read, "a reply was scripted but never read"
    assert port.index == len(port.pairs), (
        f"only {port.index} of {len(port.pairs)} expected pairs were used; next: {port.pairs[port.index]!r}"
    )
