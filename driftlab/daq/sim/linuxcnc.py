"""A simulated LinuxCNC answering the ``linuxcncrsh`` text protocol, on the virtual machine's motion model.

Written from linuxcncrsh(1) and the server's source (src/emc/usr_intf/emcrsh.cc), and checked
against the recorded session of the real server (tests/linuxcncrsh/expected-telnet-output in the
LinuxCNC tree) - the forms :mod:`driftlab.daq.linuxcnc` is tested with:

* CR LF line ends; ``hello <pw> <client> [<ver>]`` -> ``HELLO ACK <name> <ver>`` / ``HELLO NAK``;
* a linked session echoes each command while echo is on (never the hello); with verbose off a
  successful ``set`` says nothing, with verbose on ``SET <KEY> ACK``; a refused one ``error: ...``
  lines then ``SET <KEY> NAK``; ``set`` needs hello, and ``enable`` for the machine commands;
* ``get`` replies ``<KEY> <value...>``; ``get abs_act_pos`` / ``joint_pos`` nine values ``%f``;
  ``get program_status`` IDLE/RUNNING; ``get error`` ``ERROR OK`` or ``ERROR <text>`` (then cleared);
  ``get operator_display`` the last ``(DEBUG,...)`` message with its parameters expanded;
* ``set mdi`` outside MDI mode: NAK, the error ``Must be in MDI mode to issue MDI command``;
  G38.2 without contact: ``G38.2 move finished without making contact.``; #5061-#5063 the trip
  point, #5070 1 or 0 (G-code manual, G38.x).

Motion (G0/G1/G4 blocks, feeds, the stage the laser reads) is the machine-link simulator's own
(:class:`SimController`); a G38.2 move happens at once in simulated time. The sessions's state
resets at each new connection (echo on, verbose off, not linked), as the server's does.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from driftlab.daq.sim.instruments import SimController
from driftlab.vocabulary import AXES

CONNECT_PASSWORD = "EMC"
ENABLE_PASSWORD = "EMCTOO"
_MODAL = re.compile(r"\bG(?:21|90|94|17|40|49|54|64)(?![\d.])", re.IGNORECASE)
_DEBUG = re.compile(r"^\(DEBUG,(.*)\)$", re.IGNORECASE)
_G38 = re.compile(r"\bG38\.2\b", re.IGNORECASE)


class SimLinuxCNC(SimController):
    """LinuxCNC's linuxcncrsh server on the virtual machine (machine on, out of E-stop, homed)."""

    name = "linuxcncrsh"
    server_name = "driftlab-vm"

    def __init__(self, world: Any, clock: Any, **kwargs: Any) -> None:
        kwargs.setdefault("capacity", 1_000_000)  # LinuxCNC queues MDI commands; no block buffer to fill
        super().__init__(world, clock, **kwargs)
        self.estop = False
        self.machine_on = True
        self.mode = "MANUAL"
        self.error_text = ""
        self.display_text = ""
        self.params: dict[int, float] = {5061: 0.0, 5062: 0.0, 5063: 0.0, 5070: 0.0}
        self.probe_tripped = False
        self.mdi_log: list[str] = []
        self.on_connect()

    def on_connect(self) -> None:
        """A new session: echo on, verbose off, not linked, not enabled, wait mode received."""
        self.echo, self.verbose, self.linked, self.enabled = True, False, False, False
        self.wait_mode = "RECEIVED"

    def handle(self, line: str) -> str | None:
        """Answer one linuxcncrsh command line (several reply lines joined by CR LF)."""
        self._advance(self.clock.now())
        out: list[str] = []
        words = line.split()
        if not words:
            return None
        cmd = words[0].lower()
        if self.echo and self.linked and cmd != "hello":
            out.append(line)
        if cmd == "hello":
            if len(words) >= 3 and words[1] == CONNECT_PASSWORD:
                self.linked, self.enabled = True, False
                out.append(f"HELLO ACK {self.server_name} 1.1")
            else:
                self.linked = self.enabled = False
                out.append("HELLO NAK")
        elif cmd == "get" and len(words) >= 2:
            out.extend(self._get(words[1].upper(), words[2:]))
        elif cmd == "set" and len(words) >= 2:
            out.extend(self._set(words[1].upper(), words[2:], line))
        elif cmd in ("get", "set"):
            out += [f"error: Must specify subcommand for {cmd.upper()}", f"{cmd.upper()} NAK"]
        else:
            out += [f"error: Unknown command '{words[0]}'"]
        return "\r\n".join(out) + "\r" if out else None

    # -- get
    def _pose(self) -> list[float]:
        return [self.pos["X"], self.pos["Y"], self.pos["Z"], self.pos["A"], self.pos["B"], 0.0, 0.0, 0.0, 0.0]

    def _get(self, key: str, args: list[str]) -> list[str]:
        on_off = {True: "ON", False: "OFF"}
        if key in ("ABS_ACT_POS", "ABS_CMD_POS", "JOINT_POS", "REL_ACT_POS"):
            return [key + "".join(f" {v:f}" for v in self._pose())]
        if key == "PROGRAM_STATUS":
            return [f"PROGRAM_STATUS {'RUNNING' if self._queued() else 'IDLE'}"]
        if key == "ERROR":
            text, self.error_text = self.error_text, ""
            return [f"ERROR {text or 'OK'}"]
        if key == "OPERATOR_DISPLAY":
            text, self.display_text = self.display_text, ""
            return [f"OPERATOR_DISPLAY {text or 'OK'}"]
        if key == "ESTOP":
            return [f"ESTOP {on_off[self.estop]}"]
        if key == "MACHINE":
            return [f"MACHINE {on_off[self.machine_on]}"]
        if key == "MODE":
            return [f"MODE {self.mode}"]
        if key in ("ECHO", "VERBOSE", "ENABLE"):
            return [f"{key} {on_off[getattr(self, key.lower() + ('d' if key == 'ENABLE' else ''))]}"]
        if key == "WAIT_MODE":
            return [f"WAIT_MODE {self.wait_mode}"]
        if key == "PROBE_TRIPPED":
            return [f"PROBE_TRIPPED {'YES' if self.probe_tripped else 'NO'}"]
        if key == "PLAT":
            return ["PLAT Linux"]
        return [f"error: Subcommand not found: GET {key}", "GET NAK"]

    # -- set
    def _set(self, key: str, args: list[str], line: str) -> list[str]:
        known = {"ECHO", "VERBOSE", "ENABLE", "WAIT_MODE", "MODE", "MDI", "ESTOP", "MACHINE", "PROBE_CLEAR", "ABORT"}
        if key not in known:
            return [f"error: Subcommand not found: SET {key}", "SET NAK"]
        if key not in ("ECHO", "VERBOSE") and not self.linked:
            return [f"error: A HELLO must be successfully negotiated for SET {key}", f"SET {key} NAK"]
        if key not in ("ECHO", "VERBOSE", "ENABLE") and not self.enabled:
            return [f"error: Connection must be enabled for SET {key}", f"SET {key} NAK"]
        nak = [f"SET {key} NAK"]
        word = args[0].upper() if args else ""
        if key in ("ECHO", "VERBOSE"):
            if word not in ("ON", "OFF"):
                return nak
            setattr(self, key.lower(), word == "ON")
        elif key == "ENABLE":
            if args and args[0] == ENABLE_PASSWORD:
                self.enabled = True
            elif word == "OFF":
                self.enabled = False
            else:
                return nak
        elif key == "WAIT_MODE":
            if word not in ("RECEIVED", "DONE"):
                return nak
            self.wait_mode = word
        elif key == "MODE":
            if word not in ("MANUAL", "AUTO", "MDI"):
                return nak
            if not self.machine_on:
                return ["error: Machine must be 'ON' for SET MODE", "SET MODE NAK"]
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
            code = line.split(None, 2)[2] if len(line.split(None, 2)) == 3 else ""
            if not self._mdi(code):
                return nak
        return [f"SET {key} ACK"] if self.verbose else []

    def _mdi(self, code: str) -> bool:
        """Run or queue one MDI block; False (and the error text set) if LinuxCNC would refuse it."""
        if self.mode != "MDI":
            self.error_text = "Must be in MDI mode to issue MDI command"
            return False
        self.mdi_log.append(code)
        m = _DEBUG.match(code.strip())
        if m:
            self.display_text = re.sub(r"#(\d+)", lambda g: f"{self.params.get(int(g.group(1)), 0.0):f}", m.group(1))
            return True
        if _G38.search(code):
            return self._g38(code)
        code = _MODAL.sub("", code).strip()
        if not re.sub(r"\([^)]*\)", "", code).strip():
            return True  # modal settings or a comment only
        try:
            blk = self._parse_block(self.accepted_seq + 1, code)
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
        for letter, value in re.findall(r"([XYZ])\s*([-+]?\d*\.?\d+)", code.upper()):
            target[letter] = float(value)
        start = np.array([self.pos[a] for a in "XYZ"])
        end = np.array([target[a] for a in "XYZ"])
        dist = float(np.linalg.norm(end - start))
        if dist < 1e-6:
            self.error_text = "Start point too close to probe point"
            return False
        hit = self._probe(start, (end - start) / dist, dist, self.clock.now())
        point = end if hit is None else hit
        self.params.update({5061: float(point[0]), 5062: float(point[1]), 5063: float(point[2])})
        self.params[5070] = 0.0 if hit is None else 1.0
        self.probe_tripped = hit is not None
        for i, a in enumerate("XYZ"):
            self.pos[a] = float(point[i])
        if hit is None:
            self.error_text = "G38.2 move finished without making contact."
        return True

    def axis_positions(self) -> dict[str, float]:
        """Return the present positions (the laser's stage reads them too)."""
        return {a: self.pos[a] for a in AXES}
