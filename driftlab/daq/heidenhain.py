"""A Heidenhain TNC read through LSV2 with the ``pyLSV2`` library: identification, axis positions, states.

LSV2 is Heidenhain's own protocol; it is not published by Heidenhain, and pyLSV2 (drunsinn/pyLSV2,
MIT) is the public implementation of it, so the library is used as it is (``pip install
driftlab[lsv2]``) and this module only wraps it. What the wrapper relies on, from pyLSV2 1.8.0:

* ``LSV2(hostname, port, timeout, safe_mode)``, ``connect()`` (login INSPECT, versions, system
  parameters, buffer size, login FILE), ``disconnect()``; ``versions.control`` and ``versions.nc_sw``;
* ``axes_location()``: ``R_RI`` AXIS_LOCATION, ``{axis name: position}``, None if refused;
  ``execution_state()`` (``ExecState``: MANUAL, MDI, PASS_REFERENCES, SINGLE_STEP, AUTOMATIC) and
  ``program_status()`` (``PgmState``); all three need the ``DNC`` login, which pyLSV2's safe mode
  withholds. The link therefore turns safe mode off - and sends nothing but read telegrams
  (A_LG/A_LO, R_VR, R_PR, R_CI, R_RI and the C_CC buffer/secure-transfer settings of the set-up;
  the tests check the simulated control saw no other);
* ``last_error`` and ``translate_messages.get_error_text`` for a refused telegram's reason.

It is a read-only link: LSV2 gives no documented MDI move or probing command a third party can
drive and test the way linuxcncrsh gives them, so :meth:`HeidenhainLink.send_program` refuses in one
line and a campaign needs a link that moves the machine (``linuxcnc``, ``thesis-rs232``); `rig check`
and :meth:`position` read the control. Positions are the control's own, in its display units
(mm, deg): ``axes`` maps driftlab's X Y Z A B to the control's axis names (e.g. ``{B: C}``).

Faults: a timeout, a refused connection or a broken reply drops the connection; the read is
repeated once on a new one (all calls are reads), then it is a one-line :class:`InstrumentError`.
"""

from __future__ import annotations

import math
import socket
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from driftlab.daq.protocols import StreamReport
from driftlab.errors import InstrumentError, ValidationError
from driftlab.vocabulary import AXES

DEFAULT_PORT = 19000  # pyLSV2 low_level_com.LSV2TCP.DEFAULT_PORT


class _NoReply(Exception):
    """pyLSV2 got no reply telegram at all (its last response NONE): the line, not the control, failed."""


_TRANSIENT: tuple[type[BaseException], ...] = (OSError, socket.timeout, EOFError, _NoReply)


def lsv2_address(resource: str) -> tuple[str, int]:
    """Return (host, port) of an LSV2 resource: ``host`` or ``host:port`` (default port 19000)."""
    text = resource.strip()
    host, _, port = text.partition(":")
    if not host or "/" in text or "::" in text:
        raise ValidationError(f"LSV2 resource {resource!r}: give host or host:port")
    try:
        return host, int(port) if port else DEFAULT_PORT
    except ValueError:
        raise ValidationError(f"LSV2 resource {resource!r}: the port is a number") from None


def _library() -> Any:
    try:
        # optional extra (driftlab[lsv2]): imported where a link opens, so the rest runs without it
        import pyLSV2
    except ImportError:
        raise InstrumentError(
            "the heidenhain-lsv2 driver needs the pyLSV2 package: pip install driftlab[lsv2]"
        ) from None
    return pyLSV2


class HeidenhainLink:
    """A Heidenhain TNC through LSV2 (pyLSV2): positions and states read, motion refused (driver heidenhain-lsv2)."""

    read_only = True

    def __init__(
        self,
        host: str,
        port: int = DEFAULT_PORT,
        timeout_s: float = 5.0,
        axes: Mapping[str, str] | None = None,
        connect: Callable[[], Any] | None = None,
    ) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        names = dict(axes or {a: a for a in AXES})
        unknown = sorted(set(names) - set(AXES))
        if unknown:
            raise ValidationError(f"LSV2 axes: {unknown[0]!r} is not one of {', '.join(AXES)}")
        self.axes = names
        self._factory = connect
        self._client: Any | None = None
        self.reconnects = 0

    @classmethod
    def open(cls, resource: str, timeout_s: float = 5.0, **options: Any) -> HeidenhainLink:
        """Return a link to ``host[:port]``, connected (connection set-up and INSPECT/FILE logins done)."""
        host, port = lsv2_address(resource)
        link = cls(host, port, timeout_s, **options)
        link._session()
        return link

    def _session(self) -> Any:
        self._drop()
        lib = _library()
        try:
            client = (
                self._factory() if self._factory else lib.LSV2(self.host, self.port, self.timeout_s, safe_mode=False)
            )
            client.connect()
        except _TRANSIENT + (lib.LSV2ProtocolException, lib.LSV2StateException, lib.LSV2DataException) as exc:
            raise InstrumentError(f"LSV2 {self.host}:{self.port}: cannot connect ({_reason(exc)})") from exc
        self._client = client
        return client

    def _drop(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            try:
                client._llcom.disconnect()  # no logout telegrams on a line that may be gone
            except Exception:  # noqa: BLE001 - the line is gone anyway
                pass

    def _read(self, what: str, fn: Callable[[Any], Any]) -> Any:
        """Return ``fn(client)``; after a transient fault reconnect and read once more, then InstrumentError."""
        lib = _library()
        # LSV2DataException: pyLSV2 could not parse a reply's data (``misc.decode_axis_location``: "error while
        # parsing axis data"): read once more on a new connection, then one line, never the library's exception
        faults = _TRANSIENT + (lib.LSV2ProtocolException, lib.LSV2StateException, lib.LSV2DataException, ValueError)
        for attempt in (1, 2):
            try:
                client = self._client if self._client is not None else self._session()
                return fn(client)
            except faults as exc:
                self._drop()
                if attempt == 2:
                    raise InstrumentError(f"LSV2 {what}: {_reason(exc)} (gave up after 2 attempts)") from exc
                self.reconnects += 1
        raise AssertionError("unreachable")  # pragma: no cover

    def _refused(self, what: str, client: Any) -> Exception:
        """Return the exception for a read pyLSV2 answered with nothing: a lost line, or the control's T_ER."""
        lib = _library()
        err = client.last_error
        if err.e_type == -1:  # no T_ER telegram came back: the connection, not the control
            return _NoReply("no reply from the control")
        try:
            text = lib.get_error_text(err)
        except Exception:  # noqa: BLE001 - a code the translations lack
            text = str(err)
        return InstrumentError(
            f"LSV2 {what}: the control refused it ({text}; type {err.e_type}, code {int(err.e_code)})"
        )

    # -- reads
    def identify(self) -> str:
        """Return ``Heidenhain <control> NC <software>`` from the versions read at connection."""
        client = self._client if self._client is not None else self._read("versions", lambda c: c)
        return f"Heidenhain {client.versions.control} NC {client.versions.nc_sw}"

    def position(self) -> dict[str, float]:
        """Return the actual positions of the mapped axes (X, Y, Z mm; A, B deg) as the control shows them."""

        def read(client: Any) -> dict[str, float]:
            got = client.axes_location()
            if got is None:
                raise self._refused("axes_location (needs the DNC login)", client)
            return got

        got = self._read("axes_location", read)
        out = {}
        for axis, name in self.axes.items():
            if name not in got:
                raise InstrumentError(f"LSV2: the control has no axis {name!r} for {axis} (it has {', '.join(got)})")
            value = float(got[name])
            if not math.isfinite(value):
                raise InstrumentError(f"LSV2: non-finite position of {name}")
            out[axis] = value
        return out

    def execution_state(self) -> str:
        """Return the control's operating mode (MANUAL, MDI, PASS_REFERENCES, SINGLE_STEP, AUTOMATIC)."""

        def read(client: Any) -> str:
            state = client.execution_state()
            if state.name == "UNDEFINED":
                raise self._refused("execution_state (needs the DNC login)", client)
            return str(state.name)

        return str(self._read("execution_state", read))

    def program_state(self) -> str:
        """Return the state of the selected NC program (STARTED, STOPPED, FINISHED, ..., IDLE)."""
        return str(self._read("program_status", lambda c: c.program_status()).name)

    # -- MachineLink, read-only
    def send_program(self, lines: Iterable[str], low_water: int = 0, wait: bool = True) -> StreamReport:
        """Refuse: LSV2 has no documented MDI; a campaign needs a link that moves the machine."""
        raise InstrumentError(
            "heidenhain-lsv2 reads the control only: LSV2 has no documented MDI move; "
            "drive the machine through linuxcnc or thesis-rs232"
        )

    def buffer_free(self) -> int:
        """Refuse, as :meth:`send_program`: no program is streamed over LSV2."""
        raise InstrumentError("heidenhain-lsv2 streams no program: it has no buffer")

    def close(self) -> None:
        """Log out and close the connection (the control is untouched)."""
        client, self._client = self._client, None
        if client is not None:
            try:
                client.disconnect()
            except Exception:  # noqa: BLE001 - closing a line that may be gone
                pass


def _reason(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
