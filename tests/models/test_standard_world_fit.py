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


def test_zeroed_sessions_within_the_noise() -> None:
    """Every laser session zeroed at its first reading: the fit reads each as the model less its datum."""
    t = _table(1, zeroed=True)
    assert (t["fit"] <= 1.5).all(), t.to_string()
    assert (t["fit"] <= t["standard"] + 0.5).all(), t.to_string()


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


def test_coefficients_carry_their_covariance_and_the_report_names_poorly_pinned_terms() -> None:
    """Issue 21.4: standard errors, covariance in the document, a prediction interval, pinning in the report."""
    import numpy as np

    from driftlab.models.document import predict_workspace_sd

    world = standard_world(2, axes=("X",), hours=36.0, zeroed=True)
    result = fit_bundles([world.bundle], FitOptions(network=False, virtual_sensors=False))
    joint = result.joint
    assert joint is not None
    cov = joint.cov_params()
    assert cov.shape == (len(joint.columns), len(joint.columns))
    assert np.allclose(cov.to_numpy(), cov.to_numpy().T) and (np.diag(cov) >= 0).all()
    assert joint.regressors("dx").shape[1] == len(joint.columns)
    assert "std err" in joint.summary()
    doc = result.document
    assert all(t.covariance is not None and len(t.covariance) == len(t.features) for t in doc.terms)
    temps = world.bundle.temperatures.iloc[[-1]].drop(columns="time_s")
    sd = predict_workspace_sd(doc, temps, np.array([[250.0, 0, 0, 0, 0]]))
    assert sd is not None and np.all(np.isfinite(sd)) and np.all(sd > 0)
    # within an order of the laser noise (the residual variance is part of it)
    assert world.noise_mm / 3 < sd[0, 3] < 10 * world.noise_mm
    report = result.report()
    for p in report.get("pinning", []):
        assert p["poorly_pinned"] and "condition_number" in p and "vif" in p


#: a plan whose Z feed comes only at the end: the training part (first 70 % of time) never heats the Z screw
LATE_Z = ("feed-X", "spindle", "feed-X", "spindle", "feed-X", "spindle", "feed-Z")


@pytest.mark.parametrize("seed", [3, 6])
def test_a_channel_the_training_part_left_still_is_not_extrapolated(seed: int) -> None:
    """Issue 33.3: trained on the first 70 % of time, scored on the rest, within 1.5x of plain least squares.

    The Z screw (z_nut, z_motor_case) warms 3-6x further in the held-out part than in training. The
    link models read it through angles, which reach the lines through the chain's lever arm as
    position x lag and position^2 x dT (eq. 4.12): the line corrections must be able to write those
    (``lines.levered``), else the fallback to the standard model keeps them and extrapolates
    (seed 6: Z/dy 5.0x, seed 3: X/dy 1.8x plain least squares before).
    """
    world = standard_world(seed, hours=48.0, order=LATE_Z)
    result = fit_bundles(
        [world.bundle], FitOptions(network=False, virtual_sensors=False, split="time", holdout_fraction=0.3)
    )
    v = result.validation.set_index(["axis", "term"])
    ols = standard_holdout(world, 0.3, split="time")["standard_holdout"].reindex(v.index)
    ratio = v["rmse_holdout"] / ols
    assert len(ratio) == 12 and (ratio <= 1.5).all(), ratio.to_string()
