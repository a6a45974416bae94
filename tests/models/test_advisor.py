"""The campaign advisor (models.advisor) on a small world whose answer is known.

Two heat sources: the spindle warms the spindle head (T1), the X drive warms the X table (T4), both
as first-order lags (ch. 5.3). Two laser setups on the X axis: position (dx) and Z straightness
(dz). The campaign ran both sources on the position setup but only the spindle on the straightness
setup, so how the X table's warmth moves dz is pinned by nothing but the prior: the advisor must
mount the straightness optics and run the X drive.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns.bundle import Bundle, CampaignMeta
from driftlab.campaigns.plan import parse_plan
from driftlab.errors import ValidationError
from driftlab.models.advisor import (
    SOURCES,
    Candidate,
    Step,
    advise,
    fit_response,
    reduction_um2,
    session_demean,
    source_inputs,
)
from driftlab.models.document import ModelDocument
from driftlab.models.features import Inputs
from driftlab.physics.lag import first_order_lag

SCAN_S = 120.0
SWEEP_S = 900.0
POSITIONS = (0.0, 100.0, 200.0)
TAU_S = 3600.0
#: steady rise (degC) of each structure under each source
GAIN = {"spindle": {"S": 4.0, "X": 0.3}, "X": {"S": 0.2, "X": 3.0}}
CHANNELS = {
    "S1": ("spindle head upper", "spindle"),
    "S2": ("spindle head lower", "spindle"),
    "X1": ("x table left", "x_table"),
    "X2": ("x table right", "x_table"),
}
SETUPS = {
    "x-position": {"instrument": "laser", "optics": "linear", "axis": "X", "terms": ["X/dx"], "datum": "session"},
    "x-straightness-z": {
        "instrument": "laser",
        "optics": "straightness",
        "axis": "X",
        "terms": ["X/dz"],
        "datum": "session",
    },
}
#: (setup, heat source, hours): the straightness setup comes first and never sees the X drive, so
#: while it is mounted the X table only follows the spindle (the same lag: collinear)
STAGES = (
    ("x-straightness-z", "spindle", 3.0),
    ("x-straightness-z", "none", 3.0),
    ("x-position", "spindle", 3.0),
    ("x-position", "none", 3.0),
    ("x-position", "axis", 3.0),
    ("x-position", "none", 3.0),
)


def true_temperatures(u: np.ndarray, t: np.ndarray, y0: dict[float, np.ndarray] | None = None) -> np.ndarray:
    """Return (N, 4) dT of S1, S2, X1, X2 for source states u (N, 6): first-order lags (ch. 5.3)."""
    lag = first_order_lag(u, t, TAU_S, y0=None if y0 is None else y0[TAU_S])
    spindle, x = lag[:, 0], lag[:, 1]
    s = GAIN["spindle"]["S"] * spindle + GAIN["X"]["S"] * x
    xx = GAIN["spindle"]["X"] * spindle + GAIN["X"]["X"] * x
    # the two sites of a structure differ a little (the upper side warms more)
    return np.column_stack([1.1 * s, 0.9 * s, 1.05 * xx, 0.95 * xx])


def campaign() -> Bundle:
    """Return the small campaign as a bundle v2."""
    stages, t0 = [], 0.0
    for i, (setup, heat, hours) in enumerate(STAGES):
        stages.append(
            {
                "name": f"s{i}.{setup}.{heat}",
                "start_s": t0,
                "end_s": t0 + hours * 3600.0,
                "heat_source": heat,
                "axis": "X",
                "spindle_rpm": 10000.0 if heat == "spindle" else 0.0,
                "feed_mm_min": 4000.0 if heat == "axis" else 0.0,
            }
        )
        t0 += hours * 3600.0
    meta = CampaignMeta.model_validate(
        {
            "format": "driftlab-bundle/2",
            "machine": {"id": "toy-1"},
            "started_at": datetime(2026, 3, 2, 8, tzinfo=UTC),
            "channels": {c: {"location": loc, "structure": st} for c, (loc, st) in CHANNELS.items()},
            "stages": stages,
            "noise": {"length_mm": 0.0005, "angle_rad": 5e-7},
            "setups": SETUPS,
        }
    )
    t = np.arange(0.0, t0 + 1e-6, SCAN_S)
    temps = pd.DataFrame(true_temperatures(source_inputs(meta.stages, t), t) + 20.0, columns=list(CHANNELS))
    temps.insert(0, "time_s", t)
    rows = []
    for st, (setup, _, _) in zip(meta.stages, STAGES):
        term = SETUPS[setup]["terms"][0].split("/")[1]
        for ts in np.arange(st.start_s, st.end_s - 1.0, SWEEP_S):
            for k, (pos, d) in enumerate([(p, 1) for p in POSITIONS] + [(p, -1) for p in POSITIONS]):
                rows.append(
                    {
                        "time_s": ts + 6.0 * k,
                        "axis": "X",
                        "position": pos,
                        "direction": d,
                        "term": term,
                        "value": 0.0,
                        "x": pos,
                        "y": 0.0,
                        "z": 0.0,
                        "a": 0.0,
                        "b": 0.0,
                        "setup": setup,
                    }
                )
    return Bundle("toy", meta, temps, None, pd.DataFrame(rows))


@pytest.fixture(scope="module")
def bundle() -> Bundle:
    return campaign()


def document() -> ModelDocument:
    """Return a model whose terms are the structures' mean warmth on dx and dz of their links (eq. 3.3)."""
    mean = {"T1": ("spindle", ["S1", "S2"]), "T4": ("x_table", ["X1", "X2"])}
    terms = [
        {
            "element": el,
            "param": param,
            "features": [{"kind": "mean", "name": f"mean[{st}]", "channels": chans, "label": st}],
            "coefficients": [1e-3],
            "statistics": {"rmse_train": 0.0},
        }
        for el, (st, chans) in mean.items()
        for param in ("dx", "dz")
    ]
    inputs = {c: {"reference": 20.0, "min": 0.0, "max": 5.0} for c in CHANNELS}
    return ModelDocument.model_validate({"machine": "toy-1", "inputs": inputs, "terms": terms})


@pytest.fixture(scope="module")
def advice(bundle):
    return advise([bundle], document(), hours=6.0, durations_h=(3.0,), campaign="toy", structure_terms=False)


def test_the_thermal_response_recovers_the_lags(bundle):
    """The per-channel response fitted on the campaign reproduces its own temperatures."""
    t = bundle.temperatures["time_s"].to_numpy()
    dT = bundle.temperatures[list(CHANNELS)] - bundle.temperatures[list(CHANNELS)].iloc[0]
    resp = fit_response(t, dT, source_inputs(bundle.meta.stages, t))
    assert resp.rmse_degC.max() < 0.01
    assert np.all(resp.taus_s.min(axis=1) <= TAU_S)


def test_advisor_runs_the_x_drive_under_the_straightness_optics(advice):
    """The coefficient nothing pinned (X table warmth -> dz) is what the first stage isolates."""
    first = advice.stages[0].candidate
    assert (first.setup, first.source) == ("x-straightness-z", "X")
    # four coefficients and four constants (laser sessions never pin a constant: the prior does)
    assert advice.n_parameters == 8 and advice.n_candidates == 4
    assert advice.stages[0].variance_after_um2 < 0.9 * advice.stages[0].variance_before_um2


def test_predicted_reduction_matches_the_rows_actually_added(bundle, advice):
    """The advisor's variance after its stage equals trace(F^-1 M) with the stage's true rows added."""
    design = advice.design
    assert design is not None
    stage = advice.stages[0]
    c = stage.candidate
    # the true temperatures of the stage, continuing the campaign (the world, not the fitted response)
    t_c = bundle.temperatures["time_s"].to_numpy()
    u_c = source_inputs(bundle.meta.stages, t_c)
    end = {TAU_S: first_order_lag(u_c, t_c, TAU_S)[-1]}
    dt = np.arange(0.0, c.hours * 3600.0 + 1e-6, 60.0)
    u = np.zeros((dt.size, len(SOURCES)))
    u[(dt > 0) & (dt <= c.heat_h * 3600.0), SOURCES.index(c.source)] = 1.0
    T = true_temperatures(u, dt, end)
    sweeps = np.arange(0.0, c.hours * 3600.0 - 1e-6, SWEEP_S)
    pts = [(p, 1.0) for p in POSITIONS] + [(p, -1.0) for p in POSITIONS]
    at = np.repeat(sweeps, len(pts))
    dT = pd.DataFrame({ch: np.interp(at, dt, T[:, k]) for k, ch in enumerate(CHANNELS)})
    q = np.zeros((at.size, 5))
    q[:, 0] = np.tile([p for p, _ in pts], sweeps.size)
    d = np.zeros_like(q)
    d[:, 0] = np.tile([s for _, s in pts], sweeps.size)
    rows = design.builder.rows(Inputs(dT=dT, days=np.zeros(at.size)), q, d, [5])[0]  # dz
    A = session_demean(rows / 0.0005, np.full(at.size, "new", dtype=object)) * np.sqrt(0.75)
    F = design.information + A.T @ A
    actual = float(np.trace(np.linalg.inv(F) @ design.target)) * 1e6
    before = float(np.trace(np.linalg.inv(design.information) @ design.target)) * 1e6
    assert stage.variance_before_um2 == pytest.approx(before, rel=1e-6)
    assert stage.variance_after_um2 == pytest.approx(actual, rel=0.03)
    # and the reduction the greedy step scored is that difference
    gain = reduction_um2(design, design.information, before, A)
    assert gain == pytest.approx(before - actual, rel=1e-6)
    # the greedy step's shortcut (Woodbury, fewer rows than coefficients) gives the same figure
    few = A[:5]
    direct = reduction_um2(design, design.information, before, few)
    woodbury = reduction_um2(design, design.information, before, few, Step.of(design, design.information))
    assert woodbury == pytest.approx(direct, rel=1e-6) and direct > 0


def test_the_plan_passes_the_validator(advice):
    """The advised stages are a plan `driftlab plan check` and the daemon accept."""
    plan = parse_plan(advice.plan())
    assert [s.setup for s in plan.stages] == [s.candidate.setup for s in advice.stages for _ in (0, 1)]
    assert plan.total_s == pytest.approx(advice.used_h * 3600.0)
    hot = plan.stages[0]
    assert [h.kind for h in hot.heat] == ["axis"] and plan.stages[1].heat == []
    assert "x-straightness-z" in advice.summary()


def test_hours_are_respected(bundle):
    """The advised stages stay within the budget; a budget shorter than any stage advises nothing."""
    for hours in (2.5, 5.0):
        adv = advise([bundle], document(), hours=hours, durations_h=(1.0, 2.0), structure_terms=False)
        assert adv.used_h <= hours + 1e-9
        assert adv.stages
    none = advise([bundle], document(), hours=1.5, durations_h=(1.0,), structure_terms=False)
    assert none.stages == [] and none.variance_after_um2 == none.variance_before_um2


@pytest.mark.parametrize("hours", [0.0, -1.0, float("nan")])
def test_hours_must_be_positive(bundle, hours):
    with pytest.raises(ValidationError, match="--hours"):
        advise([bundle], None, hours=hours)


def test_a_campaign_without_setups_is_refused(bundle):
    meta = bundle.meta.model_copy(update={"setups": None})
    with pytest.raises(ValidationError, match="setups"):
        advise([Bundle("v1", meta, bundle.temperatures, None, bundle.errors)], None)


def test_candidate_hours():
    assert Candidate("s", "spindle", 2.0, 2.0).hours == 4.0
