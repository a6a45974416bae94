"""A control reading a tape over RS-232, in simulated time: the tests' counterpart of the DNC drip feed.

Written from the manuals, not from driftlab's code (it imports nothing of driftlab):

* the line: one character is a start bit, the data bits, the parity bit and the stop bits, sent one
  after another at the baud rate (FANUC Series 0i Connection Manual B-63503EN/02 §5.3, "start-stop
  method"); what the host writes waits in the serial server's queue until the UART sends it;
* the handshake (FANUC Series 15i Remote Buffer Descriptions B-63322EN-1/01, protocol B): the control
  sends DC1 to start the host; DC3 once its free space falls below a set value; DC1 once its data
  fall below a set value; on a reset DC3 then SYN;
* the tape: 7-bit ISO code; blank leader (NUL) and, with Haas Setting 14 "DC CODES", DC2 before
  the data and DC4 after it; ``%`` then the blocks, each ended by the end of block (LF, or CR LF: Haas
  Setting 25), then ``%`` (Haas 96-8000 "RS-232"; Mitsubishi M700V §3.1 tape codes). A HEIDENHAIN TNC
  (TNC 306/406 Technical Manual §2.4.1, §3.1.4) takes NUL NUL, lines ended CR LF, then ETX, and
  answers EOT; it starts the transfer with DC1 and stops it with DC3;
* a character arriving when the buffer is full is lost (a FANUC 087 "buffer overflow" alarm); a
  parity error (a byte with the 8th bit set on a 7-bit line) stops the read (Haas 96-8000).

The control executes one block every ``block_s`` from its buffer; a feed hold stops execution for a
while (the buffer then fills up and DC3 holds the sender for as long as it lasts).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

NUL, ETX, EOT, SYN = 0x00, 0x03, 0x04, 0x16
DC1, DC2, DC3, DC4 = 0x11, 0x12, 0x13, 0x14


@dataclass
class Tape:
    """What one family's manual says a tape looks like."""

    eob: bytes
    record_marks: bool = True  # ``%`` ... ``%``
    end: int | None = None  # a character that ends the transfer (HEIDENHAIN: ETX)
    starts_with_dc1: bool = False  # the control sends DC1 to start the transfer
    ignored_outside: bytes = bytes([NUL, DC2, DC4])  # leader and punch codes, before and after the record


#: from the manuals (module docstring)
TAPES = {
    "generic": Tape(b"\n"),
    "haas": Tape(b"\r\n"),
    "haas-dc": Tape(b"\r\n"),
    "fanuc": Tape(b"\n", starts_with_dc1=True),
    "heidenhain": Tape(b"\r\n", record_marks=False, end=ETX, starts_with_dc1=True),
}


class Clock:
    """Simulated time: ``sleep`` advances it and lets the control run up to the new time."""

    def __init__(self) -> None:
        self.t = 0.0
        self.controls: list[TapeControl] = []

    def now(self) -> float:
        """Return the simulated time (s)."""
        return self.t

    def sleep(self, dt: float) -> None:
        """Advance the time by ``dt`` (s)."""
        self.t += max(dt, 0.0)
        for c in self.controls:
            c.advance(self.t)


@dataclass
class TapeControl:
    """The control at the far end of the line (module docstring)."""

    clock: Clock
    tape: Tape
    baud: int = 115200
    bits: int = 10  # start + 8 data + 1 stop (8N1)
    buffer_bytes: int = 1024
    block_s: float = 0.005
    dc3_free: int = 128  # DC3 once fewer bytes than this are free
    dc1_fill: int = 512  # DC1 once fewer bytes than this are held
    start_at_s: float = 0.0  # when the operator starts the read (DC1, for controls that start the transfer)
    holds: list[tuple[float, float]] = field(default_factory=list)  # (start, duration) of feed holds
    reset_at_s: float | None = None

    def __post_init__(self) -> None:
        self.clock.controls.append(self)
        self.char_s = self.bits / self.baud
        self._wire: deque[tuple[float, int]] = deque()  # (arrival at the control, byte)
        self._uart_free = 0.0
        self._back: deque[tuple[float, int]] = deque()  # (arrival at the host, byte)
        self._back_free = 0.0
        self.buffer: deque[bytes] = deque()  # complete blocks, in order
        self.held = 0  # bytes held: complete blocks plus the line being received
        self.line = bytearray()
        self.blocks: list[str] = []  # executed, in order
        self.eobs: set[bytes] = set()
        self.overflow = 0
        self.parity_errors = 0
        self.early = 0  # bytes that arrived before the control started the transfer
        self.starved = 0
        self.in_record = False
        self.ended = False
        self.end_executed = False
        self.xoff = False
        self.max_held = 0
        self.dc3_sent = 0
        self.overrun = 0  # the most bytes that arrived while a DC3 had reached the host
        self._dc3_at_host: float | None = None
        self._since_dc3 = 0
        self._next_exec: float | None = None
        self._started = not self.tape.starts_with_dc1
        self._due = 0.0  # when the next block is due (the one after the last executed)
        self._start_sent = False
        self._reset_done = False
        self._t = 0.0

    # -- the host's side of the line
    def write(self, data: bytes) -> None:
        """The host writes ``data`` now: each byte arrives one character time after the one before."""
        self.advance(self.clock.t)
        for b in data:
            self._uart_free = max(self._uart_free, self.clock.t) + self.char_s
            self._wire.append((self._uart_free, b))

    def read(self) -> bytes:
        """Return what the control has sent that has reached the host by now."""
        self.advance(self.clock.t)
        out = bytearray()
        while self._back and self._back[0][0] <= self.clock.t:
            out.append(self._back.popleft()[1])
        return bytes(out)

    def _send(self, t: float, b: int) -> None:
        self._back_free = max(self._back_free, t) + self.char_s
        self._back.append((self._back_free, b))
        if b == DC3:
            self.dc3_sent += 1
            self._dc3_at_host = self._back_free
            self._since_dc3 = 0
        elif b == DC1:
            self._dc3_at_host = None

    # -- the control
    def advance(self, t: float) -> None:
        """Run the control up to time ``t``: characters arriving, blocks executing, holds, the handshake."""
        while True:
            events = []
            if self._wire:
                events.append((self._wire[0][0], 0))
            if self._next_exec is not None:
                events.append((self._exec_time(self._next_exec), 1))
            if not self._start_sent and self.tape.starts_with_dc1:
                events.append((self.start_at_s, 2))
            if self.reset_at_s is not None and not self._reset_done:
                events.append((self.reset_at_s, 3))
            events = [e for e in events if e[0] <= t]
            if not events:
                break
            when, kind = min(events)
            self._t = when
            if kind == 0:
                self._receive(when, self._wire.popleft()[1])
            elif kind == 1:
                self._execute(when)
            elif kind == 2:
                self._start_sent = self._started = True
                self._send(when, DC1)
            else:
                self._reset_done = True
                self._send(when, DC3)
                self._send(when, SYN)
        self._t = t

    def _exec_time(self, t: float) -> float:
        """Return when a block due at ``t`` runs, after any feed hold covering it."""
        for h0, dur in self.holds:
            if h0 <= t < h0 + dur:
                return h0 + dur
        return t

    def _receive(self, t: float, b: int) -> None:
        if self._dc3_at_host is not None and t > self._dc3_at_host + self.char_s:
            self._since_dc3 += 1  # sent after the host had the DC3
            self.overrun = max(self.overrun, self._since_dc3)
        if not self._started:
            self.early += 1
            return
        if b & 0x80:
            self.parity_errors += 1
            return
        if self.ended:
            return
        if not self.in_record:
            if b in self.tape.ignored_outside:
                return
            if self.tape.record_marks:
                if b == ord("%"):
                    self.in_record = True
                    self.line = bytearray(b"%")  # its end of block follows
                    self.held += 1
                return
            self.in_record = True
        if self.tape.end is not None and b == self.tape.end:
            self.ended = True
            self._send(t, EOT)
            return
        if self.held >= self.buffer_bytes:
            self.overflow += 1
            return
        self.line.append(b)
        self.held += 1
        self.max_held = max(self.max_held, self.held)
        if self.buffer_bytes - self.held < self.dc3_free and not self.xoff:
            self.xoff = True
            self._send(t, DC3)
        if b == self.tape.eob[-1]:
            self._end_of_block(t)

    def _end_of_block(self, t: float) -> None:
        text = bytes(self.line)
        eob = self.tape.eob if text.endswith(self.tape.eob) else (b"\r\n" if text.endswith(b"\r\n") else text[-1:])
        block = text[: len(text) - len(eob)]
        self.eobs.add(eob)
        self.line = bytearray()
        if block == b"%":
            if self.blocks or self.buffer:  # the closing mark: the record ends here
                self.ended = True
                self.buffer.append(text)
            else:  # the opening mark's end of block
                self.held -= len(text)
            return
        self.buffer.append(text)
        if self._next_exec is None and not self.end_executed:
            if self.blocks and t > self._due:
                self.starved += 1  # the block came after it was due: the control waited for it
            self._next_exec = max(t, self._due) if self.blocks else t

    def _execute(self, t: float) -> None:
        text = self.buffer.popleft()
        self.held -= len(text)
        if text.rstrip(b"\r\n") == b"%":
            self.end_executed = True
            self._next_exec = None
            return
        self.blocks.append(text[: len(text) - len(self.tape.eob)].decode("ascii"))
        self._due = t + self.block_s
        self._next_exec = self._due if self.buffer else None
        if self.xoff and self.held < self.dc1_fill:
            self.xoff = False
            self._send(t, DC1)


class TapeLine:
    """The host's end of the line to a ``TapeControl`` (a TCP serial server: the handshake in band)."""

    in_band = True

    def __init__(self, control: TapeControl) -> None:
        self.control = control

    def write(self, data: bytes) -> None:
        """Queue ``data`` on the line."""
        self.control.write(data)

    def read_available(self) -> bytes:
        """Return what the control has sent."""
        return self.control.read()

    def out_waiting(self) -> int:
        """A socket cannot tell."""
        return 0

    def flow_control(self, on: bool) -> None:
        """In band: nothing to switch."""

    def close(self) -> None:
        """Nothing to release."""
