"""Model documents: their schema (pydantic), validation and prediction without the training data.

Pure: storing and listing versions is ``driftlab.jobs.registry``, which joins documents and the store.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from typing import Any, Final, Literal, TypeAlias

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from driftlab.errors import ValidationError
from driftlab.jsonsafe import strict_json
from driftlab.models.envelope import Envelope
from driftlab.models.features import Feature, Inputs, design_matrix, required_lags
from driftlab.physics.kinematics import ELEMENTS, PARAMS, TABLE_A1, ElementErrors, parameter_jacobian, workspace_error
from driftlab.physics.lag import first_order_lag
from driftlab.physics.thermal import ALPHA_C

MODEL_FORMAT: Final = "driftlab-model/1"


class _Doc(BaseModel):
    """Base of document parts: unknown keys are an error, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class InputRange(_Doc):
    """A model input: its reference temperature (dT = T - reference) and the range seen in training."""

    reference: float
    min: float
    max: float

    @model_validator(mode="after")
    def _ordered(self) -> InputRange:
        """Require finite numbers and min <= max (the compensator's extrapolation guard reads them)."""
        if not all(math.isfinite(v) for v in (self.reference, self.min, self.max)):
            raise ValueError("input reference, min and max must be finite")
        if self.min > self.max:
            raise ValueError(f"input range min {self.min:g} is above max {self.max:g}")
        return self


class FeatureDoc(_Doc):
    """A regression term as stored (see ``driftlab.models.features.Feature``)."""

    kind: str
    name: str
    channels: list[str] = Field(default_factory=list)
    power: int = 1
    tau_s: float | None = None
    label: str = ""

    def feature(self) -> Feature:
        """Return the live feature."""
        return Feature.from_dict(self.model_dump())


class JointCovarianceDoc(_Doc):
    """The covariance of the link models' coefficients across terms (the joint adjustment, issue 21.4)."""

    #: one per coefficient: [element, param, feature name]
    columns: list[tuple[str, str, str]]
    matrix: list[list[float]]

    @model_validator(mode="after")
    def _square(self) -> JointCovarianceDoc:
        """Require one row and one column per named coefficient."""
        n = len(self.columns)
        if len(self.matrix) != n or any(len(r) != n for r in self.matrix):
            raise ValueError(f"joint_covariance: the matrix must be {n} x {n}, one row per column")
        return self


class SubstitutionDoc(_Doc):
    """A faulty channel replaced from ``since`` by a linear estimate from its neighbours (diagnosis sensor_fault)."""

    channel: str
    neighbours: list[str]
    coef: list[float]  # intercept first, then one per neighbour
    since: datetime
    start_s: float | None = None
    mode: str = ""

    @model_validator(mode="after")
    def _shape(self) -> SubstitutionDoc:
        """Require one coefficient per neighbour plus the intercept, and an aware time."""
        if len(self.coef) != len(self.neighbours) + 1:
            raise ValueError(
                f"substitution of {self.channel}: {len(self.neighbours)} neighbours need "
                f"{len(self.neighbours) + 1} coefficients"
            )
        if self.channel in self.neighbours:
            raise ValueError(f"substitution of {self.channel} reads itself")
        if self.since.tzinfo is None:
            raise ValueError(f"substitution of {self.channel}: since needs a time zone")
        return self


class TermStatistics(_Doc):
    """The statistics of one term model (tables 6.1/6.2): training and held-out figures."""

    rmse_train: float
    rmse_holdout: float | None = None
    r2: float | None = None
    f: float | None = None
    n_train: int = 0
    n_holdout: int = 0
    condition_number: float | None = None


class TermDoc(_Doc):
    """The model of one parameter of one link or joint: terms, coefficients and their statistics."""

    element: str
    param: str
    axis: str | None = None
    term: str | None = None
    features: list[FeatureDoc]
    coefficients: list[float]
    std_errors: list[float] = Field(default_factory=list)
    p_values: list[float] = Field(default_factory=list)
    statistics: TermStatistics
    steps: list[dict[str, Any]] = Field(default_factory=list)
    #: optional (documents before issue 21 have none): the coefficients' covariance (one row per feature)
    #: and the residual variance of the parameter, for a prediction interval sqrt(x' C x + residual variance)
    covariance: list[list[float]] | None = None
    residual_variance: float | None = None

    @field_validator("element", "param")
    @classmethod
    def _known(cls, v: str, info: ValidationInfo) -> str:
        """Require a chain element name (``element``) and an error-parameter name (``param``)."""
        names, what = (ELEMENTS, "element") if info.field_name == "element" else (PARAMS, "parameter")
        if v not in names:
            raise ValueError(f"unknown {what} {v!r}")
        return v

    @model_validator(mode="after")
    def _lengths(self) -> TermDoc:
        """Require one coefficient per feature."""
        if len(self.coefficients) != len(self.features):
            raise ValueError(
                f"{self.element}.{self.param}: {len(self.features)} features, {len(self.coefficients)} coefficients"
            )
        for f in self.features:
            f.feature()
        if self.covariance is not None and (
            len(self.covariance) != len(self.features) or any(len(r) != len(self.features) for r in self.covariance)
        ):
            raise ValueError(f"{self.element}.{self.param}: covariance must be one row and column per feature")
        return self


class ModelDocument(_Doc):
    """A fitted thermal-error model of one machine: what the compensator consumes."""

    format: Literal["driftlab-model/1"] = MODEL_FORMAT
    machine: str = Field(min_length=1)
    version: int | None = None
    created_at: str = ""
    source_campaigns: list[Any] = Field(default_factory=list)
    kept_channels: list[str] = Field(default_factory=list)
    inputs: dict[str, InputRange]
    dims: dict[str, list[float]] = Field(default_factory=lambda: {k: list(v) for k, v in TABLE_A1.items()})
    alpha_c_per_degC: float = ALPHA_C  # ch. 3.5
    terms: list[TermDoc]
    screening: dict[str, Any] = Field(default_factory=dict)
    validation: list[dict[str, Any]] = Field(default_factory=list)
    physical: list[dict[str, Any]] = Field(default_factory=list)
    #: table 6.3's status (``compared``, ``no geometry``, ``conflicting geometry``) and the geometry it used
    physical_check: dict[str, Any] | None = None
    virtual_sensors: list[dict[str, Any]] = Field(default_factory=list)
    #: the ch. 6.6 experiment of documents written before the fair comparison (read, never written now)
    extrapolation: dict[str, Any] | None = None
    #: the neural-network comparison: per target fixed in advance, both extrapolation directions
    neural_comparison: list[dict[str, Any]] | None = None
    allocation: list[dict[str, Any]] = Field(default_factory=list)
    #: days of drift terms (``days[X]``) count from here (the first training campaign's start)
    time_origin: datetime | None = None
    #: faulty channels replaced by their virtual-sensor estimates (applied before dT)
    substitutions: list[SubstitutionDoc] = Field(default_factory=list)
    #: the diagnosis findings folded into this model and what became of each
    findings: list[dict[str, Any]] = Field(default_factory=list)
    #: per measured line, the form that won (link models alone, or plus a line correction) and why
    lines: list[dict[str, Any]] = Field(default_factory=list)
    #: where the machine may go and what a correction may be (``models.envelope``); None in older documents
    envelope: Envelope | None = None
    #: the coefficients' covariance across terms (None in older documents: terms then taken independent)
    joint_covariance: JointCovarianceDoc | None = None

    @model_validator(mode="after")
    def _consistent(self) -> ModelDocument:
        """Require every channel a term reads to be a declared input, and one model per element parameter."""
        seen: set[tuple[str, str]] = set()
        for t in self.terms:
            key = (t.element, t.param)
            if key in seen:
                raise ValueError(f"two models for {t.element}.{t.param}")
            seen.add(key)
            for f in t.features:
                for c in f.channels:
                    if c not in self.inputs:
                        raise ValueError(f"{t.element}.{t.param} reads {c}, which is not among the inputs")
                if f.kind == "time" and self.time_origin is None:
                    raise ValueError(f"{t.element}.{t.param}: drift term {f.name} needs time_origin")
        if self.time_origin is not None and self.time_origin.tzinfo is None:
            raise ValueError("time_origin needs a time zone")
        subs = [s.channel for s in self.substitutions]
        for s in self.substitutions:
            for c in (s.channel, *s.neighbours):
                if c not in self.inputs:
                    raise ValueError(f"substitution of {s.channel} reads {c}, which is not among the inputs")
            if set(s.neighbours) & set(subs):
                raise ValueError(f"substitution of {s.channel} reads another substituted channel")
        for k, v in self.dims.items():
            if len(v) != 3:
                raise ValueError(f"dims[{k}] must be (a, b, c)")
        return self


def validate_document(doc: Mapping[str, Any] | ModelDocument) -> ModelDocument:
    """Return the validated document, or raise ValidationError with a one-line reason."""
    if isinstance(doc, ModelDocument):
        return doc
    try:
        return ModelDocument.model_validate(dict(doc))
    except Exception as exc:  # pydantic.ValidationError -> one line
        first = str(exc).splitlines()
        raise ValidationError(f"model document: {' '.join(first[:3])}") from None


def document_json(doc: ModelDocument) -> dict[str, Any]:
    """Return the JSON-ready form of a document (NaN statistics become null)."""
    return strict_json(doc.model_dump(mode="json"))


def now_iso() -> str:
    """Return the current UTC time as ISO 8601."""
    return datetime.now(UTC).isoformat(timespec="seconds")


# ----------------------------------------------------------------------------- prediction


#: when a prediction is made: a datetime (naive = UTC), an ISO 8601 text or POSIX seconds, one for all
#: poses or one per pose (a sequence, array, Series or Index; numpy datetime64 taken as UTC); None: no time
TimeLike: TypeAlias = (
    datetime | str | float | np.floating | np.ndarray | pd.Series | pd.Index | Sequence[datetime | str | float] | None
)


def _times(at: TimeLike, n: int) -> np.ndarray | None:
    """Return POSIX seconds (n,) from a datetime, datetimes or POSIX seconds (None stays None)."""
    if at is None:
        return None

    def stamp(x: datetime | str | float | np.floating | np.integer) -> float:
        if isinstance(x, datetime):
            return (x if x.tzinfo else x.replace(tzinfo=UTC)).timestamp()
        if isinstance(x, str):
            return stamp(datetime.fromisoformat(x.replace("Z", "+00:00")))
        return float(x)

    if isinstance(at, (datetime, str, int, float, np.floating, np.integer)):
        v = np.array([stamp(at)])
    elif np.asarray(at).dtype.kind == "M":  # numpy datetime64 (taken as UTC)
        v = np.asarray(at).astype("datetime64[us]").astype(np.int64).ravel() / 1e6
    else:
        items = at.tolist() if isinstance(at, (np.ndarray, pd.Series, pd.Index)) else at
        v = np.array([stamp(x) for x in items], float)
    if v.size == 1:
        return np.repeat(v, n)
    if v.size != n:
        raise ValidationError(f"{v.size} times for {n} poses (give 1 or {n})")
    return v


def _substitute(doc: ModelDocument, readings: dict[str, np.ndarray], times: np.ndarray | None) -> None:
    """Replace each substituted channel (in place) by its neighbours' estimate where the time is past ``since``.

    ``readings`` holds equal-length arrays and ``times`` (POSIX s) one per row. Without times the
    substitution applies everywhere: the channel was faulty when the model was fitted and is taken
    to be so still.
    """
    for s in doc.substitutions:
        est = float(s.coef[0]) + sum(float(k) * readings[c] for c, k in zip(s.neighbours, s.coef[1:]))
        if times is None or s.channel not in readings:
            readings[s.channel] = np.asarray(est, float)
        else:
            readings[s.channel] = np.where(times >= s.since.timestamp(), est, readings[s.channel])


def _inputs(
    doc: ModelDocument, temperatures: Mapping[str, float] | pd.DataFrame, n: int, at: TimeLike = None
) -> Inputs:
    """Return the dT inputs (and lags over a frame's history, days for drift terms) for ``n`` poses."""
    ref = {c: r.reference for c, r in doc.inputs.items()}
    lags = sorted({lag for t in doc.terms for lag in required_lags(f.feature() for f in t.features)})
    times = _times(at, n)
    subs = {s.channel for s in doc.substitutions}
    # a substituted channel may be absent (an open thermocouple) where its estimate replaces it
    optional = subs if times is None or all(np.all(times >= s.since.timestamp()) for s in doc.substitutions) else set()
    if isinstance(temperatures, pd.DataFrame):
        missing = [c for c in ref if c not in temperatures.columns and c not in optional]
        if missing:
            raise ValidationError(f"temperatures lack model input(s) {', '.join(missing)}")
        frame = temperatures
        if len(frame) not in (1, n):
            raise ValidationError(f"{len(frame)} temperature rows for {n} poses (give 1 or {n})")
        readings = {c: frame[c].to_numpy(float) for c in ref if c in frame.columns}
        if subs:
            _substitute(doc, readings, times if len(frame) == n else (None if times is None else times[:1]))
        dT = pd.DataFrame({c: readings[c] - ref[c] for c in ref})
        lagged: dict[tuple[str, float], np.ndarray] = {}
        # the lags of a longer history than these rows (compensator.TemperatureTable.nearest), else
        # the lags over the rows themselves (ch. 5.3); a substituted channel is lagged on its estimate
        history = frame.attrs.get("lagged") or {}
        if lags and history:
            for c, tau in lags:
                if (c, tau) in history and c not in subs:
                    lagged[(c, tau)] = np.asarray(history[(c, tau)], float) - ref[c]
        if lags and "time_s" in frame.columns and len(frame) > 1:
            t = frame["time_s"].to_numpy(float)
            for c, tau in lags:
                if (c, tau) not in lagged:
                    lagged[(c, tau)] = first_order_lag(dT[c].to_numpy(), t, tau)
    else:
        missing = [c for c in ref if c not in temperatures and c not in optional]
        if missing:
            raise ValidationError(f"temperatures lack model input(s) {', '.join(missing)}")
        readings = {c: np.array([float(temperatures[c])]) for c in ref if c in temperatures}
        if subs:
            _substitute(doc, readings, None if times is None else times[:1])
        dT = pd.DataFrame({c: readings[c] - ref[c] for c in ref})
        # a scan that carries its history's lags (physics.lag.LaggedReadings, kept by a live
        # compensator); a plain snapshot has none and its lags are taken settled. A substituted
        # channel's lag is not its faulty reading's: it stays settled on the estimate.
        history = getattr(temperatures, "lagged", None) or {}
        lagged = {
            (c, tau): np.array([float(history[(c, tau)]) - ref[c]])
            for c, tau in lags
            if (c, tau) in history and c not in subs
        }
    if not np.all(np.isfinite(dT.to_numpy(float))):
        raise ValidationError("temperatures contain missing readings: substitute virtual-sensor estimates first")
    if len(dT) == 1 and n > 1:
        dT = pd.DataFrame({c: np.repeat(dT[c].to_numpy(), n) for c in dT.columns})
        lagged = {k: np.repeat(v, n) for k, v in lagged.items()}
    days = None
    if doc.time_origin is not None and any(f.kind == "time" for t in doc.terms for f in t.features):
        t_s = times if times is not None else np.full(n, datetime.now(UTC).timestamp())
        days = (t_s - doc.time_origin.timestamp()) / 86400.0
    return Inputs(dT=dT, lagged=lagged, days=days)


def _directions(direction: np.ndarray | None, n: int) -> np.ndarray:
    """Return (N, 5) approach directions (+1/-1; 0 = mean of both) from None, (N,) or (N, 5)."""
    if direction is None:
        return np.zeros((n, 5))
    d = np.asarray(direction, float)
    if d.ndim == 2:
        if d.shape != (n, 5):
            raise ValidationError(f"direction must be (N,) or (N, 5), got {d.shape}")
        return d
    return np.repeat(np.broadcast_to(d, (n,))[:, None], 5, axis=1)


def predict_element_errors(
    document: Mapping[str, Any] | ModelDocument,
    temperatures: Mapping[str, float] | pd.DataFrame,
    q: np.ndarray,
    direction: np.ndarray | None = None,
    *,
    at: TimeLike = None,
) -> dict[str, np.ndarray]:
    """Return the (N, 6) errors of every modelled link and joint at poses ``q`` (N, 5) and these temperatures.

    ``temperatures`` is one reading per input channel (a mapping, or a one-row frame) or a frame of
    N rows aligned with ``q`` (with ``time_s`` for lagged terms; without it lags are taken settled).
    ``direction`` is +1/-1 per pose (N,) or per pose and axis (N, 5); None means the mean of both.
    ``at`` is the wall-clock time of the readings (a datetime, ISO string or POSIX seconds; one, or
    one per pose): drift terms (``days[X]``) count days from the document's ``time_origin`` to it
    (default: now), and substituted channels (``substitutions``) are replaced from their ``since`` on
    (default: everywhere).
    """
    doc = validate_document(document)
    q = np.atleast_2d(np.asarray(q, float))
    if q.ndim != 2 or q.shape[1] != 5:
        raise ValidationError(f"q must be (N, 5), got {q.shape}")
    n = q.shape[0]
    inp = _inputs(doc, temperatures, n, at)
    d = _directions(direction, n)
    out: dict[str, np.ndarray] = {}
    for t in doc.terms:
        feats = [f.feature() for f in t.features]
        X = design_matrix(feats, inp, q, d)
        arr = out.setdefault(t.element, np.zeros((n, 6)))
        arr[:, PARAMS.index(t.param)] += X.to_numpy(float) @ np.asarray(t.coefficients, float)
    return out


def document_dims(doc: ModelDocument) -> dict[str, tuple[float, float, float]]:
    """Return the kinematic link dimensions stored in a document."""
    dims = {k: tuple(v) for k, v in TABLE_A1.items()}
    dims.update({k: tuple(float(x) for x in v) for k, v in doc.dims.items()})
    return dims  # type: ignore[return-value]


def predict_workspace_errors(
    document: Mapping[str, Any] | ModelDocument,
    temperatures: Mapping[str, float] | pd.DataFrame,
    q: np.ndarray,
    direction: np.ndarray | None = None,
    *,
    at: TimeLike = None,
) -> np.ndarray:
    """Return the (N, 6) work-space errors the model predicts at poses ``q`` (through the HTM chain, eq. 4.12)."""
    doc = validate_document(document)
    errors: ElementErrors = predict_element_errors(doc, temperatures, q, direction, at=at)
    return workspace_error(np.atleast_2d(np.asarray(q, float)), errors, document_dims(doc))


def input_ranges(doc: ModelDocument, temperatures: Mapping[str, float] | pd.DataFrame) -> list[str]:
    """Return the channels whose readings lie outside the training range (the model extrapolates there)."""
    out = []
    for c, r in doc.inputs.items():
        v = np.asarray(temperatures[c], float)
        if np.any(v < r.min) or np.any(v > r.max):
            out.append(c)
    return out


def predict_workspace_sd(
    document: Mapping[str, Any] | ModelDocument,
    temperatures: Mapping[str, float] | pd.DataFrame,
    q: np.ndarray,
    direction: np.ndarray | None = None,
    *,
    at: TimeLike = None,
    residual: bool = True,
) -> np.ndarray | None:
    """Return the (N, 6) standard deviation of the predicted work-space errors, or None when the document has none.

    Each coefficient's effect is carried to the work space through the chain to first order (eq. 4.12:
    dW/dp_e at the pose times the term's regressor, evaluated as in ``predict_workspace_errors``). With
    the document's ``joint_covariance`` the coefficients of all terms are taken together (g' C g per
    point and component); the terms' own covariances give what it does not cover (the lines'
    corrections, fitted apart: independent), and documents without it are taken term by term,
    independent of each other. With ``residual``, the largest residual variance of the terms of each
    parameter is added (what the model leaves: the error of one reading, not of the correction alone).
    A prediction interval is the prediction +- z times this.
    """
    doc = validate_document(document)
    if not any(t.covariance is not None for t in doc.terms) and doc.joint_covariance is None:
        return None
    q = np.atleast_2d(np.asarray(q, float))
    n = q.shape[0]
    inp = _inputs(doc, temperatures, n, at)
    d = _directions(direction, n)
    dims = document_dims(doc)
    joint = doc.joint_covariance
    where = {tuple(c): i for i, c in enumerate(joint.columns)} if joint is not None else {}
    G = np.zeros((n, 6, len(where)))  # dW / d coefficient of every jointly estimated column
    C_joint = np.asarray(joint.matrix, float) if joint is not None else np.zeros((0, 0))
    var = np.zeros((n, 6))
    resid = np.zeros(6)
    for t in doc.terms:
        k = PARAMS.index(t.param)
        if t.residual_variance is not None:
            resid[k] = max(resid[k], float(t.residual_variance))
        X = design_matrix([f.feature() for f in t.features], inp, q, d).to_numpy(float)
        J = parameter_jacobian(q, t.element, k, dims)
        cols = [where.get((t.element, t.param, f.name)) for f in t.features]
        for j, c in enumerate(cols):
            if c is not None:
                G[:, :, c] += J * X[:, j : j + 1]
        if t.covariance is None:
            continue
        C = np.asarray(t.covariance, float)
        own = np.array([c is None for c in cols])
        # what the joint covariance does not hold: the term's own coefficients apart from it, and what a
        # line's correction added to a jointly estimated coefficient (its variance on the diagonal)
        extra = np.where(own[:, None] & own[None, :], C, 0.0)
        for j, c in enumerate(cols):
            if c is not None:
                extra[j, j] = max(C[j, j] - C_joint[c, c], 0.0)
        v = np.clip(np.einsum("ij,jk,ik->i", X, extra, X), 0.0, None)
        var += J**2 * v[:, None]
    if len(where):
        var += np.clip(np.einsum("ncj,jk,nck->nc", G, C_joint, G, optimize=True), 0.0, None)
    if residual:
        var += resid[None, :]
    return np.sqrt(var)
