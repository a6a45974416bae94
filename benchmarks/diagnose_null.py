"""False findings of `diagnose` on null open-world bundles (nothing planted): one JSON line.

Each bundle (``driftlab.testing.openworld``, fixed seeds): 24 h, 12 thermocouples, three terms
(Z/dz, X/dx, A/alpha), AR(1) laser noise with rho drawn in 0.4-0.8, single-scan glitches in
temperatures and errors, two logger gaps and a laser gap, a base field outside the standard
model's span. Target (issue 12): at most 5 % of bundles with any finding.

    .venv/bin/python benchmarks/diagnose_null.py [N]    # N bundles, default 200
"""

from __future__ import annotations

import json
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common  # noqa: E402,F401  (pins BLAS to one thread before numpy loads)

from driftlab.models.diagnosis import diagnose_bundle  # noqa: E402
from driftlab.testing.openworld import openworld_case  # noqa: E402


def main(n: int = 200) -> dict:
    """Return the measured false-finding rate over ``n`` null bundles."""
    t0 = time.perf_counter()
    with_finding, kinds, rhos = 0, Counter(), []
    for seed in range(n):
        case = openworld_case([], seed=50_000 + seed, hours=24, keep=[("Z", "dz"), ("X", "dx"), ("A", "alpha")])
        rhos.append(case.rho)
        res = diagnose_bundle(case.bundle)
        if res.effects:
            with_finding += 1
            kinds.update(e.kind for e in res.effects)
    out = {
        "benchmark": "diagnose_null",
        "bundles": n,
        "bundles_with_any_finding": with_finding,
        "rate": with_finding / n,
        "target_rate": 0.05,
        "meets_target": with_finding / n <= 0.05,
        "findings_by_kind": dict(kinds),
        "rho_range": [round(min(rhos), 3), round(max(rhos), 3)],
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    return out


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1]) if len(sys.argv) > 1 else 200)))
