"""Rig files and `driftlab rig check`: every shipped rig against the simulated instruments, the pyvisa-sim
34970A (an implementation that is not driftlab's) to 1 mK, one line per failure, one-line file errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from driftlab.cli import main
from driftlab.daemon.rigfile import load_rig, parse_rig, thermocouple_channels
from driftlab.errors import ValidationError

ROOT = Path(__file__).resolve().parents[2]
RIGS = sorted((ROOT / "examples" / "rigs").glob("*.yaml"))
RIG_FILES = [p for p in RIGS if not p.name.endswith(".pyvisa-sim.yaml")]
CLEAN = ROOT / "examples" / "scenarios" / "clean.yaml"


@pytest.mark.parametrize("rig", RIG_FILES, ids=lambda p: p.name)
def test_every_shipped_rig_passes_against_the_simulated_instruments(rig, tmp_path, capsys):
    out = tmp_path / "check.json"
    sim = [] if "pyvisa-sim" in rig.name else ["--sim", str(CLEAN)]
    assert main(["rig", "check", str(rig), *sim, "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    spec = load_rig(rig)
    assert [i["role"] for i in doc["instruments"]] == [r for r in ("thermocouples", "proximity", "laser", "machine")
                                                       if r in spec.instruments]  # fmt: skip
    for inst in doc["instruments"]:
        assert inst["idn"] and inst["reading"] and "error" not in inst
        if inst["role"] == "thermocouples":
            assert list(inst["reading"]) == thermocouple_channels(spec)
            assert all(10.0 < v < 40.0 for v in inst["reading"].values())  # degC of a machine in a shop
    assert "identification" in capsys.readouterr().out


def test_pyvisa_sim_34970a_is_identified_and_read_to_1_mk(tmp_path):
    out = tmp_path / "check.json"
    assert (
        main(["rig", "check", str(ROOT / "examples/rigs/keysight-34970a-pyvisa-sim.rig.yaml"), "--json", str(out)]) == 0
    )
    (inst,) = json.loads(out.read_text())["instruments"]
    assert inst["idn"] == "HEWLETT-PACKARD,34970A,0,13-2-2"
    # the values pyvisa-sim's dialogue sends (+2.08765000E+01 ...), read back to better than 1 mK
    want = {"T1": 21.345, "T3": 20.8765, "T4": 24.5001, "T10": 18.333}
    for name, value in want.items():
        assert abs(inst["reading"][name] - value) < 1e-3


def test_unreachable_instruments_fail_with_one_line_each(tmp_path, capsys):
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now: connections are refused at once
    rig = tmp_path / "rig.yaml"
    rig.write_text(
        "name: down\ninstruments:\n"
        f"  thermocouples: {{driver: keysight-34970a, resource: 'TCPIP0::127.0.0.1::{port}::SOCKET', timeout_s: 0.5,"
        " options: {channels: {101: T1}}}\n"
        f"  machine: {{driver: linuxcnc, resource: '127.0.0.1:{port}', timeout_s: 0.5}}\n"
    )
    assert main(["rig", "check", str(rig), "--json", str(tmp_path / "o.json")]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("driftlab:")]
    assert len(err) == 2
    assert err[0].startswith("driftlab: rig down: thermocouples (keysight-34970a at TCPIP0::127.0.0.1::")
    assert err[1].startswith("driftlab: rig down: machine (linuxcnc at 127.0.0.1:")
    doc = json.loads((tmp_path / "o.json").read_text())
    assert all(i["error"] and i["idn"] is None for i in doc["instruments"])


@pytest.mark.parametrize(
    ("doc", "needle"),
    [
        ({"name": "x", "instruments": {"oven": {"driver": "linuxcnc", "resource": "h"}}}, "unknown role"),
        ({"name": "x", "instruments": {"machine": {"driver": "keysight-34970a", "resource": "h"}}}, "plays the"),
        ({"name": "x", "instruments": {"machine": {"driver": "fanuc", "resource": "h"}}}, "is not one of"),
        ({"name": "x", "instruments": {"machine": {"driver": "linuxcnc"}}}, "instruments.machine.resource"),
        ([1, 2], "a mapping"),
    ],
)
def test_bad_rig_files_are_one_line_errors(doc, needle):
    with pytest.raises(ValidationError, match=needle) as err:
        parse_rig(doc, "rig x.yaml")
    assert "\n" not in err.value.one_line()


def test_bad_driver_options_and_missing_files_are_one_line_cli_errors(tmp_path, capsys):
    rig = tmp_path / "rig.yaml"
    rig.write_text(
        "name: x\ninstruments:\n"
        "  thermocouples: {driver: keysight-34970a, resource: 'GPIB0::1::INSTR', options: {chanels: {}}}\n"
    )
    assert main(["rig", "check", str(rig)]) == 1
    assert "unknown option 'chanels'" in capsys.readouterr().err
    assert main(["rig", "check", str(tmp_path / "none.yaml")]) == 2
    assert "no such file" in capsys.readouterr().err


@pytest.mark.parametrize("line", ["2.9", "master"])
def test_daemon_runs_a_plan_on_a_rig_file(line, tmp_path, capsys):
    """`driftlab daemon --plan P --rig R`: the 34970A, the laser and LinuxCNC (2.9 or master) at the rig's addresses."""
    from sqlalchemy import func, select

    from driftlab.campaigns import schema as sc
    from driftlab.campaigns.db import store_engine
    from driftlab.daq.sim.instruments import SimLaser, WallClock, serial_url, visa_address
    from driftlab.daq.sim.keysight34970a import Sim34970A
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC
    from driftlab.testing.tinyworld import TinyWorld

    world, clock = TinyWorld(channels=4), WallClock(acceleration=1.0)
    card = Sim34970A(world, clock, {101: "T1", 102: "T2", 103: "T3", 104: "T4", 105: "T5"}).start()
    cnc = SimLinuxCNC(world, clock, line=line).start()
    head = SimLaser(world, clock, cnc).start()
    rig = tmp_path / "rig.yaml"
    rig.write_text(
        "name: bench\ninstruments:\n"
        f"  thermocouples: {{driver: keysight-34970a, resource: '{visa_address(card)}',"
        " options: {channels: {101: T1, 102: T2, 103: T3, 104: T4, 105: T5}}}\n"
        f"  laser: {{driver: thesis-laser, resource: '{visa_address(head)}'}}\n"
        f"  machine: {{driver: linuxcnc, resource: '{serial_url(cnc)}'}}\n"
    )
    plan = tmp_path / "plan.yaml"
    plan.write_text(
        "name: bench-rig\nmachine: {id: rig-1, channels: {T1: {location: a}, T2: {location: b}, T4: {location: d}}}\n"
        "scan_interval_s: 0.1\nstages:\n  - name: idle\n    axis: X\n    duration_s: 0.6\n"
        "    sweep: {positions: [0, 0.01], directions: [1], interval_s: 0.5, point_s: 0.25}\n"
    )
    db = f"sqlite:///{tmp_path / 'r.sqlite'}"
    try:
        assert main(["daemon", "--plan", str(plan), "--rig", str(rig), "--db", db]) == 0
    finally:
        for server in (card, cnc, head):
            server.close()
    with store_engine(db).connect() as conn:
        n = conn.execute(select(func.count()).select_from(sc.TemperatureSample.__table__)).scalar_one()
        errs = conn.execute(select(func.count()).select_from(sc.ErrorSample.__table__)).scalar_one()
    assert n == 6 * 3 and errs == 2  # six scans of the plan's three channels (T3, T5 wired but not scanned)
    assert "set mdi G01 X0.0000 F2000" in cnc.received  # the approach moves went to LinuxCNC as MDI
    assert "ROUT:SCAN (@101:102,104)" in card.received
    assert main(["daemon", "--plan", str(plan), "--rig", str(tmp_path / "none.yaml"), "--db", db]) == 2
    assert "no such file" in capsys.readouterr().err
