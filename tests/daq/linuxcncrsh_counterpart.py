"""Counterparts of linuxcncrsh v2.9.10 and master, written from LinuxCNC's source, not from driftlab's code.

Sources read (the LinuxCNC tree, tag v2.9.10 and master at 5c41560ebb):

* src/emc/usr_intf/emcrsh.cc at v2.9.10: ``readClient`` echoes the raw bytes read when echo is on
  and the session linked (so never the first hello), splits lines on CR or LF; ``parseCommand``:
  an unknown command gets no reply, ``set`` before a hello ``SET NAK\\r\\n``; ``commandHello`` needs
  password, client and version; ``commandSet`` replies end in LF CR (``"SET %s ACK\\n\\r"``), a key
  from INIFILE on needs ``set enable``, a key after MACHINE needs the machine on, and every refusal
  is a bare ``SET <KEY> NAK`` (an unknown key included); ``commandGet`` needs no hello, replies
  ``<KEY> ...\\r\\n`` or ``GET <KEY> NAK\\r\\n``; ``getAbsActPos``/``getRelActPos`` print six ``%f``,
  or ``<KEY> <n> <v>`` for ``atoi`` of the argument; ``getRelActPos`` subtracts G5x and G92
  offsets only; ``set set_wait``, ``get set_wait`` -> ``SET_WAIT RECEIVED``;
  ``getProbeTripped`` ``%d``; ``sendMdiCmd`` (shcom.cc) with wait received returns once the task has
  the command, so a block the task refuses is still ``SET MDI ACK`` and the reason is in ``get error``.
* src/emc/usr_intf/emcrsh.cc on master: CR LF everywhere; an unknown command ``error: Command 'x'
  not found`` (not echoed); ``commandGetSet``: an unknown key ``error: Subcommand not found: SET X``
  then ``SET NAK``; access levels per key (hello, enable, machine on) each refused with its
  ``error:`` line then ``SET <KEY> NAK``; ``set wait_mode``, no ``set_wait``; ``printPose`` nine
  ``{:f}`` values, one axis ``<KEY> <letter> <v>`` (``axisLetter`` or a number); a "remote" setter
  (``MDI``, ``MODE``, ``PROBE_CLEAR``) is answered once the task has it, ``SET <KEY> NAK`` if its
  status is ERROR; ``getProbeTripped`` ``YES``/``NO``.
* docs/src/man/man1/linuxcncrsh.1.adoc (master) and docs/man/man1/linuxcncrsh.1 (2.9): the
  commands; tests/linuxcncrsh/expected-telnet-output (master): the reply texts
  (``ERROR Must be in MDI mode to issue MDI command``, ``error: Machine must be 'ON' for SET MODE``).
* The G-code manual: G38.2 trip point in #5061-#5063 in the current work system, #5070 1/0,
  #5420-#5422 the current position; rs274ngc ``convert_param_comment`` prints parameters ``%lf``;
  motion's ``G38.2 move finished without making contact.`` (control.c).

The machine behind it is deliberately small: moves happen at once (the next ``get program_status``
says ``RUNNING`` once, then ``IDLE``), a work offset ``g5x`` and a tool length offset ``tlo_z``
separate machine from work coordinates (work = machine - g5x - (0, 0, tlo_z)), and spheres are
probed in machine coordinates. ``g5x_rotation_deg`` rotates the work system about Z as G10 L2 R
does, which REL_ACT_POS does not show.
"""

# the servers' own printf formats ("%f") are kept as written in emcrsh.cc
# ruff: noqa: UP031

from __future__ import annotations

import math
import re
import socket
import threading
from dataclasses import dataclass, field

AXES9 = "XYZABCUVW"
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")


@dataclass
class Machine:
    """The state a linuxcncrsh session reads: task state, positions, offsets, the probe, messages."""

    estop: bool = False
    machine_on: bool = True
    mode: str = "MANUAL"
    pos: list[float] = field(default_factory=lambda: [0.0] * 9)  # machine coordinates
    g5x: list[float] = field(default_factory=lambda: [0.0] * 9)
    tlo_z: float = 0.0
    g5x_rotation_deg: float = 0.0
    spheres: list[tuple[tuple[float, float, float], float]] = field(default_factory=list)  # centre, reach
    error: str = ""
    display: str = ""
    tripped: bool = False
    params: dict[int, float] = field(default_factory=dict)
    running_polls: int = 0
    mdi_log: list[str] = field(default_factory=list)
    moved: int = 0  # every move the machine made (a check must leave it at 0)

    def work_to_machine(self, w: list[float]) -> list[float]:
        c, s = math.cos(math.radians(self.g5x_rotation_deg)), math.sin(math.radians(self.g5x_rotation_deg))
        x, y = c * w[0] - s * w[1], s * w[0] + c * w[1]
        out = [x, y, *w[2:]]
        out = [v + o for v, o in zip(out, self.g5x, strict=True)]
        out[2] += self.tlo_z
        return out

    def machine_to_work(self, m: list[float]) -> list[float]:
        v = [a - o for a, o in zip(m, self.g5x, strict=True)]
        v[2] -= self.tlo_z
        c, s = math.cos(math.radians(self.g5x_rotation_deg)), math.sin(math.radians(self.g5x_rotation_deg))
        return [c * v[0] + s * v[1], -s * v[0] + c * v[1], *v[2:]]

    def rel(self) -> list[float]:
        """REL_ACT_POS as both lines compute it: machine less G5x (and G92, zero here) offsets."""
        return [a - o for a, o in zip(self.pos, self.g5x, strict=True)]

    def execute(self, code: str) -> bool:
        """Run one MDI block as the task would; False (and the error set) when the task refuses it."""
        if self.mode != "MDI":
            self.error = "Must be in MDI mode to issue MDI command"
            return False
        self.mdi_log.append(code)
        text = code.strip()
        debug = re.match(r"^\(DEBUG,(.*)\)$", text, re.IGNORECASE)
        if debug:
            work = self.machine_to_work(self.pos)
            values = {**self.params, 5420: work[0], 5421: work[1], 5422: work[2]}
            self.display = re.sub(r"#(\d+)", lambda m: "%f" % values.get(int(m.group(1)), 0.0), debug.group(1))
            return True
        words = _WORD.findall(re.sub(r"\([^)]*\)", "", text.upper()))
        gs = {float(v) for k, v in words if k == "G"}
        target = self.machine_to_work(self.pos)
        axis_words = {k: float(v) for k, v in words if k in AXES9}
        for k, v in axis_words.items():
            target[AXES9.index(k)] = v
        if not axis_words:
            return True  # modal words only (G21 G90, F, G4 dwell at once)
        goal = self.work_to_machine(target)
        if 38.2 in gs:
            return self._probe(goal)
        self.pos = goal
        self.moved += 1
        self.running_polls = 1
        return True

    def _probe(self, goal: list[float]) -> bool:
        start = self.pos[:3]
        d = [g - s for g, s in zip(goal[:3], start, strict=True)]
        dist = math.sqrt(sum(v * v for v in d))
        if dist < 1e-9:
            self.error = "Start point too close to probe point"
            return False
        u = [v / dist for v in d]
        best = None
        for centre, reach in self.spheres:
            w = [s - c for s, c in zip(start, centre, strict=True)]
            b = sum(a * c for a, c in zip(w, u, strict=True))
            disc = b * b - (sum(a * a for a in w) - reach * reach)
            if disc >= 0 and (lam := -b - math.sqrt(disc)) >= 0 and lam <= dist and (best is None or lam < best):
                best = lam
        hit = [s + (dist if best is None else best) * e for s, e in zip(start, u, strict=True)]
        self.pos = [*hit, *self.pos[3:]]
        self.moved += 1
        self.running_polls = 1
        self.tripped = best is not None
        work = self.machine_to_work(self.pos)
        self.params.update({5061: work[0], 5062: work[1], 5063: work[2], 5070: 1.0 if self.tripped else 0.0})
        if best is None:
            self.error = "G38.2 move finished without making contact."
        return True

    def program_status(self) -> str:
        if self.running_polls > 0:
            self.running_polls -= 1
            return "RUNNING"
        return "IDLE"


class Session:
    """One client's state (both lines keep echo, verbose, linked and enabled per connection)."""

    def __init__(self) -> None:
        self.echo, self.verbose, self.linked, self.enabled = True, False, False, False
        self.wait = "RECEIVED"


class Server:
    """A linuxcncrsh of one line on 127.0.0.1 (ephemeral port); subclasses answer a line of bytes."""

    line = ""

    def __init__(self, machine: Machine | None = None, name: str = "EMCNETSVR") -> None:
        self.machine = machine or Machine()
        self.name = name
        self.received: list[str] = []
        self.lock = threading.Lock()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(4)
        self._stop = False
        self._thread = threading.Thread(target=self._accept, daemon=True)

    @property
    def resource(self) -> str:
        return f"127.0.0.1:{self._sock.getsockname()[1]}"

    def __enter__(self) -> Server:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop accepting and release the port (a server never started just releases it)."""
        self._stop = True
        if not self._thread.is_alive():
            self._sock.close()
            return
        try:
            socket.create_connection(self._sock.getsockname(), timeout=1).close()
        except OSError:
            pass
        self._thread.join(timeout=5)
        self._sock.close()

    def _accept(self) -> None:
        while not self._stop:
            conn, _ = self._sock.accept()
            if self._stop:
                conn.close()
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        session, pending = Session(), b""
        with conn:
            while True:
                try:
                    data = conn.recv(1600)
                except OSError:
                    return
                if not data:
                    return
                out = self.on_read(session, data)
                pending += data
                *lines, pending = re.split(rb"[\r\n]", pending)
                with self.lock:
                    for raw in lines:
                        if raw:
                            text = raw.decode("ascii")
                            self.received.append(text)
                            out += self.command(session, text)
                if out:
                    conn.sendall(out)

    def on_read(self, session: Session, data: bytes) -> bytes:
        return b""

    def command(self, session: Session, text: str) -> bytes:
        raise NotImplementedError


# the v2.9.10 subcommand table's order decides its access checks (commandSet: >= INIFILE needs
# enable, > MACHINE needs the machine on); only the keys up to those the tests use
_V29_KEYS = [
    "ECHO", "VERBOSE", "ENABLE", "CONFIG", "COMM_MODE", "COMM_PROT", "INIFILE", "PLAT", "INI", "DEBUG",
    "SET_WAIT", "WAIT", "TIMEOUT", "UPDATE", "ERROR", "OPERATOR_DISPLAY", "OPERATOR_TEXT", "TIME", "ESTOP",
    "MACHINE", "MODE", "MIST", "FLOOD", "LUBE", "LUBE_LEVEL", "SPINDLE", "BRAKE", "TOOL", "TOOL_OFFSET",
    "LOAD_TOOL_TABLE", "HOME", "JOG_STOP", "JOG", "JOG_INCR", "FEED_OVERRIDE", "ABS_CMD_POS", "ABS_ACT_POS",
    "REL_CMD_POS", "REL_ACT_POS", "JOINT_POS", "POS_OFFSET", "JOINT_LIMIT", "JOINT_FAULT", "JOINT_HOMED",
    "MDI", "TASK_PLAN_INIT", "OPEN", "RUN", "PAUSE", "RESUME", "STEP", "ABORT", "PROGRAM", "PROGRAM_LINE",
    "PROGRAM_STATUS", "PROGRAM_CODES", "JOINT_TYPE", "JOINT_UNITS", "PROGRAM_UNITS", "PROGRAM_LINEAR_UNITS",
    "PROGRAM_ANGULAR_UNITS", "USER_LINEAR_UNITS", "USER_ANGULAR_UNITS", "DISPLAY_LINEAR_UNITS",
    "DISPLAY_ANGULAR_UNITS", "LINEAR_UNIT_CONVERSION", "ANGULAR_UNIT_CONVERSION", "PROBE_CLEAR",
    "PROBE_TRIPPED", "PROBE_VALUE", "PROBE", "TELEOP_ENABLE", "KINEMATICS_TYPE", "OVERRIDE_LIMITS",
    "SPINDLE_OVERRIDE", "OPTIONAL_STOP",
]  # fmt: skip
_UNKNOWN = len(_V29_KEYS)


class Linuxcncrsh29(Server):
    """linuxcncrsh as released in v2.9.10."""

    line = "2.9"

    def on_read(self, session: Session, data: bytes) -> bytes:
        # readClient: the raw bytes go back before they are parsed, when echo is on and linked
        return data if session.echo and session.linked else b""

    def command(self, s: Session, text: str) -> bytes:
        toks = text.split()
        verb = toks[0].upper()
        if verb == "HELLO":
            if len(toks) >= 4 and toks[1] == "EMC" and len(toks[2]) < 80 and len(toks[3]) < 8:
                s.linked = True
                return f"HELLO ACK {self.name} 1.1\r\n".encode()
            return b"HELLO NAK\r\n"
        if verb == "GET":
            return self._get(s, toks[1:])
        if verb == "SET":
            if not s.linked:
                return b"SET NAK\r\n"
            return self._set(s, toks[1:], text)
        return b""  # QUIT, SHUTDOWN, HELP aside: an unknown command is answered with nothing

    def _get(self, s: Session, args: list[str]) -> bytes:
        if not args:
            return b"GET NAK\r\n"
        key, m = args[0].upper(), self.machine
        arg = args[1] if len(args) > 1 else None
        onoff = {True: "ON", False: "OFF"}
        out: str | None
        if key in ("ABS_ACT_POS", "REL_ACT_POS"):
            values = (m.pos if key == "ABS_ACT_POS" else m.rel())[:6]
            if arg is None:
                out = key + "".join(" %f" % v for v in values)
            else:
                n = int(re.match(r"[-+]?\d*", arg).group() or 0)  # atoi: a letter reads as 0
                out = f"{key} {n}" + (" %f" % values[n] if 0 <= n < 6 else "")
        elif key == "TOOL_OFFSET":
            out = "TOOL_OFFSET %f" % m.tlo_z
        elif key == "SET_WAIT":
            out = f"SET_WAIT {s.wait}"
        elif key == "ESTOP":
            out = f"ESTOP {onoff[m.estop]}"
        elif key == "MACHINE":
            out = f"MACHINE {onoff[m.machine_on and not m.estop]}"
        elif key == "MODE":
            out = f"MODE {m.mode}"
        elif key == "PROGRAM_STATUS":
            out = f"PROGRAM_STATUS {m.program_status()}"
        elif key == "ERROR":
            out, m.error = f"ERROR {m.error or 'OK'}", ""
        elif key == "OPERATOR_DISPLAY":
            out, m.display = f"OPERATOR_DISPLAY {m.display or 'OK'}", ""
        elif key == "PROBE_TRIPPED":
            out = f"PROBE_TRIPPED {int(m.tripped)}"
        else:
            out = None
        return ((out if out is not None else f"GET {key} NAK") + "\r\n").encode()

    def _set(self, s: Session, args: list[str], text: str) -> bytes:
        if not args:
            return b"SET NAK\n\r"
        key, m = args[0].upper(), self.machine
        nak, ack = f"SET {key} NAK\n\r".encode(), f"SET {key} ACK\n\r".encode()
        idx = _V29_KEYS.index(key) if key in _V29_KEYS else _UNKNOWN
        if idx >= _V29_KEYS.index("INIFILE") and not s.enabled:
            return nak
        if idx > _V29_KEYS.index("MACHINE") and not (m.machine_on and not m.estop):
            return nak
        word = args[1].upper() if len(args) > 1 else None
        ok = True
        if key in ("ECHO", "VERBOSE"):
            ok = word in ("ON", "OFF")
            if ok:
                setattr(s, key.lower(), word == "ON")
        elif key == "ENABLE":
            if len(args) > 1 and args[1] == "EMCTOO":
                s.enabled = True
            elif word == "OFF":
                s.enabled = False
            else:
                ok = False
        elif key == "SET_WAIT":
            ok = word in ("RECEIVED", "DONE")
            if ok:
                s.wait = word
        elif key == "ESTOP":
            ok = word in ("ON", "OFF")
            m.estop = word == "ON" if ok else m.estop
        elif key == "MACHINE":
            ok = word in ("ON", "OFF")
            m.machine_on = word == "ON" if ok else m.machine_on
        elif key == "MODE":
            ok = word in ("MANUAL", "AUTO", "MDI")
            m.mode = word if ok else m.mode
        elif key == "MDI":
            rest = re.split(r"\s+", text.strip(), maxsplit=2)
            m.execute(rest[2] if len(rest) > 2 else "")  # received: the task's verdict goes to `get error`
        elif key == "PROBE_CLEAR":
            m.tripped = False
        else:
            ok = False  # scUnknown and the keys a set cannot take: rtStandardError
        if not ok:
            return nak
        return ack if s.verbose else b""


class LinuxcncrshMaster(Server):
    """linuxcncrsh on master (the 2026 rewrite)."""

    line = "master"

    # key -> access level (0 none, 1 hello, 2 enable, 3 machine on), remote (answered once received)
    KEYS = {
        "ECHO": (0, False), "VERBOSE": (1, False), "ENABLE": (1, False), "WAIT_MODE": (2, False),
        "ESTOP": (2, False), "MACHINE": (2, False), "MODE": (3, True), "MDI": (3, True),
        "PROBE_CLEAR": (3, True), "ERROR": (2, False), "OPERATOR_DISPLAY": (2, False),
        "ABS_ACT_POS": (3, False), "REL_ACT_POS": (3, False), "TOOL_OFFSET": (3, True),
        "PROGRAM_STATUS": (3, False), "PROBE_TRIPPED": (3, False),
    }  # fmt: skip

    def command(self, s: Session, text: str) -> bytes:
        toks = text.split()
        verb = toks[0].upper()
        if verb not in ("GET", "HELLO", "HELP", "QUIT", "SET", "SHUTDOWN"):
            return f"error: Command '{toks[0]}' not found\r\n".encode()
        out = f"{text}\r\n" if s.echo and s.linked and verb != "HELLO" else ""
        if verb == "HELLO":
            if len(toks) < 3:
                return b"error: Too few arguments for 'hello' command\r\n"
            s.linked = s.enabled = False
            if toks[1] != "EMC":
                return b"HELLO NAK\r\n"
            s.linked = True
            return f"HELLO ACK {self.name} 1.1\r\n".encode()
        if verb in ("GET", "SET"):
            out += self._getset(s, verb, toks, text)
        return out.encode()

    def _getset(self, s: Session, verb: str, toks: list[str], text: str) -> str:
        if len(toks) < 2:
            return f"error: Must specify subcommand for {verb}\r\n{verb} NAK\r\n"
        key = toks[1].upper()
        if key not in self.KEYS:
            return f"error: Subcommand not found: {verb} {toks[1]}\r\n{verb} NAK\r\n"
        if verb == "GET":
            return self._get(s, key, toks[2:])
        level, remote = self.KEYS[key]
        m = self.machine
        if len(toks) < 3 and key not in ("PROBE_CLEAR",):
            return f"error: Too few arguments to SET {key}, have 0, need 1 or more\r\nSET {key} NAK\r\n"
        for need, why in (
            (1, "A HELLO must be successfully negotiated"),
            (2, "Connection must be enabled"),
            (3, "Machine must be 'ON'"),
        ):
            if level >= need and not (
                s.linked if need == 1 else s.enabled if need == 2 else (m.machine_on and not m.estop)
            ):
                return f"error: {why} for SET {key}\r\nSET {key} NAK\r\n"
        word = toks[2].upper() if len(toks) > 2 else ""
        nak = f"SET {key} NAK\r\n"
        if key in ("ECHO", "VERBOSE"):
            if word not in ("ON", "OFF", "1", "0", "TRUE", "FALSE", "YES", "NO"):
                return f"error: Invalid argument '{toks[2]}', must be {{on,off}}\r\n" + nak
            setattr(s, key.lower(), word in ("ON", "1", "TRUE", "YES"))
        elif key == "ENABLE":
            if toks[2] == "EMCTOO":
                s.enabled = True
            elif word == "OFF" and s.enabled:
                s.enabled = False
            else:
                return nak
        elif key == "WAIT_MODE":
            if word == "NONE":
                return (
                    "error: Setting 'SET WAIT_MODE' to 'NONE' has been removed as it may cause commands to be lost.\r\n"
                    + nak
                )
            if word not in ("RECEIVED", "DONE"):
                return f"error: Invalid argument '{toks[2]}', must be {{received,done}}\r\n" + nak
            s.wait = word
        elif key in ("ESTOP", "MACHINE"):
            setattr(m, "estop" if key == "ESTOP" else "machine_on", word == "ON")
        elif key == "MODE":
            if word not in ("MANUAL", "AUTO", "MDI"):
                return f"error: Invalid argument '{toks[2]}', must be {{manual,auto,mdi}}\r\n" + nak
            m.mode = word
        elif key == "MDI":
            third = text.split(None, 2)[2] if len(text.split(None, 2)) > 2 else ""
            if not m.execute(third):
                return nak  # the remote setter's status is ERROR once the task has it
        elif key == "PROBE_CLEAR":
            m.tripped = False
        else:
            return nak
        return f"SET {key} ACK\r\n" if s.verbose else ""

    def _get(self, s: Session, key: str, args: list[str]) -> str:
        m = self.machine
        onoff = {True: "ON", False: "OFF"}
        if key in ("ABS_ACT_POS", "REL_ACT_POS"):
            values = m.pos if key == "ABS_ACT_POS" else m.rel()
            if not args or args[0] == "-1":
                return key + "".join(" %f" % v for v in values) + "\r\n"
            a = args[0]
            n = int(a) if re.fullmatch(r"[-+]?\d+", a) else AXES9.find(a.upper()) if len(a) == 1 else -99
            if n == -99:
                return f"GET {key} NAK\r\n"
            if not 0 <= n < 9:
                return f"error: Invalid axis '{a}', must be one of XYZABCUVW\r\nGET {key} NAK\r\n"
            return f"{key} {AXES9[n]} %f\r\n" % values[n]
        if key == "TOOL_OFFSET":
            return "TOOL_OFFSET %f\r\n" % m.tlo_z
        if key == "WAIT_MODE":
            return f"WAIT_MODE {s.wait}\r\n"
        if key == "MODE":
            return f"MODE {m.mode}\r\n"
        if key in ("ESTOP", "MACHINE"):
            return f"{key} {onoff[m.estop if key == 'ESTOP' else (m.machine_on and not m.estop)]}\r\n"
        if key == "PROGRAM_STATUS":
            return f"PROGRAM_STATUS {m.program_status()}\r\n"
        if key == "ERROR":
            text, m.error = m.error, ""
            return f"ERROR {text or 'OK'}\r\n"
        if key == "OPERATOR_DISPLAY":
            text, m.display = m.display, ""
            return f"OPERATOR_DISPLAY {text or 'OK'}\r\n"
        if key == "PROBE_TRIPPED":
            return f"PROBE_TRIPPED {'YES' if m.tripped else 'NO'}\r\n"
        return f"GET {key} NAK\r\n"


LINES = {"2.9": Linuxcncrsh29, "master": LinuxcncrshMaster}
