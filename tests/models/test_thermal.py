"""The first-order thermal network: step response, exactness against fine Euler, any-instant evaluation."""

import numpy as np
import pytest

from driftlab.models.thermal import (
    ALPHA_C,
    ThermalNetwork,
    first_order_lag,
    integrate,
    propagate,
    step_response,
)


def test_step_response_gain_and_tau():
    h, tau, gain = 60.0, 1800.0, 7.5
    t = np.arange(0, 6 * 3600 + 1, h)
    y = integrate(np.array([tau]), h, np.full((len(t), 1), gain), np.zeros((len(t), 1)), y0=np.zeros(1))[:, 0]
    np.testing.assert_allclose(y, step_response(t, gain, tau), atol=1e-12)
    k = int(tau / h)
    assert y[k] == pytest.approx(gain * (1 - np.exp(-1)), rel=1e-12)  # 63.2 % at t = tau
    assert y[-1] == pytest.approx(gain, rel=1e-4)  # steady state after 12 tau


def _euler(tau, hold_fn, ramp_fn, y0, t_end, dt):
    """Forward Euler on the continuous ODE tau y' = hold(t) + ramp(t) - y (reference)."""
    n = int(round(t_end / dt))
    y = np.array(y0, dtype=float)
    out = [y.copy()]
    for i in range(n):
        t = i * dt
        y = y + dt * (hold_fn(t) + ramp_fn(t) - y) / tau
        out.append(y.copy())
    return np.array(out)


def test_exact_integrator_matches_fine_euler():
    h = 120.0  # coarse grid: the exponential step has no stability limit
    tau = np.array([300.0, 2400.0, 9000.0])
    gains = np.array([12.0, 3.0, 0.8])
    t_end = 4 * 3600.0
    t = np.arange(0, t_end + 1, h)

    def hold(tt):  # a heat source switched on at 0.5 h, off at 2.5 h (on the grid)
        on = (np.asarray(tt) >= 1800) & (np.asarray(tt) < 9000)
        return np.multiply.outer(on.astype(float), gains)

    def ramp(tt):  # room air rising linearly by 1 degC/h
        return np.multiply.outer(20.0 + np.asarray(tt) / 3600.0, np.ones(3))

    y = integrate(tau, h, hold(t), ramp(t), y0=np.full(3, 20.0))
    dt = 0.5
    ref = _euler(tau, lambda s: hold(s), lambda s: ramp(s), np.full(3, 20.0), t_end, dt)[:: int(h / dt)]
    # Euler's own error is O(dt / tau) of the swing: ~2e-3 degC on the fastest node here
    np.testing.assert_allclose(y, ref, atol=5e-3)
    assert np.abs(y - ref).max() > 0  # a different method, not the same numbers


def test_any_instant_is_exact_between_grid_points():
    net = ThermalNetwork(
        names=("room", "a", "b"),
        tau_s=np.array([2400.0, 600.0, 5400.0]),
        source_gain=np.array([[0.0], [10.0], [2.0]]),
        exo_gain=np.array([[1.0], [0.0], [0.0]]),
        coupling=np.array([[0, 0, 0], [1.0, 0, 0], [0.5, 0.5, 0]]),  # b also warmed by a: a 3-level cascade
    )
    assert [lev.tolist() for lev in net.levels()] == [[0], [1], [2]]
    h = 60.0
    t = np.arange(0, 3 * 3600 + 1, h)
    src = ((t >= 600) & (t < 6000)).astype(float)[:, None]
    exo = (20 + 0.5 * np.sin(t / 5000.0))[:, None]
    sol = net.simulate(0.0, h, src, exo)
    np.testing.assert_allclose(sol.at(t), sol.y, atol=1e-12)  # grid points come back exactly
    mid = t[:-1] + 17.0
    at_mid = sol.at(mid)
    # the same drives on a grid four times finer (ramps interpolated linearly, holds repeated)
    fine_t = np.arange(0, t[-1] + 1, h / 4)
    ramp_fine = np.column_stack([np.interp(fine_t, t, sol.ramp[:, i]) for i in range(3)])
    hold_fine = sol.hold[np.minimum((fine_t // h).astype(int), len(t) - 1)]
    y_fine = integrate(net.tau_s, h / 4, hold_fine, ramp_fine, y0=sol.y[0])
    np.testing.assert_allclose(y_fine[::4], sol.y, atol=1e-9)  # step length does not matter
    at_fine = sol.at(fine_t)
    np.testing.assert_allclose(at_fine, y_fine, atol=1e-9)
    assert not np.allclose(at_mid, sol.y[:-1], atol=1e-3)  # really between the grid points


def test_lag_of_a_step_is_the_analytic_response():
    h, tau = 30.0, 900.0
    x = np.r_[np.zeros(10), np.ones(200)]
    lag = first_order_lag(x, h, tau, t0_s=-300.0)
    t = lag.t0_s + h * np.arange(len(x))
    # x is a ramp from 0 to 1 over [-30, 0] then constant: compare with the exact answer after it
    after = t >= 0
    t_after = t[after]
    y0 = lag.at(np.array([0.0]))[0, 0]
    np.testing.assert_allclose(lag.y[after, 0], 1 - (1 - y0) * np.exp(-t_after / tau), atol=1e-12)
    assert 0 < y0 < 0.05


def test_propagate_zero_step_and_validation():
    y0 = np.array([1.0, 2.0])
    out = propagate(y0, np.array([10.0, 20.0]), 0.0, np.array([5.0, 5.0]), np.array([3.0, 3.0]), np.array([1.0, 1.0]))
    np.testing.assert_allclose(out, y0)
    with pytest.raises(ValueError):
        integrate(np.array([1.0, 2.0]), 1.0, np.zeros((5, 3)), np.zeros((5, 3)))
    cyc = ThermalNetwork(("a", "b"), np.ones(2), np.zeros((2, 1)), np.zeros((2, 1)), np.array([[0, 1.0], [1.0, 0]]))
    with pytest.raises(ValueError, match="cycle"):
        cyc.levels()
    assert ALPHA_C == pytest.approx(12.1e-6)
