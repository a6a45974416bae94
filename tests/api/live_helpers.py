"""Helpers of the live-page tests: a real uvicorn server in a thread, a server-sent-events reader, the daemon."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[2]
DEMO_PLAN = ROOT / "examples" / "plans" / "z-axis-demo.yaml"
CLEAN = ROOT / "examples" / "scenarios" / "clean.yaml"


def free_port() -> int:
    """Return a free TCP port on the loopback interface."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def serving(app: Any) -> Iterator[str]:
    """Run ``app`` under uvicorn on 127.0.0.1 in a thread; yield its base URL; stop it on exit."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", timeout_graceful_shutdown=1)
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


@contextmanager
def serve_process(db_url: str, *extra: str) -> Iterator[str]:
    """Run `driftlab serve` as a real subprocess on a free port; yield its base URL; SIGTERM it on exit."""
    port = free_port()
    env = {**os.environ, "DRIFTLAB_DB_URL": db_url}
    env.pop("DRIFTLAB_API_TOKEN", None)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "driftlab.cli",
            "serve",
            "--port",
            str(port),
            "--log-level",
            "warning",
            "--no-jobs",
            *extra,
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{base}/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"driftlab serve did not start: {proc.stderr.read() if proc.stderr else ''}")
            time.sleep(0.1)
        yield base
    finally:
        stop(proc)


def start_daemon(
    db_url: str, speed: float, *extra: str, plan: Path = DEMO_PLAN, scenario: Path = CLEAN
) -> subprocess.Popen[str]:
    """Start `driftlab daemon` on the virtual machine as a real subprocess."""
    env = {**os.environ, "DRIFTLAB_DB_URL": db_url}
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "driftlab.cli",
            "daemon",
            "--plan",
            str(plan),
            "--sim",
            str(scenario),
            "--speed",
            "0" if math.isinf(speed) else str(speed),
            *extra,
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def stop(proc: subprocess.Popen[Any]) -> None:
    """SIGTERM a subprocess and wait for it (SIGKILL after 15 s)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def events(response: httpx.Response) -> Iterator[tuple[str, dict[str, Any]]]:
    """Yield (event name, JSON data) from a server-sent-events response as they arrive."""
    name, data = "message", []
    for line in response.iter_lines():
        if line == "":
            if data:
                yield name, json.loads("\n".join(data))
            name, data = "message", []
        elif line.startswith("event:"):
            name = line[6:].strip()
        elif line.startswith("data:"):
            data.append(line[5:].strip())
