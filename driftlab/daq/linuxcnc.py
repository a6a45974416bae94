"""LinuxCNC through ``linuxcncrsh``: the machine link (MDI moves, positions) and G38.2 probing over TCP.

Written from LinuxCNC's own documentation and source, which are the protocol's reference:

* ``linuxcncrsh(1)`` (docs/src/man/man1/linuxcncrsh.1.adoc): the text protocol on TCP port 5007,
  ``hello <password> <client> [<version>]`` -> ``HELLO ACK <server> <version>``, ``set echo off``,
  ``set verbose on`` (then every set is answered ``SET <KEY> ACK`` or ``SET <KEY> NAK``),
  ``set enable <password>``, ``set wait_mode received|done``, ``set mode mdi``, ``set mdi <code>``,
  ``get abs_act_pos`` (``ABS_ACT_POS x y z a b c u v w``), ``get program_status``
  (``PROGRAM_STATUS IDLE|RUNNING|PAUSED``), ``get error`` (``ERROR OK`` or ``ERROR <text>``),
  ``get operator_display``, ``get estop``, ``get machine``, and the example session;
* src/emc/usr_intf/emcrsh.cc (the server): lines end in CR LF; diagnostics come as ``error: ...``
  / ``warning: ...`` lines before the ``NAK``; commands are echoed only while echo is on and the
  session linked, never the ``hello``; tests/linuxcncrsh/expected-telnet-output (a recorded
  session of the real server), from which the conformance tests take their exchanges;
* the G-code manual, G38.x: after probing #5061..#5069 hold the trip point (current work
  coordinates) and #5070 is 1 if the probe tripped; ``(DEBUG, ...)`` comments expand parameters
  into an operator-display message, which is how the result is read back over linuxcncrsh.

Safety: the driver never takes a machine out of E-stop or switches it on; it checks that the
operator has (``get estop``, ``get machine``) and refuses otherwise. Units: the driver programs in
millimetres (``G21``) and reads positions as LinuxCNC reports them in the machine's units, so the
INI's ``LINEAR_UNITS`` must be mm.

A dropped connection is reopened and the session negotiated again before the next command; a
read-only query is then repeated, a motion command never is (whether the controller received it
is unknown), it fails with a one-line :class:`InstrumentError`.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from driftlab.daq.protocols import StreamReport
from driftlab.daq.retry import GarbledReply, TransientError
from driftlab.daq.transport import RawPort, SerialPort, close_quietly
from driftlab.errors import InstrumentError, ValidationError
from driftlab.vocabulary import AXES

if TYPE_CHECKING:
    from driftlab.daq.probe import SphereMeasurement

DEFAULT_PORT = 5007
PROTOCOL_VERSION = "1.1"
#: the probe result parameters (G-code manual, G38.x): trip point X Y Z and success flag
PROBE_PARAMS = "#5061 #5062 #5063 #5070"
_COMMENT = re.compile(r"\([^)]*\)|;.*$")


def linuxcnc_url(resource: str) -> str:
    """Return the pyserial URL of a linuxcncrsh resource: ``host``, ``host:port`` or ``socket://host:port``."""
    text = resource.strip()
    if text.startswith("socket://"):
        return text
    if not text or "/" in text:
        raise ValidationError(f"linuxcncrsh resource {resource!r}: give host, host:port or socket://host:port")
    return f"socket://{text}" if ":" in text else f"socket://{text}:{DEFAULT_PORT}"


class LinuxCNCLink:
    """A MachineLink to LinuxCNC over linuxcncrsh: MDI blocks, positions, completion, G38.2 probing."""

    def __init__(
        self,
        connect: Callable[[], RawPort],
        password: str = "EMC",
        enable_password: str = "EMCTOO",
        client: str = "driftlab",
        poll_s: float = 0.2,
        sleep: Callable[[float], None] = time.sleep,
        max_idle_polls: int = 100_000,
    ) -> None:
        self._connect = connect
        self.password, self.enable_password, self.client = password, enable_password, client
        self.poll_s, self.sleep, self.max_idle_polls = poll_s, sleep, max_idle_polls
        self.server: str | None = None
        self.reconnects = 0
        self._port: RawPort | None = None

    @classmethod
    def open(cls, resource: str, timeout_s: float = 5.0, **options: object) -> LinuxCNCLink:
        """Return a link to ``host[:port]`` (or ``socket://host:port``), session negotiated and checked."""
        url = linuxcnc_url(resource)
        link = cls(lambda: SerialPort.open(url, timeout_s=timeout_s), **options)  # type: ignore[arg-type]
        link.session()
        return link

    # -- the line exchange
    def _lines_until(self, done: Callable[[str], bool]) -> tuple[str, list[str]]:
        """Return (the final line, the ``error:``/``warning:`` lines before it)."""
        assert self._port is not None
        notes: list[str] = []
        for _ in range(64):
            raw = self._port.read_line()
            try:
                text = raw.decode("ascii").strip()
            except UnicodeDecodeError as exc:
                raise GarbledReply(f"undecodable reply {raw[:40]!r}") from exc
            if not text:
                continue
            if text.startswith(("error:", "warning:")):
                notes.append(text)
                continue
            if done(text):
                return text, notes
            raise GarbledReply(f"unexpected reply {text[:60]!r}")
        raise GarbledReply("too many diagnostic lines")

    def _send(self, command: str, done: Callable[[str], bool]) -> tuple[str, list[str]]:
        if self._port is None:
            raise TransientError("not connected")
        self._port.write(command.encode("ascii") + b"\r\n")
        return self._lines_until(done)

    def _raw(self, command: str, done: Callable[[str], bool], repeat: bool) -> tuple[str, list[str]]:
        """Exchange one command; after a dropped line reconnect, and repeat it only if ``repeat``."""
        try:
            if self._port is None:
                self.session()
            return self._send(command, done)
        except TransientError as exc:
            reason = " ".join(str(exc).split())
            self._drop()
            if not repeat:
                raise InstrumentError(
                    f"linuxcncrsh {command!r}: {reason}; not repeated (motion state unknown)"
                ) from exc
            try:
                self.session()
                self.reconnects += 1
                return self._send(command, done)
            except TransientError as exc2:
                self._drop()
                raise InstrumentError(f"linuxcncrsh {command!r}: {' '.join(str(exc2).split())}") from exc2

    def _drop(self) -> None:
        port, self._port = self._port, None
        close_quietly(port)

    def get(self, key: str, *args: str) -> list[str]:
        """Return the words after ``KEY`` of ``get <key> [args]``; InstrumentError on ``GET <KEY> NAK``."""
        name = key.upper()
        cmd = " ".join(["get", key, *args])
        line, notes = self._raw(cmd, lambda t: t.split(" ", 1)[0] == name or t == f"GET {name} NAK", repeat=True)
        if line.endswith(" NAK"):
            raise InstrumentError(f"linuxcncrsh {cmd!r} refused" + (f": {notes[-1][6:].strip()}" if notes else ""))
        return line.split()[1:]

    def set(self, key: str, *args: str, repeat: bool = True) -> None:
        """Send ``set <key> [args]`` and require ``SET <KEY> ACK``; a NAK is one line with the controller's reason."""
        name = key.upper()
        cmd = " ".join(["set", key, *args])
        line, notes = self._raw(cmd, lambda t: t in (f"SET {name} ACK", f"SET {name} NAK"), repeat=repeat)
        if line.endswith("NAK"):
            reason = notes[-1].split(":", 1)[1].strip() if notes else self.last_error()
            raise InstrumentError(f"linuxcncrsh {cmd!r} refused: {reason or 'no reason given'}")

    def last_error(self) -> str | None:
        """Return the controller's last error message (``get error``), None when it reports ``ERROR OK``."""
        words = self.get("error")
        text = " ".join(words)
        return None if text == "OK" else text

    # -- the session
    def session(self) -> None:
        """Connect and negotiate: hello, echo off, verbose on, enable, wait mode, machine checks, MDI, G21 G90."""
        self._drop()
        try:
            self._port = self._connect()
        except InstrumentError:
            raise
        hello = f"hello {self.password} {self.client} {PROTOCOL_VERSION}"
        line, _ = self._send(hello, lambda t: t.startswith("HELLO "))
        if not line.startswith("HELLO ACK"):
            self._drop()
            raise InstrumentError("linuxcncrsh refused the connection password (HELLO NAK)")
        self.server = " ".join(line.split()[2:])
        # echo is still on here: the server repeats this command, and answers nothing else (verbose is off)
        self._send("set echo off", lambda t: t.lower() == "set echo off")
        self._send("set verbose on", lambda t: t == "SET VERBOSE ACK")
        self.set("enable", self.enable_password, repeat=False)
        self.set("wait_mode", "received", repeat=False)
        if self.get("estop") != ["OFF"]:
            raise InstrumentError("LinuxCNC is in E-stop: release it at the machine (driftlab never does)")
        if self.get("machine") != ["ON"]:
            raise InstrumentError("LinuxCNC machine is off: switch it on at the machine (driftlab never does)")
        self.set("mode", "mdi", repeat=False)
        self.set("mdi", "G21 G90", repeat=False)

    def identify(self) -> str:
        """Return the server's name and protocol version from the hello (``linuxcncrsh <name> <version>``)."""
        if self._port is None:
            self.session()
        return f"linuxcncrsh {self.server}"

    # -- MachineLink
    def position(self) -> dict[str, float]:
        """Return the actual positions X, Y, Z (mm) and A, B (deg) in absolute coordinates."""
        words = self.get("abs_act_pos")
        if len(words) != 9:
            raise InstrumentError(f"linuxcncrsh: ABS_ACT_POS with {len(words)} values, expected 9")
        values = dict(zip("XYZABCUVW", (float(w) for w in words), strict=True))
        if not all(math.isfinite(v) for v in values.values()):
            raise InstrumentError("linuxcncrsh: non-finite position")
        return {a: values[a] for a in AXES}

    def running(self) -> bool:
        """Return True while the interpreter is executing MDI (``PROGRAM_STATUS RUNNING`` or ``PAUSED``)."""
        return self.get("program_status") != ["IDLE"]

    def buffer_free(self) -> int:
        """Return 1 when the controller is idle, 0 while it runs: linuxcncrsh reports no queue depth."""
        return 0 if self.running() else 1

    def mdi(self, code: str) -> None:
        """Queue one MDI block (``set mdi <code>``), never repeated after a dropped line."""
        if "\n" in code or "\r" in code:
            raise ValidationError("one MDI block per line")
        self.set("mdi", code, repeat=False)

    def send_program(
        self, lines: Iterable[str], low_water: int = 0, high_water: int | None = None, wait: bool = True
    ) -> StreamReport:
        """Send each block as an MDI command (LinuxCNC queues them); wait for the end if ``wait``."""
        sent = 0
        for raw in lines:
            code = _COMMENT.sub("", raw).strip()
            if not code:
                continue
            self.mdi(code)
            sent += 1
        if wait:
            self.wait_done()
        return StreamReport(blocks_sent=sent, polls=0, min_free_seen=0, starved=0)

    def wait_done(self) -> None:
        """Return once the MDI queue has executed; InstrumentError with the controller's message if it failed."""
        for _ in range(self.max_idle_polls):
            if not self.running():
                break
            self.sleep(self.poll_s)
        else:
            raise InstrumentError("LinuxCNC did not finish the MDI commands")
        err = self.last_error()
        if err is not None:
            raise InstrumentError(f"LinuxCNC: {err}")

    # -- probing
    def probe(self, target: Sequence[float], feed_mm_min: float) -> np.ndarray | None:
        """Return the trip point (X, Y, Z mm) of a G38.2 move to ``target``, or None if it made no contact."""
        x, y, z = (float(v) for v in target)
        if not feed_mm_min > 0:
            raise ValidationError("probing needs a positive feed")
        self.set("probe_clear", repeat=False)
        self.mdi(f"G38.2 X{x:.4f} Y{y:.4f} Z{z:.4f} F{feed_mm_min:.1f}")
        try:
            self.wait_done()
        except InstrumentError as exc:
            if "without making contact" in str(exc):
                return None
            raise
        self.mdi(f"(DEBUG,PROBE {PROBE_PARAMS})")
        self.wait_done()
        words = self.get("operator_display")
        if len(words) != 5 or words[0] != "PROBE":
            raise InstrumentError(f"linuxcncrsh: unexpected probe report {' '.join(words)[:60]!r}")
        values = [float(w) for w in words[1:]]
        if values[3] != 1.0:
            return None
        return np.array(values[:3])

    def close(self) -> None:
        """Close the session (the controller keeps running)."""
        self._drop()


class LinuxCNCProbe:
    """A touch-trigger probe on LinuxCNC: each point a G38.2 move, the sphere fitted as ch. 5.6 does (a Prober).

    Between points the probe retracts to its start, climbs to ``safe_z_mm`` above the sphere and
    comes down over the next start, so no straight move between starts can cross the sphere.
    """

    def __init__(
        self,
        link: LinuxCNCLink,
        stylus_radius_mm: float = 1.0,
        feed_mm_min: float = 100.0,
        clearance_mm: float = 3.0,
        overtravel_mm: float = 3.0,
        safe_z_mm: float = 10.0,
    ) -> None:
        # lazy: daq.probe (scipy) adds 0.29 s to `import driftlab.daq.linuxcnc` (measured); only a probing link needs it
        from driftlab.daq.probe import LobingMap, TouchProbe

        self.link = link
        self.feed_mm_min, self.safe_z_mm = feed_mm_min, safe_z_mm
        outer = self

        class _Probe(TouchProbe):
            def _probe_move(self, start: np.ndarray, u: np.ndarray, distance_mm: float) -> np.ndarray | None:
                return outer._move(start, u, distance_mm)

        self._probe = _Probe(None, stylus_radius_mm, LobingMap(), clearance_mm, overtravel_mm, link=link)  # type: ignore[arg-type]
        self._top: float | None = None

    def _move(self, start: np.ndarray, u: np.ndarray, distance_mm: float) -> np.ndarray | None:
        top = self._top if self._top is not None else float(start[2])
        here = self.link.position()
        self.link.send_program(
            [
                f"G0 Z{max(top, here['Z']):.4f}",
                f"G0 X{start[0]:.4f} Y{start[1]:.4f}",
                f"G0 Z{start[2]:.4f}",
            ]
        )
        hit = self.link.probe((start + distance_mm * u).tolist(), self.feed_mm_min)
        self.link.send_program([f"G0 X{start[0]:.4f} Y{start[1]:.4f} Z{start[2]:.4f}"])
        return hit

    def probe_sphere(self, name: str, nominal_centre: Sequence[float], radius_mm: float) -> SphereMeasurement:
        """Return the sphere's centre from five G38.2 points (ch. 5.6), moving round it at a safe height."""
        self._top = float(nominal_centre[2]) + radius_mm + self._probe.stylus_radius_mm + self.safe_z_mm
        try:
            return self._probe.probe_sphere(name, nominal_centre, radius_mm)
        finally:
            self._top = None
