"""Both linuxcncrsh lines, v2.9.10 and master: conformance against counterparts written from LinuxCNC's source.

The counterparts (tests/daq/linuxcncrsh_counterpart.py) are re-implementations of each server
from emcrsh.cc at its tag, not from driftlab's code. Against them: the link identifies the line,
reads positions in the frame its MDI moves use (a G54 offset and a tool length offset in place;
within 1 nm, the %f resolution, the target was 1 µm), refuses E-stop in one line, moves nothing
in a check, probes a sphere where the machine has it; `driftlab rig check` and `driftlab
compensate --link linuxcnc` on both; and the virtual controller (driftlab.daq.sim.linuxcnc)
answers each line byte for byte as its counterpart.
"""

from __future__ import annotations

import numpy as np
import pytest

from driftlab.cli import main
from driftlab.daq.linuxcnc import LinuxCNCLink, LinuxCNCProbe
from driftlab.errors import InstrumentError
from tests.compensator.test_cli import _controller_program, files  # noqa: F401 - the fixture is used below
from tests.daq.linuxcncrsh_counterpart import LINES, Machine, Session

G54 = [120.0, -35.0, -250.0, 0, 0, 0, 0, 0, 0]
TLO_MM = 42.5
REACH = 12.7 + 1.0  # sphere radius + stylus radius


def shop_machine(**kw: object) -> Machine:
    """A machine with a G54 offset and a tool length offset: machine, work and REL_ACT_POS all differ."""
    m = Machine(g5x=list(G54), tlo_z=TLO_MM, pos=[150.0, 20.0, -100.0, 0, 0, 0, 0, 0, 0], **kw)  # type: ignore[arg-type]
    return m


def opened(server: object) -> LinuxCNCLink:
    return LinuxCNCLink.open(server.resource, timeout_s=5.0, sleep=lambda _s: None)  # type: ignore[attr-defined]


@pytest.mark.parametrize("line", LINES)
def test_the_link_identifies_the_line_and_reads_the_move_frame_within_a_micrometre(line):
    m = shop_machine()
    with LINES[line](m) as srv:
        link = opened(srv)
        try:
            assert link.line == line and link.identify().endswith(f"({line} line)")
            pos = link.position()
            truth = m.machine_to_work(m.pos)
            assert max(abs(pos[a] - truth[i]) for i, a in enumerate("XYZ")) <= 1e-6
            assert abs(pos["X"] - m.pos[0]) > 100  # not ABS_ACT_POS (machine coordinates)
            assert link.axis_position("Y") == pytest.approx(m.rel()[1], abs=1e-6)  # by number on 2.9, letter on master
            # a move to a work target ends where position() says it is
            link.send_program(["G1 X10.5 Y-3.25 Z7.125 F1000"])
            pos = link.position()
            assert [pos[a] for a in "XYZ"] == pytest.approx([10.5, -3.25, 7.125], abs=1e-6)
        finally:
            link.close()


@pytest.mark.parametrize("line", LINES)
def test_a_check_moves_nothing_and_changes_no_mode(line):
    m = shop_machine()
    with LINES[line](m) as srv:
        link = opened(srv)
        link.identify()
        link.position()
        link.close()
    assert m.moved == 0 and m.mdi_log == [] and m.mode == "MANUAL"
    sent = [c.split()[:2] for c in srv.received]
    assert all(c[0] in ("hello", "get") or c[1] in ("echo", "verbose", "enable", "set_wait", "wait_mode") for c in sent)


@pytest.mark.parametrize("line", LINES)
def test_estop_is_refused_in_one_line_and_never_released(line, tmp_path, capsys):
    m = shop_machine(estop=True)
    with LINES[line](m) as srv:
        with pytest.raises(InstrumentError, match="E-stop: release it at the machine"):
            opened(srv)
        rig = tmp_path / "rig.yaml"
        rig.write_text(f"name: bench\ninstruments:\n  machine: {{driver: linuxcnc, resource: '{srv.resource}'}}\n")
        assert main(["rig", "check", str(rig)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "E-stop: release it at the machine" in err[0]
    assert m.estop and m.moved == 0
    assert not any(c.lower().startswith("set estop") for c in srv.received)


@pytest.mark.parametrize("line", LINES)
def test_rig_check_on_both_lines(line, tmp_path, capsys):
    m = shop_machine()
    with LINES[line](m, name="mill-3") as srv:
        rig = tmp_path / "rig.yaml"
        rig.write_text(f"name: bench\ninstruments:\n  machine: {{driver: linuxcnc, resource: '{srv.resource}'}}\n")
        assert main(["rig", "check", str(rig)]) == 0
    out = capsys.readouterr().out
    assert f"linuxcncrsh mill-3 1.1 ({line} line)" in out
    x, y, z, *_ = m.machine_to_work(m.pos)
    flat = " ".join(out.split())
    assert f"X {x:.4f} mm" in flat and f"Y {y:.4f} mm" in flat and f"Z {z:.4f} mm" in flat, out
    assert m.moved == 0


@pytest.mark.parametrize("line", LINES)
def test_the_probe_cycle_finds_the_sphere_in_the_work_frame(line):
    centre_machine = np.array([180.0, 10.0, -390.0])
    m = shop_machine(spheres=[(tuple(centre_machine), REACH)])
    with LINES[line](m) as srv:
        link = opened(srv)
        try:
            nominal = centre_machine - np.array(G54[:3]) - np.array([0.0, 0.0, TLO_MM])
            got = LinuxCNCProbe(link, stylus_radius_mm=1.0).probe_sphere("s1", tuple(nominal), 12.7)
        finally:
            link.close()
    np.testing.assert_allclose(got.centre, nominal, atol=1e-6)  # %f parameters: 1 nm
    assert got.radius_mm == pytest.approx(12.7, abs=1e-6)
    assert sum(1 for c in m.mdi_log if c.startswith("G38.2")) == 5


@pytest.mark.parametrize("line", LINES)
def test_a_rotated_work_system_is_refused_before_anything_moves(line):
    m = shop_machine(g5x_rotation_deg=30.0, spheres=[((180.0, 10.0, -390.0), REACH)])
    with LINES[line](m) as srv:
        link = opened(srv)
        try:
            with pytest.raises(InstrumentError, match="rotated G5x"):
                LinuxCNCProbe(link).probe_sphere("s1", (0.0, 0.0, -100.0), 12.7)
        finally:
            link.close()
    assert m.moved == 0


@pytest.mark.parametrize("line", LINES)
def test_a_refused_block_reports_the_controls_reason(line):
    m = shop_machine()
    with LINES[line](m) as srv:
        link = opened(srv)
        try:
            link.mdi("G0 X1")
            m.mode = "MANUAL"  # the operator switched modes behind the link's back
            with pytest.raises(InstrumentError, match="Must be in MDI mode"):
                link.send_program(["G0 X2"])  # 2.9: ACKed, then `get error`; master: SET MDI NAK, then `get error`
            with pytest.raises(InstrumentError, match="refused: (Subcommand not found: SET SPINDLE_RPM|no reason)"):
                link.set("SPINDLE_RPM", "100")  # master's plain SET NAK with its reason; 2.9 gives none
        finally:
            link.close()


# -- the virtual controller against the counterparts, byte for byte

SCRIPT = [
    "get estop",  # before any hello: 2.9 answers, master too (no access level on get)
    "set echo off",  # before the hello: 2.9 "SET NAK", master's ECHO needs nothing
    "set echo on",
    "hello EMC driftlab 1.1",
    "get wait_mode",
    "get set_wait",
    "set verbose on",
    "set wait_mode received",
    "set enable EMCTOO",
    "set wait_mode received",
    "set set_wait received",
    "set spindle_speed 100",
    "set echo off",
    "get machine",
    "get tool_offset",
    "get rel_act_pos",
    "get abs_act_pos",
    "get rel_act_pos 2",
    "get rel_act_pos Z",
    "get error",
    "set mdi G1 X1",
    "get error",
    "set mode mdi",
    "get mode",
    "set mdi (DEBUG,HERE #5420 #5421 #5422)",
    "get operator_display",
    "get no_such_key",
    "bogus",
]


@pytest.mark.parametrize("line", LINES)
def test_the_virtual_controller_answers_each_line_as_its_counterpart(line):
    from driftlab.daq.sim.instruments import ManualClock
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC
    from driftlab.testing.tinyworld import TinyWorld

    m = Machine(g5x=list(G54), tlo_z=TLO_MM)
    ref = LINES[line](m, name="driftlab-vm")
    session = Session()
    sim = SimLinuxCNC(TinyWorld(channels=2), ManualClock(), line=line, g5x=G54[:3], tool_offset_mm=TLO_MM)
    try:
        for cmd in SCRIPT:
            data = (cmd + "\r\n").encode()
            want = ref.on_read(session, data) + ref.command(session, cmd)
            got = (sim.handle(cmd) or "").encode()
            assert got == want, f"{line}: {cmd!r}"
    finally:
        ref.close()
        sim.close()


# -- streaming over linuxcncrsh


@pytest.mark.parametrize("line", ["2.9", "master"])
def test_compensate_streams_the_offline_blocks_as_mdi(line, files, tmp_path, capsys):  # noqa: F811
    """`driftlab compensate --link linuxcnc`: the blocks that reach LinuxCNC are the offline file's."""
    import json

    from driftlab.daq.sim.instruments import WallClock
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC
    from driftlab.testing.tinyworld import TinyWorld

    _, model, _ = files
    temps = tmp_path / "latest.csv"
    temps.write_text("time_s,T1,T2\n0.0,26.5,21.0\n")
    prog = tmp_path / "part.nc"
    prog.write_text(_controller_program(300))
    out = tmp_path / "out.nc"
    start = "0,0,0,0,0"
    base = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "--start", start]
    assert main([*base, "-o", str(out)]) == 0
    offline = [ln.strip() for ln in out.read_text().splitlines() if ln.strip() and ln.strip()[0] not in "%("]
    with SimLinuxCNC(TinyWorld(channels=2), WallClock(acceleration=1e9), line=line, g5x=(100.0, 0.0, 0.0)) as sim:
        port = f"127.0.0.1:{sim.port}"
        code = main([*base, "--port", port, "--link", "linuxcnc", "--high-water", "16", "--json"])
        mdi = list(sim.mdi_log)
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert mdi[0] == "G21 G90" and mdi[1:] == offline
    assert summary["blocks_sent"] == len(offline) > 200
