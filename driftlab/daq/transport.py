"""Byte ports (pyserial, pyvisa) and the line channel every text-protocol driver talks through.

The seam is deliberately at the byte level (:class:`RawPort`): the real ports wrap a
``serial.Serial`` or a pyvisa message-based resource, and the tests' expected-protocol
helper implements the same two calls, so a driver test asserts the exact bytes on the wire.
"""

from __future__ import annotations

import select
import socket
import time
from collections.abc import Callable
from typing import Any, Protocol, TypeVar, runtime_checkable

from driftlab.daq.retry import GarbledReply, RetryPolicy, TransportTimeout, call_with_retry
from driftlab.errors import InstrumentError

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
    """RawPort over pyserial (a COM port, or a ``socket://`` / ``loop://`` URL)."""

    def __init__(self, serial_obj: Any) -> None:
        self._ser = serial_obj
        self._buf = b""  # bytes received past the last line returned
        # pyserial reads a line byte by byte (a select and a recv per byte on socket://); on a
        # network port the socket is read in chunks instead, with the port's timeout per line
        sock = getattr(serial_obj, "_socket", None)
        self._sock = sock if isinstance(sock, socket.socket) else None

    @classmethod
    def open(cls, url: str, timeout_s: float = 2.0, baudrate: int = 9600) -> SerialPort:
        """Return a port opened with ``serial.serial_for_url``; raise InstrumentError if it fails."""
        import serial

        try:
            ser = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise InstrumentError(f"cannot open serial port {url}: {exc}") from exc
        return cls(ser)

    def write(self, data: bytes) -> None:
        """Send ``data`` and flush it out of the OS buffer."""
        import serial

        try:
            self._ser.write(data)
            self._ser.flush()
        except (serial.SerialException, OSError) as exc:
            raise TransportTimeout(f"serial write failed: {exc}") from exc

    def _read_line_socket(self, sock: socket.socket) -> bytes:
        """Return one line read from a network port in chunks (leftover bytes kept for the next line)."""
        timeout = self._ser.timeout
        deadline = None if timeout is None else time.monotonic() + timeout
        while TERMINATOR not in self._buf:
            left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            ready, _, _ = select.select([sock], [], [], left)
            chunk = sock.recv(65536) if ready else b""
            if not chunk:
                partial, self._buf = self._buf, b""
                if ready:
                    raise TransportTimeout("connection closed by the instrument")
                raise TransportTimeout("timeout waiting for reply" + (f" (partial {partial!r})" if partial else ""))
            self._buf += chunk
        line, _, self._buf = self._buf.partition(TERMINATOR)
        return line + TERMINATOR

    def read_line(self) -> bytes:
        """Return one ``\\n``-terminated line; raise TransportTimeout on a short read."""
        import serial

        if self._sock is not None:
            try:
                return self._read_line_socket(self._sock)
            except OSError as exc:
                raise TransportTimeout(f"serial read failed: {exc}") from exc
        try:
            data = self._ser.read_until(TERMINATOR)
        except (serial.SerialException, OSError) as exc:
            raise TransportTimeout(f"serial read failed: {exc}") from exc
        if not data.endswith(TERMINATOR):
            raise TransportTimeout("timeout waiting for reply" + (f" (partial {data!r})" if data else ""))
        return bytes(data)

    def discard_input(self) -> None:
        """Drop unread received bytes."""
        self._buf = b""
        self._ser.reset_input_buffer()

    def close(self) -> None:
        """Close the serial port."""
        self._ser.close()


class VisaPort:
    """RawPort over a pyvisa message-based resource (GPIB, or TCPIP SOCKET for the simulator)."""

    def __init__(self, resource: Any) -> None:
        self._res = resource
        self._res.read_termination = TERMINATOR.decode()
        self._res.write_termination = ""

    @classmethod
    def open(
        cls, address: str, timeout_s: float = 2.0, resource_manager: Any | None = None
    ) -> VisaPort:
        """Return a port on ``address`` via pyvisa (pyvisa-py backend unless a manager is given)."""
        import pyvisa

        try:
            rm = resource_manager or pyvisa.ResourceManager("@py")
            res = rm.open_resource(address)
        except (pyvisa.Error, OSError, ValueError) as exc:
            raise InstrumentError(f"cannot open VISA resource {address}: {exc}") from exc
        res.timeout = timeout_s * 1000.0
        return cls(res)

    def write(self, data: bytes) -> None:
        """Send ``data`` unchanged (no termination added by pyvisa)."""
        import pyvisa

        try:
            self._res.write_raw(data)
        except (pyvisa.errors.VisaIOError, OSError) as exc:
            raise TransportTimeout(f"VISA write failed: {exc.__class__.__name__}") from exc

    def read_line(self) -> bytes:
        """Return one terminated line; raise TransportTimeout when the VISA read times out."""
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

    def command(self, command: str, ok: str = "OK") -> None:
        """Send a setting command and require the acknowledgement ``ok``."""

        def expect_ok(text: str) -> None:
            if text != ok:
                raise ValueError(f"expected {ok!r}")

        self.query(command, expect_ok)

    def close(self) -> None:
        """Close the underlying port."""
        self.port.close()
