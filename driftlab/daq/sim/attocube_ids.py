"""A simulated attocube IDS3010 answering its JSON-RPC remote interface, on the virtual machine's error field.

Written from the same material as :mod:`driftlab.daq.attocube_ids` (attocube-systems/IDS-APIs:
``python/ACS.py``, ``python/system.py``, ``python/displacement.py``, ``python/ecu.py``,
``python/manual.py``, ``python/system_service.py`` and the MATLAB functions):

* TCP; a request is one JSON-RPC 2.0 object, with or without a line end after it (attocube's Python
  client sends none, its MATLAB functions an LF), so requests are cut from the byte stream as
  JSON objects; each reply is one line ``{"jsonrpc": "2.0", "result": [...], "id": <the request's>}``
  ending in CR LF (the Python client reads with ``newline='\\r\\n'``);
* ``result[0]`` is the function's error or warning number, 0 for none; the rest are its values;
  an unknown method is a JSON-RPC error object (code -32601, JSON-RPC 2.0 section 5.1), a request
  that is not JSON one with code -32700;
* the interfaces ``<ns>.system``, ``<ns>.displacement`` (``ns`` = ``com.attocube.sen`` for firmware
  1.9.1 on, ``com.attocube.ids`` before), ``com.attocube.ecu``, ``com.attocube.ecu.manual`` and
  ``com.attocube.system``; displacements in pm, contrast in permille, pressure in hPa.

The simulator's own choices, where the published material is silent: the numeric error and warning
codes (:data:`ERRORS`), the device's serial number and firmware text, and Edlen's equation (Birch &
Downs) for the refractive index where the head uses Ciddor's. A beam interruption latches a
measurement error, as the head's ``resetError`` describes: displacement reads warn until
``resetError`` is called, even after the beam is back.

Beams: the linear and straightness set-ups use beam ``displacement_axis``; the angle set-up two
beams ``angle_spacing_mm`` apart, which on a linear axis both see the travel. A beam the mounted
optics do not use has no signal (``getAxisSignalQuality`` warns), so a driver asking for angle
optics while linear optics are mounted reads a lost beam.
"""

from __future__ import annotations

import json
import math
from typing import Any

from driftlab.daq.attocube_ids import IDSOptics
from driftlab.daq.laser import air_refractive_index
from driftlab.daq.sim.instruments import Clock, SimHead, Stage, World

#: the simulator's error and warning numbers and their texts (errorNumberToString)
NOT_RUNNING, BEAM_LOST, NO_SIGNAL, WRONG_STATE, BAD_PARAM = 101, 102, 103, 104, 105
ERRORS = {
    0: "No error",
    NOT_RUNNING: "Measurement not running",
    BEAM_LOST: "Measurement error: beam interrupted or signal lost (resetError to continue)",
    NO_SIGNAL: "No interference signal on this axis",
    WRONG_STATE: "Function not available in the present system state",
    BAD_PARAM: "Parameter out of range",
}
_LINEAR = ("X", "Y", "Z")


class SimIDS3010(SimHead):
    """An IDS3010 with an ECU, measuring the mounted optics' term of the world's error field."""

    name = "ids3010"

    def __init__(
        self,
        world: World,
        clock: Clock,
        stage: Stage,
        api_namespace: str = "sen",
        optics: IDSOptics = IDSOptics(),
        contrast_permille: float = 880.0,
        measuring: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(world, clock, stage, **kwargs)
        self.ns = {"sen": "com.attocube.sen", "ids": "com.attocube.ids"}[api_namespace]
        self.displacement_axis, self.angle_axes, self.angle_spacing_mm = (
            optics.displacement_axis,
            optics.angle_axes,
            optics.angle_spacing_mm,
        )
        self.contrast_permille = contrast_permille
        self.state = "measurement running" if measuring else "system idle"
        self.fault = False  # a latched measurement error (beam interrupted)
        self.ecu_connected = True
        self.manual = {"temperature": 20.0, "pressure": 1013.25, "humidity": 50.0}

    def mount(self, mode: str | None, axis: str = "X", term: str = "dx", range_deg: float | None = None) -> None:
        """Mount the optics of one measurement (None: take them off); the beams then see that term."""
        super().mount(mode, axis, term, range_deg)
        with self._lock:
            if mode is not None:
                self.mode, self.axis, self.term = mode, axis, term

    # -- framing: JSON objects cut from the stream, replies one CR LF line
    def split_frames(self, buf: bytes) -> tuple[list[bytes], bytes]:
        """Return the complete JSON requests in ``buf`` and the rest (a partial object waits for more bytes)."""
        decoder = json.JSONDecoder()
        frames: list[bytes] = []
        text = buf.decode("ascii", errors="replace")
        pos = 0
        while True:
            while pos < len(text) and text[pos] in " \t\r\n":
                pos += 1
            if pos >= len(text):
                return frames, b""
            try:
                _, end = decoder.raw_decode(text, pos)
            except ValueError:
                nl = text.find("\n", pos)
                if nl < 0:
                    return frames, text[pos:].encode("ascii", errors="replace")
                frames.append(text[pos:nl].encode("ascii", errors="replace"))  # not JSON: a parse error reply
                pos = nl + 1
                continue
            frames.append(text[pos:end].encode("ascii"))
            pos = end

    def _take_fault(self, text: str) -> str | None:
        """Match injected faults against the request's method name (``on`` is a method prefix)."""
        if not self._faults:  # none injected (the daemon's run): no second JSON parse of every request
            return None
        try:
            method = str(json.loads(text).get("method", ""))
        except (ValueError, AttributeError):
            method = ""
        return super()._take_fault(method)

    def handle(self, line: str) -> str | None:
        """Answer one JSON-RPC request with one CR LF terminated reply line."""
        try:
            req = json.loads(line)
            if not isinstance(req, dict) or not isinstance(req.get("method"), str):
                raise ValueError("not a request object")
        except ValueError:
            return _dump({"jsonrpc": "2.0", "error": {"code": -32700, "message": "Parse error"}, "id": None})
        params = req.get("params") or []
        rid = req.get("id")
        result = self._call(req["method"], params if isinstance(params, list) else [params])
        if result is None:
            return _dump({"jsonrpc": "2.0", "error": {"code": -32601, "message": "Method not found"}, "id": rid})
        return _dump({"jsonrpc": "2.0", "result": result, "id": rid})

    def _call(self, method: str, params: list[Any]) -> list[Any] | None:
        t = self.clock.now()
        iface, _, fn = method.rpartition(".")
        if iface == f"{self.ns}.system":
            return self._system(fn, params, t)
        if iface == f"{self.ns}.displacement":
            return self._displacement(fn, params, t)
        if iface == "com.attocube.ecu":
            return self._ecu(fn, t)
        if iface == "com.attocube.ecu.manual" and fn.startswith("get"):
            key = {"getTemperatureInDegrees": "temperature", "getPressureInHPa": "pressure"}.get(fn)
            key = key or {"getHumidityInPercent": "humidity"}.get(fn)
            return None if key is None else [0, self.manual[key]]
        if iface == "com.attocube.system":
            if fn == "getSerialNumber":
                return [0, "SIM-IDS-0001"]
            if fn == "getFirmwareVersion":
                return [0, "1.9.1-sim"]
            if fn == "errorNumberToString":
                number = int(params[1]) if len(params) > 1 else -1
                return [0, ERRORS.get(number, f"Unknown error {number}")]
        return None

    def _system(self, fn: str, params: list[Any], t: float) -> list[Any] | None:
        if fn == "getCurrentMode":
            return [0, self.state]
        if fn == "getDeviceType":
            return [0, "IDS3010"]
        if fn == "startMeasurement":
            if self.state != "system idle":
                return [WRONG_STATE]
            self.state, self._ref, self.fault = "measurement running", None, False
            return [0]
        if fn == "stopMeasurement":
            self.state, self._ref = "system idle", None
            return [0]
        if fn in ("resetAxes", "resetAxis"):
            if self.state != "measurement running":
                return [NOT_RUNNING]
            if self._beam_fault(t) is not None:
                return [BEAM_LOST]
            self._take_datum(t)
            return [0]
        if fn == "resetError":
            if self.state != "measurement running":
                return [WRONG_STATE]
            self.fault = False
            return [0]
        return None

    def _beam_fault(self, t: float) -> int | None:
        """Return the warning a displacement read gives now (latching a beam interruption), None when fine."""
        if self.state != "measurement running":
            return NOT_RUNNING
        if self.mounted is None:
            return NO_SIGNAL
        if self.beam == "broken" or self._optics_fault(t) is not None:
            self.fault = True
        return BEAM_LOST if self.fault else None

    def _lit(self) -> tuple[int, ...]:
        """Return the beams the mounted optics use."""
        return self.angle_axes if self.mode == "ANG" else (self.displacement_axis,)

    def _displacements(self, t: float) -> list[int]:
        """Return the three beams' displacements (pm) since the datum."""
        rel, travel = self._relative(t)
        out = [0.0, 0.0, 0.0]
        if self.mode == "ANG":
            a0, a1 = self.angle_axes
            base = travel if self.axis in _LINEAR else 0.0
            out[a0] = base
            out[a1] = base + self.angle_spacing_mm * math.sin(rel)
        elif self.mode == "LIN":
            out[self.displacement_axis] = travel + rel
        else:
            out[self.displacement_axis] = rel
        return [int(round(v * 1e9)) for v in out]

    def _displacement(self, fn: str, params: list[Any], t: float) -> list[Any] | None:
        if fn == "getMeasurementEnabled":
            return [0, self.state == "measurement running"]
        axis = params[0] if params else None
        if fn in ("getAxisDisplacement", "getAxisSignalQuality") and axis not in (0, 1, 2):
            return [BAD_PARAM, 0] if fn == "getAxisDisplacement" else [BAD_PARAM, 0, 0]
        if fn == "getAxisSignalQuality":
            if self.state != "measurement running" or self.mounted is None or self.beam == "broken":
                return [NO_SIGNAL, 0, 0]
            if int(axis) not in self._lit():  # type: ignore[arg-type]
                return [NO_SIGNAL, 0, 0]  # a beam the mounted optics do not use sees no reflector
            contrast = 40.0 if self.beam == "weak" else self.contrast_permille
            return [0, contrast, 500]
        if fn in ("getAxesDisplacement", "getAxisDisplacement"):
            warning = self._beam_fault(t)
            values = [0, 0, 0] if warning is not None else self._displacements(t)
            code = 0 if warning is None else warning
            return [code, *values] if fn == "getAxesDisplacement" else [code, values[int(axis)]]  # type: ignore[arg-type]
        return None

    def _ecu(self, fn: str, t: float) -> list[Any] | None:
        air = self._air_c(t)
        n = float(air_refractive_index(air, self.pressure_pa, self.rh_percent))
        values: dict[str, Any] = {
            "getEnabled": True,
            "getConnected": self.ecu_connected,
            "getTemperatureInDegrees": round(air, 3),
            "getPressureInHPa": round(self.pressure_pa / 100.0, 2),
            "getHumidityInPercent": round(self.rh_percent, 1),
            "getRefractiveIndex": n,
            "getRefractiveIndexForCompensation": n,
            "getRefractiveIndexCompensationMode": 0 if self.ecu_connected else 1,
        }
        return [0, values[fn]] if fn in values else None


def _dump(reply: dict[str, Any]) -> str:
    """Return a reply line; the server adds the LF after this CR."""
    return json.dumps(reply) + "\r"


def ids_resource(server: SimIDS3010) -> str:
    """Return the rig resource (host:port) of a simulated IDS3010."""
    return f"127.0.0.1:{server.port}"
