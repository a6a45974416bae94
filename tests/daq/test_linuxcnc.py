"""LinuxCNC link through linuxcncrsh: the real servers' replies byte for byte, E-stop, NAKs, reconnection.

The replies are those of linuxcncrsh itself, on master: the recorded session of the real server in
LinuxCNC's tree (tests/linuxcncrsh/expected-telnet-output: ``HELLO ACK RuntimeTestMachine 1.1``,
``ERROR G38.2 move finished without making contact.``, ``error: Machine must be 'ON' for SET
MODE`` before ``SET MODE NAK``) and its CR LF line ends; on v2.9.10, src/emc/usr_intf/emcrsh.cc at
that tag (``commandSet``'s ``"SET %s ACK\n\r"``, bare ``SET <KEY> NAK``, six ``%f`` positions,
``SET_WAIT``). The end-to-end tests drive the simulated LinuxCNC through a real TCP socket; the
conformance tests against counterparts of both servers are in test_linuxcnc_lines.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from driftlab.daq.linuxcnc import LinuxCNCLink, linuxcnc_url
from driftlab.daq.protocols import MachineLink
from driftlab.errors import InstrumentError, ValidationError
from tests.daq.protocol_helpers import TIMEOUT, ProtocolPort

HANDSHAKE: list[tuple[bytes | None, object]] = [  # master
    (b"hello EMC driftlab 1.1\r\n", b"HELLO ACK RuntimeTestMachine 1.1\r\n"),
    (b"set echo off\r\n", b"set echo off\r\n"),  # echo is still on: the server repeats the command
    (b"set verbose on\r\n", b"SET VERBOSE ACK\r\n"),
    (b"set enable EMCTOO\r\n", b"SET ENABLE ACK\r\n"),
    (b"get wait_mode\r\n", b"WAIT_MODE DONE\r\n"),
    (b"set wait_mode received\r\n", b"SET WAIT_MODE ACK\r\n"),
    (b"get estop\r\n", b"ESTOP OFF\r\n"),
    (b"get machine\r\n", b"MACHINE ON\r\n"),
]
HANDSHAKE_29: list[tuple[bytes | None, object]] = [  # v2.9.10: LF CR after a set's reply, no wait_mode
    (b"hello EMC driftlab 1.1\r\n", b"HELLO ACK EMCNETSVR 1.1\r\n"),
    (b"set echo off\r\n", b"set echo off\r\n"),
    (b"set verbose on\r\n", b"SET VERBOSE ACK\n"),
    (b"set enable EMCTOO\r\n", b"\rSET ENABLE ACK\n"),
    (b"get wait_mode\r\n", b"\rGET WAIT_MODE NAK\r\n"),
    (b"get set_wait\r\n", b"SET_WAIT RECEIVED\r\n"),
    (b"set set_wait received\r\n", b"SET SET_WAIT ACK\n"),
    (b"get estop\r\n", b"\rESTOP OFF\r\n"),
    (b"get machine\r\n", b"MACHINE ON\r\n"),
]
MDI = [(b"set mode mdi\r\n", b"SET MODE ACK\r\n"), (b"set mdi G21 G90\r\n", b"SET MDI ACK\r\n")]
POS = b"REL_ACT_POS 0.300000 0.200000 -0.100000 0.000000 0.000000 0.000000 0.000000 0.000000 0.000000\r\n"
POS_29 = b"REL_ACT_POS 0.300000 0.200000 -0.100000 0.000000 0.000000 0.000000\r\n"
TLO = [(b"get tool_offset\r\n", b"TOOL_OFFSET 0.000000\r\n")]


def link_on(*conversations: list[tuple[bytes | None, object]]) -> tuple[LinuxCNCLink, list[ProtocolPort]]:
    """Return a link whose successive connections are these scripted conversations."""
    ports = [ProtocolPort(c) for c in conversations]
    queue = list(ports)

    def connect() -> ProtocolPort:
        if not queue:
            raise InstrumentError("cannot open serial port: connection refused")
        return queue.pop(0)

    return LinuxCNCLink(connect, sleep=lambda _s: None, max_idle_polls=5), ports


def all_used(ports: list[ProtocolPort]) -> None:
    for p in ports:
        assert p.index == len(p.pairs), f"unused pairs: {p.pairs[p.index :]}"


def test_resource_names():
    assert linuxcnc_url("cnc-host") == "socket://cnc-host:5007"
    assert linuxcnc_url("10.0.0.5:6000") == "socket://10.0.0.5:6000"
    assert linuxcnc_url("socket://h:1") == "socket://h:1"
    with pytest.raises(ValidationError, match="host:port"):
        linuxcnc_url("/dev/ttyS0")


def test_session_and_positions_from_the_real_servers_replies():
    link, ports = link_on([*HANDSHAKE, (b"get rel_act_pos\r\n", POS), *TLO])
    link.session()
    assert link.identify() == "linuxcncrsh RuntimeTestMachine 1.1 (master line)"
    assert link.position() == {"X": 0.3, "Y": 0.2, "Z": -0.1, "A": 0.0, "B": 0.0}
    assert isinstance(link, MachineLink)
    all_used(ports)  # a check: no mode change, no MDI, nothing moved


def test_the_released_line_is_told_by_set_wait_and_read_with_six_values():
    convo = [
        *HANDSHAKE_29,
        (b"get rel_act_pos\r\n", POS_29),
        (b"get tool_offset\r\n", b"TOOL_OFFSET 2.500000\r\n"),  # G43 active: Z of the move frame is less it
        (b"get rel_act_pos 2\r\n", b"REL_ACT_POS 2 -0.100000\r\n"),  # 2.9 takes the axis by number
    ]
    link, ports = link_on(convo)
    link.session()
    assert link.line == "2.9" and link.identify() == "linuxcncrsh EMCNETSVR 1.1 (2.9 line)"
    assert link.position() == {"X": 0.3, "Y": 0.2, "Z": pytest.approx(-2.6), "A": 0.0, "B": 0.0}
    assert link.axis_position("Z") == -0.1
    all_used(ports)


def test_master_takes_the_axis_by_letter_and_a_wrong_label_is_refused():
    convo = [
        *HANDSHAKE,
        (b"get rel_act_pos Z\r\n", b"REL_ACT_POS Z -0.100000\r\n"),
        (b"get rel_act_pos Y\r\n", b"REL_ACT_POS X 0.300000\r\n"),
    ]
    link, ports = link_on(convo)
    link.session()
    assert link.axis_position("z") == -0.1
    with pytest.raises(InstrumentError, match="is not axis Y"):
        link.axis_position("Y")
    all_used(ports)


@pytest.mark.parametrize("n", [5, 7])
def test_a_position_of_neither_six_nor_nine_values_is_refused(n):
    words = " ".join(["0.000000"] * n)
    link, ports = link_on([*HANDSHAKE, (b"get rel_act_pos\r\n", f"REL_ACT_POS {words}\r\n".encode())])
    link.session()
    with pytest.raises(InstrumentError, match=f"with {n} values, expected 6"):
        link.position()
    all_used(ports)


@pytest.mark.parametrize("handshake", [HANDSHAKE, HANDSHAKE_29], ids=["master", "2.9"])
def test_a_machine_in_estop_is_refused_never_released(handshake):
    convo = [*handshake[:-2], (b"get estop\r\n", b"ESTOP ON\r\n")]
    link, ports = link_on(convo)
    with pytest.raises(InstrumentError, match="E-stop: release it at the machine"):
        link.session()
    all_used(ports)


def test_masters_plain_set_nak_carries_its_reason():
    convo = [
        *HANDSHAKE,
        (b"set spindle_speed 100\r\n", b"error: Subcommand not found: SET spindle_speed\r\n"),
        (None, b"SET NAK\r\n"),
    ]
    link, ports = link_on(convo)
    link.session()
    with pytest.raises(InstrumentError, match="refused: Subcommand not found: SET spindle_speed$"):
        link.set("spindle_speed", "100")
    all_used(ports)


def test_a_server_with_neither_wait_mode_is_refused_with_both_reasons():
    convo = [
        *HANDSHAKE[:4],
        (b"get wait_mode\r\n", b"GET WAIT_MODE NAK\r\n"),
        (b"get set_wait\r\n", b"error: Subcommand not found: GET set_wait\r\n"),
        (None, b"GET NAK\r\n"),
    ]
    link, ports = link_on(convo)
    with pytest.raises(InstrumentError, match="neither wait-mode query.*get set_wait: Subcommand not found"):
        link.session()
    all_used(ports)


def test_a_wrong_password_is_one_line():
    link, ports = link_on([(b"hello EMC driftlab 1.1\r\n", b"HELLO NAK\r\n")])
    with pytest.raises(InstrumentError, match="password"):
        link.session()
    all_used(ports)


def test_a_nak_carries_the_servers_error_line():
    convo = [
        *HANDSHAKE,
        (b"set mode mdi\r\n", b"error: Machine must be 'ON' for SET MODE\r\n"),
        (None, b"SET MODE NAK\r\n"),
    ]
    link, ports = link_on(convo)
    link.session()
    with pytest.raises(InstrumentError, match="'set mode mdi' refused: Machine must be 'ON' for SET MODE"):
        link.mdi("G1 X1")
    all_used(ports)


def test_a_nak_without_error_line_asks_get_error():
    convo = [
        *HANDSHAKE,
        *MDI,
        (b"set mdi G1 X1\r\n", b"SET MDI NAK\r\n"),
        (b"get error\r\n", b"ERROR Must be in MDI mode to issue MDI command\r\n"),
    ]
    link, ports = link_on(convo)
    link.session()
    with pytest.raises(InstrumentError, match="Must be in MDI mode"):
        link.mdi("G1 X1")
    all_used(ports)


def test_program_blocks_go_as_mdi_and_completion_is_polled():
    convo = [
        *HANDSHAKE,
        *MDI,
        (b"set mdi G00 Z-10.0000\r\n", b"SET MDI ACK\r\n"),
        (b"set mdi G04 P0.5\r\n", b"SET MDI ACK\r\n"),
        (b"get program_status\r\n", b"PROGRAM_STATUS RUNNING\r\n"),
        (b"get program_status\r\n", b"PROGRAM_STATUS IDLE\r\n"),
        (b"get error\r\n", b"ERROR OK\r\n"),
    ]
    link, ports = link_on(convo)
    link.session()
    report = link.send_program(["(stage warm)", "G00 Z-10.0000", "", "G04 P0.5 (settle, ch. 5.5)"])
    assert report.blocks_sent == 2
    all_used(ports)


def test_probing_reads_the_g38_parameters_and_a_miss_is_none():
    convo = [
        *HANDSHAKE,
        *MDI,
        (b"set probe_clear\r\n", b"SET PROBE_CLEAR ACK\r\n"),
        (b"set mdi G38.2 X0.0000 Y0.0000 Z-60.0000 F100.0\r\n", b"SET MDI ACK\r\n"),
        (b"get program_status\r\n", b"PROGRAM_STATUS IDLE\r\n"),
        (b"get error\r\n", b"ERROR OK\r\n"),
        (b"set mdi (DEBUG,PROBE #5061 #5062 #5063 #5070)\r\n", b"SET MDI ACK\r\n"),
        (b"get program_status\r\n", b"PROGRAM_STATUS IDLE\r\n"),
        (b"get error\r\n", b"ERROR OK\r\n"),
        (b"get operator_display\r\n", b"OPERATOR_DISPLAY PROBE 0.000000 0.000000 -38.999015 1.000000\r\n"),
        (b"set probe_clear\r\n", b"SET PROBE_CLEAR ACK\r\n"),
        (b"set mdi G38.2 X30.0000 Y0.0000 Z-20.0000 F100.0\r\n", b"SET MDI ACK\r\n"),
        (b"get program_status\r\n", b"PROGRAM_STATUS IDLE\r\n"),
        (b"get error\r\n", b"ERROR G38.2 move finished without making contact.\r\n"),
    ]
    link, ports = link_on(convo)
    link.session()
    np.testing.assert_allclose(link.probe((0, 0, -60), 100.0), [0.0, 0.0, -38.999015])
    assert link.probe((30, 0, -20), 100.0) is None
    all_used(ports)


def test_a_dropped_connection_is_reopened_a_read_repeated_a_move_never():
    first = [*HANDSHAKE, (b"get rel_act_pos\r\n", TIMEOUT)]
    second = [*HANDSHAKE, (b"get rel_act_pos\r\n", POS), *TLO, *MDI, (b"set mdi G1 X1\r\n", TIMEOUT)]
    third = [*HANDSHAKE, (b"get program_status\r\n", b"PROGRAM_STATUS IDLE\r\n")]
    link, ports = link_on(first, second, third)
    link.session()
    assert link.position()["X"] == 0.3  # the read was repeated on a new session
    assert link.reconnects == 1 and ports[0].closed
    with pytest.raises(InstrumentError, match="not repeated"):
        link.mdi("G1 X1")
    assert link.buffer_free() == 1  # the next command opens a third session
    all_used(ports)


def test_a_controller_that_never_finishes_is_an_instrument_error():
    convo = [*HANDSHAKE, *[(b"get program_status\r\n", b"PROGRAM_STATUS RUNNING\r\n")] * 5]
    link, ports = link_on(convo)
    link.session()
    with pytest.raises(InstrumentError, match="did not finish"):
        link.wait_done()
    all_used(ports)


def test_against_the_simulated_linuxcnc_over_tcp():
    from driftlab.daq.sim.instruments import ManualClock, SimSphere, serial_url
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC
    from driftlab.testing.tinyworld import TinyWorld

    clock = ManualClock()
    spheres = {"s": SimSphere((0.0, 0.0, -50.0), 10.0)}
    with SimLinuxCNC(TinyWorld(channels=2), clock, spheres=spheres, sphere_offset=lambda t, c: np.zeros(3)) as sim:
        link = LinuxCNCLink.open(serial_url(sim), timeout_s=2.0, sleep=clock.sleep)
        try:
            link.send_program(["G00 Z-10", "G01 Z-20 F1000"], wait=False)
            assert link.running()
            link.wait_done()  # polls while the simulated clock runs the moves
            assert link.position()["Z"] == pytest.approx(-20.0)
            hit = link.probe((0, 0, -60), 100.0)
            assert hit is not None and hit[2] == pytest.approx(-39.0, abs=0.01)  # sphere top + stylus
            sim.drop()
            assert link.position()["Z"] == pytest.approx(hit[2], abs=1e-6)
            assert link.reconnects == 1
            assert "set mdi G01 Z-20 F1000" in sim.received and "hello EMC driftlab 1.1" in sim.received
        finally:
            link.close()


def test_a_sphere_probed_through_linuxcnc_g38_is_found_where_the_machine_has_it():
    from driftlab.daq.linuxcnc import LinuxCNCProbe
    from driftlab.daq.protocols import Prober
    from driftlab.daq.sim.instruments import ManualClock, SimSphere, serial_url
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC
    from driftlab.testing.tinyworld import TinyWorld

    clock = ManualClock()
    drift = np.array([0.004, -0.002, 0.003])  # the machine's error at the sphere: what probing is for
    spheres = {"s1": SimSphere((50.0, 20.0, -100.0), 12.7)}
    with SimLinuxCNC(TinyWorld(channels=2), clock, spheres=spheres, sphere_offset=lambda t, c: drift) as sim:
        link = LinuxCNCLink.open(serial_url(sim), timeout_s=2.0, sleep=clock.sleep)
        try:
            probe = LinuxCNCProbe(link, stylus_radius_mm=1.0, feed_mm_min=200.0)
            assert isinstance(probe, Prober)
            got = probe.probe_sphere("s1", (50.0, 20.0, -100.0), 12.7)
        finally:
            link.close()
    np.testing.assert_allclose(got.centre, np.array([50.0, 20.0, -100.0]) + drift, atol=1e-5)
    assert got.radius_mm == pytest.approx(12.7, abs=1e-5)
    assert sum(1 for c in sim.mdi_log if c.startswith("G38.2")) == 5
