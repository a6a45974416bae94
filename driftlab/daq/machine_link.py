"""RS-232 link to the machine controller: buffered motion-code streaming (thesis ch. 7.2).

The controller needs a look-ahead of blocks to contour smoothly and stops (leaving a
chatter mark) when starved; the compensation wants the code it receives to be as fresh
as possible.  So the PC holds the program and refills the controller only when its
queue has drained to the low-water mark, then tops it up to the high-water mark
(ch. 7.2: "the PC would wait for the machine tool's buffer to reach a low point before
sending more data").  ``lines`` may be a lazy iterable: a compensator's generator is
evaluated block by block at send time, with the latest temperatures.

Legacy protocol of the thesis' RS-232 line, driftlab's own (rig driver ``thesis-rs232``; the
compensator streams through it; a real controller: :mod:`driftlab.daq.linuxcnc`). Controller
protocol (ASCII, ``\\n`` terminated, every command answered):

========================  ==========================================================
``STAT?``                 ``STAT <free> <capacity> <last executed seq>``
``BLK <seq> <code>``      queue one block -> ``ACK <seq>``; ``ERR FULL`` if no room.
                          Sequence numbers make a resent block harmless: a block whose
                          seq was already accepted is acknowledged and not queued again.
``POS?``                  ``POS X<mm> Y<mm> Z<mm> A<deg> B<deg>``
``PRB <x>,<y>,<z>,<ux>,<uy>,<uz>,<dist>``  probe move from (x,y,z) along u up to dist mm
                          -> ``HIT <x>,<y>,<z>`` (stylus centre at trigger) or ``MISS``
========================  ==========================================================
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from driftlab.daq.dnc import carries_code
from driftlab.daq.protocols import StreamReport
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.transport import LineChannel, SerialPort
from driftlab.errors import InstrumentError, ValidationError
from driftlab.vocabulary import AXES


@dataclass(frozen=True)
class ControllerStatus:
    """The controller's buffer state."""

    free: int
    capacity: int
    done_seq: int

    @property
    def queued(self) -> int:
        """Return the number of blocks waiting or executing."""
        return self.capacity - self.free


def _parse_stat(text: str) -> ControllerStatus:
    word, free_s, cap_s, done_s = text.split()
    if word != "STAT":
        raise ValueError("not a STAT reply")
    status = ControllerStatus(int(free_s), int(cap_s), int(done_s))
    if not (0 <= status.free <= status.capacity and status.capacity > 0 and status.done_seq >= 0):
        raise ValueError("inconsistent buffer state")
    return status


def _parse_pos(text: str) -> dict[str, float]:
    words = text.split()
    if words[0] != "POS" or len(words) != 1 + len(AXES):
        raise ValueError("not a POS reply")
    pos = {}
    for axis, word in zip(AXES, words[1:], strict=True):
        if word[0] != axis:
            raise ValueError(f"expected axis {axis}")
        value = float(word[1:])
        if not math.isfinite(value):
            raise ValueError("non-finite position")
        pos[axis] = value
    return pos


class SerialMachineLink:
    """The thesis' RS-232 controller link (legacy protocol) over pyserial (a COM port, or ``socket://``)."""

    def __init__(
        self,
        channel: LineChannel,
        poll_s: float = 0.5,
        sleep: Callable[[float], None] = time.sleep,
        max_idle_polls: int = 100_000,
    ) -> None:
        self._io = channel
        self.poll_s = poll_s
        self.sleep = sleep
        self.max_idle_polls = max_idle_polls
        self._seq = 0

    @classmethod
    def open(
        cls,
        url: str,
        timeout_s: float = 2.0,
        poll_s: float = 0.5,
        sleep: Callable[[float], None] = time.sleep,
        max_idle_polls: int = 100_000,
        policy: RetryPolicy | None = None,
    ) -> SerialMachineLink:
        """Return a link on a serial device or pyserial URL."""
        port = SerialPort.open(url, timeout_s=timeout_s)
        return cls(LineChannel(port, "controller", policy, sleep), poll_s, sleep, max_idle_polls)

    @property
    def channel(self) -> LineChannel:
        """Return the line channel (shared with the probe, which reports through the controller)."""
        return self._io

    def status(self) -> ControllerStatus:
        """Return the controller's buffer state."""
        return self._io.query("STAT?", _parse_stat)

    def buffer_free(self) -> int:
        """Return the number of free blocks in the controller's buffer."""
        return self.status().free

    def position(self) -> dict[str, float]:
        """Return the axis positions (X, Y, Z mm; A, B deg)."""
        return self._io.query("POS?", _parse_pos)

    def _send_block(self, code: str) -> bool:
        seq = self._seq + 1

        def parse(text: str) -> bool:
            if text == "ERR FULL":
                return False
            if text != f"ACK {seq}":
                raise ValueError(f"expected ACK {seq}")
            return True

        accepted = self._io.query(f"BLK {seq} {code}", parse)
        if accepted:
            self._seq = seq
        return accepted

    def send_program(
        self,
        lines: Iterable[str],
        low_water: int = 4,
        high_water: int | None = None,
        wait: bool = True,
    ) -> StreamReport:
        """Stream ``lines``: refill to high_water whenever the queue has drained to low_water."""
        if low_water < 0:
            raise ValidationError("low_water must be >= 0")
        blocks = (ln.strip() for ln in lines)
        pending = next(blocks, None)
        while pending is not None and not carries_code(pending):
            pending = next(blocks, None)
        sent = polls = starved = 0
        min_free: int | None = None
        idle = 0
        while pending is not None:
            status = self.status()
            polls += 1
            min_free = status.free if min_free is None else min(min_free, status.free)
            top = status.capacity if high_water is None else min(high_water, status.capacity)
            if low_water >= top:
                raise ValidationError(f"low_water ({low_water}) must be below the high-water mark ({top})")
            if status.queued == 0 and sent > 0:
                starved += 1
            if status.queued > low_water:
                idle += 1
                if idle > self.max_idle_polls:
                    raise InstrumentError("controller buffer is not draining")
                self.sleep(self.poll_s)
                continue
            idle = 0
            queued = status.queued
            while pending is not None and queued < top:
                if not self._send_block(pending):
                    break  # the controller says full after all: poll again
                sent += 1
                queued += 1
                pending = next(blocks, None)
                while pending is not None and not carries_code(pending):
                    pending = next(blocks, None)
        if wait:
            self.wait_done()
        return StreamReport(blocks_sent=sent, polls=polls, min_free_seen=min_free or 0, starved=starved)

    def wait_done(self) -> None:
        """Return once every block sent so far has been executed."""
        for _ in range(self.max_idle_polls):
            if self.status().done_seq >= self._seq:
                return
            self.sleep(self.poll_s)
        raise InstrumentError("controller did not finish the program")

    def close(self) -> None:
        """Close the serial link."""
        self._io.close()
