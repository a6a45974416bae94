"""Stepwise regression: finds the planted terms, refuses collinear duplicates, carries statistics."""

import numpy as np
import pandas as pd
import pytest

from driftlab.errors import ValidationError
from driftlab.metrics import rmse
from driftlab.models.features import INTERCEPT, Feature, Inputs, design_matrix
from driftlab.models.regression import StepwiseOptions, TermFit, r_squared, stepwise


def _data(n=3000, seed=1):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n)
    dT = pd.DataFrame(
        {
            "T9": 6 * (1 - np.exp(-t * 4)) + 0.2 * rng.standard_normal(n),
            "T32": 3 * np.sin(3 * t) + 0.1 * rng.standard_normal(n),
            "T34": 5 * np.sin(3 * t) + 1.5 * t + 0.1 * rng.standard_normal(n),
            "T49": np.cos(5 * t) + 0.1 * rng.standard_normal(n),
        }
    )
    dT["T11"] = dT["T9"] * 1.0 + 0.002 * rng.standard_normal(n)  # a near copy of T9
    pos = rng.uniform(0, 500, n)
    inp = Inputs(dT=dT)
    y = 0.02 + 12.1e-6 * pos * dT["T9"] + 0.0103 * (dT["T34"] - dT["T32"]) + 0.0005 * rng.standard_normal(n)
    return inp, pos, y.to_numpy()


def test_stepwise_recovers_planted_terms_and_statistics():
    inp, pos, y = _data()
    cands = [Feature("position"), Feature("direction")] + [Feature("dT", (c,)) for c in inp.dT.columns]
    cands += [Feature("pos_dT", (c,)) for c in inp.dT.columns] + [Feature("gradient", ("T34", "T32"))]
    X = design_matrix([INTERCEPT, *cands], inp, pos, np.zeros(len(pos)))
    res = stepwise(X, y, cands, forced=[INTERCEPT])
    assert set(res.names) >= {"const", "grad[T34-T32]"}
    screw = [n for n in res.names if n.startswith("pos*dT[T")]
    assert screw and screw[0] in ("pos*dT[T9]", "pos*dT[T11]")
    assert res.params[screw[0]] == pytest.approx(12.1e-6, rel=0.03)
    assert res.params["grad[T34-T32]"] == pytest.approx(0.0103, rel=0.02)
    assert res.rmse == pytest.approx(0.0005, rel=0.1)
    assert res.rsquared > 0.99 and res.fvalue > 1000
    assert res.steps[0].action == "add"
    # the near copy of the chosen screw channel was refused by the VIF guard, not entered
    other = "pos*dT[T11]" if screw[0] == "pos*dT[T9]" else "pos*dT[T9]"
    assert other not in res.names and other in res.collinear
    assert len(res.names) <= 5


def test_term_fit_predicts_from_inputs_and_scores():
    inp, pos, y = _data()
    cands = [Feature("pos_dT", ("T9",)), Feature("gradient", ("T34", "T32"))]
    X = design_matrix([INTERCEPT, *cands], inp, pos)
    res = stepwise(X, y, cands, forced=[INTERCEPT])
    fit = TermFit("phi_x", "dx", res)
    pred = fit.predict(inp, pos)
    np.testing.assert_allclose(pred, res.ols.fittedvalues, atol=1e-12)
    assert rmse(y - pred) == pytest.approx(res.rmse)
    assert r_squared(y, pred) == pytest.approx(res.rsquared, abs=1e-9)


def test_stepwise_noise_only_keeps_intercept():
    rng = np.random.default_rng(3)
    inp = Inputs(dT=pd.DataFrame({"A": rng.standard_normal(500), "B": rng.standard_normal(500)}))
    cands = [Feature("dT", ("A",)), Feature("dT", ("B",))]
    X = design_matrix([INTERCEPT, *cands], inp)
    res = stepwise(X, rng.standard_normal(500), cands, forced=[INTERCEPT])
    assert res.names == ["const"]
    assert np.isnan(res.fvalue)


def test_stepwise_rejects_bad_data():
    inp = Inputs(dT=pd.DataFrame({"A": [1.0, np.nan, 3.0]}))
    X = design_matrix([INTERCEPT, Feature("dT", ("A",))], inp)
    with pytest.raises(ValidationError):
        stepwise(X, np.ones(3), [Feature("dT", ("A",))], forced=[INTERCEPT])


def test_stepwise_rules_as_options_or_keywords_are_one_fit():
    """``StepwiseOptions`` and the older keywords give the same fit; a misspelt rule is refused."""
    inp, pos, y = _data()
    cands = [Feature("pos_dT", (c,)) for c in inp.dT.columns] + [Feature("gradient", ("T34", "T32"))]
    X = design_matrix([INTERCEPT, *cands], inp, pos)
    by_keywords = stepwise(X, y, cands, forced=[INTERCEPT], max_terms=2, tiered=False)
    by_options = stepwise(X, y, cands, forced=[INTERCEPT], options=StepwiseOptions(max_terms=2, tiered=False))
    assert by_keywords.names == by_options.names and len(by_options.names) == 2
    # the keyword wins over the options it is given with
    assert stepwise(X, y, cands, forced=[INTERCEPT], options=StepwiseOptions(max_terms=2), max_terms=3).names != (
        by_options.names
    )
    with pytest.raises(TypeError, match="p_entre"):
        stepwise(X, y, cands, forced=[INTERCEPT], p_entre=0.01)
