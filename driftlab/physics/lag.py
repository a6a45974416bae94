"""The first-order lag of sampled readings: the one lag filter of driftlab.

The thesis observed every thermocouple and every thermal error to respond to a heat source as a
first-order lag in time (ch. 2.3, after Okushima et al., 1975; ch. 5.3, Fig. 5.4). A lagged
temperature ``L`` of a reading ``u`` with time constant ``tau`` obeys

    tau dL/dt = u(t) - L(t)

Readings are samples; between two samples the input is taken as held at the newer one (the value
the scanning card reports for the interval that ends at it, and all an on-line compensator has at
that instant). For an input held constant over a step of length ``d`` the equation has the exact
solution (the thermal network's step, ``physics.thermal.propagate``, with a zero ramp slope):

    L(t + d) = a L(t) + (1 - a) u(t + d),    a = exp(-d / tau)

which holds for any ``d``: uneven scans and gaps need no resampling and there is no stability limit.
The filter starts settled (``L = u`` at the first sample) unless a start value is given.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np


def first_order_lag(u: np.ndarray, t_s: np.ndarray, tau_s: float, y0: np.ndarray | float | None = None) -> np.ndarray:
    """Return the first-order lag (time constant ``tau_s``) of samples ``u`` taken at times ``t_s``.

    ``u`` holds samples along axis 0 (any trailing shape, filtered column by column); ``t_s`` is
    increasing. The result has the shape of ``u``.
    """
    x = np.asarray(u, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if x.shape[:1] != t.shape:
        raise ValueError(f"first_order_lag: {x.shape[0] if x.ndim else 0} samples but {t.size} times")
    if not tau_s > 0:
        raise ValueError(f"first_order_lag: time constant must be positive, got {tau_s}")
    if x.shape[0] == 0:
        return x.copy()
    flat = x.reshape(x.shape[0], -1)
    start = flat[0] if y0 is None else np.broadcast_to(np.asarray(y0, dtype=float).reshape(-1), flat.shape[1:])
    d = np.diff(t)
    if d.size and np.any(d < 0):
        raise ValueError("first_order_lag: times must not decrease")
    if d.size and np.allclose(d, d[0], rtol=1e-9, atol=0.0):
        # even steps: the recursion runs in compiled code
        # (imported here: scipy.signal is large, and a compensator's snapshots never lag)
        from scipy.signal import lfilter

        a = float(np.exp(-d[0] / tau_s))
        out = np.empty_like(flat)
        out[0] = start
        if flat.shape[0] > 1:
            out[1:], _ = lfilter([1.0 - a], [1.0, -a], flat[1:], axis=0, zi=(a * start)[None, :])
        return out.reshape(x.shape)
    a_k = np.exp(-d / tau_s)
    out = np.empty_like(flat)
    out[0] = start
    for k in range(1, flat.shape[0]):
        out[k] = a_k[k - 1] * out[k - 1] + (1.0 - a_k[k - 1]) * flat[k]
    return out.reshape(x.shape)


def first_order_lag_even(u: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """Return :func:`first_order_lag` of samples ``u`` taken every ``dt_s`` seconds (settled start)."""
    x = np.asarray(u, dtype=float)
    return first_order_lag(x, np.arange(x.shape[0]) * float(dt_s), tau_s)


class LagState:
    """:func:`first_order_lag` one scan at a time: the state a live compensator keeps between readings.

    Each scan ``u`` at time ``t`` advances every tracked lag by the exact step of the module docstring,
    ``L <- a L + (1 - a) u`` with ``a = exp(-(t - t_prev) / tau)``, so a run of :meth:`update` calls
    gives what :func:`first_order_lag` gives over the same samples. A lag starts settled (``L = u``)
    at the first scan after its time constant is asked for (:meth:`track`), as the filter does at
    its first sample.
    """

    def __init__(self, taus_s: tuple[float, ...] = ()) -> None:
        self._taus: set[float] = set()
        self._values: dict[tuple[str, float], float] = {}
        self._t: float | None = None
        self._last: dict[str, float] = {}
        self.track(taus_s)

    def track(self, taus_s: tuple[float, ...] | set[float]) -> None:
        """Follow these time constants too (each channel's lag starts settled at its latest reading)."""
        for tau in taus_s:
            if not tau > 0:
                raise ValueError(f"LagState: time constant must be positive, got {tau}")
            tau = float(tau)
            if tau not in self._taus:
                self._taus.add(tau)
                for c, u in self._last.items():
                    self._values[(c, tau)] = u

    def update(self, t_s: float, readings: Mapping[str, float]) -> None:
        """Advance every lag to scan time ``t_s`` with the scan's ``readings`` (held since the previous scan)."""
        t = float(t_s)
        if self._t is not None and t < self._t:
            raise ValueError("LagState: times must not decrease")
        d = 0.0 if self._t is None else t - self._t
        for c, raw in readings.items():
            u = float(raw)
            if not math.isfinite(u):
                continue  # a missing reading: the lag keeps its state (the input is unknown)
            for tau in self._taus:
                key = (c, tau)
                prev = self._values.get(key)
                if prev is None:
                    self._values[key] = u
                else:
                    a = math.exp(-d / tau)
                    self._values[key] = a * prev + (1.0 - a) * u
            self._last[c] = u
        self._t = t

    def values(self) -> dict[tuple[str, float], float]:
        """Return {(channel, tau): lagged reading} as of the last scan."""
        return dict(self._values)


class LaggedReadings(dict[str, float]):
    """One scan of readings (channel -> degC) that also carries the lags of its channels up to it.

    ``lagged`` maps (channel, tau_s) to the lagged reading (same units as the readings), as a
    :class:`LagState` kept over the scans before it gives. A model's ``lag`` term evaluated on a
    plain snapshot has no history and takes the lag as settled (equal to the reading); on these
    readings it takes the lag the history gives.
    """

    def __init__(self, readings: Mapping[str, float], lagged: Mapping[tuple[str, float], float]) -> None:
        super().__init__(readings)
        self.lagged: dict[tuple[str, float], float] = dict(lagged)
