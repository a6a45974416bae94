"""The API through a real uvicorn server on 127.0.0.1 (``driftlab serve`` in a subprocess), with the
compensator's model poller as the client."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from driftlab.compensator.stream import ApiModel, ApiTemperatures
from tests.api.helpers import AUTH, MACHINE, TOKEN, Seeded, model_document

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    """Return a port that was free on 127.0.0.1 a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def server(seeded: Seeded, tmp_path: Path) -> Iterator[str]:
    """`driftlab serve` on a free loopback port over the seeded database; yields its base URL."""
    port = free_port()
    env = {**os.environ, "DRIFTLAB_API_TOKEN": TOKEN, "PYTHONPATH": str(ROOT)}
    log = (tmp_path / "serve.log").open("wb")
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "driftlab.cli",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--db",
            seeded.url,
            "--log-level",
            "warning",
        ],
        cwd=ROOT,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        for _ in range(300):  # up to ~30 s on a loaded machine
            if proc.poll() is not None:
                raise AssertionError(f"driftlab serve exited: {(tmp_path / 'serve.log').read_text()}")
            try:
                if httpx.get(f"{base}/health", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        else:
            raise AssertionError("driftlab serve did not answer")
        yield base
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
    assert "Traceback" not in (tmp_path / "serve.log").read_text()


def test_compensator_polls_the_served_model_and_sees_promotions(server: str, seeded: Seeded) -> None:
    with httpx.Client(base_url=server, timeout=10.0) as c:
        poller = ApiModel(server, MACHINE, client=c)
        assert poller.refresh() is True and poller.document["version"] == seeded.model_version
        first = poller.etag
        assert poller.refresh() is False  # 304: nothing new
        r = c.post(f"/machines/{MACHINE}/models", json={"document": model_document(coefficient=0.004)}, headers=AUTH)
        assert r.status_code == 201
        assert poller.refresh() is True and poller.etag != first
        assert poller.document["version"] == seeded.model_version + 1
        assert c.post(f"/machines/{MACHINE}/models/{seeded.model_version}/promote").status_code == 401
        assert c.post(f"/machines/{MACHINE}/models/{seeded.model_version}/promote", headers=AUTH).status_code == 200
        assert poller.refresh() is True and poller.etag == first
        # the compensator's temperature source reads the latest scan
        temps = ApiTemperatures(server, MACHINE, client=c).read()
        assert sorted(temps) == ["T1", "T2", "T49", "T50"] and all(20.0 < v < 30.0 for v in temps.values())
        # histories and problems over the wire
        page = c.get(f"/campaigns/{seeded.campaign_id}/temperatures/T1", params={"limit": 5}).json()
        assert len(page["points"]) == 5 and page["next_cursor"]
        bad = c.get("/machines/ghost/model/current")
        assert bad.status_code == 404 and bad.headers["content-type"] == "application/problem+json"


def test_serve_reports_an_unreachable_database_in_one_line() -> None:
    url = "postgresql://nobody@127.0.0.1:1/none"
    r = subprocess.run(
        [sys.executable, "-m", "driftlab.cli", "serve", "--port", str(free_port()), "--db", url],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "DRIFTLAB_API_TOKEN": TOKEN},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.startswith("driftlab: error:") and r.stderr.count("\n") == 1, r.stderr


def test_serve_on_a_busy_port_is_one_line_and_nothing_else() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        r = subprocess.run(
            [sys.executable, "-m", "driftlab.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT), "DRIFTLAB_API_TOKEN": TOKEN, "DRIFTLAB_DB_URL": "sqlite://"},
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert r.returncode == 2
    assert (
        r.stderr == f"driftlab: error: cannot serve on 127.0.0.1:{port}: the port is already in use "
        "(another server is listening there; give another --port)\n"
    ), r.stderr
    assert r.stdout == ""
