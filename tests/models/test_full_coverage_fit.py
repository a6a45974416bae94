"""A full-coverage campaign through the daemon, fitted: every one of the thirty terms near the laser noise.

The compressed plan (examples/plans/demo-full.yaml) mounts 22 setups one after the other; each laser
setup is zeroed when mounted (bundle v2 ``datum: session``), so its readings carry an unknown offset:
the error at the moment it was zeroed, which depends on how warm the machine still was from the
setups before. The fit must treat that offset as a nuisance of the session, not of the machine.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns.db import store_engine
from driftlab.campaigns.plan import load_plan
from driftlab.campaigns.store import Store
from driftlab.daemon.run import run_daemon
from driftlab.models.diagnosis import NON_PHYSICAL_KINDS, diagnose_bundle
from driftlab.models.document import predict_workspace_errors
from driftlab.models.features import Feature, session_terms
from driftlab.models.fitting import FitOptions, fit_bundles

ROOT = Path(__file__).resolve().parents[2]
DEMO_FULL = ROOT / "examples" / "plans" / "demo-full.yaml"
CLEAN = ROOT / "examples" / "scenarios" / "clean.yaml"


def test_session_terms_leave_the_intercept_one_session_when_every_row_is_zeroed() -> None:
    s = np.array(["0.a.0", "0.a.0", "0.b.1", "0.b.1", "0.a.2"], dtype=object)
    rows = np.ones(s.size, bool)
    assert session_terms(s, rows) == [Feature("session", label="0.b.1"), Feature("session", label="0.a.2")]
    # an absolute reading among them pins the intercept: every zeroed session keeps its offset
    s2 = s.copy()
    s2[0] = ""
    assert [f.label for f in session_terms(s2, rows)] == ["0.a.0", "0.b.1", "0.a.2"]
    assert session_terms(None, rows) == []
    assert session_terms(s, np.array([False, False, True, True, False])) == []


@pytest.fixture(scope="module")
def full_fit(tmp_path_factory):
    """Run the compressed full-coverage plan through the daemon (nothing hidden) and fit it."""
    db = tmp_path_factory.mktemp("full") / "full.sqlite"
    url = f"sqlite:///{db}"
    r = run_daemon(load_plan(DEMO_FULL), db_url=url, scenario_path=CLEAN, speed=math.inf)
    bundle = Store(store_engine(url)).campaigns.load(r.campaign_id)
    result = fit_bundles([bundle], FitOptions(network=False, virtual_sensors=False))
    return bundle, result


@pytest.mark.slow
def test_every_term_within_twice_the_noise_on_held_out_data(full_fit) -> None:
    bundle, result = full_fit
    assert bundle.meta.v2 and len(bundle.meta.setups) >= 20
    v = result.validation
    cells = set(zip(v.axis, v.term))
    assert len(cells) == 30  # the plan measures all thirty motion-error terms
    noise = {"mm": bundle.meta.noise.length_mm, "rad": bundle.meta.noise.angle_rad}
    ratio = v.rmse_holdout / v.unit.map(noise)
    worst = v.assign(ratio=ratio).sort_values("ratio").iloc[-1]
    assert (ratio <= 2.0).all(), f"{worst.axis}/{worst.term}: held-out {worst.ratio:.2f}x the noise"
    assert (v.n_holdout > 0).all()


@pytest.mark.slow
def test_the_document_alone_follows_every_session_up_to_its_datum(full_fit) -> None:
    """The registered document (no session offsets) explains each zeroed session's readings but for a constant."""
    bundle, result = full_fit
    doc = result.document
    assert "session" not in {f.kind for t in doc.terms for f in t.features}
    e = bundle.errors.sort_values("time_s", kind="stable").reset_index(drop=True)
    temps = bundle.temperatures
    # the registry filters lagged terms over the frame's own history: give it every scan, and the
    # readings' times among them (poses at the scans alone are not used)
    t_all = np.union1d(temps.time_s.to_numpy(float), e.time_s.to_numpy(float))
    at = pd.DataFrame({"time_s": t_all, **{c: np.interp(t_all, temps.time_s, temps[c]) for c in doc.inputs}})
    row = np.searchsorted(t_all, e.time_s.to_numpy(float))
    q = np.zeros((t_all.size, 5))
    direction = np.zeros_like(q)
    q[row] = e[["x", "y", "z", "a", "b"]].to_numpy(float)
    q[:, 3:] = np.radians(q[:, 3:])
    for k, ax in enumerate("XYZAB"):
        on = (e.axis == ax).to_numpy()
        direction[row[on], k] = e.direction[on]
    W = predict_workspace_errors(doc, at, q, direction)[row]
    col = e.term.map({t: i for i, t in enumerate(("alpha", "beta", "gamma", "dx", "dy", "dz"))}).to_numpy()
    r = e.value.to_numpy() - W[np.arange(len(e)), col]
    run = (e.setup != e.setup.shift()).cumsum()
    spread = pd.Series(r).groupby([e.setup, run, e.term]).transform(lambda x: x - x.mean())
    noise = np.where(e.term.str.startswith("d"), bundle.meta.noise.length_mm, bundle.meta.noise.angle_rad)
    # the combined spindle + feed stages at the end (ch. 6.4) are the validation the fit never trained on
    stage_of = pd.cut(
        e.time_s,
        [s.start_s for s in bundle.meta.stages] + [np.inf],
        right=False,
        labels=[s.name for s in bundle.meta.stages],
        ordered=False,
    )
    combined = stage_of.astype(str).str.contains(r"\+|cool3", regex=True).to_numpy()
    z = (spread / noise).pow(2)
    per_cell = z[~combined].groupby([e.axis[~combined], e.term[~combined]]).mean().pow(0.5)
    assert len(per_cell) == 30
    assert (per_cell <= 2.0).all(), per_cell.sort_values().tail(3).to_dict()
    on_combined = z[combined].groupby([e.axis[combined], e.term[combined]]).mean().pow(0.5)
    # Z/dz: 2.08 until the virtual machine's carriage and table grew along their link vectors (27 Nov), 3.02
    # since: the truth drives both thicknesses by T7 (ch. 5.4's stand-in for T1-T8), the table's physical term
    # reads the table's own sites T1-T4, which the X feed of the combined stages warms apart
    assert len(on_combined) == 3 and (on_combined <= 3.2).all(), on_combined.to_dict()


def test_the_daemon_campaign_carries_the_stated_geometry_into_table_6_3(full_fit) -> None:
    """The plan and the scenario state the thesis machine's lengths: the campaign keeps them, the fit compares."""
    from driftlab.daq.sim.truth import STATED_GEOMETRY
    from driftlab.physics.geometry import Geometry

    bundle, result = full_fit
    assert bundle.meta.machine.geometry == Geometry.model_validate(dict(STATED_GEOMETRY))
    assert result.physical_check["status"] == "compared" and len(result.physical) > 0
    assert result.document.physical_check["geometry"]["bending"]["spindle_arm"]["length_mm"] == 400.0


@pytest.mark.slow
def test_diagnosis_judges_the_fitted_model_and_states_its_held_out_figures(full_fit) -> None:
    """One model (issue 33): the diagnosis' baseline is the fit on its training part, figure for figure."""
    bundle, _ = full_fit
    res = diagnose_bundle(bundle)
    assert len(res.terms) == 30 and all(t.base.model == "fitted" for t in res.terms)
    # the same pipeline with the diagnosis' split states the same held-out figure for every term
    timed = fit_bundles([bundle], FitOptions(network=False, virtual_sensors=False, split="time"))
    v = timed.validation.set_index(["axis", "term"])
    for t in res.terms:
        fit_ho = float(v.loc[(t.td.axis, t.td.term), "rmse_holdout"])
        assert t.base.rmse_holdout == pytest.approx(fit_ho, rel=1e-6), (t.td.axis, t.td.term)
    # nothing is hidden in this campaign: no physical finding, and the extended model is the fitted one
    assert [e.to_dict() for e in res.effects if e.kind not in NON_PHYSICAL_KINDS] == []
    assert all(t.extended_dict()["rmse_holdout"] == t.base.rmse_holdout for t in res.terms)
