"""Bundle import memory: peak resident memory and time of `driftlab import` at about 50 MB and 200 MB of readings.

Prints ONE JSON line. Each figure is the peak RSS (``VmHWM`` of a child process, as in
``compensate_memory.py``) of one ``driftlab import BUNDLE --db sqlite:///...`` (through
``driftlab.cli.main`` in the child) of a bundle of 50 channels at 1 Hz (``ingest.py``'s generator)
whose temperatures.csv is about 50 MB and 200 MB, and the wall time of that child. Beside them,
measured the same way in the same run into a fresh database:

- ``in_memory_*``: the bundle read whole and imported from memory (``load_bundle`` then
  ``store.campaigns.import_bundle`` of the frames): what `driftlab import` did before it staged bundles;
- ``baseline_import_mb``: a Python that builds the CLI and imports the store and bundle modules,
  and does nothing else;
- ``baseline_readlines_*_mb``: a bare Python that reads temperatures.csv line by line.

Target: flat in bundle size (issue 13: streaming reads with bounded memory).

Usage: python benchmarks/import_memory.py [--sizes-mb 50 200] [--channels 50]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import _common  # noqa: E402,F401  (pins numeric thread pools before numpy loads)

ROOT = Path(__file__).resolve().parents[1]
#: bytes of temperatures.csv per scan and channel written by ingest.make_bundle (4 decimals near 20 degC)
BYTES_PER_READING = 8.0

HWM = 'int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1])'

IMPORT = rf"""
import json, sys
from driftlab.cli import main
assert main(["import", sys.argv[1], "--db", sys.argv[2]]) == 0
print(json.dumps({{"kb": {HWM}}}))
"""

IN_MEMORY = rf"""
import json, sys
from driftlab.campaigns.bundle import load_bundle
from driftlab.campaigns.store import connect
from driftlab.commands.bundle_io import import_summary
bundle = load_bundle(sys.argv[1])
with connect(sys.argv[2]) as store:
    import_summary(store.campaigns.import_bundle(bundle), bundle)
print(json.dumps({{"kb": {HWM}}}))
"""

IMPORT_ONLY = rf"""
import json, sys
from driftlab.cli import build_parser
from driftlab.campaigns import staging, store
build_parser()
print(json.dumps({{"kb": {HWM}}}))
"""

READLINES = rf"""
import json, sys
n = 0
with open(sys.argv[1] + "/temperatures.csv", "rb") as fh:
    for line in fh:
        n += 1
print(json.dumps({{"kb": {HWM}, "lines": n}}))
"""


def child(code: str, bundle: Path, db: str) -> tuple[dict, float]:
    """Run ``code`` in a fresh interpreter; return its JSON line and its wall time (s)."""
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", code, str(bundle), db], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return json.loads(proc.stdout.strip().splitlines()[-1]), time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    """Run the imports and print one JSON line."""
    from ingest import make_bundle

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes-mb", type=float, nargs="+", default=[50.0, 200.0])
    ap.add_argument("--channels", type=int, default=50)
    args = ap.parse_args(argv)
    figures: dict[str, object] = {
        "benchmark": "import_memory",
        "channels": args.channels,
        "load_average_1m_at_start": _common.load_average(),
    }
    tmp = Path(tempfile.mkdtemp(prefix="driftlab-bench-"))
    try:
        for mb in args.sizes_mb:
            hours = mb * 2**20 / (BYTES_PER_READING * args.channels * 3600)
            bundle = make_bundle(tmp / f"b{mb:g}", hours, args.channels)
            label = f"{mb:g}mb"
            figures[f"temperatures_csv_{label}"] = round((bundle / "temperatures.csv").stat().st_size / 2**20, 1)
            figures[f"readings_{label}"] = int(hours * 3600) * args.channels
            run, wall = child(IMPORT, bundle, f"sqlite:///{tmp / f'import{mb:g}.sqlite'}")
            figures[f"import_{label}_peak_mb"] = round(run["kb"] / 1024, 1)
            figures[f"import_{label}_s"] = round(wall, 1)
            run, wall = child(IN_MEMORY, bundle, f"sqlite:///{tmp / f'memory{mb:g}.sqlite'}")
            figures[f"in_memory_{label}_peak_mb"] = round(run["kb"] / 1024, 1)
            figures[f"in_memory_{label}_s"] = round(wall, 1)
            figures[f"baseline_readlines_{label}_mb"] = round(child(READLINES, bundle, "")[0]["kb"] / 1024, 1)
            shutil.rmtree(bundle)
            for db in tmp.glob("*.sqlite*"):
                db.unlink()
        figures["baseline_import_mb"] = round(child(IMPORT_ONLY, tmp, "")[0]["kb"] / 1024, 1)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    labels = [f"{mb:g}mb" for mb in args.sizes_mb]
    if len(labels) > 1:
        for kind in ("import", "in_memory"):
            first, last = (float(figures[f"{kind}_{lb}_peak_mb"]) for lb in (labels[0], labels[-1]))  # type: ignore[arg-type]
            figures[f"{kind}_growth_{labels[0]}_to_{labels[-1]}_mb"] = round(last - first, 1)
    _common.emit(figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
