"""Heidenhain TNC through LSV2 (pyLSV2): the simulated control's telegrams byte for byte, the link on the real
library, refusals, a dropped connection and a swallowed reply.

The telegram forms are pyLSV2's (``low_level_com.LSV2TCP.telegram``: 4-byte big-endian payload length,
4-character code, payload; ``T_ER`` with error type and code), and the replies are checked with
pyLSV2's own decoders (``misc.decode_axis_location``, ``decode_system_parameters``), so the simulated
control is held to what the library reads.
"""

from __future__ import annotations

import socket
import struct

import pytest

pyLSV2 = pytest.importorskip("pyLSV2")

from driftlab.daq.heidenhain import HeidenhainLink, lsv2_address  # noqa: E402
from driftlab.daq.sim.heidenhain import SimLSV2, lsv2_resource, telegram  # noqa: E402
from driftlab.daq.sim.instruments import FixedStage, ManualClock  # noqa: E402
from driftlab.errors import InstrumentError, ValidationError  # noqa: E402

READS = {"A_LG", "A_LO", "R_VR", "R_PR", "R_CI", "C_CC", "R_RI"}


def exchange(sock: socket.socket, data: bytes) -> tuple[str, bytes]:
    sock.sendall(data)
    head = b""
    while len(head) < 8:
        head += sock.recv(8 - len(head))
    n = struct.unpack("!L", head[:4])[0]
    body = b""
    while len(body) < n:
        body += sock.recv(n - len(body))
    return head[4:8].decode(), body


def test_telegrams_byte_for_byte():
    with SimLSV2(ManualClock()) as sim, socket.create_connection(("127.0.0.1", sim.port), timeout=5) as s:
        sim.pos.update(X=-12.25, B=30.0)
        # before any login the control answers nothing but logins: T_ER, type 1, T_ER_NO_PRIV (23)
        assert exchange(s, b"\x00\x00\x00\x00R_VR") == ("T_ER", b"\x01\x17")
        # pyLSV2's first telegram: A_LG with the NUL-terminated login INSPECT (8 bytes of payload)
        assert telegram("A_LG", b"INSPECT\x00") == b"\x00\x00\x00\x08A_LGINSPECT\x00"
        assert exchange(s, b"\x00\x00\x00\x08A_LGINSPECT\x00") == ("T_OK", b"")
        code, body = exchange(s, b"\x00\x00\x00\x00R_VR")
        assert code == "S_VR" and body.rstrip(b"\x00").split(b"\x00")[:2] == [b"TNC640", b"340595 10 SP5"]
        code, body = exchange(s, b"\x00\x00\x00\x00R_PR")
        assert code == "S_PR" and pyLSV2.misc.decode_system_parameters(bytearray(body)).max_block_length == 4096
        # buffer size 4096 (ParCCC.SET_BUF4096 = 7)
        assert exchange(s, b"\x00\x00\x00\x02C_CC\x00\x07") == ("T_OK", b"")
        # R_RI AXIS_LOCATION (22) needs the DNC login
        assert exchange(s, b"\x00\x00\x00\x02R_RI\x00\x16") == ("T_ER", b"\x01\x17")
        assert exchange(s, telegram("A_LG", b"DNC\x00")) == ("T_OK", b"")
        code, body = exchange(s, b"\x00\x00\x00\x02R_RI\x00\x16")
        assert code == "S_RI"
        assert pyLSV2.misc.decode_axis_location(bytearray(body)) == {"X": -12.25, "Y": 0, "Z": 0, "A": 0, "B": 30}
        # EXEC_STATE (23): AUTOMATIC (4); an unknown telegram: T_ER_UNKNOWN_TELE (22)
        assert exchange(s, b"\x00\x00\x00\x02R_RI\x00\x17") == ("S_RI", b"\x00\x04")
        assert exchange(s, telegram("K_KY", b"\x00\x01")) == ("T_ER", b"\x01\x16")


def test_link_reads_the_control_through_pylsv2_and_sends_only_reads():
    stage = FixedStage()
    stage.move("X", 101.5)
    stage.move("B", -15.0, -1)
    with SimLSV2(ManualClock(), stage) as sim:
        link = HeidenhainLink.open(lsv2_resource(sim), timeout_s=2.0)
        try:
            assert link.identify() == "Heidenhain TNC640 NC 340595 10 SP5"
            assert link.position() == {"X": 101.5, "Y": 0.0, "Z": 0.0, "A": 0.0, "B": -15.0}
            assert link.execution_state() == "AUTOMATIC" and link.program_state() == "IDLE"
            with pytest.raises(InstrumentError, match="reads the control only"):
                link.send_program(["G0 X0"])
        finally:
            link.close()
        assert set(sim.telegrams) <= READS and "R_RI" in sim.telegrams


def test_axes_are_mapped_to_the_controls_names():
    with SimLSV2(ManualClock(), axes=("X", "Y", "Z", "C")) as sim:
        sim.pos.update(C=90.0)
        link = HeidenhainLink.open(lsv2_resource(sim), timeout_s=2.0, axes={"X": "X", "Y": "Y", "Z": "Z", "B": "C"})
        try:
            assert link.position() == {"X": 0.0, "Y": 0.0, "Z": 0.0, "B": 90.0}
        finally:
            link.close()
        wrong = HeidenhainLink.open(lsv2_resource(sim), timeout_s=2.0)
        try:
            with pytest.raises(InstrumentError, match=r"no axis 'A' for A \(it has X, Y, Z, C\)"):
                wrong.position()
        finally:
            wrong.close()
    with pytest.raises(ValidationError, match="not one of"):
        HeidenhainLink("h", axes={"W": "W"})


def test_dropped_connection_and_swallowed_reply_are_read_again_on_a_new_connection():
    with SimLSV2(ManualClock()) as sim:
        sim.pos.update(Z=-40.0)
        link = HeidenhainLink.open(lsv2_resource(sim), timeout_s=0.5)
        try:
            sim.drop()  # the cable pulled
            assert link.position()["Z"] == -40.0 and link.reconnects == 1
            sim.inject("timeout", on="R_RI")  # a reply that never comes
            assert link.position()["Z"] == -40.0 and link.reconnects == 2
            sim.inject("garble", on="R_RI")  # a reply too short for a header
            assert link.position()["Z"] == -40.0 and link.reconnects == 3
            sim.inject("timeout", "timeout", on="R_RI")
            with pytest.raises(InstrumentError, match=r"LSV2 axes_location: .* \(gave up after 2 attempts\)"):
                link.position()
        finally:
            link.close()


def test_reply_data_pylsv2_cannot_parse_is_one_line_not_its_exception():
    with SimLSV2(ManualClock()) as sim:
        link = HeidenhainLink.open(lsv2_resource(sim), timeout_s=2.0)
        try:
            sim.axis_trailer = b"C\x00"  # a name too many: pyLSV2 "error while parsing axis data"
            with pytest.raises(InstrumentError, match=r"LSV2 axes_location: .*parsing axis data.*gave up") as err:
                link.position()
            assert "\n" not in str(err.value) and not isinstance(err.value, pyLSV2.LSV2DataException)
            sim.axis_trailer = b""
            assert link.position()["X"] == 0.0  # the next read works again
        finally:
            link.close()


def test_refused_dnc_login_is_one_line_with_the_controls_reason():
    with SimLSV2(ManualClock(), dnc_allowed=False) as sim:
        link = HeidenhainLink.open(lsv2_resource(sim), timeout_s=2.0)
        try:
            with pytest.raises(InstrumentError, match=r"needs the DNC login.*T_ER_NO_PRIV; type 1, code 23"):
                link.position()
        finally:
            link.close()


def test_unreachable_control_and_resource_names():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here once the socket is closed
    with pytest.raises(InstrumentError, match=f"LSV2 127.0.0.1:{port}: cannot connect"):
        HeidenhainLink.open(f"127.0.0.1:{port}", timeout_s=0.5)
    assert lsv2_address("tnc") == ("tnc", 19000) and lsv2_address("tnc:19001") == ("tnc", 19001)
    with pytest.raises(ValidationError, match="host or host:port"):
        lsv2_address("GPIB0::1::INSTR")


def test_a_campaign_on_a_read_only_link_is_refused_before_anything_opens(tmp_path):
    from driftlab.campaigns.plan import parse_plan
    from driftlab.daemon.rig import build_file_rig
    from driftlab.daemon.rigfile import parse_rig

    rig = parse_rig(
        {
            "name": "tnc",
            "instruments": {
                "thermocouples": {
                    "driver": "keysight-34970a",
                    "resource": "GPIB0::9::INSTR",
                    "options": {"channels": {101: "T1"}},
                },
                "machine": {"driver": "heidenhain-lsv2", "resource": "tnc-host"},
            },
        }
    )
    plan = parse_plan(
        {
            "name": "p",
            "machine": {"id": "m", "channels": {"T1": {"location": "a"}}},
            "scan_interval_s": 1,
            "stages": [{"name": "idle", "axis": "X", "duration_s": 2}],
        }
    )
    with pytest.raises(ValidationError, match="heidenhain-lsv2 reads the control but cannot move the machine"):
        build_file_rig(plan, rig, ["T1"], ManualClock())
