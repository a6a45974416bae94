"""The daemon's heartbeat (issue 24): a campaign whose daemon was killed reads "stale since ...", a finished one
reads done, and retries are shown as counted or not at all.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from rich.console import Console
from sqlalchemy import text

from driftlab.campaigns import live
from driftlab.campaigns.db import store_engine
from driftlab.campaigns.plan import load_plan
from driftlab.campaigns.status import beat, campaign_status, format_status, stale_since
from driftlab.cli import main
from driftlab.commands.campaign import render
from driftlab.daemon.run import run_daemon
from tests.campaigns.test_live import PLAN, SCENARIO


@pytest.fixture
def files(tmp_path: Path) -> tuple[Path, Path]:
    plan, scen = tmp_path / "plan.yaml", tmp_path / "open.yaml"
    plan.write_text(PLAN)
    scen.write_text(SCENARIO)
    return plan, scen


def _text(head: dict) -> str:
    """Return what `campaign status --watch` draws for a header, as plain text."""
    console = Console(width=160, record=True, file=open(os.devnull, "w"))  # noqa: SIM115
    console.print(render(head, [], {"seq": [], "axis": [], "term": [], "direction": [], "sweep": []}))
    return console.export_text()


def test_the_daemon_beats_while_it_runs_and_a_silent_one_is_stale(store_url: str, files, capsys) -> None:
    plan, scen = files
    r = run_daemon(load_plan(plan), db_url=store_url, scenario_path=scen, speed=math.inf, stop_after_commits=3)
    engine = store_engine(store_url)
    with engine.connect() as c:
        beat_at = c.execute(
            text("SELECT heartbeat_at FROM acquisition_progress WHERE campaign_id = :c"), {"c": r.campaign_id}
        ).scalar_one()
    assert beat_at is not None  # the run wrote its heartbeat
    # what kill -9 leaves: the campaign still `running`, its heartbeat getting older
    with engine.begin() as c:
        c.execute(text("UPDATE campaigns SET status = 'running' WHERE id = :c"), {"c": r.campaign_id})
    old = datetime.now(UTC) - timedelta(minutes=5)
    beat(engine, r.campaign_id, at=old)
    (row,) = campaign_status(engine, r.campaign_id)
    assert row["status"] == "running" and row["stale_since"] is not None
    assert datetime.fromisoformat(row["stale_since"].replace("Z", "+00:00")) == old.replace(microsecond=0)
    assert "[running, stale since " in format_status([row])
    head = live.header(engine, r.campaign_id)
    assert head is not None and head["stale_since"][:19] == row["stale_since"][:19]
    assert head["progress"]["stage_left_s"] is None and head["progress"]["total_left_s"] is None
    drawn = _text(head)
    assert "stale since" in drawn and "left" not in drawn
    assert live.live_marks(engine)[r.campaign_id]["stale"] is True
    assert main(["health", "--daemon", "--db", store_url]) == 1  # the container healthcheck fails too
    assert "health: the daemon stopped beating: live-test (stale since " in capsys.readouterr().err
    # a daemon that beats again (resumed) is not stale
    beat(engine, r.campaign_id)
    (row,) = campaign_status(engine, r.campaign_id)
    assert row["stale_since"] is None and "stale" not in format_status([row])
    assert live.live_marks(engine)[r.campaign_id]["stale"] is False
    assert main(["health", "--daemon", "--db", store_url]) == 0
    assert capsys.readouterr().out.strip() == "healthy"


@pytest.mark.postgres
def test_health_of_this_containers_worker_and_of_a_database_that_does_not_answer(pg_cluster, capsys, tmp_path) -> None:
    """`health --worker` judges the worker of its own container (its pulse file), not any worker of the queue."""
    from driftlab.campaigns.store import connect

    pg_url = pg_cluster.create_database()
    with connect(pg_url) as store:
        store.ensure_schema()
    assert main(["health", "--db", pg_url]) == 0
    pulse = tmp_path / "worker.pulse.json"
    check = ["health", "--worker", "--db", pg_url, "--pulse-file", str(pulse)]
    assert main(check) == 1
    assert "no worker pulse at" in capsys.readouterr().err  # no worker runs here

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    cmd = [
        sys.executable,
        "-m",
        "driftlab.cli",
        "worker",
        "--db",
        pg_url,
        "--name",
        "w-here",
        "--pulse-file",
        str(pulse),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        for _ in range(600):  # a safety net of 60 s for the worker to register, not a timing assertion
            body = json.loads(pulse.read_text()) if pulse.exists() else {}
            if body.get("worker_id") is not None:
                break
            time.sleep(0.1)
        assert body.get("worker_id") is not None and body["pid"] == proc.pid and body["name"] == "w-here"
        capsys.readouterr()
        assert main(check) == 0 and capsys.readouterr().out.strip() == "healthy"

        # another pulse file in the same state but naming a worker the queue does not know: unhealthy,
        # although a worker (the one above) beats in the queue
        other = tmp_path / "other.json"
        other.write_text(json.dumps({**body, "pid": os.getpid(), "worker_id": body["worker_id"] + 1000}))
        assert main([*check[:-1], str(other)]) == 1
        assert "is no longer registered in the job queue" in capsys.readouterr().err
        # a process that is gone, a pulse that stopped, a worker without its database
        dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
        other.write_text(json.dumps({**body, "pid": int(dead.stdout)}))
        assert main([*check[:-1], str(other)]) == 1 and "is gone" in capsys.readouterr().err
        other.write_text(json.dumps({**body, "pid": os.getpid(), "written_at": time.time() - 600}))
        assert main([*check[:-1], str(other)]) == 1 and "wrote no pulse for 600 s" in capsys.readouterr().err
        other.write_text(json.dumps({**body, "pid": os.getpid(), "worker_id": None, "lost_since": time.time() - 120}))
        assert main([*check[:-1], str(other)]) == 1
        assert "has been without its database for 120 s" in capsys.readouterr().err
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-2000:]
    assert not pulse.exists()  # removed when the worker ends: the check fails again
    assert main(check) == 1 and "no worker pulse at" in capsys.readouterr().err
    assert main(["health", "--db", "postgresql+psycopg://postgres@127.0.0.1:1/nowhere"]) == 1
    assert capsys.readouterr().err.startswith("driftlab: error: database: ")


def test_a_finished_campaign_reads_done_not_97_percent(store_url: str, files) -> None:
    plan, scen = files
    r = run_daemon(load_plan(plan), db_url=store_url, scenario_path=scen, speed=math.inf)
    engine = store_engine(store_url)
    head = live.header(engine, r.campaign_id)
    assert head is not None and head["status"] == "done" and head["stale_since"] is None
    p = head["progress"]
    assert (p["fraction"], p["stage_fraction"], p["stage_left_s"], p["total_left_s"]) == (1.0, 1.0, 0.0, 0.0)
    drawn = _text(head)
    assert "100 % done, campaign done" in drawn and "0.0 s left" not in drawn
    assert "retries" not in drawn  # the simulated daemon counts none: nothing is shown, not "not recorded"
    head["health"]["retries"] = {"laser": 2}
    assert "retries  laser 2" in _text(head)


def test_stale_since_needs_a_running_campaign_and_an_old_sign_of_life(monkeypatch) -> None:
    now = datetime(2026, 11, 25, 12, 0, tzinfo=UTC)
    old, recent = now - timedelta(seconds=61), now - timedelta(seconds=59)
    assert stale_since("running", old, recent, now) == old
    assert stale_since("running", recent, old, now) is None  # the heartbeat counts, not the last commit
    assert stale_since("running", None, old, now) == old  # rows from before the heartbeat: the last commit
    assert stale_since("done", old, old, now) is None
    assert stale_since("running", None, None, now) is None
    monkeypatch.setenv("DRIFTLAB_STALE_AFTER_S", "120")
    assert stale_since("running", old, old, now) is None


@pytest.mark.slow
def test_kill_9_of_the_daemon_process_reads_stale(tmp_path: Path, files, monkeypatch, capsys) -> None:
    """The real thing: `driftlab daemon` killed with SIGKILL; `campaign status` says stale, not running.

    Until the daemon has committed, `campaign status --json` is asked in this process (the same command,
    without a new interpreter per poll); the verdict after the kill comes from a `driftlab` process.
    """
    plan, scen = files
    url = f"sqlite:///{tmp_path / 'd.sqlite'}"
    env = {**os.environ, "DRIFTLAB_STALE_AFTER_S": "1"}
    cmd = [sys.executable, "-m", "driftlab.cli", "daemon", "--plan", str(plan), "--sim", str(scen), "--db", url]
    with (tmp_path / "daemon.log").open("w") as log:
        proc = subprocess.Popen([*cmd, "--speed", "60"], stdout=log, stderr=subprocess.STDOUT, env=env)
    monkeypatch.setenv("DRIFTLAB_STALE_AFTER_S", "3600")
    try:
        status: list = []
        for _ in range(6000):  # a safety net of polls until the daemon has committed (not a timing assertion)
            if proc.poll() is not None:
                break
            capsys.readouterr()
            code = main(["campaign", "status", "--db", url, "--json"])
            shown = capsys.readouterr().out
            status = json.loads(shown) if code == 0 and shown.strip() else []
            if status and status[0]["progress"]["scans"] > 0:
                break
            time.sleep(0.2)
        assert proc.poll() is None, (tmp_path / "daemon.log").read_text()[-2000:]
        assert status and status[0]["status"] == "running" and status[0]["stale_since"] is None
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        time.sleep(1.5)  # older than the 1 s threshold: no process is left to beat
        out = subprocess.run(
            [sys.executable, "-m", "driftlab.cli", "campaign", "status", "--db", url],
            capture_output=True,
            text=True,
            env=env,
        )
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert out.returncode == 0, out.stderr
    assert "[running, stale since " in out.stdout and ": no daemon]" in out.stdout
