"""A simulated LinuxCNC answering the ``linuxcncrsh`` text protocol of either line, on the virtual machine's motion.

Written from linuxcncrsh(1) and the server's source, src/emc/usr_intf/emcrsh.cc, at tag v2.9.10
(``line="2.9"``, what shops install) and on master at 5c41560ebb (``line="master"``), and checked
against the recorded session of the real master server (tests/linuxcncrsh/expected-telnet-output):

* both: ``hello <pw> <client> <ver>`` -> ``HELLO ACK <name> 1.1`` / ``HELLO NAK``; a linked session
  echoes each command while echo is on (never the first hello); with verbose off a successful
  ``set`` says nothing, with verbose on ``SET <KEY> ACK``; ``get error`` ``ERROR OK`` or
  ``ERROR <text>`` (then cleared); ``get operator_display`` the last ``(DEBUG,...)`` message with
  its parameters expanded ``%f`` (rs274ngc's ``convert_param_comment``); ``get program_status``
  IDLE/RUNNING; ``get tool_offset``; ``REL_ACT_POS`` = machine less the G5x offset (no tool offset);
* 2.9 (``readClient``, ``parseCommand``, ``commandSet``, ``commandGet``): ``set`` replies end in
  LF CR; every refusal is a bare ``SET <KEY> NAK`` (an unknown key too, ``set wait_mode``
  included); ``set`` before the hello ``SET NAK``; a key from INIFILE on needs ``set enable``, one
  after MACHINE the machine on; ``set set_wait`` / ``get set_wait``; six positions, one axis by
  number (``atoi``: a letter reads as 0) answered ``<KEY> <n> <v>``; an unknown command gets no
  reply; ``PROBE_TRIPPED 0|1``; ``set mdi`` with wait received is ACKed once the task has it, and a
  block the task refuses leaves its reason in ``get error``;
* master (``commandGetSet``, ``printPose``): CR LF; ``error: <reason>`` before each NAK;
  ``error: Subcommand not found: SET <KEY>`` then a plain ``SET NAK``; ``set wait_mode`` /
  ``get wait_mode``; nine positions, one axis by letter or number answered ``<KEY> <letter> <v>``;
  an unknown command ``error: Command '<x>' not found``; ``PROBE_TRIPPED YES|NO``; a refused MDI
  block ``SET MDI NAK`` (its status is ERROR once received);
* ``set mdi`` outside MDI mode: the error ``Must be in MDI mode to issue MDI command``; G38.2
  without contact: ``G38.2 move finished without making contact.``; #5061-#5063 the trip point in
  work coordinates, #5070 1 or 0, #5420-#5422 the interpreter's position (G-code manual).

Frames: the motion model (:class:`SimController`, and the laser reading its stage) runs in machine
coordinates; MDI blocks are in the work system, machine = work + ``g5x`` + (0, 0,
``tool_offset_mm``) (only G90 blocks exist here, so each axis word is shifted as it is parsed).
Motion (G0/G1/G4 blocks, feeds) is the machine-link simulator's own; a G38.2 move happens at once
in simulated time. The session's state resets at each new connection (echo on, verbose off, not
linked), as the server's does.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from driftlab.daq.sim.instruments import SimController
from driftlab.vocabulary import AXES

CONNECT_PASSWORD = "EMC"
ENABLE_PASSWORD = "EMCTOO"
LINES = ("2.9", "master")
_AXES9 = "XYZABCUVW"
_MODAL = re.compile(r"\bG(?:21|90|94|17|40|49|54|64)(?![\d.])", re.IGNORECASE)
_DEBUG = re.compile(r"^\(DEBUG,(.*)\)$", re.IGNORECASE)
_G38 = re.compile(r"\bG38\.2\b", re.IGNORECASE)
_XYZ = re.compile(r"([XYZ])\s*([-+]?\d*\.?\d+)", re.IGNORECASE)
# v2.9.10's subcommand table, in order: commandSet needs enable from INIFILE on, the machine on after MACHINE
_V29_ORDER = (
    "ECHO VERBOSE ENABLE CONFIG COMM_MODE COMM_PROT INIFILE PLAT INI DEBUG SET_WAIT WAIT TIMEOUT UPDATE "
    "ERROR OPERATOR_DISPLAY OPERATOR_TEXT TIME ESTOP MACHINE"
).split()
# master's access levels (getsetList): 1 hello, 2 enable, 3 machine on
_MASTER_LEVEL = {"ECHO": 0, "VERBOSE": 1, "ENABLE": 1, "WAIT_MODE": 2, "ESTOP": 2, "MACHINE": 2}


class SimLinuxCNC(SimController):
    """LinuxCNC's linuxcncrsh server (2.9 or master) on the virtual machine (machine on, out of E-stop, homed)."""

    name = "linuxcncrsh"
    server_name = "driftlab-vm"
    terminator = b""  # each reply carries the line ends of its line (2.9: LF CR after a set)

    def __init__(
        self,
        world: Any,
        clock: Any,
        line: str = "2.9",
        g5x: Sequence[float] = (0.0, 0.0, 0.0),
        tool_offset_mm: float = 0.0,
        **kwargs: Any,
    ) -> None:
        if line not in LINES:
            raise ValueError(f"linuxcncrsh line {line!r}: one of {', '.join(LINES)}")
        kwargs.setdefault("capacity", 1_000_000)  # LinuxCNC queues MDI commands; no block buffer to fill
        super().__init__(world, clock, **kwargs)
        self.line = line
        self.g5x = np.array([float(v) for v in g5x], dtype=float)
        self.tool_offset_mm = float(tool_offset_mm)
        self.estop = False
        self.machine_on = True
        self.mode = "MANUAL"
        self.error_text = ""
        self.display_text = ""
        self.params: dict[int, float] = {5061: 0.0, 5062: 0.0, 5063: 0.0, 5070: 0.0}
        self.probe_tripped = False
        self.mdi_log: list[str] = []
        self._token = ""
        self.on_connect()

    def on_connect(self) -> None:
        """A new session: echo on, verbose off, not linked, not enabled, wait mode received."""
        self.echo, self.verbose, self.linked, self.enabled = True, False, False, False
        self.wait_mode = "RECEIVED"

    # -- frames
    def _shift(self) -> np.ndarray:
        """Return machine - work for X Y Z: the G5x offset and the tool length offset on Z."""
        return self.g5x + np.array([0.0, 0.0, self.tool_offset_mm])

    def _machine(self) -> list[float]:
        return [self.pos["X"], self.pos["Y"], self.pos["Z"], self.pos["A"], self.pos["B"], 0.0, 0.0, 0.0, 0.0]

    def _rel(self) -> list[float]:
        m = self._machine()
        return [v - (float(self.g5x[i]) if i < 3 else 0.0) for i, v in enumerate(m)]

    def _to_machine(self, code: str) -> str:
        """Return the block with its X Y Z words moved from the work system to machine coordinates."""
        shift = self._shift()
        code = re.sub(r"\([^)]*\)|;.*$", "", code)
        return _XYZ.sub(
            lambda m: f"{m.group(1).upper()}{float(m.group(2)) + shift['XYZ'.index(m.group(1).upper())]:.6f}", code
        )

    # -- the line protocol
    def handle(self, line: str) -> str | None:
        """Answer one linuxcncrsh command line (the reply lines with their line ends)."""
        self._advance(self.clock.now())
        words = line.split()
        if not words:
            return None
        cmd = words[0].upper()
        self._token = words[1] if len(words) > 1 else ""  # master quotes the key as it was typed
        out = ""
        if self.line == "2.9":
            if self.echo and self.linked:
                out += line + "\r\n"  # readClient echoes what it read, before parsing
        elif cmd not in ("HELLO", "GET", "SET", "QUIT", "HELP", "SHUTDOWN"):
            return f"error: Command '{words[0]}' not found\r\n"
        elif self.echo and self.linked and cmd != "HELLO":
            out += line + "\r\n"
        if cmd == "HELLO":
            out += self._hello(words)
        elif cmd == "GET":
            out += self._get(words[1].upper(), words[2:]) if len(words) > 1 else self._nak("GET", None)
        elif cmd == "SET":
            out += self._set(words[1].upper(), words[2:], line) if len(words) > 1 else self._nak("SET", None)
        return out or None

    def _hello(self, words: list[str]) -> str:
        need = 4 if self.line == "2.9" else 3  # 2.9's commandHello needs the version too
        self.linked = self.enabled = False
        if len(words) >= need and words[1] == CONNECT_PASSWORD:
            self.linked = True
            return f"HELLO ACK {self.server_name} 1.1\r\n"
        return "HELLO NAK\r\n"

    def _nak(self, verb: str, key: str | None, reason: str | None = None) -> str:
        """Return the line's refusal: 2.9 a bare NAK (LF CR after a set), master the reason first."""
        if self.line == "2.9":
            return f"{verb} {key} NAK" + ("\n\r" if verb == "SET" and key else "\r\n") if key else f"{verb} NAK\r\n"
        if key is None:
            return f"error: Must specify subcommand for {verb}\r\n{verb} NAK\r\n"
        return (f"error: {reason}\r\n" if reason else "") + f"{verb} {key} NAK\r\n"

    # -- get
    def _pose(self, key: str, args: list[str]) -> str:
        values = self._rel() if key.startswith("REL") else self._machine()
        if self.line == "2.9":
            values = values[:6]
            if not args:
                return key + "".join(f" {v:f}" for v in values) + "\r\n"
            n = int(m.group()) if (m := re.match(r"[-+]?\d+", args[0])) else 0  # atoi
            return f"{key} {n}" + (f" {values[n]:f}" if 0 <= n < 6 else "") + "\r\n"
        if not args or args[0] == "-1":
            return key + "".join(f" {v:f}" for v in values) + "\r\n"
        a = args[0].upper()
        n = int(a) if re.fullmatch(r"\d", a) else _AXES9.find(a) if len(a) == 1 else -1
        if n < 0:
            return self._nak("GET", key, f"Invalid axis '{args[0]}', must be one of XYZABCUVW")
        return f"{key} {_AXES9[n]} {values[n]:f}\r\n"

    def _get(self, key: str, args: list[str]) -> str:
        on_off = {True: "ON", False: "OFF"}
        if key in ("ABS_ACT_POS", "ABS_CMD_POS", "REL_ACT_POS", "REL_CMD_POS"):
            return self._pose(key, args)
        simple = {
            "PROGRAM_STATUS": f"PROGRAM_STATUS {'RUNNING' if self._queued() else 'IDLE'}",
            "ESTOP": f"ESTOP {on_off[self.estop]}",
            "MACHINE": f"MACHINE {on_off[self.machine_on and not self.estop]}",
            "MODE": f"MODE {self.mode}",
            "ECHO": f"ECHO {on_off[self.echo]}",
            "VERBOSE": f"VERBOSE {on_off[self.verbose]}",
            "ENABLE": f"ENABLE {on_off[self.enabled]}",
            "TOOL_OFFSET": f"TOOL_OFFSET {self.tool_offset_mm:f}",
            "PLAT": "PLAT Linux",
            "PROBE_TRIPPED": "PROBE_TRIPPED "
            + (str(int(self.probe_tripped)) if self.line == "2.9" else "YES" if self.probe_tripped else "NO"),
        }
        wait_key = "SET_WAIT" if self.line == "2.9" else "WAIT_MODE"
        simple[wait_key] = f"{wait_key} {self.wait_mode}"
        if key in simple:
            return simple[key] + "\r\n"
        if key == "ERROR":
            text, self.error_text = self.error_text, ""
            return f"ERROR {text or 'OK'}\r\n"
        if key == "OPERATOR_DISPLAY":
            text, self.display_text = self.display_text, ""
            return f"OPERATOR_DISPLAY {text or 'OK'}\r\n"
        if self.line == "2.9":
            return f"GET {key} NAK\r\n"
        return f"error: Subcommand not found: GET {self._token}\r\nGET NAK\r\n"

    # -- set
    def _refused_access(self, key: str, known: bool) -> str | None:
        """Return the refusal for a set this session may not issue yet, None when it may."""
        on = self.machine_on and not self.estop
        if self.line == "2.9":
            idx = _V29_ORDER.index(key) if key in _V29_ORDER else len(_V29_ORDER)
            if (idx >= _V29_ORDER.index("INIFILE") and not self.enabled) or (
                idx > _V29_ORDER.index("MACHINE") and not on
            ):
                return self._nak("SET", key)
            return None
        if not known:
            return f"error: Subcommand not found: SET {self._token}\r\nSET NAK\r\n"
        level = _MASTER_LEVEL.get(key, 3)
        for need, ok, why in ((1, self.linked, "A HELLO must be successfully negotiated"),
                              (2, self.enabled, "Connection must be enabled"),
                              (3, on, "Machine must be 'ON'")):  # fmt: skip
            if level >= need and not ok:
                return self._nak("SET", key, f"{why} for SET {key}")
        return None

    def _set(self, key: str, args: list[str], line: str) -> str:
        wait_key = "SET_WAIT" if self.line == "2.9" else "WAIT_MODE"
        known = {"ECHO", "VERBOSE", "ENABLE", wait_key, "MODE", "MDI", "ESTOP", "MACHINE", "PROBE_CLEAR", "ABORT"}
        if self.line == "2.9" and not self.linked:
            return "SET NAK\r\n"  # parseCommand, before commandSet
        refused = self._refused_access(key, key in known)
        if refused is not None:
            return refused
        if key not in known:
            return self._nak("SET", key)  # 2.9's scUnknown: rtStandardError
        word, typed = (args[0].upper(), args[0]) if args else ("", "")
        if key in ("ECHO", "VERBOSE"):
            if word not in ("ON", "OFF"):
                return self._nak("SET", key, f"Invalid argument '{typed}', must be {{on,off}}")
            setattr(self, key.lower(), word == "ON")
        elif key == "ENABLE":
            if args and args[0] == ENABLE_PASSWORD:
                self.enabled = True
            elif word == "OFF":
                self.enabled = False
            else:
                return self._nak("SET", key)
        elif key == wait_key:
            if word not in ("RECEIVED", "DONE"):
                return self._nak("SET", key, f"Invalid argument '{typed}', must be {{received,done}}")
            self.wait_mode = word
        elif key == "MODE":
            if word not in ("MANUAL", "AUTO", "MDI"):
                return self._nak("SET", key, f"Invalid argument '{typed}', must be {{manual,auto,mdi}}")
            self.mode = word
        elif key == "ESTOP":
            self.estop = word == "ON"
        elif key == "MACHINE":
            self.machine_on = word == "ON"
        elif key == "PROBE_CLEAR":
            self.probe_tripped = False
        elif key == "ABORT":
            self._queue.clear()
            self._current = None
        elif key == "MDI":
            parts = line.split(None, 2)
            if not self._mdi(parts[2] if len(parts) == 3 else "") and self.line == "master":
                return self._nak("SET", key)  # 2.9 with wait received: ACKed; the reason waits in `get error`
        if not self.verbose:
            return ""
        return f"SET {key} ACK" + ("\n\r" if self.line == "2.9" else "\r\n")

    def _interp_work(self) -> np.ndarray:
        """Return the interpreter's position (#5420-#5422): the last queued target, in work coordinates."""
        last = self._queue[-1].target if self._queue else self._current[0].target if self._current else self.pos
        return np.array([last[a] for a in "XYZ"]) - self._shift()

    def _mdi(self, code: str) -> bool:
        """Run or queue one MDI block; False (and the error text set) if LinuxCNC would refuse it."""
        if self.mode != "MDI":
            self.error_text = "Must be in MDI mode to issue MDI command"
            return False
        self.mdi_log.append(code)
        m = _DEBUG.match(code.strip())
        if m:
            interp = self._interp_work()
            values = {**self.params, 5420: float(interp[0]), 5421: float(interp[1]), 5422: float(interp[2])}
            self.display_text = re.sub(r"#(\d+)", lambda g: f"{values.get(int(g.group(1)), 0.0):f}", m.group(1))
            return True
        if _G38.search(code):
            return self._g38(code)
        code = _MODAL.sub("", code).strip()
        if not re.sub(r"\([^)]*\)", "", code).strip():
            return True  # modal settings or a comment only
        try:
            blk = self._parse_block(self.accepted_seq + 1, self._to_machine(code))
        except ValueError as exc:
            self.error_text = f"MDI: {exc}"
            return False
        self.accepted_seq += 1
        self._queue.append(blk)
        self.executed.append(code)
        self.max_queued = max(self.max_queued, self._queued())
        self._advance(self.clock.now())
        return True

    def _g38(self, code: str) -> bool:
        """Probe from the present position towards the block's target (G38.2), at once in simulated time."""
        if self._queued():
            self.error_text = "G38.2: the MDI queue is still moving"  # the virtual machine probes from rest only
            return False
        target = dict(self.pos)
        for letter, value in _XYZ.findall(self._to_machine(code)):
            target[letter.upper()] = float(value)
        start = np.array([self.pos[a] for a in "XYZ"])
        end = np.array([target[a] for a in "XYZ"])
        dist = float(np.linalg.norm(end - start))
        if dist < 1e-6:
            self.error_text = "Start point too close to probe point"
            return False
        hit = self._probe(start, (end - start) / dist, dist, self.clock.now())
        point = end if hit is None else hit
        work = point - self._shift()  # #5061-#5063: in the work system the G38.2 ran in
        self.params.update({5061: float(work[0]), 5062: float(work[1]), 5063: float(work[2])})
        self.params[5070] = 0.0 if hit is None else 1.0
        self.probe_tripped = hit is not None
        for i, a in enumerate("XYZ"):
            self.pos[a] = float(point[i])
        if hit is None:
            self.error_text = "G38.2 move finished without making contact."
        return True

    def axis_positions(self) -> dict[str, float]:
        """Return the present positions in machine coordinates (the laser's stage reads them too)."""
        return {a: self.pos[a] for a in AXES}
