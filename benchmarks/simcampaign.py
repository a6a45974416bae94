"""Benchmark: a 72-hour simulated campaign written as a bundle v1 (target: under 20 s).

Prints one JSON line: wall and CPU time of simulate + write, the rows and bytes written, and an
in-run baseline - plain ``DataFrame.to_csv`` of the same three frames - so the figure can be read
on a loaded machine.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit, load_average  # noqa: E402  (pins BLAS threads before numpy loads)

from driftlab.campaigns.bundle import load_bundle, write_bundle  # noqa: E402
from driftlab.daq.sim.campaign import simulate_campaign  # noqa: E402
from driftlab.daq.sim.scenario import Scenario  # noqa: E402

HOURS = 72.0


def main() -> None:
    """Simulate and write a 72 h campaign, time it against plain pandas CSV output, print one JSON line."""
    scenario = Scenario(name="bench-72h", hours=HOURS, seed=1)
    simulate_campaign(Scenario(hours=0.5))  # warm imports and caches (kinematics, base coefficients)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bundle"
        w0, c0 = time.perf_counter(), time.process_time()
        sim = simulate_campaign(scenario)
        w1 = time.perf_counter()
        write_bundle(out, sim.meta, sim.temperatures, sim.conditions, sim.errors)
        w2, c2 = time.perf_counter(), time.process_time()
        sizes = {p.name: p.stat().st_size for p in out.iterdir()}
        b0 = time.perf_counter()
        for name, frame in (("t.csv", sim.temperatures), ("c.csv", sim.conditions), ("e.csv", sim.errors)):
            frame.to_csv(Path(tmp) / name, index=False)
        b1 = time.perf_counter()
        l0 = time.perf_counter()
        bundle = load_bundle(out)
        l1 = time.perf_counter()
        assert len(bundle.errors) == len(sim.errors)
    emit(
        {
            "benchmark": "simcampaign",
            "hours": HOURS,
            "total_s": round(w2 - w0, 3),
            "target_s": 20.0,
            "simulate_s": round(w1 - w0, 3),
            "write_s": round(w2 - w1, 3),
            "cpu_s": round(c2 - c0, 3),
            "baseline_pandas_to_csv_s": round(b1 - b0, 3),
            "load_bundle_s": round(l1 - l0, 3),
            "temperature_rows": len(sim.temperatures),
            "error_rows": len(sim.errors),
            "bytes": sum(sizes.values()),
            "files": sizes,
            "load_average": load_average(),
        }
    )


if __name__ == "__main__":
    main()
