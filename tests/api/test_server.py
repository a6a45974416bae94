"""The API through a real uvicorn server on 127.0.0.1 (``driftlab serve`` in a subprocess), with the
compensator's model poller as the client."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
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
    yield from _serve(seeded, tmp_path, {})


def _serve(seeded: Seeded, tmp_path: Path, extra_env: dict[str, str]) -> Iterator[str]:
    """Run `driftlab serve` (environment plus ``extra_env``) until the generator is closed; yield its base URL."""
    port = free_port()
    env = {**os.environ, "DRIFTLAB_API_TOKEN": TOKEN, "PYTHONPATH": str(ROOT), **extra_env}
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


#: the connection limits of the slow-client test's server (s): short, so the test is quick
SHORT_LIMITS = {
    "DRIFTLAB_API_HEADER_TIMEOUT_S": "1",
    "DRIFTLAB_API_BODY_TIMEOUT_S": "2",
    "DRIFTLAB_API_KEEP_ALIVE_S": "1",
}


@pytest.fixture
def short_server(seeded: Seeded, tmp_path: Path) -> Iterator[str]:
    """`driftlab serve` with head, body and idle limits of 1, 2 and 1 s."""
    yield from _serve(seeded, tmp_path, SHORT_LIMITS)


def _until_closed(sock: socket.socket, trickle: bytes = b"", every_s: float = 0.2) -> bytes:
    """Send ``trickle`` a byte every ``every_s`` while reading; return what the server sent before it closed.

    The read waits up to 120 s (a loaded machine): a server that never closes fails the test there.
    """
    stop = threading.Event()

    def feed() -> None:
        for i in range(len(trickle)):
            if stop.wait(every_s):
                return
            try:
                sock.sendall(trickle[i : i + 1])
            except OSError:
                return

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    sock.settimeout(120.0)
    got = b""
    try:
        while chunk := sock.recv(4096):
            got += chunk
    except ConnectionResetError:
        pass
    finally:
        stop.set()
        feeder.join(10)
    return got


def test_slow_and_idle_connections_are_closed(short_server: str) -> None:
    """A silent connection, a head or a body trickled faster than any idle timer, and an idle kept-alive
    connection are all closed by the server, each after its deadline; the server still answers."""
    port = int(short_server.rsplit(":", 1)[1])
    address = ("127.0.0.1", port)
    # silent from the start: closed with nothing said
    with socket.create_connection(address) as sock:
        assert _until_closed(sock) == b""
    # a head trickled a byte per 0.2 s (the head deadline is 1 s, bytes do not reset it): 408, closed
    head = b"GET /health HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 200
    with socket.create_connection(address) as sock:
        assert _until_closed(sock, head).startswith(b"HTTP/1.1 408 ")
    # a body trickled: the head is in, the body's 2 s deadline closes the connection
    post = b"POST /jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 500\r\n"
    with socket.create_connection(address) as sock:
        sock.sendall(post + f"Authorization: Bearer {TOKEN}\r\n\r\n".encode())
        got = _until_closed(sock, b" " * 500)
        assert b"202" not in got  # never a job from a body that did not arrive
    # kept alive after an answer, then idle: closed after the idle limit
    with socket.create_connection(address) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
        got = _until_closed(sock)
        assert got.startswith(b"HTTP/1.1 200 ") and b'"status":"ok"' in got
    assert httpx.get(f"{short_server}/health", timeout=30.0).status_code == 200


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
