"""First-order thermal network, solved exactly per time step (exponential integrator).

Each node i obeys ``tau_i dT_i/dt = h_i(t) + r_i(t) - T_i`` - the first-order lag that the thesis
observed at every thermocouple (ch. 5.3, Fig. 5.4: "the temperature's response to a heat source
can be seen as a first order lag function in time"), where

* ``h_i`` is the *held* drive: the steady rise from heat sources, ``sum_j G_ij u_j``, constant over
  a step (heat sources switch at stage boundaries on the grid);
* ``r_i`` is the *ramped* drive: exogenous air temperatures and upstream nodes (``sum_k C_ik T_k``,
  a directed acyclic coupling, e.g. machine sites following the room air sites), linear between
  grid samples.

For such inputs the ODE has a closed-form solution over a step of length ``d`` with
``a = exp(-d / tau)`` and ramp slope ``s``:

    T(t + d) = a T(t) + (1 - a) (h + r(t)) + s d - tau s (1 - a)

which is exact for any ``d`` (no stability limit), so the grid can be coarse and any instant
between grid points is evaluated exactly too. The recursion along time runs in compiled code
(``scipy.signal.lfilter``), vectorised over time; Python loops only over nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: ch. 3.5: typical coefficient of thermal expansion of the machine's castings and steel (/degC)
ALPHA_C = 12.1e-6


def step_response(t_s: np.ndarray, gain: float, tau_s: float) -> np.ndarray:
    """Return the analytic first-order step response gain * (1 - exp(-t / tau)) for t >= 0."""
    t = np.asarray(t_s, dtype=float)
    return np.where(t >= 0.0, gain * -np.expm1(-np.maximum(t, 0.0) / tau_s), 0.0)


def propagate(
    y0: np.ndarray, tau_s: np.ndarray, d_s: np.ndarray, hold: np.ndarray, ramp0: np.ndarray, slope: np.ndarray
) -> np.ndarray:
    """Return T after an exact step of length d from y0 (held drive, ramp starting at ramp0 with slope)."""
    tau = np.asarray(tau_s, dtype=float)
    d = np.asarray(d_s, dtype=float)
    one_minus_a = -np.expm1(-d / tau)  # 1 - exp(-d/tau), accurate for small d
    a = 1.0 - one_minus_a
    # closed-form solution of tau y' = h + r0 + s t - y over [0, d]
    return a * y0 + one_minus_a * (hold + ramp0) + slope * d - tau * slope * one_minus_a


def integrate(
    tau_s: np.ndarray, h_s: float, hold: np.ndarray, ramp: np.ndarray, y0: np.ndarray | None = None
) -> np.ndarray:
    """Return (N, n) node temperatures on a uniform grid of step h from drives hold (N, n), ramp (N, n).

    ``hold[k]`` acts over [t_k, t_k + h); ``ramp`` is linear between samples; ``y0`` defaults to the
    steady state of the first sample.
    """
    from scipy.signal import lfilter  # here: scipy.signal is large, and most users of ALPHA_C never filter

    tau = np.atleast_1d(np.asarray(tau_s, dtype=float))
    hold = np.asarray(hold, dtype=float).reshape(len(hold), -1)
    ramp = np.asarray(ramp, dtype=float).reshape(len(ramp), -1)
    n_t, n = ramp.shape
    if hold.shape != (n_t, n) or tau.shape != (n,):
        raise ValueError(f"integrate: shapes hold {hold.shape}, ramp {ramp.shape}, tau {tau.shape} disagree")
    if y0 is None:
        y0 = hold[0] + ramp[0]
    out = np.empty((n_t, n))
    if n_t == 0:
        return out
    slope = np.diff(ramp, axis=0) / h_s
    one_minus_a = -np.expm1(-h_s / tau)
    a = 1.0 - one_minus_a
    # forcing of the recursion y[k+1] = a y[k] + f[k] (the exact step above with y0 = 0)
    f = one_minus_a * (hold[:-1] + ramp[:-1]) + slope * h_s - tau * slope * one_minus_a
    z = np.empty((n_t, n))
    z[0] = y0
    z[1:] = f
    for i in range(n):
        out[:, i] = lfilter([1.0], [1.0, -a[i]], z[:, i])
    return out


@dataclass(frozen=True)
class ThermalSolution:
    """Node temperatures on a uniform grid plus the drives, evaluable exactly at any instant."""

    t0_s: float
    h_s: float
    tau_s: np.ndarray  # (n,)
    y: np.ndarray  # (N, n) temperatures at t0 + k h
    hold: np.ndarray  # (N, n) held drive over [t_k, t_k + h)
    ramp: np.ndarray  # (N, n) ramped drive at t_k

    @property
    def t_end_s(self) -> float:
        """Return the last grid instant."""
        return self.t0_s + (len(self.y) - 1) * self.h_s

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """Return (M, n) temperatures at instants t (exact within the grid's drive model)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if t.size and (t.min() < self.t0_s - 1e-9 or t.max() > self.t_end_s + 1e-9):
            raise ValueError(f"t outside the solved span [{self.t0_s}, {self.t_end_s}] s")
        pos = (t - self.t0_s) / self.h_s
        k = np.clip(np.floor(pos + 1e-9).astype(np.int64), 0, max(len(self.y) - 2, 0))
        d = np.clip(t - (self.t0_s + k * self.h_s), 0.0, None)[:, None]
        if len(self.y) == 1:
            return np.repeat(self.y[:1], len(t), axis=0)
        slope = (self.ramp[k + 1] - self.ramp[k]) / self.h_s
        return propagate(self.y[k], self.tau_s, d, self.hold[k], self.ramp[k], slope)


@dataclass(frozen=True)
class ThermalNetwork:
    """Nodes with time constants, source gains, exogenous weights and acyclic upstream coupling."""

    names: tuple[str, ...]
    tau_s: np.ndarray  # (n,)
    source_gain: np.ndarray  # (n, m): steady degC rise per unit of each held source
    exo_gain: np.ndarray  # (n, e): weight of each exogenous (ramped) temperature
    coupling: np.ndarray  # (n, n): weight of upstream node temperatures (ramped); must be acyclic

    def levels(self) -> list[np.ndarray]:
        """Return node indices grouped in topological order of the coupling (upstream first)."""
        n = len(self.names)
        dep = self.coupling != 0.0
        np.fill_diagonal(dep, False)
        done = np.zeros(n, dtype=bool)
        out: list[np.ndarray] = []
        while not done.all():
            ready = np.flatnonzero(~done & ~(dep & ~done[None, :]).any(axis=1))
            if ready.size == 0:
                raise ValueError("thermal network coupling has a cycle")
            out.append(ready)
            done[ready] = True
        return out

    def simulate(
        self,
        t0_s: float,
        h_s: float,
        sources: np.ndarray,
        exogenous: np.ndarray,
        y0: np.ndarray | None = None,
        local: np.ndarray | None = None,
    ) -> ThermalSolution:
        """Return the exact solution on the grid t0 + k h for held sources (N, m), exogenous ramps (N, e)
        and optional per-node ramped disturbances ``local`` (N, n)."""
        sources = np.asarray(sources, dtype=float)
        exogenous = np.asarray(exogenous, dtype=float)
        n_t, n = len(exogenous), len(self.names)
        hold = sources @ self.source_gain.T
        ramp = exogenous @ self.exo_gain.T
        if local is not None:
            ramp = ramp + np.asarray(local, dtype=float)
        y = np.zeros((n_t, n))  # unsolved levels must read as 0, not garbage, in y @ up.T
        for lev in self.levels():
            up = self.coupling[lev]
            if up.any():
                ramp[:, lev] += y @ up.T  # upstream levels are already solved
            start = None if y0 is None else np.asarray(y0, dtype=float)[lev]
            y[:, lev] = integrate(self.tau_s[lev], h_s, hold[:, lev], ramp[:, lev], start)
        return ThermalSolution(float(t0_s), float(h_s), self.tau_s.copy(), y, hold, ramp)


def driven_node(
    ramp: np.ndarray, h_s: float, tau_s: float, t0_s: float = 0.0, y0: np.ndarray | None = None
) -> ThermalSolution:
    """Return one network node (time constant tau) driven only by ``ramp`` (N,) or (N, k) on a step-h grid.

    This is how the simulator lags a continuous temperature exactly (the step above, with the input
    linear between grid samples); readings, which are samples, are lagged by ``physics.lag``.
    """
    x = np.asarray(ramp, dtype=float)
    x2 = x.reshape(len(x), -1)
    tau = np.full(x2.shape[1], float(tau_s))
    start = x2[0] if y0 is None else np.atleast_1d(np.asarray(y0, dtype=float))
    y = integrate(tau, h_s, np.zeros_like(x2), x2, start)
    return ThermalSolution(float(t0_s), float(h_s), tau, y, np.zeros_like(x2), x2)
