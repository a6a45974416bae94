"""kill -9 of a real daemon process at random moments, then --resume: exactly the rows of a run never interrupted."""

from __future__ import annotations

import multiprocessing
import os
import random
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from driftlab.campaigns.plan import load_plan
from driftlab.cli import main as cli_main
from driftlab.daemon.run import run_daemon

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "examples" / "scenarios" / "clean.yaml"

PLAN = """\
format: driftlab-plan/1
name: resume-test
machine: {id: vmc-5ax-01, channels: from scenario}
scan_interval_s: 60
state_every: 2
stages:
  - name: baseline
    axis: Z
    duration_s: 1200
    sweep: &sw {positions: [-250, -125, 0], interval_s: 600, point_s: 6, term: dz}
  - name: spindle-10k
    heat: [{kind: spindle, rpm: 10000}]
    axis: Z
    duration_s: 2400
    sweep: *sw
  - name: z-feed
    heat: [{kind: axis, axis: Z, feed_mm_min: 5000, from_pos: 0, to_pos: -250}]
    axis: Z
    duration_s: 1800
    sweep: *sw
  - name: both
    heat: [{kind: spindle, rpm: 10000}, {kind: axis, axis: Z, feed_mm_min: 5000, from_pos: 0, to_pos: -250}]
    axis: Z
    duration_s: 1800
    sweep: *sw
"""
N_SCANS, N_POINTS = 120, 72  # 7200 s / 60 s; 12 sweeps x 6 points
#: the same timeline with the setup changing between stages (issue 11): a laser on Z, a proximity pair on
#: a Z reference edge, the A axis' proximity array (five terms a point) and its angular optics within +-10 deg
PLAN_SETUPS = """\
format: driftlab-plan/1
name: resume-test
machine: {id: vmc-5ax-01, channels: from scenario}
scan_interval_s: 60
state_every: 2
setups:
  z-pos: {instrument: laser, optics: linear, axis: Z, terms: [dz]}
  z-roll: {instrument: proximity, fixture: reference_edge, axis: Z, terms: [gamma]}
  a-runout: {instrument: proximity, fixture: cylinder, axis: A, terms: [dx, dy, dz, beta, gamma]}
  a-pos: {instrument: laser, optics: angular, axis: A, terms: [alpha]}
stages:
  - {name: baseline, axis: Z, setup: z-pos, duration_s: 1200,
     sweep: &sw {positions: [-250, -125, 0], interval_s: 600, point_s: 6}}
  - {name: spindle-10k, heat: [{kind: spindle, rpm: 10000}], axis: Z, setup: z-roll, duration_s: 2400, sweep: *sw}
  - {name: a-feed, heat: [{kind: axis, axis: A, feed_mm_min: 2000, from_pos: -10, to_pos: 10}], axis: A,
     setup: a-runout, duration_s: 1800, sweep: &sa {positions: [-10, 0, 10], interval_s: 600, point_s: 6}}
  - {name: cool, axis: A, setup: a-pos, duration_s: 1800, sweep: *sa}
"""
N_ERRORS = {PLAN: N_POINTS, PLAN_SETUPS: 12 + 24 + 18 * 5 + 18}
SPEED = "7200"  # accelerated time: about a second of wall clock per run once started


def _daemon(plan: Path, db: Path, *extra: str) -> subprocess.Popen:
    """Start `driftlab daemon` on the virtual machine as a real subprocess."""
    env = {**os.environ, "DRIFTLAB_DB_URL": f"sqlite:///{db}"}
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "driftlab.cli",
            "daemon",
            "--plan",
            str(plan),
            "--sim",
            str(SCENARIO),
            "--speed",
            SPEED,
            *extra,
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _forked_daemon(plan: Path, db: Path, *extra: str) -> multiprocessing.Process:
    """Start `driftlab daemon` in a forked child process (a real process, without re-importing everything)."""
    argv = ["daemon", "--plan", str(plan), "--sim", str(SCENARIO), "--speed", SPEED, "--db", f"sqlite:///{db}", *extra]
    proc = multiprocessing.get_context("fork").Process(target=_child, args=(argv,), daemon=False)
    proc.start()
    return proc


def _child(argv: list[str]) -> None:
    """Run the CLI in the child, quietly, and exit with its status."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    os._exit(cli_main(argv))


def _done(db: Path) -> int:
    """Return how many scans plus sweep points the store holds per its cursor (0 before the campaign exists)."""
    if not db.exists():
        return 0
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            row = con.execute(
                "SELECT json_extract(cursor, '$.next_scan') + json_extract(cursor, '$.next_point') "
                "FROM acquisition_progress"
            ).fetchone()
        finally:
            con.close()
    except sqlite3.OperationalError:
        return 0  # schema not there yet
    return int(row[0]) if row and row[0] is not None else 0


def _rows(db: Path) -> dict[str, list[tuple]]:
    """Return every stored reading, in key order, as plain tuples."""
    con = sqlite3.connect(db)
    try:
        return {
            "temperatures": con.execute(
                "SELECT c.name, t.time_s, t.value FROM temperature_samples t "
                "JOIN channels c ON c.id = t.channel_id ORDER BY c.name, t.time_s"
            ).fetchall(),
            "errors": con.execute(
                "SELECT seq, time_s, axis, term, position, direction, value, sweep FROM error_samples ORDER BY seq"
            ).fetchall(),
            "conditions": con.execute(
                "SELECT time_s, spindle_rpm, feed_mm_min, x, y, z, a, b FROM condition_samples ORDER BY time_s"
            ).fetchall(),
            "campaign": con.execute("SELECT name, status FROM campaigns").fetchall(),
            "stages": con.execute("SELECT ordinal, name, status FROM stages ORDER BY ordinal").fetchall(),
        }
    finally:
        con.close()


@pytest.mark.slow
@pytest.mark.parametrize("text", [PLAN, PLAN_SETUPS], ids=["one-setup", "setups-change"])
def test_killed_five_times_ends_with_exactly_the_uninterrupted_rows(tmp_path: Path, text: str) -> None:
    """Five SIGKILLs at random moments (one during start-up) and a SIGTERM, each followed by --resume: same rows."""
    plan = tmp_path / "plan.yaml"
    plan.write_text(text)
    clean_db, killed_db = tmp_path / "clean.sqlite", tmp_path / "killed.sqlite"

    # the run that is never interrupted (in this process: the same code path without the CLI around it)
    result = run_daemon(load_plan(plan), db_url=f"sqlite:///{clean_db}", scenario_path=SCENARIO, speed=7200.0)
    assert result.stats.finished and result.stats.faults == 0

    rng = random.Random(20261122)
    total = N_SCANS + N_POINTS
    targets = sorted(rng.sample(range(5, total - 80), 4))  # room left for the SIGTERM stop below
    kills: list[int] = []
    # kill 1: at a random moment of start-up (schema, servers, drivers), possibly before the campaign exists
    proc = _forked_daemon(plan, killed_db, "--resume")
    time.sleep(rng.uniform(0.0, 0.3))
    assert proc.is_alive()
    os.kill(proc.pid, signal.SIGKILL)
    proc.join()
    kills.append(_done(killed_db))
    # kills 2-5: once the stored cursor passes a random target, after a further random few milliseconds
    for target in targets:
        proc = _forked_daemon(plan, killed_db, "--resume")
        while proc.is_alive() and _done(killed_db) < target:
            time.sleep(0.005)
        time.sleep(rng.uniform(0.0, 0.03))
        assert proc.is_alive(), f"the daemon finished (status {proc.exitcode}) before its kill at {target}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.join()
        assert proc.exitcode == -signal.SIGKILL
        kills.append(_done(killed_db))
    assert kills == sorted(kills) and kills[-1] < total  # every kill left the campaign unfinished
    # SIGTERM (a supervisor stopping it) ends the run between two commits with the "resumable" status
    # (as soon as it has stored something: on a loaded machine the poll below can lag the daemon by many rows)
    proc = _forked_daemon(plan, killed_db, "--resume")
    while proc.is_alive() and _done(killed_db) <= kills[-1]:
        time.sleep(0.002)
    assert proc.is_alive(), f"the daemon finished (status {proc.exitcode}) before its SIGTERM"
    os.kill(proc.pid, signal.SIGTERM)
    proc.join()
    assert proc.exitcode == 3
    assert kills[-1] < _done(killed_db) < total
    # the last resume through the installed entry point, as an operator (or a supervisor) would run it
    proc = _daemon(plan, killed_db, "--resume")
    out, err = proc.communicate()
    assert proc.returncode == 0, err

    clean, killed = _rows(clean_db), _rows(killed_db)
    assert len(clean["temperatures"]) == N_SCANS * 50
    assert len(clean["errors"]) == N_ERRORS[text]
    assert len(clean["conditions"]) == N_SCANS // 2
    for table in clean:
        assert len(killed[table]) == len(clean[table]), table
        assert killed[table] == clean[table], table  # identical values, bit for bit
    assert killed["campaign"] == [("resume-test", "done")]
    assert {s for _, _, s in killed["stages"]} == {"done"}


def test_resume_of_a_complete_campaign_does_nothing(tmp_path: Path) -> None:
    """--resume after the end stores nothing more (a supervisor restarting the daemon is harmless)."""
    plan = load_plan(ROOT / "examples" / "plans" / "z-axis-demo.yaml")
    short = plan.model_copy(update={"stages": plan.stages[:2]})
    db = tmp_path / "d.sqlite"
    first = run_daemon(short, db_url=f"sqlite:///{db}", scenario_path=SCENARIO, speed=float("inf"), resume=True)
    again = run_daemon(short, db_url=f"sqlite:///{db}", scenario_path=SCENARIO, speed=float("inf"), resume=True)
    assert first.stats.finished and again.stats.finished
    assert first.stats.scans == short.n_scans and again.stats.scans == 0 and again.stats.points == 0
    assert again.campaign_id == first.campaign_id and again.resumed
    assert len(_rows(db)["temperatures"]) == short.n_scans * 50
