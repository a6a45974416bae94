"""`driftlab compensate --port URL --link dnc`: a drip feed to the virtual controller's DNC port, end to end.

The virtual controller (``daq.sim.dnc``) reads the tape over a real TCP socket in real time, as a
TCP serial server would pass it to the control's RS-232 port; 38400 baud keeps the tests short while
leaving the control's DC3 margin (256 characters, 67 ms of line) far above the thread latencies of a
loaded machine (the issue's 115200-baud target is checked in simulated time in tests/daq/test_dnc.py). Nothing here
depends on how fast the machine is: the assertions are on what arrived, never on how long it took.
"""

from __future__ import annotations

import json
import threading

import pytest

from driftlab.cli import main
from driftlab.daq.dnc import PROFILES
from driftlab.daq.sim.dnc import SimDncControl
from tests.compensator.test_cli import _controller_program, files  # noqa: F401 - the fixture


def _offline(prog, model, temps, out) -> list[str]:
    assert main(["compensate", str(prog), "--model", str(model), "--temps", str(temps), "-o", str(out)]) == 0
    return [
        ln.strip()
        for ln in out.read_text().splitlines()
        if ln.strip() and ln.strip() != "%" and not ln.strip().startswith("(")
    ]


def _dnc(prog, model, temps, url, name, *extra) -> int:
    args = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "--port", url, "--link", "dnc"]
    return main([*args, "--profile", name, "--baud", "38400", "--line", "8N1", "--json", *extra])


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_every_profile_drip_feeds_exactly_the_offline_blocks(name, files, tmp_path, capsys):  # noqa: F811
    _, model, _ = files
    temps = tmp_path / "latest.csv"
    temps.write_text("time_s,T1,T2\n0.0,26.5,21.0\n")
    prog = tmp_path / "p.nc"
    prog.write_text(_controller_program(300))
    offline = _offline(prog, model, temps, tmp_path / "out.nc")
    capsys.readouterr()
    with SimDncControl(PROFILES[name], buffer_bytes=1024, block_s=0.005) as sim:
        if name == "haas":  # a feed hold in the middle: the buffer fills, DC3 holds the feed, then it resumes
            threading.Timer(0.3, sim.hold, args=(1.0,)).start()
        code = _dnc(prog, model, temps, sim.url, name)
        assert sim.done.wait(30.0)
        blocks = list(sim.blocks)
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert blocks == offline and summary["blocks_sent"] == len(offline)
    assert sim.overflow == 0 and sim.parity_errors == 0 and sim.max_held <= 1024
    assert any("Z-" in b for b in blocks[:30])  # corrected: 26.5 degC, the head has grown
    if name == "haas":
        assert summary["dnc"]["dc3"] >= 1 and summary["dnc"]["longest_hold_s"] > 0.5


def test_a_latin1_comment_in_a_block_is_refused_before_the_port_is_opened(files, tmp_path, capsys):  # noqa: F811
    _, model, _ = files
    temps = tmp_path / "latest.csv"
    temps.write_text("time_s,T1,T2\n0.0,26.5,21.0\n")
    prog = tmp_path / "p.nc"
    lines = _controller_program(1600).splitlines()
    at = next(i for i in range(1500, 1600) if lines[i].strip() and not lines[i].startswith("("))
    lines[at] = lines[at] + " (r\xe9glage)"
    prog.write_bytes(("\n".join(lines) + "\n").encode("latin-1"))
    with SimDncControl(PROFILES["generic"]) as sim:
        code = _dnc(prog, model, temps, sim.url, "generic")
        blocks = list(sim.blocks)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and blocks == []
    assert len(err) == 1 and f"p.nc:{at + 1}: byte 0xe9" in err[0] and "not 7-bit ASCII" in err[0]


def test_comment_lines_are_not_sent_and_may_hold_anything(files, tmp_path, capsys):  # noqa: F811
    _, model, _ = files
    temps = tmp_path / "latest.csv"
    temps.write_text("time_s,T1,T2\n0.0,20.0,20.0\n")
    prog = tmp_path / "p.nc"
    prog.write_bytes(b"%\n(r\xe9glage 50%)\nG90 G1 F3000\n(note) X1 Y1\nX2 Y2 ; fin\n%\n")
    with SimDncControl(PROFILES["generic"]) as sim:
        code = _dnc(prog, model, temps, sim.url, "generic")
        assert sim.done.wait(30.0)
        blocks = list(sim.blocks)
    assert code == 0
    assert blocks == ["G90 G1 F3000", "(note) X1 Y1", "X2 Y2 ; fin"]  # a block behind a comment is a block


def test_dnc_options_are_checked_in_one_line(files, capsys):  # noqa: F811
    prog, model, temps = files
    base = ["compensate", str(prog), "--model", str(model), "--temps", str(temps), "--port", "socket://127.0.0.1:9"]
    for extra, needle in (
        (["--link", "dnc", "--profile", "okuma"], "unknown DNC profile 'okuma'"),
        (["--link", "dnc", "--line", "8O1"], "--line must be one of"),
        (["--link", "dnc", "--baud", "7"], "--baud must be between"),
        (["--profile", "haas"], "are for --link dnc"),
    ):
        assert main(base + extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
