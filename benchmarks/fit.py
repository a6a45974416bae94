"""Benchmark: the fitting pipeline on a 70-hour, 50-channel virtual-machine campaign (target: under 120 s).

Prints one JSON line: wall and CPU time of the whole fit and of each stage (screening, samples,
allocation and stepwise regression, joint adjustment, validation, neural network, virtual sensors,
document), the size of the problem, the figures that say whether the fit is any good (kept
channels, worst held-out RMSE of lengths and angles, the extrapolation experiment), and an in-run
baseline: one plain statsmodels OLS of every work-space term on all channels over the same points,
so the figure can be read on a loaded machine.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit, load_average  # noqa: E402  (pins BLAS threads before numpy loads)

# isort: split

import numpy as np  # noqa: E402
import statsmodels.api as sm  # noqa: E402

from driftlab.campaigns.bundle import Bundle, CampaignMeta  # noqa: E402
from driftlab.daq.sim.campaign import simulate_campaign  # noqa: E402
from driftlab.daq.sim.scenario import Room, Scenario  # noqa: E402
from driftlab.models.fitting import FitOptions, fit_bundles  # noqa: E402

HOURS = 70.0
TARGET_S = 120.0


def _bundle(scenario: Scenario) -> Bundle:
    """Simulate a campaign and return it as an in-memory bundle."""
    sim = simulate_campaign(scenario)
    return Bundle(scenario.name, CampaignMeta.model_validate(sim.meta), sim.temperatures, sim.conditions, sim.errors)


def _baseline(bundle: Bundle) -> float:
    """Return the seconds of one OLS per (axis, term) on all 50 channels at the error points."""
    t0 = time.perf_counter()
    temps = bundle.temperatures
    for (_axis, _term), g in bundle.errors.groupby(["axis", "term"]):
        t = g["time_s"].to_numpy(float)
        X = np.column_stack([np.interp(t, temps["time_s"], temps[c]) for c in temps.columns if c != "time_s"])
        sm.OLS(g["value"].to_numpy(float), sm.add_constant(X)).fit()
    return time.perf_counter() - t0


def main() -> None:
    """Fit a 70 h campaign and a warm-room one (the neural comparison on Z/dz, both directions); print one JSON line."""
    train = _bundle(Scenario(name="bench-70h", hours=HOURS, seed=1))
    warm = _bundle(Scenario(name="bench-warm", hours=16.0, seed=2, room=Room(mean_degC=24.0)))
    w0, c0 = time.perf_counter(), time.process_time()
    result = fit_bundles([train, warm], FitOptions())
    w1, c1 = time.perf_counter(), time.process_time()
    v = result.validation
    lengths = v[v["unit"] == "mm"]
    angles = v[v["unit"] == "rad"]
    neural = [
        {
            "target": c.target,
            "status": c.status,
            "split": c.split,
            "directions": [
                {k: d.to_dict()[k] for k in ("direction", "regression_test", "network_test", "max_excess_degC")}
                for d in c.directions
            ],
        }
        for c in result.neural
    ]
    emit(
        {
            "benchmark": "fit",
            "hours": HOURS,
            "channels": len(train.channels),
            "error_points": int(len(train.errors) // 6),
            "total_s": round(w1 - w0, 3),
            "cpu_s": round(c1 - c0, 3),
            "target_s": TARGET_S,
            "ok": bool(w1 - w0 < TARGET_S),
            "stages_s": result.timings_s,
            "baseline_ols_all_channels_s": round(_baseline(train), 3),
            "kept_channels": result.document.kept_channels,
            "worst_rmse_holdout_mm": float(lengths["rmse_holdout"].max()),
            "worst_rmse_holdout_rad": float(angles["rmse_holdout"].max()),
            "neural_comparison": neural,
            "load_average": load_average(),
        }
    )


if __name__ == "__main__":
    main()
