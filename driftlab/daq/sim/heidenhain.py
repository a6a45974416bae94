"""A simulated Heidenhain control answering LSV2 over TCP: the telegrams a read-only client needs.

Written from pyLSV2 1.8.0 (the MIT-licensed client driftlab uses, drunsinn/pyLSV2), which is the
public description of the protocol:

* ``low_level_com.py`` (``LSV2TCP``): TCP port 19000; a telegram is the payload length as a 4-byte
  big-endian unsigned integer, a 4-character command or response and the payload; the client
  reads a reply's header in one ``recv`` of its buffer size (256 bytes until a larger one is
  negotiated); an error reply ``T_ER`` (or ``T_BD``) carries two bytes, error type and code;
* ``client.py``: the connection set-up (``_configure_connection``): ``A_LG`` INSPECT, ``R_VR``
  (versions: four NUL-terminated strings; with a one-byte parameter ID, RELEASE_TYPE or
  SPLC_VERSION a single string, or ``T_ER`` where not supported), ``R_PR`` (system parameters),
  ``R_CI`` (turbo mode, DNC allowed, axes sampling rate), ``C_CC`` buffer size and secure file
  send, ``A_LG`` FILE; reading ``R_RI`` needs the ``DNC`` login;
* ``misc.py``: ``decode_system_parameters`` (120 bytes, ``!14L8B8L2BH4B2L2HL``; the maximum block
  length is field 32), ``decode_system_information`` (8 bytes: type 1 bool or 2 integer, then the
  value), ``decode_axis_location`` (a byte, the number of axes, then the values and then the axis
  names as NUL-terminated strings);
* ``const.py``: the commands (A_LG, A_LO, R_VR, R_PR, R_CI, C_CC, R_RI), responses (T_OK, T_ER,
  S_VR, S_PR, S_CI, S_RI), parameters (``ParRRI`` AXIS_LOCATION 22, EXEC_STATE 23, PGM_STATE 26;
  ``ParCCC`` SET_BUF512..4096, SECURE_FILE_SEND 19) and status codes (``T_ER_UNKNOWN_TELE`` 22,
  ``T_ER_NO_PRIV`` 23, ``T_ER_WRONG_PARA`` 24).

The axes are the machine's own (``pos``, settable; or a :class:`~driftlab.daq.sim.instruments.Stage`
such as the virtual machine's controller). Anything else (file transfer, keys, PLC writes) is
answered ``T_ER`` unknown telegram: the simulator is the control as a read-only client sees it.
"""

from __future__ import annotations

import struct

from driftlab.daq.sim.instruments import Clock, LineServer, Stage
from driftlab.vocabulary import AXES

LOGINS = ("INSPECT", "FILE", "DNC", "MONITOR", "DIAGNOSTICS")
AXIS_LOCATION, EXEC_STATE, PGM_STATE = 22, 23, 26  # const.ParRRI
SET_BUFFERS = {3: 1024, 4: 512, 5: 2048, 6: 3072, 7: 4096}  # const.ParCCC SET_BUF*
SECURE_FILE_SEND = 19
T_ER_UNKNOWN_TELE, T_ER_NO_PRIV, T_ER_WRONG_PARA = 22, 23, 24
EXEC_AUTOMATIC, PGM_IDLE = 4, 7  # const.ExecState, const.PgmState


def telegram(code: str, payload: bytes = b"") -> bytes:
    """Return one LSV2 telegram: payload length (4 bytes, big-endian), the 4-character code, the payload."""
    return struct.pack("!L", len(payload)) + code.encode("ascii") + payload


def system_parameters(max_block_length: int = 4096, lsv2_version: int = 1) -> bytes:
    """Return an ``S_PR`` payload (120 bytes, pyLSV2 ``decode_system_parameters``) with the given block length."""
    fields: list[int] = [0] * 42
    fields[30], fields[32] = lsv2_version, max_block_length
    return struct.pack("!14L8B8L2BH4B2L2HL", *fields)


class SimLSV2(LineServer):
    """A Heidenhain TNC's LSV2 service (read-only telegrams) with the machine's axes."""

    name = "lsv2"

    def __init__(
        self,
        clock: Clock,
        stage: Stage | None = None,
        control: str = "TNC640",
        nc_software: str = "340595 10 SP5",
        axes: tuple[str, ...] = AXES,
        dnc_allowed: bool = True,
    ) -> None:
        super().__init__()
        self.clock, self.stage = clock, stage
        self.control, self.nc_software = control, nc_software
        self.axes = axes
        self.dnc_allowed = dnc_allowed
        self.pos: dict[str, float] = {a: 0.0 for a in axes}
        #: bytes after the axis names (R_RI data pyLSV2 cannot parse, e.g. a name too many: its LSV2DataException)
        self.axis_trailer = b""
        self.exec_state, self.pgm_state = EXEC_AUTOMATIC, PGM_IDLE
        self.telegrams: list[str] = []  # every command received, in order (what a client asked of the control)
        self.on_connect()

    def on_connect(self) -> None:
        """A new connection: no logins, the smallest buffer."""
        self.logins: set[str] = set()
        self.buffer = 256

    def split_frames(self, buf: bytes) -> tuple[list[bytes], bytes]:
        """Return the complete telegrams in ``buf`` (length-prefixed) and the bytes of one still arriving."""
        frames = []
        while len(buf) >= 8:
            n = struct.unpack("!L", buf[:4])[0]
            if len(buf) < 8 + n:
                break
            frames.append(buf[: 8 + n])
            buf = buf[8 + n :]
        return frames, buf

    def _reply(self, line: bytes) -> bytes | None:
        """Answer one telegram (binary: no line ends), with the injected faults applied to its command."""
        code = line[4:8].decode("ascii", errors="replace")
        with self._lock:
            self.received.append(code)
            self.telegrams.append(code)
            reply = self.answer(code, bytes(line[8:]))
            fault = self._take_fault(code)
        if fault == "drop":
            return b""
        if fault == "timeout":
            return None
        if fault == "garble":
            return b"\x00\x00"  # shorter than a header: pyLSV2 raises its protocol exception
        return reply

    def handle(self, line: str) -> str | None:  # pragma: no cover - telegrams are binary, see _reply
        """Not used: LSV2 telegrams are answered by :meth:`answer`."""
        return None

    def _error(self, code: int) -> bytes:
        return telegram("T_ER", struct.pack("!BB", 1, code))

    def positions(self) -> dict[str, float]:
        """Return the axes' present positions (from the stage when one is given)."""
        if self.stage is None:
            return dict(self.pos)
        t = self.clock.now()
        return {a: float(self.stage.where(a, t)[0]) for a in self.axes}

    def where(self, axis: str, t_s: float) -> tuple[float, int]:
        """Return (position, +1) of ``axis``: the control is a Stage for a simulated laser beside it."""
        return self.positions()[axis], 1

    def answer(self, code: str, payload: bytes) -> bytes:
        """Return the reply telegram to ``code`` with ``payload``."""
        if code == "A_LG":
            name = payload.split(b"\x00", 1)[0].decode("ascii", errors="replace")
            if name not in LOGINS or (name == "DNC" and not self.dnc_allowed):
                return self._error(T_ER_NO_PRIV)
            self.logins.add(name)
            return telegram("T_OK")
        if code == "A_LO":
            name = payload.split(b"\x00", 1)[0].decode("ascii", errors="replace")
            if name:
                self.logins.discard(name)
            else:
                self.logins.clear()
            return telegram("T_OK")
        if "INSPECT" not in self.logins:
            return self._error(T_ER_NO_PRIV)
        if code == "R_VR":
            if not payload:
                parts = (self.control, self.nc_software, "PLC 340595 10", "000000000000")
                return telegram("S_VR", b"".join(p.encode("ascii") + b"\x00" for p in parts))
            if payload[:1] == b"\x05":
                return telegram("S_VR", b"1234567-01\x00")
            return self._error(T_ER_WRONG_PARA)
        if code == "R_PR":
            return telegram("S_PR", system_parameters())
        if code == "R_CI" and len(payload) == 4:
            which = struct.unpack("!L", payload)[0]
            if which == 2:
                return telegram("S_CI", struct.pack("!L3x?", 1, self.dnc_allowed))
            return self._error(T_ER_WRONG_PARA)
        if code == "C_CC" and len(payload) >= 2:
            cmd = struct.unpack("!H", payload[:2])[0]
            if cmd in SET_BUFFERS:
                self.buffer = SET_BUFFERS[cmd]
                return telegram("T_OK")
            if cmd == SECURE_FILE_SEND:
                return telegram("T_OK")
            return self._error(T_ER_WRONG_PARA)
        if code == "R_RI" and len(payload) == 2:
            if "DNC" not in self.logins:
                return self._error(T_ER_NO_PRIV)
            which = struct.unpack("!H", payload)[0]
            if which == AXIS_LOCATION:
                return telegram("S_RI", self._axis_location())
            if which == EXEC_STATE:
                return telegram("S_RI", struct.pack("!H", self.exec_state))
            if which == PGM_STATE:
                return telegram("S_RI", struct.pack("!H", self.pgm_state))
            return self._error(T_ER_WRONG_PARA)
        return self._error(T_ER_UNKNOWN_TELE)

    def _axis_location(self) -> bytes:
        """Return the R_RI AXIS_LOCATION payload: a byte, the axis count, the values, the names (NUL-terminated)."""
        pos = self.positions()
        out = bytearray(b"\x00" + struct.pack("!b", len(self.axes)))
        for a in self.axes:
            out += f"{pos[a]:.4f}".encode("ascii") + b"\x00"
        for a in self.axes:
            out += a.encode("ascii") + b"\x00"
        return bytes(out) + self.axis_trailer


def lsv2_resource(server: SimLSV2) -> str:
    """Return the rig resource (host:port) of a simulated control."""
    return f"127.0.0.1:{server.port}"
