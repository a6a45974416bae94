"""The one lag filter: exact for piecewise-constant input, on even and uneven steps, vectorised."""

import numpy as np
import pytest

from driftlab.physics.lag import first_order_lag, first_order_lag_even
from driftlab.physics.thermal import driven_node


def _fine_reference(u_held, t, tau, substeps=2000):
    """Integrate tau y' = u - y with explicit Euler on a very fine grid, u held at the newer sample."""
    y = np.empty(t.size)
    y[0] = u_held[0]
    for k in range(1, t.size):
        h = (t[k] - t[k - 1]) / substeps
        v = y[k - 1]
        for _ in range(substeps):
            v += h * (u_held[k] - v) / tau
        y[k] = v
    return y


def test_step_response_is_the_closed_form_at_every_sample():
    t = np.arange(0.0, 20000.0, 30.0)
    u = np.where(t > 0, 1.0, 0.0)
    y = first_order_lag(u, t, 3000.0)
    # the step is held from the first interval on: y(t) = 1 - exp(-t / tau) exactly at the samples
    np.testing.assert_allclose(y, 1 - np.exp(-t / 3000.0), atol=1e-12)


def test_uneven_steps_and_gaps_agree_with_a_fine_integration():
    rng = np.random.default_rng(4)
    t = np.cumsum(np.r_[0.0, rng.uniform(20.0, 200.0, 80)])
    t[40:] += 3600.0  # an hour's gap
    u = np.sin(t / 2500.0) + rng.normal(0, 0.1, t.size)
    y = first_order_lag(u, t, 900.0)
    ref = _fine_reference(u, t, 900.0)
    assert np.abs(y - ref).max() < 1e-3  # Euler's own error at 2000 substeps


def test_even_steps_take_the_compiled_path_and_match_the_loop():
    t = np.arange(0.0, 7200.0, 60.0)
    u = np.column_stack([np.cos(t / 1000.0), 3 * np.cos(t / 1000.0), np.ones(t.size)])
    even = first_order_lag_even(u, 60.0, 1200.0)
    # nudging one step makes the times uneven: the per-step loop must give the same answer elsewhere
    t2 = t.copy()
    t2[-1] += 1e-6
    uneven = first_order_lag(u, t2, 1200.0)
    np.testing.assert_allclose(even[:-1], uneven[:-1], atol=1e-12)
    np.testing.assert_allclose(even[:, 1], 3 * even[:, 0], atol=1e-12)
    np.testing.assert_allclose(even[:, 2], 1.0)  # a settled start stays settled
    assert even.shape == u.shape


def test_start_value_and_bad_input():
    t = np.arange(0.0, 600.0, 60.0)
    y = first_order_lag(np.zeros(t.size), t, 300.0, y0=2.0)
    np.testing.assert_allclose(y, 2.0 * np.exp(-t / 300.0), atol=1e-12)
    assert first_order_lag(np.zeros(0), np.zeros(0), 10.0).size == 0
    with pytest.raises(ValueError, match="positive"):
        first_order_lag(np.ones(3), np.arange(3.0), 0.0)
    with pytest.raises(ValueError, match="decrease"):
        first_order_lag(np.ones(3), np.array([0.0, 2.0, 1.0]), 10.0)
    with pytest.raises(ValueError, match="samples"):
        first_order_lag(np.ones(3), np.arange(4.0), 10.0)


def test_sampled_lag_follows_the_simulators_continuous_lag_within_half_a_step():
    # the simulator lags a continuous temperature exactly (a driven node of the thermal network);
    # the filter of its samples leads it by at most half a step times the input's slope
    h, tau = 60.0, 1800.0
    t = np.arange(0.0, 36000.0, h)
    u = 5 * (1 - np.exp(-t / 7000.0))
    sampled = first_order_lag(u, t, tau)
    continuous = driven_node(u, h, tau).y[:, 0]
    slope = np.abs(np.gradient(u, t)).max()
    assert np.abs(sampled - continuous).max() <= 0.5 * h * slope * 1.05


def test_lag_state_scan_by_scan_is_the_batch_filter():
    """A live compensator's lag, advanced one scan at a time, is first_order_lag over the same scans."""
    from driftlab.physics.lag import LagState

    rng = np.random.default_rng(8)
    t = np.cumsum(np.r_[0.0, rng.uniform(10.0, 120.0, 150)])
    u = {"T1": 20.0 + np.sin(t / 1500.0) * 4.0, "T2": 21.0 + t / 3600.0}
    state = LagState((3600.0,))
    for k in range(t.size):
        state.update(float(t[k]), {c: float(v[k]) for c, v in u.items()})
        if k == 60:
            state.track((600.0,))  # a model with a new time constant arrives mid-run: settled from here
    got = state.values()
    for c, v in u.items():
        assert got[(c, 3600.0)] == pytest.approx(first_order_lag(v, t, 3600.0)[-1], abs=1e-9)
        assert got[(c, 600.0)] == pytest.approx(first_order_lag(v[60:], t[60:], 600.0)[-1], abs=1e-9)
    # a ramp lags behind its reading: the settled value would be wrong by about slope * tau
    assert u["T2"][-1] - got[("T2", 3600.0)] > 0.5


def test_lag_state_keeps_its_state_through_a_missing_reading_and_refuses_time_going_back():
    from driftlab.physics.lag import LagState

    state = LagState((100.0,))
    state.update(0.0, {"T1": 0.0})
    state.update(100.0, {"T1": float("nan")})
    assert state.values()[("T1", 100.0)] == 0.0
    state.update(200.0, {"T1": 1.0})
    assert state.values()[("T1", 100.0)] == pytest.approx(1.0 - np.exp(-1.0))  # held at the newer reading
    with pytest.raises(ValueError, match="must not decrease"):
        state.update(150.0, {"T1": 1.0})
    with pytest.raises(ValueError, match="positive"):
        state.track((0.0,))
