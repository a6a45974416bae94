"""Benchmark: is the demo's cutting figure robust to luck? The demo-full campaign with several noise seeds.

For each seed, the compressed full-coverage plan (examples/plans/demo-full.yaml) runs through the
daemon on the demo's scenario (examples/scenarios/demo-full.yaml) with only its ``seed`` changed;
the campaign is fitted as ``driftlab fit`` fits it, and the demo's thermal cutting test (ch. 7.3:
the campaign's machine, a day after its start, 700 raster passes) runs with the off-line model alone
and with the on-line model on top (local RLS, lambda 0.9), as ``driftlab demo`` does through the API.
The figures are the CMM's, aligned on the part's reference pass (ch. 7.3); ``*_unaligned_um`` are before
that alignment.

Prints one JSON line: per seed the fit's wall time, the cutting figures (RMSE of the normal
deviation, um) uncompensated, off-line and on-line, and whether the targets hold (off-line <= 3 um,
on-line <= 2.5 um on every seed, fit < 30 s).

    .venv/bin/python benchmarks/fit_seeds.py [--seeds 1 5 7 11 19] [--passes 700]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit, load_average  # noqa: E402  (pins BLAS threads before numpy loads)

# isort: split

import yaml  # noqa: E402

from driftlab.campaigns.db import store_engine  # noqa: E402
from driftlab.campaigns.plan import load_plan  # noqa: E402
from driftlab.campaigns.store import Store  # noqa: E402
from driftlab.compensator.compensate import ErrorModel  # noqa: E402
from driftlab.compensator.cutting_test import LocalRLS, run_cutting_test  # noqa: E402
from driftlab.compensator.stream import StaticModel  # noqa: E402
from driftlab.daemon.run import run_daemon  # noqa: E402
from driftlab.daq.sim.scenario import load_scenario  # noqa: E402
from driftlab.models.fitting import FitOptions, fit_bundles  # noqa: E402
from driftlab.resources import examples_dir  # noqa: E402

PLAN = examples_dir() / "plans" / "demo-full.yaml"
SCENARIO = examples_dir() / "scenarios" / "demo-full.yaml"
AGE_DAYS = 1.0  # driftlab demo --age-days default
OFFLINE_UM, ONLINE_UM, FIT_S = 3.0, 2.5, 30.0


def campaign(seed: int, work: Path):
    """Return the demo-full campaign run through the daemon with the scenario's noise seed set to ``seed``."""
    doc = yaml.safe_load(SCENARIO.read_text())
    doc["seed"] = seed
    path = work / f"scenario-{seed}.yaml"
    path.write_text(yaml.safe_dump(doc))
    url = f"sqlite:///{work / f'seed-{seed}.sqlite'}"
    run = run_daemon(load_plan(PLAN), db_url=url, scenario_path=path, speed=math.inf)
    return Store(store_engine(url)).campaigns.load(run.campaign_id), path


def one_seed(seed: int, passes: int, work: Path) -> dict[str, object]:
    """Return the fit time and the thermal cutting figures of one seed."""
    bundle, scenario_path = campaign(seed, work)
    t0, c0 = time.perf_counter(), time.process_time()
    result = fit_bundles([bundle], FitOptions())
    fit_s, fit_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    doc = result.document.model_dump(mode="json")
    origin = datetime.fromisoformat(str(doc["time_origin"]).replace("Z", "+00:00")).timestamp()
    test = run_cutting_test(
        load_scenario(scenario_path),
        lambda: StaticModel(ErrorModel.from_document(doc)),
        lambda: LocalRLS(doc, channels=[], forgetting=0.9),
        passes=passes,
        age_s=AGE_DAYS * 86400.0,
        epoch_s=origin + AGE_DAYS * 86400.0,
    )
    um = {k: round(r.rmse_mm * 1000.0, 2) for k, r in test.runs.items()}
    # before the CMM's alignment on the reference pass (ch. 7.3): where the surface sits in the machine frame
    um |= {f"{k}_unaligned": round(float(r.summary()["unaligned_rmse_mm"]) * 1000.0, 2) for k, r in test.runs.items()}
    return {
        "seed": seed,
        "fit_s": round(fit_s, 1),
        "fit_cpu_s": round(fit_cpu_s, 1),
        **{f"{k}_um": v for k, v in um.items()},
        "constants_held_at_zero": len(
            next((a["joint_adjustment"] for a in doc["allocation"] if "joint_adjustment" in a), {}).get(
                "constants_held_at_zero", []
            )
        ),
    }


def main() -> None:
    """Run every seed; print one JSON line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 5, 7, 11, 19])
    ap.add_argument("--passes", type=int, default=700)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            rows.append(one_seed(seed, args.passes, Path(tmp)))
            print(rows[-1], file=sys.stderr)
    worst_off = max(float(r["offline_um"]) for r in rows)  # type: ignore[arg-type]
    worst_on = max(float(r["online_um"]) for r in rows)  # type: ignore[arg-type]
    worst_fit = max(float(r["fit_s"]) for r in rows)  # type: ignore[arg-type]
    worst_cpu = max(float(r["fit_cpu_s"]) for r in rows)  # type: ignore[arg-type]
    emit(
        {
            "benchmark": "fit_seeds",
            "passes": args.passes,
            "seeds": rows,
            "worst_offline_um": worst_off,
            "worst_online_um": worst_on,
            "worst_fit_s": worst_fit,
            "worst_fit_cpu_s": worst_cpu,
            "offline_ok": worst_off <= OFFLINE_UM,
            "online_ok": worst_on <= ONLINE_UM,
            # wall time on a shared machine counts the waiting: the CPU time is what one core does
            "fit_ok": worst_cpu < FIT_S,
            "load_average": load_average(),
        }
    )


if __name__ == "__main__":
    main()
