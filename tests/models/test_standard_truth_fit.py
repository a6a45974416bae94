"""A machine whose drift is the standard model (spec section 2), not the virtual machine's links.

Issue 12: on a bundle whose errors are exactly a cubic in position plus dT of each line's
``model_channels`` (different coefficients per line, so the lines' home values disagree), the
per-link models alone left 6-13 um held-out against 0.5 um of noise. The fit must not be worse
than the standard model: each line's correction (``models.lines``) is kept by validation inside
the training part, and every term's held-out RMSE comes within 1.5x the noise. The noise here is
AR(1) (rho 0.6), as laser residuals are, and one bundle is written as another lab would
(renamed channels, no stages, gaps).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from effects_generator import foreign, make_case  # noqa: E402

from driftlab.campaigns.bundle import Bundle  # noqa: E402
from driftlab.models.fitting import FitOptions, fit_bundles  # noqa: E402

NOISE_MM = 5e-4
TERMS = {"X": ["dx", "dy", "dz"], "Y": ["dx", "dz"], "Z": ["dx", "dz"]}


def _with_ar1(bundle: Bundle, rho: float, sigma: float, seed: int) -> Bundle:
    """Return the bundle with AR(1) noise of stationary RMS ``sigma`` on every line, in time order."""
    rng = np.random.default_rng(seed)
    err = bundle.errors.copy()
    for _, idx in err.groupby(["axis", "term"]).groups.items():
        rows = err.loc[idx].sort_values("time_s").index
        e = np.empty(len(rows))
        e[0] = rng.normal(0, sigma)
        shocks = rng.normal(0, sigma * np.sqrt(1 - rho**2), len(rows))
        for i in range(1, len(rows)):
            e[i] = rho * e[i - 1] + shocks[i]
        err.loc[rows, "value"] = err.loc[rows, "value"].to_numpy(float) + e
    return Bundle(
        name=bundle.name, meta=bundle.meta, temperatures=bundle.temperatures, conditions=bundle.conditions, errors=err
    )


def _standard_bundle(seed: int) -> Bundle:
    case = make_case([], seed=seed, hours=72.0, terms=TERMS, n_channels=12, noise_mm=1e-7)
    return _with_ar1(case.bundle, rho=0.6, sigma=NOISE_MM, seed=seed + 100)


def _holdout(result) -> pd.DataFrame:
    v = result.validation
    return v[v["unit"] == "mm"].set_index(["axis", "term"])


@pytest.mark.parametrize("seed", [0, 3])
def test_fit_reaches_the_noise_on_a_standard_model_machine(seed: int) -> None:
    result = fit_bundles([_standard_bundle(seed)], FitOptions(network=False))
    held = _holdout(result)
    assert len(held) == sum(len(v) for v in TERMS.values())
    worst = held["rmse_holdout"].max()
    assert worst <= 1.5 * NOISE_MM, held[["rmse_train", "rmse_holdout"]].to_string()
    lines = {(ln["axis"], ln["term"]): ln for ln in result.document.lines}
    # the decision is stated per line, with the checked figures it was made on
    for key in held.index:
        ln = lines[key]
        assert ln["form"] in ("link", "link+stepwise", "link+full", "link+standard")
        assert ln["checked_rmse"]["link"] > 0 and ln["why"]


def test_lines_are_not_added_where_the_links_already_explain_the_data() -> None:
    """Without line corrections the same fit is far from the noise: the layer is what closes the gap."""
    bundle = _standard_bundle(0)
    plain = _holdout(fit_bundles([bundle], FitOptions(network=False, lines=False)))
    assert plain["rmse_holdout"].max() > 5 * NOISE_MM


def test_foreign_bundle_of_a_standard_model_machine() -> None:
    """Renamed channels, no stages (one allocation per axis), irregular scans with two gaps."""
    case = make_case([], seed=5, hours=72.0, terms={"X": ["dx", "dz"], "Z": ["dz"]}, n_channels=10, noise_mm=1e-7)
    bundle = _with_ar1(foreign(case, seed=5), rho=0.6, sigma=NOISE_MM, seed=7)
    held = _holdout(fit_bundles([bundle], FitOptions(network=False)))
    assert held["rmse_holdout"].max() <= 1.5 * NOISE_MM, held[["rmse_train", "rmse_holdout"]].to_string()


def test_the_compensator_reads_the_line_corrections(tmp_path: Path) -> None:
    """The registered document alone (the compensator's view) carries the corrections on T1.

    On a single measured line there is no other line to disagree with, so the document's
    work-space prediction at that line's points equals the fit's own.
    """
    from driftlab.models.document import predict_workspace_errors

    case = make_case([], seed=2, hours=48.0, terms={"X": ["dz"]}, n_channels=10, noise_mm=1e-7)
    bundle = _with_ar1(case.bundle, rho=0.6, sigma=NOISE_MM, seed=9)
    result = fit_bundles([bundle], FitOptions(network=False))
    doc = result.document
    assert any(ln["form"] != "link" for ln in doc.lines)
    assert all(ln["home_deviation"] is None for ln in doc.lines)
    err = bundle.errors.sort_values("time_s")
    temps = bundle.temperatures.set_index("time_s")
    t = err["time_s"].to_numpy(float)
    # readings at the error times, as the fit interpolates them
    at = pd.DataFrame(
        {c: np.interp(t, temps.index.to_numpy(float), temps[c].to_numpy(float)) for c in doc.inputs}
    ).assign(time_s=t)
    q = np.zeros((len(err), 5))
    q[:, 0] = err["position"].to_numpy(float)
    pred = predict_workspace_errors(doc, at, q, err["direction"].to_numpy(float))[:, 5]
    resid = err["value"].to_numpy(float) - pred
    late = t >= np.quantile(t, 0.8)
    assert np.sqrt(np.mean(resid[late] ** 2)) <= 1.5 * NOISE_MM
