"""Compensator memory: peak resident memory of `driftlab compensate` at 10k, 100k and 1M lines, offline and --port.

Prints ONE JSON line. Each figure is the peak RSS (``VmHWM`` of a child process: unlike ``ru_maxrss``
it restarts at exec, so the parent's memory does not leak into it) of one ``driftlab compensate P
--model M --temps T -o OUT`` (through ``driftlab.cli.main`` in the child) of a five-axis finishing
program (``benchmarks/compensate.py``'s program and model document), beside two baselines measured
the same way in the same run: a bare Python that reads the same file line by line
(``baseline_readlines_*_mb``), and a Python that builds the CLI and loads the model and does nothing
else (``baseline_import_mb``). Target: flat in program length, the 1M-line program under 200 MB
resident (issue 13; before the streaming pipeline it took about 1.4 GB).

``compensate_port_*``: the same program (in the simulated controller's dialect) streamed with
``driftlab compensate P --model M --temps T --port socket://...`` to the simulated controller
served by this process over a local socket; the controller runs blocks as fast as they come
(capacity 256), so the figures are the compensator's, and ``*_s`` is the wall time of the run
(the link's round trip per block dominates it). ``--port-max-lines N`` leaves out larger sizes
(1M lines take several minutes over the socket).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import _common  # noqa: E402,F401  (pins numeric thread pools before numpy loads)

ROOT = Path(__file__).resolve().parents[1]
SIZES = (10_000, 100_000, 1_000_000)

COMPENSATE = r"""
import json, sys
from driftlab.cli import main
code = main(["compensate", sys.argv[1], "--model", sys.argv[3], "--temps", sys.argv[5], "-o", sys.argv[2], "--json"])
assert code == 0
print(json.dumps({"kb": int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1])}))
"""

READLINES = r"""
import json, sys
n = 0
with open(sys.argv[1], "rb") as fh:
    for line in fh:
        n += 1
print(json.dumps({"kb": int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1]),
                  "lines": n}))
"""

PORT = r"""
import json, sys
from driftlab.cli import main
code = main(["compensate", sys.argv[1], "--model", sys.argv[3], "--temps", sys.argv[5], "--port", sys.argv[4],
             "--json"])
assert code == 0
print(json.dumps({"kb": int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1])}))
"""

IMPORT_ONLY = r"""
import json, sys
from driftlab.cli import build_parser
from driftlab.compensator.compensate import ErrorModel
build_parser()
ErrorModel.from_document(json.loads(open(sys.argv[3]).read()))
print(json.dumps({"kb": int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1])}))
"""


def child(code: str, program: Path, out: Path, model: Path, temps: Path, port: str = "") -> dict:
    """Run ``code`` in a fresh interpreter and return its JSON line."""
    proc = subprocess.run(
        [sys.executable, "-c", code, str(program), str(out), str(model), port, str(temps)],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def label_of(n: int) -> str:
    """Return 10k, 100k, 1M for a line count."""
    return f"{n // 1000}k" if n < 1_000_000 else f"{n // 1_000_000}M"


def port_figures(program: Path, out: Path, model: Path, temps: Path, n: int) -> dict[str, float]:
    """Return peak RSS and wall time of `driftlab compensate --port` streaming to the simulated controller."""
    from driftlab.daq.sim.instruments import SimController, WallClock, serial_url
    from driftlab.testing.tinyworld import TinyWorld

    # a controller that executes blocks as fast as they come: the link never waits for its buffer to drain
    with SimController(TinyWorld(channels=2), WallClock(acceleration=1e9), capacity=256) as sim:
        t0 = time.perf_counter()
        run = child(PORT, program, out, model, temps, serial_url(sim))
        wall = time.perf_counter() - t0
        blocks = sim.accepted_seq
    label = label_of(n)
    return {
        f"compensate_port_{label}_lines_mb": round(run["kb"] / 1024, 1),
        f"compensate_port_{label}_lines_s": round(wall, 1),
        f"compensate_port_{label}_blocks": blocks,
    }


def main(argv: list[str] | None = None) -> None:
    """Print the peak RSS figures as one JSON line."""
    from compensate import document, program_text

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port-max-lines", type=int, default=max(SIZES), help="largest program streamed with --port")
    args = ap.parse_args(argv)
    figures: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as tmp:
        model = Path(tmp) / "model.json"
        doc = document()
        model.write_text(json.dumps(doc))
        temps = Path(tmp) / "temperatures.csv"
        chans = sorted(doc["inputs"])
        temps.write_text("time_s," + ",".join(chans) + "\n0.0," + ",".join("24.0" for _ in chans) + "\n")
        out = Path(tmp) / "out.nc"
        for n in SIZES:
            program = Path(tmp) / f"p{n}.nc"
            program.write_bytes(program_text(n))
            run = child(COMPENSATE, program, out, model, temps)
            base = child(READLINES, program, out, model, temps)
            label = label_of(n)
            figures[f"compensate_{label}_lines_mb"] = round(run["kb"] / 1024, 1)
            figures[f"baseline_readlines_{label}_mb"] = round(base["kb"] / 1024, 1)
            figures[f"program_{label}_mb"] = round(program.stat().st_size / 2**20, 1)
            if n <= args.port_max_lines:
                program.write_bytes(program_text(n, head="G90 G1 F2000\n"))  # the simulated controller's dialect
                figures.update(port_figures(program, out, model, temps, n))
            program.unlink()
        figures["baseline_import_mb"] = round(child(IMPORT_ONLY, program, out, model, temps)["kb"] / 1024, 1)
    figures["growth_10k_to_1M_mb"] = round(
        float(figures["compensate_1M_lines_mb"])  # type: ignore[arg-type]
        - float(figures["compensate_10k_lines_mb"]),
        1,
    )  # type: ignore[arg-type]
    ports = [n for n in SIZES if n <= args.port_max_lines]
    if len(ports) > 1:
        figures[f"growth_port_10k_to_{label_of(ports[-1])}_mb"] = round(
            float(figures[f"compensate_port_{label_of(ports[-1])}_lines_mb"])  # type: ignore[arg-type]
            - float(figures["compensate_port_10k_lines_mb"]),
            1,
        )  # type: ignore[arg-type]
    figures["target_1M_under_mb"] = 200
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
