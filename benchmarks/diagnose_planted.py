"""Found/planted table of `diagnose` on open-world bundles (effects planted in element errors): one JSON line.

Each effect is planted in an element error of the HTM chain (``driftlab.testing.openworld``) and
scaled so that the part of it no standard model can absorb is ``SIZE`` x the laser noise RMS
(default 3). One and two effects per bundle; AR(1) noise, glitches and gaps as in the null benchmark.
A row is "found" when an effect of the right kind, axis, term and channel (a site of the same body)
is reported with its parameters within 30 % of what the chain shows on that term.

    .venv/bin/python benchmarks/diagnose_planted.py [SIZE] [SEEDS] [FIRST]    # seeds FIRST .. FIRST + SEEDS - 1
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402,F401  (pins BLAS to one thread before numpy loads)

from driftlab.models.diagnosis import diagnose_bundle  # noqa: E402
from driftlab.testing.openworld import OpenPlanted as P  # noqa: E402
from driftlab.testing.openworld import OpenWorld, openworld_case  # noqa: E402

SAME_BODY = {
    "T7": {"T7", "T8"},
    "T8": {"T7", "T8"},
    "T5": {"T5", "T6"},
    "T6": {"T5", "T6"},
    "T1": {"T1", "T2"},
    "T2": {"T1", "T2"},
    "T3": {"T3", "T4"},
    "T4": {"T3", "T4"},
}
SCALE_KEY = {
    "reversal": "magnitude",
    "screw_expansion": "coef_per_mm_degC",
    "unmapped_channel": "coef_per_degC",
    "thermal_lag": "coef_per_degC",
    "drift": "rate_per_day",
    "quadratic": "coef_per_degC2",
    "operating_condition": "coef_per_unit",
}

CASES: dict[str, list[P]] = {
    "reversal A (theta_x alpha)": [P("reversal", "A", "alpha", "theta_x", "alpha", [], {"magnitude": 1e-6})],
    "reversal X (phi_x dx)": [P("reversal", "X", "dx", "phi_x", "dx", [], {"magnitude": 1e-3})],
    "screw X (phi_x dx, T7)": [P("screw_expansion", "X", "dx", "phi_x", "dx", ["T7"], {"coef_per_mm_degC": 1e-5})],
    "unmapped Z (T2 dz, T9)": [P("unmapped_channel", "Z", "dz", "T2", "dz", ["T9"], {"coef_per_degC": 1e-3})],
    "lag Z (T2 dz, T5)": [P("thermal_lag", "Z", "dz", "T2", "dz", ["T5"], {"tau_s": 3000.0, "coef_per_degC": 1e-2})],
    "drift X/alpha (T3 alpha)": [P("drift", "X", "alpha", "T3", "alpha", [], {"rate_per_day": 1e-6})],
    "quadratic Z (T1 dz, T1)": [P("quadratic", "Z", "dz", "T1", "dz", ["T1"], {"coef_per_degC2": 1e-5})],
    "rpm^2 Z (T1 dz)": [P("operating_condition", "Z", "dz", "T1", "dz", [], {"power": 2, "coef_per_unit": -1e-10})],
    "two: reversal Z + lag Z": [
        P("reversal", "Z", "dz", "phi_z", "dz", [], {"magnitude": 1e-3}),
        P("thermal_lag", "Z", "dz", "T2", "dz", ["T5"], {"tau_s": 3000.0, "coef_per_degC": 1e-2}),
    ],
    "two: screw X + rpm^2 Z": [
        P("screw_expansion", "X", "dx", "phi_x", "dx", ["T7"], {"coef_per_mm_degC": 1e-5}),
        P("operating_condition", "Z", "dz", "T1", "dz", [], {"power": 2, "coef_per_unit": -1e-10}),
    ],
}


def _scaled(planted: list[P], seed: int, size: float) -> list[P]:
    """Return ``planted`` with each effect scaled so its part beyond the standard model is ``size`` x noise."""
    keep = sorted({(p.axis, p.term) for p in planted})
    probe = openworld_case(planted, OpenWorld(seed=seed, keep=keep))
    out = []
    for p, beyond in zip(planted, probe.beyond_model_rms):
        noise = probe.noise["angle_rad" if p.term in ("alpha", "beta", "gamma") else "length_mm"]
        k = SCALE_KEY[p.kind]
        params = dict(p.params)
        params[k] = float(params[k]) * size * noise / max(beyond, 1e-30)
        out.append(P(p.kind, p.axis, p.term, p.element, p.param, list(p.channels), params))
    return out


def _match(p: P, exp: dict, effects: list) -> tuple[bool, dict]:
    """Return whether ``p`` is found with its parameters within 30 %, and what was reported for it."""
    for e in effects:
        if e.kind != p.kind or (e.axis, e.term) != (p.axis, p.term):
            continue
        if not all(set(e.channels) <= SAME_BODY.get(c, {c}) for c in p.channels):
            continue
        ok = True
        for key, truth in exp.items():
            if isinstance(truth, str) or key == "power":
                ok &= e.params.get(key) == truth
            else:
                ok &= abs(float(e.params.get(key, float("nan"))) - truth) <= 0.3 * abs(truth)
        return bool(ok), {"channels": e.channels, **{k: e.params.get(k) for k in exp}}
    return False, {}


def main(size: float = 3.0, seeds: int = 3, first: int = 700) -> dict:
    """Return the found/planted table."""
    t0 = time.perf_counter()
    rows, found, total, extra = [], 0, 0, 0
    for name, planted in CASES.items():
        for s in range(seeds):
            seed = first + s
            pl = _scaled(planted, seed, size)
            case = openworld_case(pl, OpenWorld(seed=seed, keep=sorted({(p.axis, p.term) for p in pl})))
            res = diagnose_bundle(case.bundle)
            hit_any = set()
            for p, exp in zip(pl, case.expected):
                ok, got = _match(p, exp, res.effects)
                total += 1
                found += ok
                rows.append(
                    {
                        "case": name,
                        "seed": seed,
                        "kind": p.kind,
                        "axis": p.axis,
                        "term": p.term,
                        "channels": p.channels,
                        "planted": exp,
                        "found": ok,
                        "reported": got,
                    }
                )
                if got:
                    hit_any.add((p.kind, p.axis, p.term))
            extra += sum(1 for e in res.effects if (e.kind, e.axis, e.term) not in hit_any)
    return {
        "benchmark": "diagnose_planted",
        "size_x_noise": size,
        "planted": total,
        "found": found,
        "other_findings": extra,
        "rows": rows,
        "wall_s": round(time.perf_counter() - t0, 1),
    }


if __name__ == "__main__":
    print(
        json.dumps(
            main(
                float(sys.argv[1]) if len(sys.argv) > 1 else 3.0,
                int(sys.argv[2]) if len(sys.argv) > 2 else 3,
                int(sys.argv[3]) if len(sys.argv) > 3 else 700,
            ),
            default=str,
        )
    )
