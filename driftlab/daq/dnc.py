"""DNC drip feed: a program sent to the control's serial port as a tape, paced by its DC1/DC3 handshake.

What a shop's control reads over RS-232 (thesis ch. 7.2: the PC "would wait for the machine tool's
buffer to reach a low point before sending more data"). There is no read-back on such a line: the
control executes what arrives, stops the sender with DC3 (XOFF) when its buffer is nearly full and
resumes it with DC1 (XON); a feed hold is simply a DC3 that lasts. The manuals followed:

* **ISO tape framing and code**: 7-bit ISO code (ISO 646 / the ISO 840 tape code), a leader of
  NUL (blank tape), ``%`` (start of record) and its end of block, the blocks, ``%`` (end of record).
  Mitsubishi M700V Programming Manual §3.1 "Tape codes": ISO end of block is LF (or CR LF), ``%`` the
  end of record; FANUC Series 0i Connection Manual (Hardware) B-63503EN/02 §5.3.
* **haas** - Haas Mill Operator's Manual 96-8000 (June 1999), "RS-232": programs begin and end
  with ``%``; Setting 25 "EOB pattern" (CR LF default); Settings 11-13, 37: baud, parity, stop and
  data bits (7E2 is the shop setting a CAM vendor's guide lists: BobCAD "Haas controller RS-232
  information"); Setting 14 "Synchronization" XON/XOFF. **haas-dc** - Setting 14 "DC CODES": the
  full DC1-DC4 tape sequence, DC2 (0x12) before all other data and DC4 (0x14) after it.
* **fanuc** - FANUC Series 0i Connection Manual B-63503EN/02 §5.3 (ISO code plus DC1-DC4: DC1
  "tape reader start", DC3 "tape reader stop"; a character is 8 information bits including the
  parity bit and 2 stop bits: 7E2) and FANUC Series 15i Remote Buffer Descriptions B-63322EN-1/01
  protocol B (the control sends DC1, the host starts; DC3 when its free space falls below a set value,
  DC1 when the data fall below one; after a reset or an alarm it sends DC3 then SYN (reset) or NAK
  (alarm) and the host stops). End of block LF.
* **heidenhain** - HEIDENHAIN TNC 306/406 Technical Manual (3/97) §2.4.1 "Standard transmission
  protocol" and TNC 426/430 Technical Manual §8.3: EXT1 with software handshake (MP5020 bit 3,
  "transmission stop through DC3"); reading a file in, the TNC first outputs DC1, the peripheral sends
  NUL NUL, the lines each ended CR LF, and ETX after the last; the TNC stops it with DC3 and resumes it
  with DC1, and answers EOT when done. No ``%`` record marks (a TNC ISO program carries its own
  ``%NAME G71`` block).
* **generic** - ISO framing, end of block LF, 8N1, DC1/DC3.

Two transports, one pacing rule. A local serial device is opened with pyserial's ``xonxoff=True``:
the OS driver stops the UART on DC3 (termios IXON; pyserial ``serialposix``), and driftlab keeps at
most ``ahead_chars`` in the OS output queue (``out_waiting``), so nothing piles up ahead of the line.
A TCP serial server (``socket://``, rfc2217) carries the handshake in band (pyserial's
``protocol_socket`` ignores every port setting, xonxoff included): driftlab reads DC1/DC3 itself
and paces its writes at the line's character rate (start bit, data bits, parity, stop bits at
``baud``), at most ``ahead_chars`` ahead of the line, so a DC3 is honoured within about
``ahead_chars`` + 2 characters (the FANUC remote buffer's own overrun allowance is ten).
Blocks are pulled from the iterable only when the line can take them: a compensator's generator
corrects each block as late as the line allows, and the link's waits (``sleep``, a streamer's
``idle``) let it refresh the model and temperatures. A feed hold is waited out, never timed out.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import serial

from driftlab.daq.protocols import StreamReport
from driftlab.errors import InstrumentError, ValidationError

log = logging.getLogger(__name__)

NUL, ETX, EOT, NAK, SYN = 0x00, 0x03, 0x04, 0x15, 0x16
DC1, DC2, DC3, DC4 = 0x11, 0x12, 0x13, 0x14  # XON, punch on, XOFF, punch off (ISO 646 device controls)
#: the line settings accepted: data bits, parity (pyserial's constant), stop bits
LINES: dict[str, tuple[int, str, float]] = {
    "8N1": (8, serial.PARITY_NONE, 1),
    "7E1": (7, serial.PARITY_EVEN, 1),
    "7E2": (7, serial.PARITY_EVEN, 2),
}


@dataclass(frozen=True)
class Profile:
    """How one control family frames a tape and speaks the handshake (module docstring for the manuals)."""

    name: str
    eob: bytes
    line: str  # default line setting
    leader: bytes = b""
    record_marks: bool = True  # ``%`` before the first block and after the last
    wait_dc1: bool = False  # the control starts the transfer with DC1
    dc2_dc4: bool = False  # DC2 before all other data, DC4 after it
    trailer: bytes = b""  # after the last block (and its ``%``)
    #: bytes from the control that end the transfer, with what they mean
    aborts: dict[int, str] = field(default_factory=dict)

    def head(self) -> bytes:
        """Return what precedes the first block."""
        return (bytes([DC2]) if self.dc2_dc4 else b"") + self.leader + (b"%" + self.eob if self.record_marks else b"")

    def tail(self) -> bytes:
        """Return what follows the last block."""
        return (b"%" + self.eob if self.record_marks else b"") + self.trailer + (bytes([DC4]) if self.dc2_dc4 else b"")


PROFILES: dict[str, Profile] = {
    "generic": Profile("generic", b"\n", "8N1"),
    "haas": Profile("haas", b"\r\n", "7E2"),
    "haas-dc": Profile("haas-dc", b"\r\n", "7E2", dc2_dc4=True),
    "fanuc": Profile(
        "fanuc",
        b"\n",
        "7E2",
        leader=b"\x00" * 10,
        wait_dc1=True,
        aborts={SYN: "the control was reset (SYN)", NAK: "the control raised an alarm (NAK)"},
    ),
    "heidenhain": Profile(
        "heidenhain", b"\r\n", "7E2", leader=b"\x00\x00", record_marks=False, wait_dc1=True, trailer=bytes([ETX])
    ),
}


def profile(name: str) -> Profile:
    """Return the profile called ``name``; ValidationError naming the known ones."""
    try:
        return PROFILES[name]
    except KeyError:
        raise ValidationError(f"unknown DNC profile {name!r} (known: {', '.join(PROFILES)})") from None


def line_settings(text: str) -> tuple[int, str, float]:
    """Return (data bits, parity, stop bits) of ``8N1``, ``7E1`` or ``7E2``; ValidationError otherwise."""
    try:
        return LINES[text.upper()]
    except KeyError:
        raise ValidationError(f"--line must be one of {', '.join(LINES)}, got {text!r}") from None


def char_bits(line: str) -> int:
    """Return the bits one character takes on the line: start, data, parity, stop."""
    data, parity, stop = line_settings(line)
    return 1 + data + (0 if parity == serial.PARITY_NONE else 1) + int(stop)


_COMMENTS = re.compile(r"\([^)]*\)")


def carries_code(text: str) -> bool:
    """Return True for a program line a control must get: code left once comments are taken out (not blank,
    a comment alone, or a ``%`` mark)."""
    code = _COMMENTS.sub("", text).split(";", 1)[0].strip()
    return bool(code) and code != "%"


def unsendable(text: bytes) -> str | None:
    """Return why a program line cannot go down a 7-bit tape line (None when it can): a byte that is not
    printable ASCII (or tab), or a ``%`` inside a block (it would end the record)."""
    for i, b in enumerate(text):
        if not (0x20 <= b < 0x7F or b == 0x09):
            ch = "a control character" if b < 0x20 or b == 0x7F else "not 7-bit ASCII"
            return f"byte 0x{b:02x} at column {i + 1} is {ch} (a tape line carries printable ASCII only)"
    if b"%" in text and text.strip() != b"%":
        return "'%' inside a block would end the tape's record"
    return None


def encode_block(text: str, eob: bytes) -> bytes:
    """Return one block as sent: its 7-bit ASCII bytes and the end of block; ValidationError for anything else."""
    data = text.encode("ascii", "strict") if text.isascii() else b"\x80"
    why = unsendable(data)
    if why is not None:
        raise ValidationError(f"block {text[:40]!r}: {why}")
    return data + eob


# ----------------------------------------------------------------------------- ports


class DncPort(Protocol):
    """The byte line to the control: what ``DncLink`` needs of it."""

    #: True when the handshake arrives in the byte stream (a TCP serial server), False when the OS does it
    in_band: bool

    def write(self, data: bytes) -> None:
        """Queue ``data`` for the line."""

    def read_available(self) -> bytes:
        """Return the bytes the control has sent since the last call (never blocks)."""

    def out_waiting(self) -> int:
        """Return the bytes written but not yet on the line (0 when the port cannot tell)."""

    def flow_control(self, on: bool) -> None:
        """Let the OS honour DC1/DC3 (``on``) or pass them through (a local device; in band: nothing to do)."""

    def close(self) -> None:
        """Release the port."""


class SerialDncPort:
    """``DncPort`` over pyserial: a local device (OS XON/XOFF) or a ``socket://`` / ``rfc2217://`` URL (in band)."""

    def __init__(self, ser: Any, in_band: bool) -> None:
        self._ser = ser
        self.in_band = in_band

    @classmethod
    def open(cls, url: str, baud: int, line: str) -> SerialDncPort:
        """Return the port at ``url`` with the line's settings; InstrumentError when it cannot be opened."""
        data, parity, stop = line_settings(line)
        in_band = "://" in url
        try:
            ser = serial.serial_for_url(
                url,
                baudrate=baud,
                bytesize=data,
                parity=parity,
                stopbits=stop,
                xonxoff=False,  # on a local device, switched on once the control has started the transfer
                timeout=0,
                write_timeout=None,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise InstrumentError(f"cannot open serial port {url}: {exc}") from None
        return cls(ser, in_band)

    def write(self, data: bytes) -> None:
        """Write ``data`` (blocks while the OS holds the line on XOFF and its queue is full)."""
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as exc:
            raise InstrumentError(f"DNC line: write failed: {exc}") from None

    def read_available(self) -> bytes:
        """Return what has arrived (non-blocking)."""
        try:
            return bytes(self._ser.read(65536))
        except (serial.SerialException, OSError) as exc:
            raise InstrumentError(f"DNC line: read failed: {exc}") from None

    def out_waiting(self) -> int:
        """Return the OS output queue's length (TIOCOUTQ); 0 over a socket."""
        if self.in_band:
            return 0
        try:
            return int(self._ser.out_waiting)
        except (serial.SerialException, OSError, AttributeError):
            return 0

    def flow_control(self, on: bool) -> None:
        """Switch the OS's XON/XOFF on a local device (pyserial reconfigures the port)."""
        if not self.in_band:
            self._ser.xonxoff = on

    def close(self) -> None:
        """Close the port."""
        self._ser.close()


# ----------------------------------------------------------------------------- the link


@dataclass
class DncReport:
    """What a drip feed did besides the blocks: characters, holds, the handshake seen."""

    chars: int = 0
    dc3: int = 0
    dc1: int = 0
    held_s: float = 0.0
    longest_hold_s: float = 0.0


class DncLink:
    """A drip feed to one control (module docstring): ``send_program`` is the ``MachineLink`` call."""

    def __init__(
        self,
        port: DncPort,
        prof: Profile,
        baud: int = 9600,
        line: str | None = None,
        *,
        ahead_chars: int = 16,
        poll_s: float = 0.05,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not 50 <= baud <= 4_000_000:
            raise ValidationError(f"--baud must be between 50 and 4000000, got {baud}")
        if ahead_chars < 1:
            raise ValidationError("ahead_chars must be at least 1")
        self.port, self.profile, self.baud = port, prof, baud
        self.line = line or prof.line
        self.char_s = char_bits(self.line) / baud
        self.ahead_chars, self.poll_s = ahead_chars, poll_s
        self.clock, self.sleep = clock, sleep
        self.xoff = False
        self._line_busy_until = -float("inf")  # when the line will have sent what was written (in band)
        self.report = DncReport()
        self._hold_start: float | None = None

    @classmethod
    def open(cls, url: str, prof: Profile, baud: int = 9600, line: str | None = None, **kw: Any) -> DncLink:
        """Return a link on a serial device or pyserial URL with the profile's (or the given) line settings."""
        return cls(SerialDncPort.open(url, baud, line or prof.line), prof, baud, line, **kw)

    # -- the handshake
    def _poll(self) -> None:
        """Read what the control sent: DC3 stops, DC1 resumes, an abort code ends the transfer."""
        for b in self.port.read_available():
            b &= 0x7F  # 7-bit code: the parity bit of a 7-bit line read as 8 bits
            if b == DC3 and self.port.in_band:
                if not self.xoff:
                    self.report.dc3 += 1
                    self._hold_start = self.clock()
                self.xoff = True
            elif b == DC1 and self.port.in_band:
                if self.xoff:
                    self.report.dc1 += 1
                    self._end_hold()
                self.xoff = False
            elif b in self.profile.aborts:
                raise InstrumentError(f"DNC: {self.profile.aborts[b]}: the drip feed stopped")

    def _end_hold(self) -> None:
        if self._hold_start is not None:
            held = self.clock() - self._hold_start
            self.report.held_s += held
            self.report.longest_hold_s = max(self.report.longest_hold_s, held)
            self._hold_start = None

    def _wait_start(self) -> None:
        """Wait (without a limit) for the control's DC1 that starts the transfer."""
        told = False
        while True:
            for b in self.port.read_available():
                if b & 0x7F == DC1:
                    return
                if b & 0x7F in self.profile.aborts:
                    raise InstrumentError(f"DNC: {self.profile.aborts[b & 0x7F]} before the transfer started")
            if not told:
                log.warning("DNC: waiting for the control's DC1 (start the program input on the control)")
                told = True
            self.sleep(self.poll_s)

    def _room(self) -> int:
        """Return how many characters may be written now without running more than ``ahead_chars`` ahead."""
        if self.xoff:
            return 0
        if not self.port.in_band:
            return max(self.ahead_chars - self.port.out_waiting(), 0)
        ahead = max(self._line_busy_until - self.clock(), 0.0) / self.char_s
        return max(int(self.ahead_chars - ahead + 1e-9), 0)

    def _wait(self) -> None:
        """Wait until the line has room again (a hold is polled every ``poll_s``, for as long as it lasts)."""
        if self.xoff:
            self.sleep(self.poll_s)
            return
        if self.port.in_band:
            # wake when half the window has gone out
            due = self._line_busy_until - self.ahead_chars * self.char_s / 2 - self.clock()
        else:
            due = (self.port.out_waiting() - self.ahead_chars / 2) * self.char_s
        self.sleep(min(max(due, self.char_s), self.poll_s))

    def _put(self, data: bytes) -> None:
        """Write ``data`` as the line and the handshake allow."""
        while data:
            self._poll()
            n = self._room()
            if n <= 0:
                self._wait()
                continue
            chunk, data = data[:n], data[n:]
            self.port.write(chunk)
            if self.port.in_band:
                self._line_busy_until = max(self._line_busy_until, self.clock()) + len(chunk) * self.char_s
            self.report.chars += len(chunk)

    def _ready(self) -> None:
        """Return once the line can take a character (so a block pulled now is sent at once)."""
        while True:
            self._poll()
            if self._room() > 0:
                return
            self._wait()

    def send_program(
        self, lines: Iterable[str], low_water: int = 0, high_water: int | None = None, wait: bool = True
    ) -> StreamReport:
        """Drip-feed ``lines`` as a tape; return the blocks sent (the buffer marks are the control's own here)."""
        del low_water, high_water  # the control's DC1/DC3 are its buffer's marks
        prof = self.profile
        if prof.wait_dc1:
            self._wait_start()
        self.port.flow_control(True)
        self._put(prof.head())
        sent = 0
        blocks: Iterator[str] = iter(lines)
        while True:
            self._ready()  # the block is pulled (and corrected) only when the line can take it
            text = next(blocks, None)
            if text is None:
                break
            text = text.strip()
            if not carries_code(text):
                continue
            self._put(encode_block(text, prof.eob))
            sent += 1
        self._put(prof.tail())
        if wait:
            self.drain()
        self._end_hold()
        return StreamReport(blocks_sent=sent, polls=self.report.dc3, min_free_seen=0, starved=0)

    def drain(self) -> None:
        """Return once everything written has left (a hold at the end is waited out too)."""
        while True:
            self._poll()
            if self.port.in_band:
                left = self._line_busy_until - self.clock()
            else:
                left = self.port.out_waiting() * self.char_s
            if left <= 0:
                return
            self.sleep(min(max(left, self.char_s), self.poll_s))

    def position(self) -> dict[str, float]:
        """A drip feed has no read-back: the start pose is ``--start`` or home."""
        raise InstrumentError("a DNC drip feed cannot read the machine's position: give --start (default home)")

    def buffer_free(self) -> int:
        """A drip feed does not know the control's buffer (its DC1/DC3 say when to send)."""
        raise InstrumentError("a DNC drip feed cannot read the control's buffer")

    def close(self) -> None:
        """Close the line."""
        self.port.close()
