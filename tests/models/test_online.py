"""RLS with forgetting factor (eqs. 6.10-6.13): equals batch LS at lambda=1, stays stable, tracks drift."""

import numpy as np
import pytest

from driftlab.errors import ValidationError
from driftlab.models.online import RLSState, online_regressors, rls_init, rls_run, rls_update


def test_rls_without_forgetting_equals_batch_least_squares():
    rng = np.random.default_rng(0)
    Phi = np.column_stack([np.ones(400), rng.standard_normal((400, 2))])
    y = Phi @ [0.01, -0.002, 0.005] + 1e-4 * rng.standard_normal(400)
    run = rls_run(rls_init(3, lam=1.0, p0=1e8), Phi, y)
    batch, *_ = np.linalg.lstsq(Phi, y, rcond=None)
    np.testing.assert_allclose(run.state.theta, batch, rtol=1e-5, atol=1e-9)


def test_rls_stays_symmetric_and_bounded_over_long_runs():
    rng = np.random.default_rng(1)
    n = 6000
    Phi = np.column_stack([np.ones(n), 0.5 + 0.01 * rng.standard_normal(n)])  # poorly excited: P grows
    y = Phi @ [0.003, 0.002] + 1e-4 * rng.standard_normal(n)
    run = rls_run(rls_init(2, lam=0.98), Phi, y)
    P = run.state.P
    assert np.array_equal(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    assert np.all(np.isfinite(run.theta_history))
    assert run.rmse_prior < 5e-4


def test_rls_tracks_a_slow_drift_that_a_frozen_fit_misses():
    days = np.linspace(0, 30, 600)
    drift = 0.0004 * days  # mm/day: wear
    rng = np.random.default_rng(2)
    y = drift + 0.0003 * rng.standard_normal(days.size)
    run = rls_run(rls_init(1, lam=0.95), online_regressors(days.size), y)
    late = days > 20
    assert np.sqrt(np.mean((y[late] - run.prior_prediction[late]) ** 2)) < 0.0006
    frozen = np.mean(y[days < 3])
    assert np.sqrt(np.mean((y[late] - frozen) ** 2)) > 0.007


def test_state_round_trip_and_errors():
    st, err = rls_update(rls_init(2), np.array([1.0, 2.0]), 3.0)
    assert err == 3.0 and st.n_updates == 1
    back = RLSState.from_dict(st.to_dict())
    np.testing.assert_array_equal(back.P, st.P)
    with pytest.raises(ValidationError):
        rls_init(2, lam=1.5)
    with pytest.raises(ValidationError):
        rls_run(rls_init(2), np.ones((3, 3)), np.ones(3))
    with pytest.raises(ValidationError):
        online_regressors(3, {"A": np.ones(3)}, ["B"])
