"""Opt-in pytest plugin: the wall and CPU time of every test, to find what makes `make test` slow.

The machine is shared, so wall time alone says little: CPU time (this process's plus that of the
children it reaped, e.g. `driftlab` subprocesses; a PostgreSQL server's own is not in it) is what a
test costs. Setup and teardown are counted with the test that ran them (a module fixture with the
first test of its module). Each xdist worker appends JSON lines to the same file.

    rm -f /tmp/cpu.jsonl
    CPUTIME_OUT=/tmp/cpu.jsonl .venv/bin/python -m pytest -p tests.cputime_plugin -n 2 --dist loadfile -q
    .venv/bin/python -m tests.cputime_plugin /tmp/cpu.jsonl 25    # sums, then the top files and tests
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import pytest


def _cpu_s() -> tuple[float, float]:
    """Return (this process, its reaped children) user + system CPU seconds."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Time one test's setup, call and teardown; append a line to $CPUTIME_OUT (nothing when unset)."""
    out = os.environ.get("CPUTIME_OUT")
    wall0, (cpu0, kids0) = time.perf_counter(), _cpu_s()
    yield
    wall1, (cpu1, kids1) = time.perf_counter(), _cpu_s()
    if out:
        line = {"id": item.nodeid, "wall": wall1 - wall0, "cpu": cpu1 - cpu0, "child": kids1 - kids0}
        with open(out, "a") as f:
            f.write(json.dumps(line) + "\n")


def report(path: Path, top: int = 25) -> str:
    """Return the sums and the ``top`` files and tests by CPU time of a CPUTIME_OUT file."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    cpu = {r["id"]: r["cpu"] + r["child"] for r in rows}
    files: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])
    for r in rows:
        f = files[r["id"].split("::")[0]]
        f[0] += cpu[r["id"]]
        f[1] += r["wall"]
        f[2] += 1
    lines = [
        f"tests {len(rows)}: CPU {sum(cpu.values()):.1f} s (own {sum(r['cpu'] for r in rows):.1f}, "
        f"children {sum(r['child'] for r in rows):.1f}), wall summed over workers {sum(r['wall'] for r in rows):.1f} s",
        "-- files by CPU s (wall s, tests)",
    ]
    for name, (c, w, n) in sorted(files.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"{c:7.1f} {w:7.1f} {int(n):4d}  {name}")
    lines.append("-- tests by CPU s (wall s)")
    for r in sorted(rows, key=lambda r: -cpu[r["id"]])[:top]:
        lines.append(f"{cpu[r['id']]:7.1f} {r['wall']:7.1f}  {r['id']}")
    return "\n".join(lines)


if __name__ == "__main__":
    print(report(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 25))
