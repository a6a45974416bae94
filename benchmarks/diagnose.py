"""Benchmark `driftlab diagnose` on a 72 h, 50-channel campaign, six terms per axis, five axes.

The bundle is simulated once on the virtual machine (two hidden effects), then diagnosed; the line
reports the time of each diagnosis phase (wall and CPU), the whole run, and a baseline: the plain
numpy lstsq fits of the 30 standard models alone on the same rows. Target: total < 30 s.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402  (pins BLAS to one thread before numpy loads)
import numpy as np  # noqa: E402

from driftlab.campaigns.bundle import Bundle, _as_meta  # noqa: E402
from driftlab.daq.sim.campaign import simulate_campaign  # noqa: E402
from driftlab.daq.sim.scenario import HiddenEffect, Scenario  # noqa: E402
from driftlab.models.diagnosis import diagnose_bundle  # noqa: E402
from driftlab.models.diagnosis_report import to_json_dict as diagnosis_json  # noqa: E402


def _baseline_lstsq(bundle: Bundle) -> float:
    """Return the seconds of plain numpy lstsq standard-model fits of every (axis, term) (no cleaning)."""
    temps = bundle.temperatures
    t_scan = temps["time_s"].to_numpy()
    meta = bundle.meta
    start = time.perf_counter()
    for (axis, _term), g in bundle.errors.groupby(["axis", "term"]):
        chans = (meta.model_channels or {}).get(axis, [])
        t = g["time_s"].to_numpy()
        p = g["position"].to_numpy()
        u = (p - p.mean()) / max(np.ptp(p), 1e-9)
        cols = [np.ones_like(u), u, u**2, u**3]
        for ch in chans:
            x = np.interp(t, t_scan, temps[ch].to_numpy())
            cols.append(x - x[0])
        X = np.column_stack(cols)
        n = int(0.75 * len(t))
        np.linalg.lstsq(X[:n], g["value"].to_numpy()[:n], rcond=None)
    return time.perf_counter() - start


def main() -> None:
    """Simulate the campaign, diagnose it, print one JSON line of figures."""
    hidden = [
        HiddenEffect(kind="thermal_lag", axis="Z", term="dz", channels=["T34"], params={"tau_s": 2400.0}),
        HiddenEffect(kind="reversal", axis="X", term="dx", params={"magnitude_mm": 0.003}),
    ]
    sc = Scenario(seed=1, hours=72.0, scan_interval_s=60.0, sweep_interval_s=600.0, points_per_axis=11, hidden=hidden)
    t0 = time.perf_counter()
    sim = simulate_campaign(sc)
    t_sim = time.perf_counter() - t0
    bundle = Bundle(
        name="bench-72h",
        meta=_as_meta(sim.meta),
        temperatures=sim.temperatures,
        conditions=sim.conditions,
        errors=sim.errors,
    )
    wall0, cpu0 = time.perf_counter(), time.process_time()
    res = diagnose_bundle(bundle)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    t_json = time.perf_counter()
    diagnosis_json(res)
    t_json = time.perf_counter() - t_json
    _common.emit(
        {
            "benchmark": "diagnose",
            "hours": sc.hours,
            "channels": sim.temperatures.shape[1] - 1,
            "scans": len(sim.temperatures),
            "error_rows": len(sim.errors),
            "terms": len(res.terms),
            "hypotheses": res.n_hypotheses,
            "effects_found": [f"{e.kind}:{e.axis}/{e.term}" for e in res.effects],
            "phase_s": {k: round(v, 3) for k, v in res.timings_s.items()},
            "diagnose_wall_s": round(wall, 3),
            "diagnose_cpu_s": round(cpu, 3),
            "report_json_s": round(t_json, 3),
            "baseline_lstsq_standard_models_s": round(_common.timeit_best(lambda: _baseline_lstsq(bundle), 3), 3),
            "simulate_s": round(t_sim, 3),
            "target_s": 30.0,
            "load_average": _common.load_average(),
        }
    )


if __name__ == "__main__":
    main()
