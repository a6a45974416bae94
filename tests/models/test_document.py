"""Model documents: validation, JSON round trip, prediction without training data."""

import json

import numpy as np
import pandas as pd
import pytest

from driftlab.errors import ValidationError
from driftlab.models.document import (
    ModelDocument,
    document_json,
    input_ranges,
    predict_element_errors,
    predict_workspace_errors,
    validate_document,
)
from driftlab.physics.kinematics import workspace_error


def _doc(**over):
    d = {
        "machine": "vmc-5ax-01",
        "inputs": {
            "T9": {"reference": 20.0, "min": 19.0, "max": 30.0},
            "T32": {"reference": 20.0, "min": 19.0, "max": 25.0},
            "T34": {"reference": 21.0, "min": 19.0, "max": 28.0},
        },
        "terms": [
            {
                "element": "phi_x",
                "param": "dx",
                "axis": "X",
                "term": "dx",
                "features": [
                    {"kind": "intercept", "name": "const"},
                    {"kind": "pos_dT", "name": "pos[X]*dT[T9]", "channels": ["T9"], "label": "X"},
                    {"kind": "direction", "name": "dir[X]", "label": "X"},
                ],
                "coefficients": [0.001, 12.1e-6, 0.002],
                "statistics": {"rmse_train": 0.0005, "r2": 0.98, "f": 2e4, "n_train": 100},
            },
            {
                "element": "T1",
                "param": "dz",
                "axis": "Z",
                "term": "dz",
                "features": [
                    {"kind": "gradient", "name": "grad[T34-T32]", "channels": ["T34", "T32"]},
                    {"kind": "lag", "name": "lag600[T32]", "channels": ["T32"], "tau_s": 600.0},
                ],
                "coefficients": [0.0103, 0.001],
                "statistics": {"rmse_train": 0.001},
            },
        ],
    }
    d.update(over)
    return d


def test_document_validates_and_round_trips_through_json():
    doc = validate_document(_doc())
    again = validate_document(json.loads(json.dumps(document_json(doc))))
    assert again == doc
    assert doc.format == "driftlab-model/1" and doc.alpha_c_per_degC == 12.1e-6


@pytest.mark.parametrize(
    "change",
    [
        {"terms": [{**_doc()["terms"][0], "coefficients": [1.0]}]},
        {"terms": [{**_doc()["terms"][0], "element": "T9"}]},
        {"terms": [_doc()["terms"][0], _doc()["terms"][0]]},
        {"inputs": {"T9": {"reference": 20.0, "min": 19.0, "max": 30.0}}},
        {"format": "driftlab-model/2"},
    ],
)
def test_bad_documents_are_one_line_validation_errors(change):
    with pytest.raises(ValidationError) as exc:
        validate_document(_doc(**change))
    assert "\n" not in exc.value.one_line()


def test_predict_element_errors_from_a_snapshot_and_from_a_frame():
    doc = validate_document(_doc())
    q = np.zeros((3, 5))
    q[:, 0] = [0.0, 100.0, 200.0]
    temps = {"T9": 25.0, "T32": 22.0, "T34": 25.0}
    el = predict_element_errors(doc, temps, q, direction=np.array([1.0, -1.0, 0.0]))
    np.testing.assert_allclose(el["phi_x"][:, 3], 0.001 + 12.1e-6 * q[:, 0] * 5.0 + 0.002 * np.array([1, -1, 0]))
    # settled lag of a snapshot equals its dT; gradient uses each channel's own reference
    np.testing.assert_allclose(el["T1"][:, 5], 0.0103 * ((25 - 21) - (22 - 20)) + 0.001 * 2.0)
    assert np.all(el["phi_x"][:, [0, 1, 2, 4, 5]] == 0)
    # (N, 5) directions pick the joint's own axis
    d5 = np.zeros((3, 5))
    d5[:, 0] = 1.0
    el5 = predict_element_errors(doc, temps, q, direction=d5)
    np.testing.assert_allclose(el5["phi_x"][:, 3] - el["phi_x"][:, 3], 0.002 * np.array([0, 2, 1]))
    # a frame with time_s: the lag has memory, so a step in T32 is followed slowly
    t = np.arange(0, 3 * 60.0, 60.0)
    frame = pd.DataFrame({"time_s": t, "T9": 25.0, "T32": [20.0, 30.0, 30.0], "T34": 25.0})
    el_f = predict_element_errors(doc, frame, q)
    lag = el_f["T1"][:, 5] - 0.0103 * (4.0 - frame["T32"].to_numpy() + 20)
    assert 0 < lag[1] / 0.001 < 10 * (1 - np.exp(-60 / 600)) + 1e-9


def test_predict_workspace_errors_goes_through_the_chain():
    doc = validate_document(_doc())
    q = np.zeros((2, 5))
    q[:, 0] = [50.0, 250.0]
    temps = {"T9": 25.0, "T32": 22.0, "T34": 25.0}
    W = predict_workspace_errors(doc, temps, q)
    np.testing.assert_allclose(W, workspace_error(q, predict_element_errors(doc, temps, q)))
    assert abs(W[1, 3] - W[0, 3] - 12.1e-6 * 200 * 5) < 1e-9


def test_missing_or_out_of_range_inputs():
    doc = validate_document(_doc())
    with pytest.raises(ValidationError, match="T34"):
        predict_element_errors(doc, {"T9": 25.0, "T32": 22.0}, np.zeros((1, 5)))
    with pytest.raises(ValidationError):
        predict_element_errors(doc, {"T9": 25.0, "T32": np.nan, "T34": 1.0}, np.zeros((1, 5)))
    with pytest.raises(ValidationError):
        predict_element_errors(doc, {"T9": 25.0, "T32": 22.0, "T34": 25.0}, np.zeros((1, 3)))
    assert input_ranges(doc, {"T9": 31.0, "T32": 22.0, "T34": 25.0}) == ["T9"]
    assert isinstance(doc, ModelDocument)


def test_covariance_is_optional_checked_and_gives_a_prediction_interval():
    """Issue 21.4: a document may carry each term's coefficient covariance and residual variance."""
    from driftlab.models.document import predict_workspace_sd

    old = validate_document(_doc())
    assert old.terms[0].covariance is None
    assert predict_workspace_sd(old, {"T9": 25.0, "T32": 22.0, "T34": 24.0}, np.zeros((1, 5))) is None
    terms = _doc()["terms"]
    terms[1] = {**terms[1], "covariance": [[1e-8, 0.0], [0.0, 4e-8]], "residual_variance": 2.5e-7}
    doc = validate_document(_doc(terms=terms))
    sd = predict_workspace_sd(doc, {"T9": 25.0, "T32": 22.0, "T34": 24.0}, np.zeros((1, 5)))
    assert sd is not None and sd.shape == (1, 6)
    # dz at home: grad = (24 - 21) - (22 - 20) = 1 degC, settled lag = 2 degC: 1e-8 + 4 * 4e-8, plus the residual
    assert sd[0, 5] == pytest.approx(np.sqrt(1e-8 + 16e-8 + 2.5e-7), rel=1e-3)
    bad = [dict(terms[0]), dict(terms[1], covariance=[[1.0]])]
    with pytest.raises(ValidationError):
        validate_document(_doc(terms=bad))


def test_joint_covariance_carries_the_trade_off_between_terms():
    """Two constants the campaign pins only as a sum: the interval of the sum is small, not the parts' spread."""
    from driftlab.models.document import predict_workspace_sd

    sigma = 0.004  # mm: each constant alone
    terms = [
        {
            "element": el,
            "param": "dz",
            "features": [{"kind": "intercept", "name": "const"}],
            "coefficients": [0.0],
            "covariance": [[sigma**2]],
            "statistics": {"rmse_train": 0.0},
        }
        for el in ("T3", "T4")
    ]
    cols = [["T3", "dz", "const"], ["T4", "dz", "const"]]
    temps, home = {"T9": 20.0}, np.zeros((1, 5))
    inputs = {"T9": {"reference": 20.0, "min": 19.0, "max": 30.0}}

    def sd(rho=None):
        over = {"inputs": inputs, "terms": terms}
        if rho is not None:
            over["joint_covariance"] = {
                "columns": cols,
                "matrix": [[sigma**2, rho * sigma**2], [rho * sigma**2, sigma**2]],
            }
        out = predict_workspace_sd(validate_document(_doc(**over)), temps, home, residual=False)
        assert out is not None
        return float(out[0, 5])

    # both translate the table along Z at home: taken independent sqrt(2) sigma, as the joint fit says 0 to 2 sigma
    assert sd() == pytest.approx(np.sqrt(2) * sigma, rel=1e-3)
    assert sd(0.0) == pytest.approx(np.sqrt(2) * sigma, rel=1e-3)
    assert sd(-0.99) == pytest.approx(np.sqrt(0.02) * sigma, rel=1e-2)
    assert sd(1.0) == pytest.approx(2 * sigma, rel=1e-3)
    with pytest.raises(ValidationError):
        validate_document(_doc(inputs=inputs, terms=terms, joint_covariance={"columns": cols, "matrix": [[1.0]]}))
