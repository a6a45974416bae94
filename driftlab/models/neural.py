"""The neural-network comparison (ch. 6.4.1, 6.6): scaled inputs (eq. 6.3), sigmoidal hidden layers, linear output."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from sklearn.neural_network import MLPRegressor

from driftlab.errors import ValidationError


def scale_inputs(X: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Return inputs mapped to [-0.9, 0.9] over the training range (eq. 6.3)."""
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    return 1.8 * (np.asarray(X, float) - lo) / span - 0.9


@dataclass
class NeuralModel:
    """A trained network with the training range of its inputs (to know when it extrapolates)."""

    inputs: list[str]
    lo: np.ndarray
    hi: np.ndarray
    y_mean: float
    y_scale: float
    net: MLPRegressor

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """Return the network's estimate (eqs. 6.4-6.6) for the rows of ``X``."""
        from threadpoolctl import threadpool_limits

        Z = scale_inputs(X[self.inputs].to_numpy(float), self.lo, self.hi)
        with threadpool_limits(limits=1):
            return self.y_mean + self.y_scale * self.net.predict(Z)

    def outside_training_range(self, X: pd.DataFrame) -> np.ndarray:
        """Return a boolean per row: True where any input is beyond its training range."""
        A = X[self.inputs].to_numpy(float)
        return np.any((A < self.lo) | (A > self.hi), axis=1)


def fit_network(
    X: pd.DataFrame,
    y: np.ndarray,
    *,
    hidden: Sequence[int] = (30, 15, 7),
    max_samples: int = 10_000,
    seed: int = 0,
    max_iter: int = 400,
) -> NeuralModel:
    """Return a network trained on up to ``max_samples`` random rows (ch. 6.6: 30-15-7 tanh nodes)."""
    y = np.asarray(y, float)
    if len(X) != y.size or y.size < 20:
        raise ValidationError("the network needs at least 20 samples with matching inputs")
    rng = np.random.default_rng(seed)
    idx = rng.choice(y.size, size=min(max_samples, y.size), replace=False)
    A = X.to_numpy(float)
    lo, hi = A.min(axis=0), A.max(axis=0)
    y_mean, y_scale = float(y.mean()), float(y.std()) or 1.0
    # tanh is eq. 6.5 up to a factor 2 in the argument; lbfgs stands in for Levenberg-Marquardt (eq. 6.7)
    net = MLPRegressor(
        hidden_layer_sizes=tuple(hidden),
        activation="tanh",
        solver="lbfgs",
        max_iter=max_iter,
        alpha=1e-5,
        random_state=seed,
        tol=1e-7,
    )
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    from threadpoolctl import threadpool_limits

    # small dense products: one BLAS thread is fastest, and keeps a shared machine responsive
    with warnings.catch_warnings(), threadpool_limits(limits=1):
        warnings.simplefilter("ignore", ConvergenceWarning)
        net.fit(scale_inputs(A[idx], lo, hi), (y[idx] - y_mean) / y_scale)
    return NeuralModel(list(X.columns), lo, hi, y_mean, y_scale, net)


@dataclass
class ExtrapolationResult:
    """The ch. 6.6 experiment: both models scored on data beyond the training range."""

    regression_mm: float
    network_mm: float
    regression_in_range_mm: float
    network_in_range_mm: float
    shift_degC: float
    n: int

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form of the report's ``extrapolation`` field."""
        return {
            "regression_mm": self.regression_mm,
            "network_mm": self.network_mm,
            "regression_in_range_mm": self.regression_in_range_mm,
            "network_in_range_mm": self.network_in_range_mm,
            "shift_degC": self.shift_degC,
            "n": self.n,
        }


def _rms(x: np.ndarray) -> float:
    """Return the root mean square."""
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def extrapolation_errors(
    y_in: np.ndarray,
    reg_in: np.ndarray,
    net_in: np.ndarray,
    y_out: np.ndarray,
    reg_out: np.ndarray,
    net_out: np.ndarray,
    shift_degC: float,
) -> ExtrapolationResult:
    """Return the RMS prediction errors of both models in and beyond the training range."""
    return ExtrapolationResult(
        regression_mm=_rms(np.asarray(y_out) - reg_out),
        network_mm=_rms(np.asarray(y_out) - net_out),
        regression_in_range_mm=_rms(np.asarray(y_in) - reg_in),
        network_in_range_mm=_rms(np.asarray(y_in) - net_in),
        shift_degC=float(shift_degC),
        n=int(len(y_out)),
    )
