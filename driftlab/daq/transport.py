"""Byte ports (pyserial, pyvisa) and the line channel every text-protocol driver talks through.

The seam is deliberately at the byte level (:class:`RawPort`): the real ports wrap a
``serial.Serial`` or a pyvisa message-based resource, and the tests' expected-protocol
helper implements the same two calls, so a driver test asserts the exact bytes on the wire.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, runtime_checkable

import serial

from driftlab.daq.retry import GarbledReply, RetryPolicy, TransportTimeout, call_with_retry
from driftlab.errors import InstrumentError, ValidationError

if TYPE_CHECKING:
    from pyvisa import ResourceManager

T = TypeVar("T")

TERMINATOR = b"\n"


@runtime_checkable
class RawPort(Protocol):
    """A byte stream to one instrument: write bytes, read one terminated line."""

    def write(self, data: bytes) -> None:
        """Send ``data`` exactly as given."""

    def read_line(self) -> bytes:
        """Return the next line including its terminator; raise TransportTimeout if none comes."""

    def discard_input(self) -> None:
        """Drop any bytes already received but not read (used before a retry)."""

    def close(self) -> None:
        """Release the port."""


class SerialPort:
    """RawPort over pyserial (a COM port, or a ``socket://`` / ``loop://`` URL), through its public API only.

    pyserial's ``read_until`` reads a line byte by byte (a select and a recv per byte on
    ``socket://``). Lines are read in chunks instead: wait for one byte with the time left of the
    line's timeout, then take whatever else has arrived with a non-blocking read (``timeout = 0``),
    keeping bytes past the terminator for the next line.
    """

    CHUNK = 65536

    def __init__(self, serial_obj: Any) -> None:
        self._ser = serial_obj
        self._buf = b""  # bytes received past the last line returned
        self._timeout = serial_obj.timeout  # the port's timeout per line (None: wait for ever)

    @classmethod
    def open(cls, url: str, timeout_s: float = 2.0, baudrate: int = 9600) -> SerialPort:
        """Return a port opened with ``serial.serial_for_url``; raise InstrumentError if it fails."""
        try:
            ser = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise InstrumentError(f"cannot open serial port {url}: {exc}") from exc
        return cls(ser)

    def write(self, data: bytes) -> None:
        """Send ``data`` and flush it out of the OS buffer."""
        try:
            self._ser.write(data)
            self._ser.flush()
        except (serial.SerialException, OSError) as exc:
            raise TransportTimeout(f"serial write failed: {exc}") from exc

    def read_line(self) -> bytes:
        """Return one ``\\n``-terminated line; raise TransportTimeout on a short read or a closed port."""
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        try:
            while TERMINATOR not in self._buf:
                left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
                self._ser.timeout = left
                first = self._ser.read(1)  # blocks until a byte comes or the line's time is up
                if not first:
                    partial, self._buf = self._buf, b""
                    raise TransportTimeout("timeout waiting for reply" + (f" (partial {partial!r})" if partial else ""))
                self._ser.timeout = 0  # non-blocking: whatever has already arrived
                self._buf += first + self._ser.read(self.CHUNK)
        except serial.SerialException as exc:
            self._buf = b""
            what = "connection closed by the instrument" if "disconnected" in str(exc) else f"serial read failed: {exc}"
            raise TransportTimeout(what) from exc
        except OSError as exc:
            raise TransportTimeout(f"serial read failed: {exc}") from exc
        finally:
            self._ser.timeout = self._timeout
        line, _, self._buf = self._buf.partition(TERMINATOR)
        return line + TERMINATOR

    def discard_input(self) -> None:
        """Drop unread received bytes."""
        self._buf = b""
        self._ser.reset_input_buffer()

    def close(self) -> None:
        """Close the serial port."""
        self._ser.close()


def _socket_nodelay(resource: Any) -> None:
    """Turn Nagle's algorithm off on a ``TCPIP::...::SOCKET`` session, as VISA does by default.

    VPP-4.3 (The VISA Library, VI_ATTR_TCPIP_NODELAY) makes VI_TRUE the default: a raw socket
    carries short SCPI commands, and a command followed at once by a query (a setting and its
    ``SYST:ERR?``) would otherwise wait for the instrument's delayed ACK (about 40 ms on Linux)
    before the query leaves. pyvisa-py 0.8 opens SOCKET sessions with the algorithm on and does
    not wire that attribute's setter (``set_visa_attribute`` raises its UnknownAttribute), so
    the option is set on the session's socket where the backend exposes one; other backends
    (NI-VISA, Keysight IO) already follow the default.
    """
    if not str(getattr(resource, "resource_name", "")).upper().endswith("::SOCKET"):
        return
    sessions = getattr(getattr(resource, "visalib", None), "sessions", None)
    session = sessions.get(resource.session) if isinstance(sessions, dict) else None
    sock = getattr(session, "interface", None)
    if isinstance(sock, socket.socket):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class VisaPort:
    """RawPort over a pyvisa message-based resource (GPIB, or TCPIP SOCKET for the simulator)."""

    def __init__(self, resource: Any) -> None:
        self._res = resource
        self._res.read_termination = TERMINATOR.decode()
        self._res.write_termination = ""
        _socket_nodelay(resource)

    @classmethod
    def open(
        cls, address: str, timeout_s: float = 2.0, resource_manager: Any | None = None, library: str | None = None
    ) -> VisaPort:
        """Return a port on ``address`` via pyvisa: the given manager, else one on ``library``
        (DRIFTLAB_VISA_LIBRARY)."""
        # lazy: pyvisa adds 0.13 s to `import driftlab.daq.transport` (measured); serial links never need it
        import pyvisa

        rm = resource_manager or visa_resource_manager(library)
        try:
            res = rm.open_resource(address)
        except (pyvisa.Error, OSError, ValueError) as exc:
            raise InstrumentError(f"cannot open VISA resource {address}: {exc}") from exc
        res.timeout = timeout_s * 1000.0
        return cls(res)

    def write(self, data: bytes) -> None:
        """Send ``data`` unchanged (no termination added by pyvisa)."""
        # lazy: pyvisa adds 0.13 s to `import driftlab.daq.transport` (measured); serial links never need it
        import pyvisa

        try:
            self._res.write_raw(data)
        except (pyvisa.errors.VisaIOError, OSError) as exc:
            raise TransportTimeout(f"VISA write failed: {exc.__class__.__name__}") from exc

    def read_line(self) -> bytes:
        """Return one terminated line; raise TransportTimeout when the VISA read times out."""
        # lazy: pyvisa adds 0.13 s to `import driftlab.daq.transport` (measured); serial links never need it
        import pyvisa

        try:
            data = self._res.read_raw()
        except pyvisa.errors.VisaIOError as exc:
            raise TransportTimeout("timeout waiting for reply") from exc
        except OSError as exc:
            raise TransportTimeout(f"VISA read failed: {exc}") from exc
        if not data.endswith(TERMINATOR):
            raise GarbledReply(f"unterminated reply {data[:40]!r}")
        return bytes(data)

    def discard_input(self, drain_reads: int = 8, drain_timeout_ms: float = 10.0) -> None:
        """Drop unread bytes: the session's buffer, then whatever arrives within a few short reads."""
        # lazy: pyvisa adds 0.13 s to `import driftlab.daq.transport` (measured); serial links never need it
        import pyvisa
        from pyvisa.constants import BufferOperation

        # Not viClear: pyvisa-py's clear() spins forever on a socket the peer has closed.
        try:
            self._res.flush(BufferOperation.discard_read_buffer_no_io)
        except (pyvisa.errors.VisaIOError, OSError, NotImplementedError):
            pass
        saved = self._res.timeout
        self._res.timeout = drain_timeout_ms
        try:
            for _ in range(drain_reads):
                try:
                    if not self._res.read_raw():
                        break
                except (pyvisa.errors.VisaIOError, OSError):
                    break
        finally:
            self._res.timeout = saved

    def close(self) -> None:
        """Close the VISA session."""
        self._res.close()


def visa_library_spec(library: str | None = None) -> str:
    """Return the pyvisa backend spec to use: ``library``, else DRIFTLAB_VISA_LIBRARY; checked, one-line errors."""
    # lazy: driftlab.config (pydantic-settings) adds 0.10 s to `import driftlab.daq.transport` (measured)
    from driftlab.config import get_settings

    spec = (library if library is not None else get_settings().visa_library).strip() or "@py"
    if spec in ("@py", "@ivi", "@sim"):
        return spec
    if spec.endswith("@sim"):  # FILE.yaml@sim: pyvisa-sim with the instruments defined in FILE.yaml
        path = spec[: -len("@sim")]
        if not Path(path).is_file():
            raise ValidationError(f"VISA library {spec!r}: no such pyvisa-sim definitions file {path}")
        return spec
    if spec.startswith("@"):
        raise ValidationError(
            f"VISA library {spec!r}: use @py, @sim, FILE.yaml@sim, @ivi or the path of a vendor VISA library"
        )
    if not Path(spec).is_file():
        raise ValidationError(f"VISA library {spec!r}: no such file (give the path of the vendor's VISA library)")
    return spec


def visa_resource_manager(library: str | None = None) -> ResourceManager:
    """Return a pyvisa ResourceManager on the configured backend (pyvisa-py, pyvisa-sim, or a vendor VISA)."""
    # lazy: pyvisa adds 0.13 s to `import driftlab.daq.transport` (measured); serial links never need it
    import pyvisa

    spec = visa_library_spec(library)
    try:
        return pyvisa.ResourceManager(spec)
    except (pyvisa.Error, OSError, ValueError) as exc:
        hint = " (the @sim backend needs the pyvisa-sim package)" if spec.endswith("@sim") else ""
        raise InstrumentError(f"cannot load VISA library {spec!r}: {' '.join(str(exc).split())}{hint}") from exc


def close_quietly(port: RawPort | None) -> None:
    """Close a port whose line may already be gone (a dropped connection): a failing close is ignored."""
    if port is None:
        return
    try:
        port.close()
    except Exception:  # noqa: BLE001 - the line is gone anyway
        pass


def open_port(address: str, timeout_s: float = 2.0) -> RawPort:
    """Return a RawPort for a VISA resource name (``GPIB0::..``, ``TCPIP0::..``) or a serial URL/device."""
    if "::" in address:
        return VisaPort.open(address, timeout_s=timeout_s)
    return SerialPort.open(address, timeout_s=timeout_s)


class LineChannel:
    """ASCII line exchanges with one instrument, each validated and retried with backoff."""

    def __init__(
        self,
        port: RawPort,
        name: str = "instrument",
        policy: RetryPolicy | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.port = port
        self.name = name
        self.policy = policy or RetryPolicy()
        self.sleep = sleep

    def _exchange(self, command: str, parse: Callable[[str], T]) -> T:
        self.port.write(command.encode("ascii") + TERMINATOR)
        raw = self.port.read_line()
        try:
            text = raw[: -len(TERMINATOR)].decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise GarbledReply(f"undecodable reply to {command!r}: {raw[:40]!r}") from exc
        try:
            return parse(text)
        except (ValueError, IndexError, KeyError) as exc:
            raise GarbledReply(f"invalid reply to {command!r}: {text[:40]!r} ({exc})") from exc

    def query(self, command: str, parse: Callable[[str], T]) -> T:
        """Return ``parse(reply)`` for ``command``; retried, then InstrumentError if it never validates."""
        return call_with_retry(
            lambda: self._exchange(command, parse),
            what=f"{self.name} {command.split(' ', 1)[0]}",
            policy=self.policy,
            sleep=self.sleep,
            before_retry=self.port.discard_input,
        )

    def query_once(self, command: str, parse: Callable[[str], T]) -> T:
        """Return ``parse(reply)`` for a query that must not be repeated (it changes the instrument's state,
        e.g. SCPI ``DATA:REMove?``); any fault is one InstrumentError, never a retry."""
        return call_with_retry(
            lambda: self._exchange(command, parse),
            what=f"{self.name} {command.split(' ', 1)[0]}",
            policy=RetryPolicy(attempts=1),
            sleep=self.sleep,
        )

    def write(self, command: str) -> None:
        """Send a command that has no reply (SCPI settings); a failed write is retried, then InstrumentError."""

        def send() -> None:
            self.port.write(command.encode("ascii") + TERMINATOR)

        call_with_retry(send, what=f"{self.name} {command.split(' ', 1)[0]}", policy=self.policy, sleep=self.sleep)

    def command(self, command: str, ok: str = "OK") -> None:
        """Send a setting command and require the acknowledgement ``ok``."""

        def expect_ok(text: str) -> None:
            if text != ok:
                raise ValueError(f"expected {ok!r}")

        self.query(command, expect_ok)

    def close(self) -> None:
        """Close the underlying port."""
        self.port.close()
