"""Recast regression terms: dT, lags, gradients, position x dT, JSON round trip."""

import numpy as np
import pandas as pd
import pytest

from driftlab.errors import ValidationError
from driftlab.models.features import (
    CandidateSpec,
    Feature,
    Inputs,
    build_inputs,
    candidate_features,
    design_matrix,
    inputs_from_snapshot,
    required_lags,
)


def _temps():
    t = np.arange(0.0, 36000.0, 60.0)
    return pd.DataFrame(
        {"time_s": t, "A": 20 + 5 * (1 - np.exp(-t / 7200)), "B": 20 + 0.0001 * t, "C": np.full(t.size, 21.0)}
    )


def test_build_inputs_interpolates_and_fills_gaps():
    temps = _temps()
    temps.loc[10:20, "B"] = np.nan
    ref = {"A": 20.0, "B": 20.0, "C": 20.0}
    inp = build_inputs(temps, np.array([90.0, 900.0]), ref, lags=[("A", 3600.0)])
    assert inp.dT["C"].tolist() == [1.0, 1.0]
    assert inp.dT["B"].iloc[1] == pytest.approx(0.09, abs=1e-9)
    assert ("A", 3600.0) in inp.lagged
    assert inp.lagged[("A", 3600.0)][1] < inp.dT["A"].iloc[1]
    with pytest.raises(ValidationError):
        build_inputs(temps, np.array([0.0]), {"Z": 20.0})


def test_design_matrix_physical_terms():
    temps = _temps()
    ref = {"A": 20.0, "B": 20.0, "C": 20.0}
    inp = build_inputs(temps, temps["time_s"].to_numpy(), ref)
    pos = np.linspace(0, 200, len(temps))
    feats = [
        Feature("intercept"),
        Feature("pos_dT", ("A",)),
        Feature("gradient", ("A", "B")),
        Feature("mean", ("A", "B"), label="s"),
        Feature("direction"),
        Feature("position", power=2),
    ]
    X = design_matrix(feats, inp, pos, np.ones(len(temps)))
    assert list(X.columns) == ["const", "pos*dT[A]", "grad[A-B]", "mean[s]", "dir", "pos^2"]
    np.testing.assert_allclose(X["pos*dT[A]"], pos * inp.dT["A"])
    np.testing.assert_allclose(X["grad[A-B]"], inp.dT["A"] - inp.dT["B"])
    np.testing.assert_allclose(X["mean[s]"], (inp.dT["A"] + inp.dT["B"]) / 2)
    np.testing.assert_allclose(X["pos^2"], pos**2)


def test_feature_json_round_trip_and_validation():
    f = Feature("lag", ("T34",), tau_s=2900.0)
    assert Feature.from_dict(f.to_dict()) == f
    assert f.name == "lag2900[T34]"
    with pytest.raises(ValidationError):
        Feature("gradient", ("T34",))
    with pytest.raises(ValidationError):
        Feature("bogus")


def test_snapshot_inputs_take_settled_lag():
    inp = inputs_from_snapshot({"A": 23.0, "B": 21.0}, {"A": 20.0, "B": 20.0})
    X = design_matrix([Feature("lag", ("A",), tau_s=100.0), Feature("dT", ("B",))], inp)
    assert X.iloc[0].tolist() == [3.0, 1.0]


def test_candidates_joint_vs_link():
    structs = {"T9": "x_screw", "T10": "x_motor", "T32": "arm", "T34": "arm", "T49": "room", "T50": "room"}
    chans = list(structs)
    joint = candidate_features(
        chans,
        structs,
        axes=["X"],
        screw_channels={"X": ["T9"]},
        lag_taus_s=[3600],
        room_channels=["T49", "T50"],
        structure_members={"arm": ["T32", "T33", "T34"]},
    )
    names = [f.name for f in joint]
    assert {"pos[X]*dT[T9]", "dir[X]", "pos[X]^3", "grad[T34-T32]", "grad[T49-T50]", "lag3600[T9]"} <= set(names)
    assert "mean[arm]" in names and next(f for f in joint if f.kind == "mean").channels == ("T32", "T33", "T34")
    link = candidate_features(chans, structs)
    assert not any(f.kind in ("position", "direction", "pos_dT") for f in link)
    assert required_lags(joint) == [(c, 3600.0) for c in chans]


def test_axis_labelled_features_read_their_column_of_q():
    inp = Inputs(dT=pd.DataFrame({"T9": [1.0, 2.0]}))
    q = np.array([[100.0, 0, 0, 0, 0], [0, 0, -50.0, 0, 0]])
    d = np.array([[1.0, 0, 0, 0, 0], [0, 0, -1.0, 0, 0]])
    X = design_matrix(
        [
            Feature("pos_dT", ("T9",), label="X"),
            Feature("position", power=2, label="Z"),
            Feature("direction", label="Z"),
        ],
        inp,
        q,
        d,
    )
    assert X.to_numpy().tolist() == [[100.0, 0.0, 0.0], [0.0, 2500.0, -1.0]]
    with pytest.raises(ValidationError):
        design_matrix([Feature("position")], inp, q)


def test_candidates_from_a_spec_or_keywords_are_one_list():
    """``CandidateSpec`` and the keywords name the same candidates; a keyword overrides the spec's field."""
    structs = {"T9": "x_screw", "T32": "arm", "T34": "arm", "T49": "room", "T50": "room"}
    chans = list(structs)
    spec = CandidateSpec(axes=("X",), screw_channels={"X": ["T9"]}, lag_taus_s=(3600.0,), room_channels=("T49", "T50"))
    by_spec = candidate_features(chans, structs, spec)
    assert by_spec == candidate_features(
        chans, structs, axes=["X"], screw_channels={"X": ["T9"]}, lag_taus_s=[3600.0], room_channels=["T49", "T50"]
    )
    assert "pos[X]^3" in {f.name for f in by_spec}
    assert "pos[X]^3" not in {f.name for f in candidate_features(chans, structs, spec, max_power=2)}


def test_lever_terms_are_position_times_a_lag_or_position_squared_times_dt():
    """What the chain's lever arm makes of a link's lag or screw term along a line (eq. 4.12, models.lines)."""
    temps = _temps()
    inp = build_inputs(temps, np.array([600.0, 7200.0]), {"A": 20.0, "B": 20.0, "C": 20.0}, lags=[("A", 3600.0)])
    q = np.array([[100.0, 0, 0, 0, 0], [250.0, 0, 0, 0, 0]])
    by_lag = Feature("lever", ("A",), power=1, tau_s=3600.0, label="X")
    by_square = Feature("lever", ("B",), power=2, label="X")
    X = design_matrix([by_lag, by_square], inp, q)
    assert by_lag.name == "pos[X]*lag3600[A]" and by_square.name == "pos[X]^2*dT[B]"
    assert np.allclose(X[by_lag.name], q[:, 0] * inp.lagged[("A", 3600.0)])
    assert np.allclose(X[by_square.name], q[:, 0] ** 2 * inp.dT["B"].to_numpy())
    # the lag differs from dT while A still warms: the lever term is not position x dT
    assert not np.allclose(X[by_lag.name], q[:, 0] * inp.dT["A"].to_numpy())
    assert required_lags([by_lag, by_square]) == [("A", 3600.0)]
    for f in (by_lag, by_square):
        assert Feature.from_dict(f.to_dict()) == f
    with pytest.raises(ValidationError):  # position x dT is pos_dT, not a lever term
        Feature("lever", ("A",), power=1, label="X")
    with pytest.raises(ValidationError):
        Feature("lever", ("A",), power=2)
