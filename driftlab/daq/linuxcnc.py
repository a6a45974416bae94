"""LinuxCNC through ``linuxcncrsh``: the machine link (MDI moves, positions) and G38.2 probing over TCP.

Written from LinuxCNC's own documentation and source, which are the protocol's reference, on both
lines a shop meets (read at tag v2.9.10 and on master at 5c41560ebb, 2026-08):

* ``linuxcncrsh(1)`` (2.9: docs/man/man1/linuxcncrsh.1; master: docs/src/man/man1/linuxcncrsh.1.adoc):
  the text protocol on TCP port 5007, ``hello <password> <client> <version>`` ->
  ``HELLO ACK <server> <version>``, ``set echo off``, ``set verbose on`` (then every set is answered
  ``SET <KEY> ACK`` or ``SET <KEY> NAK``), ``set enable <password>``, ``set mode mdi``,
  ``set mdi <code>``, ``get rel_act_pos`` / ``abs_act_pos``, ``get tool_offset``,
  ``get program_status`` (``IDLE|RUNNING|PAUSED``), ``get error`` (``ERROR OK`` or
  ``ERROR <text>``), ``get operator_display``, ``get estop``, ``get machine``;
* src/emc/usr_intf/emcrsh.cc, the server, where the two lines differ:

  - wait mode: 2.9 ``set set_wait received|done`` (``get set_wait`` -> ``SET_WAIT ...``); master
    ``set wait_mode received|done`` (``get wait_mode`` -> ``WAIT_MODE ...``), ``GET <KEY> NAK``
    from the line that lacks it;
  - an unknown ``set`` key: 2.9 ``SET <KEY> NAK`` with no reason; master
    ``error: Subcommand not found: SET <KEY>`` then a plain ``SET NAK``;
  - a refused ``set``: 2.9 ``SET <KEY> NAK`` only (the task's reason, if any, in ``get error``);
    master ``error: <reason>`` line(s) then ``SET <KEY> NAK``;
  - ``set`` replies end in LF CR on 2.9 (``"SET %s ACK\\n\\r"`` in ``commandSet``), CR LF on master;
  - all axes: 2.9 six values, X Y Z A B C; master nine, X Y Z A B C U V W;
  - one axis: 2.9 by number, ``get rel_act_pos 2`` -> ``REL_ACT_POS 2 <z>`` (a letter is read by
    ``atoi`` as axis 0: X's value comes back); master by letter or number,
    ``get rel_act_pos Z`` -> ``REL_ACT_POS Z <z>``.

  (master between 2023-12 and 2026-02 had ``wait_mode`` with a ``set_wait`` alias and six values;
  the link tells the lines apart by what they answer, not by a version number, so it reads that
  one too.) Both print positions with ``%f``: six decimals of a mm, 1 nm. ``REL_ACT_POS`` is the actual
  position less the G5x and G92 offsets (``actualPosition - g5x_offset - g92_offset`` in both
  lines' ``getRelActPos``); it does not take off the tool length offset, which ``get tool_offset``
  gives (``toolOffset.tran.z``), nor a G5x rotation (G10 L2 R);
* the G-code manual, G38.x: after probing #5061..#5069 hold the trip point in the coordinate system
  in which the G38 took place, and #5070 is 1 if the probe tripped; #5420..#5428 the interpreter's
  current position in that system; ``(DEBUG, ...)`` comments expand parameters into an
  operator-display message, which is how they are read back over linuxcncrsh.

The frame: moves go as MDI in the active work system (G90, G5x); positions are read in the same
frame, ``REL_ACT_POS`` less the tool length offset on Z, so they compare with MDI targets and with
#5061-#5063. (``ABS_ACT_POS`` is machine coordinates: with any G54 offset it differs from both.)
:meth:`LinuxCNCLink.frame_check` compares that reading with the interpreter's own #5420-#5422 and
refuses a frame REL_ACT_POS cannot show (a rotated G5x); the probe cycle runs it first.

Safety: the driver never takes a machine out of E-stop or switches it on; it checks that the
operator has (``get estop``, ``get machine``) and refuses otherwise, in one line, on either line.
A check (``rig check``: hello, the session, one position read) moves nothing. Units: the driver
programs in millimetres (``G21``) and reads positions as LinuxCNC reports them in the machine's
units, so the INI's ``LINEAR_UNITS`` must be mm.

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
#: the interpreter's current position X Y Z in the active work system (G-code manual, parameters)
FRAME_PARAMS = "#5420 #5421 #5422"
#: the released line (2.9) and master, told apart by their wait-mode command (module docstring)
LINES = {"2.9": ("set_wait", "SET_WAIT"), "master": ("wait_mode", "WAIT_MODE")}
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
        self.line: str | None = None  # "2.9" or "master", from what the server answers
        self.reconnects = 0
        self._port: RawPort | None = None
        self._mdi_ready = False  # MDI mode and G21 G90 set on this session (only once a block is sent)

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

    @staticmethod
    def _reason(notes: list[str]) -> str | None:
        """Return the server's own reason from its ``error:`` lines (master sends them before a NAK)."""
        errors = [n.split(":", 1)[1].strip() for n in notes if n.startswith("error:")]
        return "; ".join(errors) if errors else None

    def _try_get(self, key: str, *args: str) -> tuple[list[str] | None, str | None]:
        """Return (the words after ``KEY``, None), or (None, the server's reason) on a ``GET`` NAK."""
        name = key.upper()
        cmd = " ".join(["get", key, *args])
        naks = (f"GET {name} NAK", "GET NAK")  # master's plain form for an unknown key
        line, notes = self._raw(cmd, lambda t: t.split(" ", 1)[0] == name or t in naks, repeat=True)
        if line in naks:
            return None, self._reason(notes) or "no reason given"
        return line.split()[1:], None

    def get(self, key: str, *args: str) -> list[str]:
        """Return the words after ``KEY`` of ``get <key> [args]``; InstrumentError on ``GET <KEY> NAK``."""
        words, reason = self._try_get(key, *args)
        if words is None:
            raise InstrumentError(f"linuxcncrsh {' '.join(['get', key, *args])!r} refused: {reason}")
        return words

    def set(self, key: str, *args: str, repeat: bool = True) -> None:
        """Send ``set <key> [args]`` and require ``SET <KEY> ACK``; a NAK is one line with the controller's reason.

        The reason is the server's ``error:`` line (master), else its ``get error`` (what 2.9's task
        reported); a plain ``SET NAK`` (master: unknown key, or no hello) is a NAK like the other.
        """
        name = key.upper()
        cmd = " ".join(["set", key, *args])
        naks = (f"SET {name} NAK", "SET NAK")
        line, notes = self._raw(cmd, lambda t: t == f"SET {name} ACK" or t in naks, repeat=repeat)
        if line in naks:
            reason = self._reason(notes) or self.last_error()
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
        self.line = self._detect_line()
        self.set(LINES[self.line][0], "received", repeat=False)
        if self.get("estop") != ["OFF"]:
            raise InstrumentError("LinuxCNC is in E-stop: release it at the machine (driftlab never does)")
        if self.get("machine") != ["ON"]:
            raise InstrumentError("LinuxCNC machine is off: switch it on at the machine (driftlab never does)")
        self._mdi_ready = False

    def _detect_line(self) -> str:
        """Return "master" or "2.9" from which wait-mode query the server answers (``get`` moves nothing)."""
        reasons = []
        for line, (key, _reply) in reversed(LINES.items()):
            words, reason = self._try_get(key)
            if words is not None:
                return line
            reasons.append(f"get {key}: {reason}")
        raise InstrumentError(f"linuxcncrsh answers neither wait-mode query ({'; '.join(reasons)})")

    def _ensure_mdi(self) -> None:
        """Switch to MDI mode and G21 G90 before this session's first block (a check never gets here)."""
        if not self._mdi_ready:
            self.set("mode", "mdi", repeat=False)
            self.set("mdi", "G21 G90", repeat=False)
            self._mdi_ready = True

    def identify(self) -> str:
        """Return the server's name, protocol version and line (``linuxcncrsh <name> <version> (2.9 line)``)."""
        if self._port is None:
            self.session()
        return f"linuxcncrsh {self.server} ({self.line} line)"

    # -- positions
    def _numbers(self, key: str, words: list[str]) -> list[float]:
        try:
            values = [float(w) for w in words]
        except ValueError:
            raise InstrumentError(f"linuxcncrsh: {key} {' '.join(words)[:60]!r} is not numbers") from None
        if not all(math.isfinite(v) for v in values):
            raise InstrumentError(f"linuxcncrsh: non-finite {key}")
        return values

    def tool_offset(self) -> float:
        """Return the active tool length offset on Z (mm, ``get tool_offset``; 0 without G43)."""
        words = self.get("tool_offset")
        if len(words) != 1:
            raise InstrumentError(f"linuxcncrsh: TOOL_OFFSET with {len(words)} values, expected 1")
        return self._numbers("TOOL_OFFSET", words)[0]

    def axes(self, key: str = "rel_act_pos") -> dict[str, float]:
        """Return every axis of ``get <key>`` by letter: six values on 2.9 (X..C), nine on master (X..W)."""
        words = self.get(key)
        if len(words) not in (6, 9):
            raise InstrumentError(f"linuxcncrsh: {key.upper()} with {len(words)} values, expected 6 (2.9) or 9")
        return dict(zip("XYZABCUVW", self._numbers(key.upper(), words), strict=False))

    def axis_position(self, axis: str, key: str = "rel_act_pos") -> float:
        """Return one axis of ``get <key> <axis>``: by number on 2.9 (it reads a letter as 0), by letter on master."""
        letter = axis.upper()
        if len(letter) != 1 or letter not in "XYZABCUVW":
            raise ValidationError(f"axis {axis!r}: one of X Y Z A B C U V W")
        if self._port is None:
            self.session()
        index = "XYZABCUVW".index(letter)
        label = str(index) if self.line == "2.9" else letter
        words = self.get(key, label)
        if len(words) != 2 or words[0].upper() != label:
            raise InstrumentError(f"linuxcncrsh: {key.upper()} {' '.join(words)[:40]!r} is not axis {letter}")
        return self._numbers(key.upper(), words[1:])[0]

    # -- MachineLink
    def position(self) -> dict[str, float]:
        """Return the actual X, Y, Z (mm), A, B (deg) in the frame the MDI moves use (work system, tool on Z).

        ``REL_ACT_POS`` less the tool length offset on Z: the frame of G90 MDI targets and of the
        probe results #5061-#5063 (module docstring), not ``ABS_ACT_POS``'s machine coordinates.
        """
        values = self.axes("rel_act_pos")
        values["Z"] -= self.tool_offset()
        return {a: values[a] for a in AXES}

    def frame_check(self, tol_mm: float = 0.005) -> float:
        """Return how far (mm) :meth:`position` is from the interpreter's #5420-#5422; refuse beyond ``tol_mm``.

        At rest the two agree to the servo's following error unless the work system is one that
        REL_ACT_POS cannot show (a G5x rotation, G10 L2 R): then the probe's points and its moves
        would be in different frames, and nothing is probed. Sends a ``(DEBUG, ...)`` MDI comment, no move.
        """
        self.mdi(f"(DEBUG,FRAME {FRAME_PARAMS})")
        self.wait_done()
        words = self.get("operator_display")
        if len(words) != 4 or words[0] != "FRAME":
            raise InstrumentError(f"linuxcncrsh: unexpected frame report {' '.join(words)[:60]!r}")
        interp = np.array(self._numbers("OPERATOR_DISPLAY", words[1:]))
        here = self.position()
        gap = float(np.abs(interp - np.array([here[a] for a in "XYZ"])).max())
        if gap > tol_mm:
            raise InstrumentError(
                f"LinuxCNC's work frame is not what REL_ACT_POS shows ({gap * 1000:.1f} µm apart: "
                "a rotated G5x (G10 L2 R)?); probe in an unrotated work system"
            )
        return gap

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
        if self._port is None:
            self.session()
        self._ensure_mdi()
        self.set("mdi", code, repeat=False)

    def send_program(
        self, lines: Iterable[str], low_water: int = 0, high_water: int | None = None, wait: bool = True
    ) -> StreamReport:
        """Send each block as an MDI command (LinuxCNC queues them); wait for the end if ``wait``.

        linuxcncrsh reports no queue depth: with ``high_water`` at most that many blocks are queued,
        then the link waits for the queue to run empty before the next batch (blocks are pulled,
        and so corrected, no earlier than that); without it every block is queued as it comes.
        """
        sent = batch = polls = 0
        for raw in lines:
            code = _COMMENT.sub("", raw).strip()
            if not code:
                continue
            if high_water is not None and batch >= max(high_water, 1):
                polls += self.wait_done()
                batch = 0
            self.mdi(code)
            sent += 1
            batch += 1
        if wait:
            polls += self.wait_done()
        return StreamReport(blocks_sent=sent, polls=polls, min_free_seen=0, starved=0)

    def wait_done(self) -> int:
        """Return the status polls the MDI queue took to run empty; InstrumentError with the reason on failure."""
        polls = 0
        while self.running():
            polls += 1
            if polls >= self.max_idle_polls:
                raise InstrumentError("LinuxCNC did not finish the MDI commands")
            self.sleep(self.poll_s)
        err = self.last_error()
        if err is not None:
            raise InstrumentError(f"LinuxCNC: {err}")
        return polls

    # -- probing
    def probe(self, target: Sequence[float], feed_mm_min: float) -> np.ndarray | None:
        """Return the trip point (X, Y, Z mm) of a G38.2 move to ``target``, or None if it made no contact."""
        x, y, z = (float(v) for v in target)
        if not feed_mm_min > 0:
            raise ValidationError("probing needs a positive feed")
        if self._port is None:
            self.session()
        self._ensure_mdi()
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
        self.frame_gap_mm: float | None = None

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
        self.frame_gap_mm = self.link.frame_check()  # points, moves and readings in one frame, or nothing moves
        self._top = float(nominal_centre[2]) + radius_mm + self._probe.stylus_radius_mm + self.safe_z_mm
        try:
            return self._probe.probe_sphere(name, nominal_centre, radius_mm)
        finally:
            self._top = None
