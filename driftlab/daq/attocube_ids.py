"""The attocube IDS3010 laser displacement interferometer through its published remote interface.

Of the laser systems the issue lists, this is the one whose remote command set is published in full:
the HP-IB codes of the thesis' HP 5528A-family processor, the Keysight 5530's measurement-board
library, API's and Renishaw XL-80's interfaces are not in any public manual or source that could be
found (docs/instruments.md says what was searched); attocube publishes the IDS3010's interface with
its own client code under the MIT licence. This driver is written from that material:

* attocube-systems/IDS-APIs (github), ``python/ACS.py``: JSON-RPC 2.0 over TCP port 9090, one
  request object per call with ``"jsonrpc": "2.0"``, ``"method"``, ``"params"`` (a list),
  ``"id"`` and ``"api": 2``; one reply line ``{"jsonrpc": "2.0", "result": [...], "id": n}`` matched
  to its request by ``id`` (the client keeps replies to other ids); a JSON-RPC ``"error"`` member is
  a failed call; ``result[0]`` is the function's error number (0: none), which
  ``com.attocube.system.errorNumberToString(language, errNo)`` turns into text (language 1: the
  user-friendly message). The client reads replies with ``newline='\\r\\n'``, so a reply line ends
  in CR LF; this driver accepts LF or CR LF.
* ``matlab/displacement_getAbsolutePositions.m`` and its siblings: the request written as one line,
  ``{"jsonrpc": "2.0", "method": "com.attocube.sen.displacement.getAbsolutePositions", "params": [],
  "id": 1, "api": 2}`` + LF, and the reply's ``result`` read as (warning number, value...). This
  driver writes its requests in exactly that form (the conformance tests check the bytes).
* ``python/system.py`` (``com.attocube.sen.system``): ``getCurrentMode`` ("system idle",
  "measurement starting", "measurement running", ...), ``startMeasurement`` (only from "system
  idle"), ``resetAxes`` (displacement of all axes to zero), ``resetError(performRenormalization)``
  (continue after a measurement error), ``getDeviceType`` (e.g. "IDS3010");
  ``python/system_service.py`` (``com.attocube.system``): ``getSerialNumber``,
  ``getFirmwareVersion``, ``errorNumberToString``.
* ``python/displacement.py`` (``com.attocube.sen.displacement``): ``getAxesDisplacement`` ->
  (warning number, displacement of axes 0, 1, 2 in pm); ``getAxisSignalQuality(axis)`` -> (warning
  number, contrast and baseline in permille).
* ``python/ecu.py`` (``com.attocube.ecu``): ``getEnabled``, ``getConnected``,
  ``getTemperatureInDegrees``, ``getPressureInHPa``, ``getHumidityInPercent``,
  ``getRefractiveIndexForCompensation(-1)`` and the compensation modes (0: the ECU's values,
  1: manually set temperature/pressure/humidity, Ciddor's equation; 2: a manual index);
  ``python/manual.py`` (``com.attocube.ecu.manual``): the manual values (axis -1).
* the commit "API-Update for IDS-Firmware 1.9.1" renamed the ``com.attocube.ids.*`` interfaces to
  ``com.attocube.sen.*``: option ``api_namespace`` is ``sen`` (firmware 1.9.1 on) or ``ids`` (before).

The head compensates the refractive index of air itself (the compensation modes above), so its
displacements are lengths in air; :meth:`AttocubeIDS.environment` reads the weather it compensates
with. Not verified against the device: the numeric warning codes (the driver treats any non-zero
warning of a displacement read as a lost beam, as the thesis' processor's beam error), and whether a
firmware accepts requests without the trailing LF (attocube's Python client sends none, its MATLAB
functions send one; this driver sends one).

Optics (table 5.3 terms, as the thesis' processor): linear (LIN) and straightness (STR: a sensor
head facing a straightedge along the travel, ISO 230-1's straightedge method) read the displacement
of one axis (beam); angle (ANG) reads two beams ``angle_spacing_mm`` apart, asin(difference /
spacing). Each point is the mean of ``readings_per_point`` readings after the axis has settled
(ch. 5.5), asked for back to back in one exchange with the contrast check and two settle readings
(attocube's client keeps several requests in flight on one connection and matches replies by id);
a lost beam flags the sample and marks the reference lost until :meth:`reference`.

The count lives in the head: a dropped TCP connection is reopened and, if the head still reports
"measurement running", the datum is kept and a read-only call is repeated; a command (reset,
start) is never repeated after a dropped line, it fails with a one-line :class:`InstrumentError`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from driftlab.daq.laser import LASER_TERMS, Environment, LaserMeasures, SettleOptions
from driftlab.daq.protocols import FLAG_BEAM_BREAK, FLAG_REFERENCE_LOST, Reading
from driftlab.daq.retry import GarbledReply, TransientError
from driftlab.daq.transport import RawPort, SerialPort, close_quietly
from driftlab.errors import InstrumentError, ValidationError

DEFAULT_PORT = 9090  # ACS.py: TCP_PORT
API_VERSION = 2  # ACS.py: apiversion
NAMESPACES = {"sen": "com.attocube.sen", "ids": "com.attocube.ids"}
ECU = "com.attocube.ecu"
SYSTEM_SERVICE = "com.attocube.system"
RUNNING = "measurement running"
PM_PER_MM = 1e9


def ids_url(resource: str) -> str:
    """Return the pyserial URL of an IDS resource: ``host``, ``host:port`` or ``socket://host:port``."""
    text = resource.strip()
    if text.startswith("socket://"):
        return text
    if not text or "/" in text or "::" in text:
        raise ValidationError(f"IDS3010 resource {resource!r}: give host, host:port or socket://host:port")
    return f"socket://{text}" if ":" in text else f"socket://{text}:{DEFAULT_PORT}"


def request_line(method: str, params: list[Any], request_id: int) -> bytes:
    """Return the bytes of one request, in the form of attocube's MATLAB functions (keys in their order, LF)."""
    req = {"jsonrpc": "2.0", "method": method, "params": params, "id": request_id, "api": API_VERSION}
    return json.dumps(req).encode("ascii") + b"\n"


@dataclass(frozen=True)
class IDSOptics:
    """Which beams read which optics, and the angle set-up's beam spacing."""

    displacement_axis: int = 0  # the beam of the linear and straightness set-ups
    angle_axes: tuple[int, int] = (0, 1)  # the two beams of the angle set-up
    angle_spacing_mm: float = 32.0  # their distance apart

    def __post_init__(self) -> None:
        beams = (self.displacement_axis, *self.angle_axes)
        if any(b not in (0, 1, 2) for b in beams) or self.angle_axes[0] == self.angle_axes[1]:
            raise ValidationError(
                "IDS3010 optics: beams are axes 0, 1, 2, and the angle set-up uses two different ones"
            )
        if not self.angle_spacing_mm > 0:
            raise ValidationError("IDS3010 optics: angle_spacing_mm must be positive")


@dataclass(frozen=True)
class IDSSession:
    """How the driver talks to the head: the JSON-RPC namespace of its firmware (``sen`` or ``ids``),
    the least signal contrast (per mille) it trusts, and whether it may start the measurement from
    "system idle" (polling the mode at most ``start_polls`` times)."""

    api_namespace: str = "sen"
    min_contrast_permille: float = 250.0
    start_measurement: bool = True
    start_polls: int = 120


class AttocubeIDS(LaserMeasures):
    """An attocube IDS3010 on the network: an ErrorMeter of table 5.3's laser terms (rig driver attocube-ids3010)."""

    def __init__(
        self,
        connect: Callable[[], RawPort],
        optics: IDSOptics = IDSOptics(),
        settle: SettleOptions = SettleOptions(),
        session: IDSSession = IDSSession(),
    ) -> None:
        if session.api_namespace not in NAMESPACES:
            raise ValidationError(f"IDS3010 api_namespace {session.api_namespace!r}: one of {', '.join(NAMESPACES)}")
        self._connect = connect
        self.optics = optics
        self.ns = NAMESPACES[session.api_namespace]
        self._settle_with(settle)
        self.min_contrast_permille = session.min_contrast_permille
        self.start_measurement, self.start_polls = session.start_measurement, session.start_polls
        self.mode: str | None = None
        self.axis: str | None = None
        self.term: str | None = None
        self.reference_lost = True  # no datum until reference() is called
        self.reference_epoch = 0
        self.reference_position: float = 0.0
        self.reconnects = 0
        self._fault = False  # a measurement error is pending in the head (resetError before the next datum)
        self._port: RawPort | None = None
        self._id = 0

    @classmethod
    def open(
        cls,
        resource: str,
        timeout_s: float = 5.0,
        optics: IDSOptics = IDSOptics(),
        settle: SettleOptions = SettleOptions(),
        session: IDSSession = IDSSession(),
    ) -> AttocubeIDS:
        """Return a driver on ``host[:port]`` with the head measuring (started from "system idle" if allowed)."""
        url = ids_url(resource)
        ids = cls(lambda: SerialPort.open(url, timeout_s=timeout_s), optics, settle, session)
        try:
            ids.session()
        except TransientError as exc:
            ids.close()
            raise InstrumentError(f"IDS3010 {resource}: {' '.join(str(exc).split())}") from exc
        except BaseException:
            ids.close()
            raise
        return ids

    # -- JSON-RPC exchange
    def _send_many(self, calls: list[tuple[str, list[Any]]]) -> list[list[Any]]:
        """Write the requests back to back, then collect their replies by id (replies to other ids are skipped)."""
        if self._port is None:
            raise TransientError("not connected")
        ids: dict[int, str] = {}
        data = b""
        for method, params in calls:
            self._id += 1
            ids[self._id] = method
            data += request_line(method, params, self._id)
        self._port.write(data)
        results: dict[int, list[Any]] = {}
        for _ in range(len(calls) + 16):  # replies to earlier (timed-out) requests are skipped, as ACS.py buffers them
            if len(results) == len(ids):
                return [results[i] for i in ids]
            raw = self._port.read_line()
            try:
                reply = json.loads(raw.decode("ascii"))
            except (UnicodeDecodeError, ValueError) as exc:
                raise GarbledReply(f"undecodable reply: {raw[:40]!r}") from exc
            if not isinstance(reply, dict):
                raise GarbledReply("a reply that is not a JSON object")
            rid = reply.get("id")
            if not isinstance(rid, int) or rid not in ids or rid in results:
                continue
            method = ids[rid]
            if "error" in reply:
                err = reply["error"]
                text = err.get("message", err) if isinstance(err, dict) else err
                raise InstrumentError(f"IDS3010 {method}: JSON-RPC error {text}")
            result = reply.get("result")
            if not isinstance(result, list) or not result or not isinstance(result[0], int):
                raise GarbledReply(f"reply to {method} has no result list")
            results[rid] = result
        if len(results) == len(ids):
            return [results[i] for i in ids]
        raise GarbledReply(f"no reply to {ids[min(set(ids) - set(results))]}")

    def _send(self, method: str, params: list[Any]) -> list[Any]:
        return self._send_many([(method, params)])[0]

    def call_many(self, calls: list[tuple[str, list[Any]]], repeat: bool = True) -> list[list[Any]]:
        """Return the result lists of several calls sent back to back (attocube's client keeps several requests
        in flight on one connection, matching replies by id); after a dropped line reconnect and repeat them
        only if ``repeat``."""
        what = calls[0][0] if len(calls) == 1 else f"{calls[-1][0]} (x{len(calls)})"
        try:
            if self._port is None:
                self.session()
            return self._send_many(calls)
        except TransientError as exc:
            reason = " ".join(str(exc).split())
            self._drop()
            if not repeat:
                raise InstrumentError(f"IDS3010 {what}: {reason}; not repeated (its effect is unknown)") from exc
            try:
                self.session()
                self.reconnects += 1
                return self._send_many(calls)
            except TransientError as exc2:
                self._drop()
                raise InstrumentError(f"IDS3010 {what}: {' '.join(str(exc2).split())}") from exc2

    def call(self, method: str, *params: Any, repeat: bool = True) -> list[Any]:
        """Return the result list of ``method``; after a dropped line reconnect, and repeat it only if ``repeat``."""
        return self.call_many([(method, list(params))], repeat=repeat)[0]

    def command(self, method: str, *params: Any) -> list[Any]:
        """Call a function that changes the head's state; a non-zero error number is an InstrumentError (its text)."""
        result = self.call(method, *params, repeat=False)
        if result[0] != 0:
            raise InstrumentError(f"IDS3010 {method.rsplit('.', 1)[-1]}: {self.error_text(result[0])}")
        return result

    def query(self, method: str, *params: Any, n: int = 1) -> list[Any]:
        """Return the ``n`` values after the error number of a read-only call (error number must be 0)."""
        result = self.call(method, *params)
        if result[0] != 0:
            raise InstrumentError(f"IDS3010 {method.rsplit('.', 1)[-1]}: {self.error_text(result[0])}")
        if len(result) < 1 + n:
            raise InstrumentError(f"IDS3010 {method.rsplit('.', 1)[-1]}: {len(result) - 1} values, expected {n}")
        return result[1 : 1 + n]

    def error_text(self, number: int) -> str:
        """Return the head's user-friendly text for an error number (``errorNumberToString``, language 1)."""
        try:
            result = self.call(f"{SYSTEM_SERVICE}.errorNumberToString", 1, int(number))
        except InstrumentError:
            return f"error {number}"
        return f"{result[1]} (error {number})" if len(result) > 1 and result[0] == 0 else f"error {number}"

    def _drop(self) -> None:
        port, self._port = self._port, None
        close_quietly(port)

    # -- session
    def session(self) -> None:
        """Connect and make sure the head is measuring; a head found not measuring has lost the datum."""
        self._drop()
        self._port = self._connect()
        mode = self._send(f"{self.ns}.system.getCurrentMode", [])
        state = str(mode[1]) if len(mode) > 1 else "?"
        if state == RUNNING:
            return
        self.reference_lost = True
        if state != "system idle" or not self.start_measurement:
            raise InstrumentError(f"IDS3010 is in mode {state!r}: start the measurement at the instrument")
        started = self._send(f"{self.ns}.system.startMeasurement", [])
        if started[0] != 0:
            raise InstrumentError(f"IDS3010 startMeasurement: error {started[0]}")
        for _ in range(self.start_polls):
            state = str(self._send(f"{self.ns}.system.getCurrentMode", [])[1])
            if state == RUNNING:
                return
            self.sleep(1.0)
        raise InstrumentError(f"IDS3010 did not start measuring (mode {state!r})")

    def identify(self) -> str:
        """Return ``attocube <type> SN <serial> FW <version>``."""
        (kind,) = self.query(f"{self.ns}.system.getDeviceType")
        (serial,) = self.query(f"{SYSTEM_SERVICE}.getSerialNumber")
        (firmware,) = self.query(f"{SYSTEM_SERVICE}.getFirmwareVersion")
        return f"attocube {kind} SN {serial} FW {firmware}"

    def environment(self) -> Environment:
        """Return the weather the head compensates with: the ECU's if enabled and connected, else the manual one."""
        (enabled,) = self.query(f"{ECU}.getEnabled")
        connected = bool(enabled) and bool(self.query(f"{ECU}.getConnected")[0])
        where = ECU if connected else f"{ECU}.manual"
        args: tuple[int, ...] = () if connected else (-1,)
        (t_c,) = self.query(f"{where}.getTemperatureInDegrees", *args)
        (p_hpa,) = self.query(f"{where}.getPressureInHPa", *args)
        (rh,) = self.query(f"{where}.getHumidityInPercent", *args)
        env = Environment(float(t_c), float(p_hpa) * 100.0, float(rh))
        if not (-40 <= env.t_c <= 100 and 80e3 <= env.pressure_pa <= 120e3 and 0 <= env.rh_percent <= 100):
            raise InstrumentError(f"IDS3010 {where}: weather out of range {env}")
        return env

    def refractive_index(self) -> float:
        """Return the refractive index the head compensates with (``getRefractiveIndexForCompensation(-1)``)."""
        (n,) = self.query(f"{ECU}.getRefractiveIndexForCompensation", -1)
        return float(n)

    # -- measurement
    def configure(self, axis: str, term: str) -> str:
        """Select the table 5.3 measurement (the optics the operator mounted); return its mode."""
        mode = LASER_TERMS.get(axis, {}).get(term)
        if mode is None:
            raise ValidationError(f"the laser does not measure {term} of the {axis} axis (table 5.3)")
        if (mode, axis, term) != (self.mode, self.axis, self.term):
            self.mode, self.axis, self.term = mode, axis, term
            self.reference_lost = True  # new optics set-up: the count no longer refers to the old datum
        return mode

    def _beams(self) -> tuple[int, ...]:
        return self.optics.angle_axes if self.mode == "ANG" else (self.optics.displacement_axis,)

    def reference(self, position: float = 0.0) -> None:
        """Zero the displacements at the present axis ``position`` (after clearing a pending measurement error)."""
        if self._fault:
            self.command(f"{self.ns}.system.resetError", False)
            self._fault = False
        self.command(f"{self.ns}.system.resetAxes")
        self.reference_position = float(position)
        self.reference_lost = False
        self.reference_epoch += 1

    def _lose_reference(self) -> Reading:
        self.reference_lost = True
        self._fault = True
        return Reading.missing(FLAG_BEAM_BREAK)

    def _value_of(self, result: list[Any]) -> float | None:
        """Return one reading (mm or rad) of the configured optics from a getAxesDisplacement result, None when the
        head reports a measurement warning."""
        if result[0] != 0:
            return None
        if len(result) != 4 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in result[1:]):
            raise InstrumentError(f"IDS3010 getAxesDisplacement: malformed displacements {result[1:]!r}")
        d = [float(v) / PM_PER_MM for v in result[1:]]
        if self.mode == "ANG":
            a0, a1 = self.optics.angle_axes
            ratio = (d[a1] - d[a0]) / self.optics.angle_spacing_mm
            if abs(ratio) > 1.0:
                raise InstrumentError(f"IDS3010: angle beams {d[a1] - d[a0]:.6f} mm apart, beyond the spacing")
            return math.asin(ratio)
        return d[self.optics.displacement_axis]

    def _readings(self, n: int) -> list[float] | None:
        """Return ``n`` readings taken back to back (one pipelined exchange), None if any warns."""
        calls: list[tuple[str, list[Any]]] = [(f"{self.ns}.displacement.getAxesDisplacement", [])] * n
        values = [self._value_of(r) for r in self.call_many(calls)]
        return None if any(v is None for v in values) else [float(v) for v in values if v is not None]

    def read(self) -> Reading:
        """Return the settled mean of ``readings_per_point`` readings in mm or rad; flagged missing on a lost beam.

        One exchange asks for the signal contrast of the optics' beams and two settle readings plus the
        readings to average, back to back; only when those two disagree (the axis still moving) does it
        poll with pauses until two agree, then take the readings (ch. 5.5: the mean of ten readings taken
        after the axis has settled).
        """
        if self.mode is None:
            raise ValidationError("laser not configured: call configure(axis, term) first")
        if self.reference_lost:
            return Reading.missing(FLAG_REFERENCE_LOST)
        n = self.readings_per_point
        beams = self._beams()
        calls = [(f"{self.ns}.displacement.getAxisSignalQuality", [b]) for b in beams]
        calls += [(f"{self.ns}.displacement.getAxesDisplacement", [])] * (2 + n)
        results = self.call_many(calls)
        for q in results[: len(beams)]:
            if q[0] != 0 or len(q) < 2 or float(q[1]) < self.min_contrast_permille:
                return self._lose_reference()
        got = [self._value_of(r) for r in results[len(beams) :]]
        values = [v for v in got if v is not None]
        if len(values) != len(got):
            return self._lose_reference()
        tol = self.settle_tolerance_rad if self.mode == "ANG" else self.settle_tolerance_mm
        first, second = values[0], values[1]
        if abs(second - first) <= tol:
            return Reading(float(np.mean(values[2:])))
        previous: float | None = None  # still moving: poll until it settles
        for _ in range(self.max_settle_polls):
            self.sleep(self.settle_poll_s)
            poll = self._readings(1)
            if poll is None:
                return self._lose_reference()
            if previous is not None and abs(poll[0] - previous) <= tol:
                break
            previous = poll[0]
        else:
            raise InstrumentError(f"IDS3010: axis did not settle within {self.max_settle_polls} polls")
        settled = self._readings(n)
        if settled is None:
            return self._lose_reference()
        return Reading(float(np.mean(settled)))

    def close(self) -> None:
        """Close the connection (the head keeps measuring)."""
        self._drop()
