"""What a person reads on the command line: the watch view, log lines and files, verdicts, labels, stage bars."""

from __future__ import annotations

import io
import json
import logging
import math
import re
from pathlib import Path

import pytest
from rich.console import Console

from driftlab.campaigns.db import store_engine
from driftlab.campaigns.plan import load_plan
from driftlab.cli import main
from driftlab.commands.campaign import watch
from driftlab.commands.fit import fit_steps, verdict
from driftlab.daemon.run import run_daemon
from driftlab.labels import duration, effect_label, feature_label
from driftlab.progress import Stages

ROOT = Path(__file__).resolve().parents[1]
PLAN = """\
format: driftlab-plan/1
name: watch-test
machine: {id: vmc-5ax-01, channels: from scenario}
scan_interval_s: 60
stages:
  - name: warm-up
    heat: [{kind: spindle, rpm: 10000}]
    axis: Z
    duration_s: 1800
    sweep: {positions: [-250, 0], interval_s: 600, point_s: 6, term: dz}
  - name: cool
    axis: Z
    duration_s: 1800
    sweep: {positions: [-250, 0], interval_s: 600, point_s: 6, term: dz}
"""
OPEN = """\
name: open-t34
seed: 3
hours: 2
scan_interval_s: 60
sweep_interval_s: 600
hidden:
  - {kind: sensor_fault, channels: [T34], params: {start_s: 300, mode: open}}
"""


@pytest.fixture
def running(tmp_path: Path) -> tuple[str, int]:
    """A campaign the daemon stopped half way (still 'running' in the store): its URL and id."""
    plan, scen = tmp_path / "plan.yaml", tmp_path / "open.yaml"
    plan.write_text(PLAN)
    scen.write_text(OPEN)
    url = f"sqlite:///{tmp_path / 'store.sqlite'}"
    r = run_daemon(load_plan(plan), db_url=url, scenario_path=scen, speed=math.inf, max_batch=10, stop_after_commits=4)
    return url, r.campaign_id


def test_watch_draws_stage_progress_temperatures_errors_and_health(running) -> None:
    url, cid = running
    con = Console(file=io.StringIO(), force_terminal=True, width=140, color_system=None)
    head = watch(store_engine(url), cid, con, interval_s=0.01, max_frames=2)
    text = con.file.getvalue()
    assert head["status"] == "running"
    p = head["progress"]
    assert f"{p['scans']} of {p['n_scans']} scans" in text and p["scans"] > 0
    assert head["stage"]["name"] in text and "spindle 10000 rpm" in text
    assert "T34 open" in text and re.search(r"open thermocouples\s+T34", text)
    assert re.search(r"Z/dz\s+│\s+[+-]\s+│ -250 mm: -?\d+\.\d", text)  # a sweep, in um at each position
    assert "spindle arm" in text and "retries" not in text  # none counted: nothing shown (issue 24)


def test_watch_command_ends_with_the_campaign(running, tmp_path: Path, capsys) -> None:
    url, cid = running
    plan = tmp_path / "plan.yaml"
    run_daemon(load_plan(plan), db_url=url, scenario_path=tmp_path / "open.yaml", speed=math.inf, resume=True)
    assert main(["campaign", "status", str(cid), "--watch", "--db", url]) == 0
    out = capsys.readouterr().out
    assert "[done]" in out and "100.0 %" in out
    assert main(["campaign", "status", "watch-test", "--db", url]) == 0  # without --watch: as before
    assert "watch-test" in capsys.readouterr().out
    for argv, msg in (
        (["--watch"], "give its id or name"),
        (["nope", "--watch"], "no daemon campaign 'nope'"),
        ([str(cid), "--watch", "--json"], "--json prints the status once"),
        ([str(cid), "--watch", "--interval", "0"], "--interval must be positive"),
    ):
        assert main(["campaign", "status", *argv, "--db", url]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err


def test_log_file_gets_timestamped_lines_and_migrations_stay_quiet(tmp_path: Path, capsys) -> None:
    log = tmp_path / "logs" / "driftlab.log"
    url = f"sqlite:///{tmp_path / 'fresh.sqlite'}"
    assert main(["--log-file", str(log), "campaign", "list", "--db", url]) == 0
    err = capsys.readouterr().err
    assert err == ""  # WARNING by default: nothing on the terminal
    lines = log.read_text().splitlines()
    assert lines and all(re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} (INFO|WARNING) ", ln) for ln in lines)
    assert any("Running upgrade" in ln for ln in lines)  # what the migrations did...
    assert not any("setup plugin" in ln or "Context impl" in ln for ln in lines)  # ...not their chatter
    url2 = f"sqlite:///{tmp_path / 'fresh2.sqlite'}"
    assert main(["-v", "campaign", "list", "--db", url2]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err and all(re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d INFO ", ln) for ln in err)
    assert not any("setup plugin" in ln for ln in err)
    assert main(["--log-file", str(tmp_path), "campaign", "list", "--db", url2]) == 2  # a directory: one line
    assert capsys.readouterr().err.startswith("driftlab: error: --log-file")
    for h in [h for h in logging.getLogger().handlers if getattr(h, "_driftlab", False)]:
        logging.getLogger().removeHandler(h)
        h.close()


def test_verdicts_judge_held_out_rmse_against_the_stated_noise_else_the_resolution() -> None:
    ref = {"noise_mm": 0.0005, "noise_rad": 5e-7, "resolution_mm": 0.0025, "resolution_rad": 1.745e-5}
    assert verdict(0.0006, "dz", ref)[1] == "at the noise"
    assert verdict(0.0012, "dz", ref)[:2] == ("2.4x noise", "near the noise")
    assert verdict(0.004, "dz", ref)[1].startswith("above the noise")
    assert verdict(4e-6, "gamma", ref)[1].startswith("above the noise")
    bare = {**ref, "noise_mm": None, "noise_rad": None}
    assert verdict(0.002, "dz", bare)[:2] == ("0.8x resolution", "at the resolution")
    assert verdict(None, "dz", ref)[1] == "no held-out rows"


def test_labels_read_as_words() -> None:
    assert feature_label("lag_T4", tau_s=900) == "lag of T4, tau 15 min"
    assert feature_label("lag2400[T34]") == "lag of T34, tau 40 min"
    assert feature_label("time_days") == "days since start"
    assert feature_label("grad[T34-T32]") == "gradient T34 - T32"
    assert feature_label("mean[spindle_arm]") == "mean temperature of the spindle arm"
    assert feature_label("dT_T7^2") == "square of the temperature rise of T7"
    assert (
        effect_label({"kind": "thermal_lag", "channels": ["T4"], "params": {"tau_s": 900.0}})
        == "thermal lag of T4, tau 15 min"
    )
    assert (
        effect_label({"kind": "sensor_fault", "channels": ["T34"], "params": {"start_s": 90000, "mode": "detached"}})
        == "faulty thermocouple T34 (detached) from 25.0 h into the campaign"
    )
    assert duration(3725, clock=True) == "1:02:05" and duration(None) == "-" and duration(5 * 86400) == "5.0 days"


class _Recorder:
    """A progress task that records what it was told."""

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def update(self, **kw) -> None:
        self.calls.append(kw)


def test_stage_bar_never_runs_past_its_end() -> None:
    rec = _Recorder()
    steps = fit_steps(network=False)
    bar = Stages(rec, "fitting", steps)
    assert rec.calls[-1] == {"description": "fitting: screening", "total": len(steps), "completed": 0}
    for s in [
        "screening",
        "samples",
        "allocation_and_regression",
        "joint_adjustment",
        "validation",
        "surprise",
        "virtual_sensors",
        "document",
    ]:
        bar.done(s)
        assert rec.calls[-1]["completed"] <= rec.calls[-1]["total"]
    assert rec.calls[-1] == {"description": "fitting: done", "total": len(steps) + 1, "completed": len(steps) + 1}
    assert "network" in fit_steps() and "network" not in steps


def test_import_says_what_it_stored(tmp_path: Path, capsys) -> None:
    from driftlab.campaigns.bundle import write_bundle
    from tests.api.helpers import small_frames, small_meta

    temps, cond, errors = small_frames()
    path = write_bundle(tmp_path / "b", small_meta(), temps, cond, errors)
    url = f"sqlite:///{tmp_path / 's.sqlite'}"
    assert main(["import", str(path), "--db", url]) == 0
    out = capsys.readouterr().out
    assert "campaign 1 (b) of machine vmc-api-01" in out and "4 (2 in the room air)" in out
    assert "80 scans, 319 readings, 1 missing" in out and "Z/dx, Z/dz, Z/gamma" in out
    assert main(["export", "1", str(tmp_path / "out"), "--db", url]) == 0
    capsys.readouterr()
    assert main(["import", str(tmp_path / "out"), "--json", "--db", f"sqlite:///{tmp_path / 't.sqlite'}"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["campaign_id"] == 1 and s["error_readings"] == len(errors) and s["span_s"] == 79 * 30.0


def test_piped_tables_take_their_width_from_columns(monkeypatch) -> None:
    """Piped (not a terminal): COLUMNS when it is set, else 120 so that tables do not wrap."""
    from driftlab.progress import stdout_console

    monkeypatch.setattr("sys.stdout", io.StringIO())
    monkeypatch.setenv("COLUMNS", "88")
    assert stdout_console().width == 88
    monkeypatch.delenv("COLUMNS")
    assert stdout_console().width == 120
    monkeypatch.setenv("COLUMNS", "not a number")
    assert stdout_console().width == 120


def test_the_demo_verdict_says_worse_when_the_figures_say_so() -> None:
    """Issue 35.2: a cut whose error before the CMM's alignment stays is not "as much as in the thesis"."""
    from driftlab.commands.demo_report import judge

    wear = {
        "uncompensated_mm": 0.0241,
        "offline_mm": 0.0012,
        "uncompensated_unaligned_mm": 0.0564,
        "offline_unaligned_mm": 0.0318,
        "offline_predicted": {"inside": 0.0},
    }
    words, worse = judge("offline", wear)
    assert worse and "worse than in the thesis" in words and "as much as" not in words
    assert "44% before the alignment" in words and "only 0% of the CMM points" in words
    clean = {**wear, "offline_unaligned_mm": 0.0012, "offline_predicted": {"inside": 1.0}}
    words, worse = judge("offline", clean)
    assert not worse and "as much as in the thesis" in words
    words, worse = judge("online", {"uncompensated_mm": 0.01, "online_mm": 0.02})
    assert worse and "worse than without compensation" in words
