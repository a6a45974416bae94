"""attocube IDS3010 over its JSON-RPC interface: the vendor's own request form byte for byte, points, beam
loss, error numbers, timeouts, a dropped connection and reconnection; then the simulator through TCP.

The request form is that of attocube's MATLAB functions in attocube-systems/IDS-APIs
(``matlab/displacement_getAbsolutePositions.m``: ``{"jsonrpc": "2.0", "method":
"com.attocube.sen.displacement.getAbsolutePositions", "params": [], "id": 1, "api": 2}`` written as a
line), the replies' shape that of ``python/ACS.py`` and ``python/displacement.py`` (``result`` = error
or warning number, then the values; a CR LF line end, as the client reads with ``newline='\\r\\n'``).
"""

from __future__ import annotations

import json
import math
import socket

import numpy as np
import pytest

from driftlab.daq.attocube_ids import AttocubeIDS, IDSOptics, IDSSession, ids_url, request_line
from driftlab.daq.laser import SettleOptions
from driftlab.daq.protocols import FLAG_BEAM_BREAK, FLAG_REFERENCE_LOST, ErrorMeter
from driftlab.daq.sim.attocube_ids import SimIDS3010, ids_resource
from driftlab.daq.sim.instruments import FixedStage, ManualClock
from driftlab.errors import InstrumentError, ValidationError
from driftlab.testing.tinyworld import TinyWorld
from tests.daq.protocol_helpers import TIMEOUT, ProtocolPort

SEN = "com.attocube.sen"


class Conversation:
    """Builds (request bytes, reply bytes) pairs with the driver's request ids counted along."""

    def __init__(self) -> None:
        self.rid = 0
        self.pairs: list[tuple[bytes | None, object]] = []

    def __call__(self, method: str, params: list, result: object) -> Conversation:
        self.rid += 1
        if isinstance(result, list):
            reply = json.dumps({"jsonrpc": "2.0", "result": result, "id": self.rid}).encode() + b"\r\n"
        elif isinstance(result, bytes):
            reply = result
        else:
            reply = result  # TIMEOUT
        self.pairs.append((request_line(method, params, self.rid), reply))
        return self

    def batch(self, calls: list[tuple[str, list, list]]) -> Conversation:
        """Requests written back to back in one write, then their replies read one by one (in order here)."""
        data, replies = b"", []
        for method, params, result in calls:
            self.rid += 1
            data += request_line(method, params, self.rid)
            replies.append(json.dumps({"jsonrpc": "2.0", "result": result, "id": self.rid}).encode() + b"\r\n")
        self.pairs.append((data, replies[0]))
        self.pairs.extend((None, r) for r in replies[1:])
        return self


def running(c: Conversation) -> Conversation:
    return c(f"{SEN}.system.getCurrentMode", [], [0, "measurement running"])


def ids_on(
    *conversations: Conversation, settle_tolerance_mm: float = 0.0005, **kw
) -> tuple[AttocubeIDS, list[ProtocolPort]]:
    ports = [ProtocolPort(c.pairs) for c in conversations]
    queue = list(ports)

    def connect() -> ProtocolPort:
        if not queue:
            raise InstrumentError("cannot open serial port: connection refused")
        return queue.pop(0)

    settle = SettleOptions(settle_tolerance_mm=settle_tolerance_mm, sleep=lambda _s: None)
    return AttocubeIDS(connect, settle=settle, **kw), ports


def all_used(ports: list[ProtocolPort]) -> None:
    for p in ports:
        assert p.index == len(p.pairs), f"unused pairs: {p.pairs[p.index :]}"


def test_request_bytes_are_the_vendors_matlab_form():
    # matlab/displacement_getAbsolutePositions.m and IDS_displacement_getAbsolutePosition.m, verbatim
    assert request_line(f"{SEN}.displacement.getAbsolutePositions", [], 1) == (
        b'{"jsonrpc": "2.0", "method": "com.attocube.sen.displacement.getAbsolutePositions", '
        b'"params": [], "id": 1, "api": 2}\n'
    )
    assert request_line("com.attocube.ids.displacement.getAbsolutePosition", [2], 1) == (
        b'{"jsonrpc": "2.0", "method": "com.attocube.ids.displacement.getAbsolutePosition", '
        b'"params": [2], "id": 1, "api": 2}\n'
    )


def test_resource_names():
    assert ids_url("ids-host") == "socket://ids-host:9090"
    assert ids_url("10.0.0.7:9091") == "socket://10.0.0.7:9091"
    with pytest.raises(ValidationError, match="host:port"):
        ids_url("GPIB0::3::INSTR")
    with pytest.raises(ValidationError, match="beams"):
        IDSOptics(angle_axes=(1, 1))


def test_identify_and_environment_from_the_ecu():
    c = running(Conversation())
    c(f"{SEN}.system.getDeviceType", [], [0, "IDS3010"])
    c("com.attocube.system.getSerialNumber", [], [0, "IDS-1234"])
    c("com.attocube.system.getFirmwareVersion", [], [0, "1.9.1"])
    c("com.attocube.ecu.getEnabled", [], [0, True])
    c("com.attocube.ecu.getConnected", [], [0, True])
    c("com.attocube.ecu.getTemperatureInDegrees", [], [0, 20.5])
    c("com.attocube.ecu.getPressureInHPa", [], [0, 1002.5])
    c("com.attocube.ecu.getHumidityInPercent", [], [0, 41.0])
    ids, ports = ids_on(c)
    ids.session()
    assert ids.identify() == "attocube IDS3010 SN IDS-1234 FW 1.9.1"
    env = ids.environment()
    assert (env.t_c, env.pressure_pa, env.rh_percent) == (20.5, 100250.0, 41.0)
    all_used(ports)


def test_environment_falls_back_to_the_manual_values_without_an_ecu():
    c = running(Conversation())
    c("com.attocube.ecu.getEnabled", [], [0, False])
    c("com.attocube.ecu.manual.getTemperatureInDegrees", [-1], [0, 20.0])
    c("com.attocube.ecu.manual.getPressureInHPa", [-1], [0, 1013.25])
    c("com.attocube.ecu.manual.getHumidityInPercent", [-1], [0, 50.0])
    ids, ports = ids_on(c)
    ids.session()
    assert ids.environment().pressure_pa == pytest.approx(101325.0)
    all_used(ports)


def point(c: Conversation, displacements: list[list[int]], beams=(0,), contrast=880) -> Conversation:
    """One point's exchange: the beams' contrast, then two settle readings and the readings to average."""
    calls = [(f"{SEN}.displacement.getAxisSignalQuality", [b], [0, contrast, 500]) for b in beams]
    calls += [(f"{SEN}.displacement.getAxesDisplacement", [], d if len(d) == 4 else [0, *d]) for d in displacements]
    return c.batch(calls)


def test_linear_point_mean_of_ten_after_settling():
    c = running(Conversation())
    c(f"{SEN}.system.resetAxes", [], [0])
    travel_pm = [100_003_000 + 10 * k for k in range(-5, 5)]
    point(c, [[100_003_100, 0, 0], [100_003_000, 0, 0]] + [[v, 0, 0] for v in travel_pm])
    ids, ports = ids_on(c)
    ids.session()
    ids.configure("X", "dx")
    ids.reference(0.0)
    sample = ids.measure_error("X", "dx", 100.0, -1)
    assert isinstance(ids, ErrorMeter)
    assert sample.flag is None and sample.value == pytest.approx(np.mean(travel_pm) * 1e-9 - 100.0, abs=1e-12)
    all_used(ports)


def test_a_moving_axis_is_polled_until_it_settles():
    c = running(Conversation())
    c(f"{SEN}.system.resetAxes", [], [0])
    point(c, [[5000, 0, 0], [9000, 0, 0]] + [[9500, 0, 0]] * 10)  # still moving: the batch is not used
    for d in (9800, 9900, 9900):
        c(f"{SEN}.displacement.getAxesDisplacement", [], [0, d, 0, 0])
    c.batch([(f"{SEN}.displacement.getAxesDisplacement", [], [0, 9900 + k, 0, 0]) for k in range(10)])
    sleeps: list[float] = []
    ids, ports = ids_on(c, settle_tolerance_mm=5e-8)
    ids.sleep = sleeps.append
    ids.session()
    ids.configure("X", "dx")
    ids.reference()
    assert ids.read().value == pytest.approx((9900 + 4.5) * 1e-9, abs=1e-15)
    assert sleeps == [0.5] * 3
    all_used(ports)


def test_angle_point_from_two_beams():
    c = running(Conversation())
    c(f"{SEN}.system.resetAxes", [], [0])
    # both beams see 50 mm of travel; beam 1 is 96 pm further: 3 urad over 32 mm
    reading = [50_000_000_000, 50_000_000_096, 0]
    point(c, [reading] * 12, beams=(0, 1))
    ids, ports = ids_on(c)
    ids.session()
    ids.configure("Z", "beta")
    ids.reference()
    assert ids.read_angle().value == pytest.approx(math.asin(96e-9 / 32.0), rel=1e-12)
    all_used(ports)


def test_lost_beam_flags_the_point_and_the_next_datum_clears_the_error_first():
    c = running(Conversation())
    c(f"{SEN}.system.resetAxes", [], [0])
    point(c, [[42, 0, 0, 0]] + [[0, 0, 0]] * 11)  # a measurement warning on the first reading
    c(f"{SEN}.system.resetError", [False], [0])
    c(f"{SEN}.system.resetAxes", [], [0])
    point(c, [[7000, 0, 0]] * 12)
    ids, ports = ids_on(c)
    ids.session()
    ids.configure("X", "dy")
    ids.reference()
    assert ids.read().flag == FLAG_BEAM_BREAK
    assert ids.read().flag == FLAG_REFERENCE_LOST  # no reading refers to the old datum
    ids.reference()
    assert ids.read_displacement().value == pytest.approx(7e-6)
    all_used(ports)


def test_weak_signal_is_a_beam_break():
    c = running(Conversation())
    c(f"{SEN}.system.resetAxes", [], [0])
    point(c, [[0, 0, 0]] * 12, contrast=40)
    ids, ports = ids_on(c)
    ids.session()
    ids.configure("X", "dx")
    ids.reference()
    assert ids.read().flag == FLAG_BEAM_BREAK
    all_used(ports)


def test_refused_command_names_the_heads_error_text():
    c = running(Conversation())
    c(f"{SEN}.system.resetAxes", [], [7])
    c("com.attocube.system.errorNumberToString", [1, 7], [0, "Function not available in this state"])
    ids, ports = ids_on(c)
    ids.session()
    ids.configure("X", "dx")
    with pytest.raises(InstrumentError, match=r"resetAxes: Function not available in this state \(error 7\)"):
        ids.reference()
    assert ids.reference_lost
    all_used(ports)


def test_json_rpc_error_object_is_one_line():
    c = running(Conversation())
    nak = b'{"jsonrpc": "2.0", "error": {"code": -32601, "message": "Method not found"}, "id": 2}\r\n'
    c(f"{SEN}.system.getDeviceType", [], nak)
    ids, ports = ids_on(c)
    ids.session()
    with pytest.raises(InstrumentError, match="JSON-RPC error Method not found"):
        ids.identify()
    all_used(ports)


def test_timeout_reconnects_repeats_a_read_and_keeps_the_datum():
    first = running(Conversation())
    first(f"{SEN}.system.resetAxes", [], [0])
    point(first, [[1000, 0, 0]] * 12)
    first.pairs[-12:] = []  # the first reply never comes: the whole exchange times out
    first.pairs[-1] = (first.pairs[-1][0], TIMEOUT)
    second = Conversation()
    second.rid = first.rid  # request ids go on counting on the new connection
    running(second)  # the head still measures: the count (and the datum) live in the head
    point(second, [[1000, 0, 0]] * 12)  # the same reads, repeated
    ids, ports = ids_on(first, second)
    ids.session()
    ids.configure("X", "dy")
    ids.reference()
    assert ids.read().value == pytest.approx(1e-6)
    assert ids.reconnects == 1 and not ids.reference_lost and ports[0].closed
    all_used(ports)


def test_dropped_line_during_a_reset_is_not_repeated():
    first = running(Conversation())
    first(f"{SEN}.system.resetAxes", [], TIMEOUT)
    ids, ports = ids_on(first)
    ids.session()
    ids.configure("X", "dx")
    with pytest.raises(InstrumentError, match="resetAxes: timeout waiting for reply; not repeated"):
        ids.reference()
    assert ids.reference_lost
    all_used(ports)


def test_a_head_found_idle_is_started_and_the_datum_is_lost():
    c = Conversation()
    c(f"{SEN}.system.getCurrentMode", [], [0, "system idle"])
    c(f"{SEN}.system.startMeasurement", [], [0])
    c(f"{SEN}.system.getCurrentMode", [], [0, "measurement starting"])
    c(f"{SEN}.system.getCurrentMode", [], [0, "measurement running"])
    ids, ports = ids_on(c)
    ids.reference_lost = False
    ids.session()
    assert ids.reference_lost
    all_used(ports)
    c2 = Conversation()
    c2(f"{SEN}.system.getCurrentMode", [], [0, "optics alignment running"])
    ids2, _ = ids_on(c2)
    with pytest.raises(InstrumentError, match="optics alignment running"):
        ids2.session()


def test_a_late_reply_to_an_earlier_request_is_skipped():
    c = running(Conversation())
    late = json.dumps({"jsonrpc": "2.0", "result": [0, "old"], "id": 1}).encode() + b"\r\n"
    now = json.dumps({"jsonrpc": "2.0", "result": [0, "IDS3010"], "id": 2}).encode() + b"\r\n"
    c(f"{SEN}.system.getDeviceType", [], late)
    c.pairs.append((None, now))
    ids, ports = ids_on(c)
    ids.session()
    assert ids.query(f"{SEN}.system.getDeviceType") == ["IDS3010"]
    all_used(ports)


def test_unknown_term_and_namespace_are_refused():
    ids, _ = ids_on()
    with pytest.raises(ValidationError, match="table 5.3"):
        ids.configure("X", "alpha")
    with pytest.raises(ValidationError, match="api_namespace"):
        AttocubeIDS(lambda: None, session=IDSSession(api_namespace="foo"))  # type: ignore[arg-type,return-value]


# ------------------------------------------------------------------ the simulator through a real socket


def _raw(port: int, data: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(data)
        buf = b""
        while not buf.endswith(b"\r\n"):
            chunk = s.recv(4096)
            if not chunk:
                break
            buf += chunk
        return buf


def test_simulator_answers_the_vendors_example_with_and_without_a_line_end():
    world, clock, stage = TinyWorld(channels=2), ManualClock(), FixedStage()
    with SimIDS3010(world, clock, stage) as sim:
        sim.mount("LIN", "X", "dx")
        example = (
            b'{"jsonrpc": "2.0", "method": "com.attocube.sen.displacement.getAxesDisplacement", '
            b'"params": [], "id": 1, "api": 2}'
        )
        for data in (example, example + b"\n"):  # the Python client sends none, the MATLAB functions an LF
            reply = _raw(sim.port, data)
            assert reply.endswith(b"}\r\n")
            body = json.loads(reply)
            assert body["id"] == 1 and body["result"][0] == 0 and len(body["result"]) == 4
        bad = json.loads(_raw(sim.port, b'{"jsonrpc": "2.0", "method": "com.attocube.ids.system.getCurrentMode", '
                                        b'"params": [], "id": 5, "api": 2}'))  # fmt: skip
        assert bad["error"]["code"] == -32601 and bad["id"] == 5  # the pre-1.9.1 namespace on a 1.9.1 head


def test_driver_on_the_simulator_follows_the_world_and_survives_a_drop_and_a_timeout():
    world, clock, stage = TinyWorld(channels=2), ManualClock(), FixedStage()
    with SimIDS3010(world, clock, stage) as sim:
        sim.mount("LIN", "X", "dx")
        ids = AttocubeIDS.open(ids_resource(sim), timeout_s=0.5, settle=SettleOptions(sleep=clock.sleep))
        try:
            assert ids.identify().startswith("attocube IDS3010")
            ids.configure("X", "dx")
            ids.reference(0.0)
            stage.move("X", 200.0)
            got = ids.measure_error("X", "dx", 200.0, 1)
            truth = world.measure_error(clock.now(), "X", 200.0, 1)["dx"] - world.measure_error(0.0, "X", 0.0, 1)["dx"]
            assert got.value == pytest.approx(truth, abs=2e-9)  # 1 pm counts, ten readings
            sim.drop()  # the cable pulled: the next call reconnects; the head kept counting
            again = ids.measure_error("X", "dx", 200.0, 1)
            assert again.flag is None and ids.reconnects == 1
            sim.inject("timeout", on=f"{SEN}.displacement.getAxisSignalQuality")
            assert ids.measure_error("X", "dx", 200.0, 1).flag is None and ids.reconnects == 2
            sim.break_beam()
            assert ids.read().flag == FLAG_BEAM_BREAK
            sim.restore_beam()
            ids.reference(200.0)  # resetError, then resetAxes: the latched error is cleared
            assert ids.read().value == pytest.approx(0.0, abs=1e-6)
            env = ids.environment()
            assert env.pressure_pa == pytest.approx(101325.0) and ids.refractive_index() > 1.00027
        finally:
            ids.close()


def test_rig_options_of_the_ids3010_are_checked_in_one_line():
    from driftlab.daemon.rigfile import ids_optics

    assert ids_optics("laser", {"angle_axes": [1, 2], "angle_spacing_mm": 25}).angle_axes == (1, 2)
    with pytest.raises(ValidationError, match=r"options: displacement_axis a beam 0..2, angle_axes two beams"):
        ids_optics("laser", {"angle_axes": [1]})
    with pytest.raises(ValidationError, match=r"instruments.laser.options: IDS3010 optics: beams are axes"):
        ids_optics("laser", {"displacement_axis": 3})


def test_a_head_that_never_answers_is_one_line_at_open():
    world, clock = TinyWorld(channels=2), ManualClock()
    with SimIDS3010(world, clock, FixedStage()) as sim:
        sim.inject("timeout", on=f"{SEN}.system.getCurrentMode")
        with pytest.raises(InstrumentError, match=r"IDS3010 127.0.0.1:\d+: timeout waiting for reply"):
            AttocubeIDS.open(ids_resource(sim), timeout_s=0.3)
