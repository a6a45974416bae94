"""Neural comparison: eq. 6.3 scaling; interpolates well; extrapolates worse than physical regression."""

import numpy as np
import pandas as pd
import pytest

from driftlab.errors import ValidationError
from driftlab.models.neural import extrapolation_errors, fit_network, scale_inputs


def test_scaling_maps_training_range_to_plus_minus_0_9():
    X = np.array([[1.0, 10.0], [3.0, 30.0], [2.0, 20.0]])
    Z = scale_inputs(X, X.min(0), X.max(0))
    np.testing.assert_allclose(Z, [[-0.9, -0.9], [0.9, 0.9], [0.0, 0.0]])


def _frame(room, rng):
    n = room.size
    heat = rng.uniform(0, 6, n)
    return pd.DataFrame({"room": room, "heat": heat, "T34": room + heat})


def test_network_interpolates_but_drifts_when_the_room_leaves_its_range():
    rng = np.random.default_rng(0)
    train = _frame(rng.uniform(19.0, 22.0, 3000), rng)
    y = 0.0121 * (train["T34"] - 20) + 0.004 * (train["room"] - 20)
    net = fit_network(train, y.to_numpy(), hidden=(12, 6), max_iter=300)
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones(len(train)), train.to_numpy()]), y, rcond=None)
    test_in = _frame(rng.uniform(19.0, 22.0, 500), rng)
    test_out = _frame(rng.uniform(23.5, 24.5, 500), rng)  # two degrees beyond the training range

    def reg(df):
        return coef[0] + df.to_numpy() @ coef[1:]

    def truth(df):
        return (0.0121 * (df["T34"] - 20) + 0.004 * (df["room"] - 20)).to_numpy()

    assert net.outside_training_range(test_out).all() and net.outside_training_range(test_in).mean() < 0.02
    res = extrapolation_errors(
        truth(test_in), reg(test_in), net.predict(test_in), truth(test_out), reg(test_out), net.predict(test_out), 2.0
    )
    assert res.network_in_range_mm < 0.001
    assert res.network_mm > 3 * max(res.regression_mm, res.network_in_range_mm)
    assert res.to_dict()["n"] == 500


def test_network_needs_data():
    with pytest.raises(ValidationError):
        fit_network(pd.DataFrame({"a": [1.0, 2.0]}), np.array([1.0, 2.0]))
