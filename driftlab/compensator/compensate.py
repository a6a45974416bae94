"""Per-block correction: model + latest temperatures -> link errors -> axis offsets (ch. 4.4, 7.2).

For every point of the program (block targets, and points inside long segments) the model
predicts the errors of the links and joints, ``physics.kinematics.compensate`` solves the axis
commands that cancel them (angles first, then translations: eqs. 4.23-4.26), and the correction
is quantised to the machine's resolution with the remainder carried over (ch. 7.2: small
corrections are accumulated until they reach a level near the positioning resolution instead of
being sent): a step goes out once the correction is more than half a step (and an optional
hysteresis) away from what was sent (``quantise_carry``).
Angles come first (eq. 4.25): their corrections go onto the angular grid with the remainder carried
over; the translations (eq. 4.26) then also take up what the angles on their grid leave at the
tool (``rotary_lever``), and go onto the linear grid the same way.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import stat
import tempfile
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from decimal import Decimal
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, NotRequired, TypeAlias, TypedDict, TypeVar

import numpy as np
import pandas as pd
from typing_extensions import Unpack

from driftlab.compensator.gcode import (
    MAX_DECIMALS,
    ROTARY,
    ParserState,
    Points,
    Program,
    count_points,
    decimals_of,
    emit,
    emit_program,
    parse_program,
    subdivide,
)
from driftlab.compensator.header import HeaderedOut
from driftlab.compensator.parsed import KeptPiece, ParsedPieces, usable
from driftlab.errors import ValidationError
from driftlab.models import document as documents
from driftlab.physics import kinematics
from driftlab.physics.lag import LaggedReadings, first_order_lag
from driftlab.vocabulary import AXES

if TYPE_CHECKING:
    from _typeshed import DataclassInstance
    from numpy.typing import ArrayLike

    from driftlab.compensator.guard import Guard
    from driftlab.models.document import ModelDocument
    from driftlab.models.envelope import Envelope

log = logging.getLogger(__name__)

_Options = TypeVar("_Options", bound="DataclassInstance")

#: positioning resolution of the thesis machine (ch. 7.2; bundle v1 ``machine.resolution_*``)
RESOLUTION_MM = 0.0025
RESOLUTION_DEG = 0.001
#: the quantiser's hysteresis beyond half a step, in steps (``quantise_carry``): 0, the nearest step.
#: Ch. 4 puts the strategy's limit at the resolution: rounding keeps every point within half a step.
#: Waiting for a full step (hysteresis 0.5, before 2026-11-27) let a drifting correction lag by up to a
#: step, half a step on average against the drift (1.25 um at 0.0025 mm); a hysteresis of 0.1 kept a
#: correction that rose past 0.6 and fell back one step high (cutting test, 9 noise seeds: 8 of 9 worse
#: than rounding, one 3.2 against 2.5 um). A hysteresis stops noise from toggling a step where the
#: correction sits at a half-way point (``--hysteresis-steps``), at that cost.
QUANTISER_HYSTERESIS = 0.0

#: one reading per channel (degC), or a frame of N rows aligned with the poses (with ``time_s``)
Temperatures: TypeAlias = Mapping[str, float] | pd.DataFrame
#: (q (N, 5) mm/rad, temperatures, direction (N, 5) +1/-1) -> link and joint errors
#: predict(q, temperatures, direction[, at=POSIX s]) -> element errors; ``at`` is passed only when known
#: (to models with time-dependent terms: the drift of ch. 6.4.3 is evaluated at the block's time)
Predict = Callable[..., kinematics.ElementErrors]


@dataclass(frozen=True)
class ErrorModel:
    """What the compensator needs from a model: a prediction of element errors and the chain's dims."""

    predict: Predict
    dims: Mapping[str, Any] = field(default_factory=lambda: dict(kinematics.TABLE_A1))
    label: str = "model"
    channels: tuple[str, ...] = ()
    machine: str = ""
    #: the temperature range (degC) each input was fitted on, and the document's machine envelope
    ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    envelope: Envelope | None = None
    #: the time constants (s) of the model's lagged terms (ch. 5.3): a live compensator keeps these
    #: lags of every reading between scans (``physics.lag.LagState``) and hands them with each scan
    lag_taus: tuple[float, ...] = ()

    @classmethod
    def from_document(cls, document: Mapping[str, Any] | ModelDocument, label: str | None = None) -> ErrorModel:
        """Return the model of a registry document (the JSON of ``driftlab models show``).

        The document's terms are linear in dT, position and direction, so they are evaluated
        here directly over numpy arrays (``fast_predict``); temperature frames with a history
        and lagged terms go through ``models.document.predict_element_errors``, which owns the lags.
        """
        doc = documents.validate_document(document)
        name = label or f"{doc.machine} v{doc.version if doc.version is not None else '?'}"
        if not doc.terms:
            raise ValidationError(f"model {name} has no terms (terms: []): it would correct nothing; refused")
        return cls(
            predict=_checked_predict(doc),
            dims=documents.document_dims(doc),
            label=name,
            channels=tuple(doc.inputs),
            machine=doc.machine,
            ranges={c: (r.min, r.max) for c, r in doc.inputs.items()},
            envelope=doc.envelope,
            lag_taus=tuple(
                sorted(
                    {float(f.tau_s) for t in doc.terms for f in t.features if f.kind in ("lag", "lever") and f.tau_s}
                )
            ),
        )


#: feature kinds ``fast_predict`` evaluates (the others go to the registry)
_FAST_KINDS = ("intercept", "position", "direction", "dT", "lag", "pos_dT", "gradient", "mean", "lever")
_AXIS_KINDS = ("position", "direction", "pos_dT", "lever")


@dataclass(frozen=True)
class _Feature:
    """One feature of a term as ``fast_predict`` evaluates it: kind, channels, power, axis column, lag tau (s)."""

    kind: str
    channels: tuple[str, ...]
    power: int
    col: int | None
    tau: float


def _fast_terms(doc: ModelDocument) -> list[tuple[str, int, list[_Feature], list[float]]]:
    """Return (element, parameter index, features, coefficients) of every term; refuse what the registry must do."""
    if getattr(doc, "substitutions", None):
        raise ValidationError("substituted channels are evaluated by the registry")
    terms = []
    for t in doc.terms:
        feats = []
        for f in t.features:
            if f.kind not in _FAST_KINDS:
                raise ValidationError(f"feature kind {f.kind} is evaluated by the registry")
            col = AXES.index(f.label) if f.label in AXES else None
            if f.kind in _AXIS_KINDS and col is None:
                raise ValidationError(f"{t.element}.{t.param}: feature {f.name} names no axis")
            feats.append(_Feature(f.kind, tuple(f.channels), int(f.power), col, float(f.tau_s or 0.0)))
        terms.append((t.element, kinematics.PARAMS.index(t.param), feats, [float(c) for c in t.coefficients]))
    return terms


def _snapshot_deltas(
    temps: Temperatures, refs: Mapping[str, float], n: int
) -> tuple[dict[str, float | np.ndarray], Mapping[tuple[str, float], ArrayLike]]:
    """Return dT of every model input (scalars for one reading, (N,) for a frame of N rows) and the lags it carries."""
    if isinstance(temps, pd.DataFrame):
        missing = [c for c in refs if c not in temps.columns]
        if missing:
            raise ValidationError(f"temperatures lack model input(s) {', '.join(missing)}")
        if len(temps) not in (1, n):
            raise ValidationError(f"{len(temps)} temperature rows for {n} poses (give 1 or {n})")
        dT: dict[str, float | np.ndarray] = {c: temps[c].to_numpy(float) - r for c, r in refs.items()}
        if len(temps) == 1:
            dT = {c: float(np.asarray(v)[0]) for c, v in dT.items()}
        history = temps.attrs.get("lagged") or {}  # the lags of a table's history (TemperatureTable.nearest)
    else:
        missing = [c for c in refs if c not in temps]
        if missing:
            raise ValidationError(f"temperatures lack model input(s) {', '.join(missing)}")
        dT = {c: float(temps[c]) - r for c, r in refs.items()}
        history = getattr(temps, "lagged", None) or {}  # a live scan's lags (physics.lag.LaggedReadings)
    if not all(np.all(np.isfinite(v)) for v in dT.values()):
        raise ValidationError("temperatures contain missing readings: substitute virtual-sensor estimates first")
    return dT, history


def _term_value(
    feats: list[_Feature],
    coefs: list[float],
    q: np.ndarray,
    d: np.ndarray | None,
    dT: Mapping[str, float | np.ndarray],
    history: Mapping[tuple[str, float], ArrayLike],
    refs: Mapping[str, float],
) -> float | np.ndarray:
    """Return one term's value at poses ``q`` with directions ``d``: its features times their coefficients."""
    const: float | np.ndarray = 0.0  # everything that does not vary along the path (scalars for a snapshot)
    lin: dict[int, float | np.ndarray] = {}  # axis -> coefficient of its coordinate
    acc: float | np.ndarray = 0.0  # remaining (N,) columns
    for f, c in zip(feats, coefs):
        ch = f.channels
        if f.kind == "intercept":
            const = const + c
        elif f.kind == "position":
            assert f.col is not None  # _fast_terms refused axis kinds that name no axis
            if f.power == 1:
                lin[f.col] = lin.get(f.col, 0.0) + c
            else:
                acc = acc + c * q[:, f.col] ** f.power
        elif f.kind == "direction":
            if d is not None:
                acc = acc + c * (d[:, f.col] if d.ndim == 2 else d)
        elif f.kind == "lag" and (ch[0], f.tau) in history:  # ch. 5.3: first-order lag of the reading
            lag = np.asarray(history[(ch[0], f.tau)], dtype=float) - refs[ch[0]]
            const = const + c * (float(lag) if lag.ndim == 0 else lag)
        elif f.kind in ("dT", "lag"):  # a snapshot carries no history: a settled lag equals dT
            const = const + c * dT[ch[0]]
        elif f.kind == "pos_dT":
            assert f.col is not None  # as above
            lin[f.col] = lin.get(f.col, 0.0) + c * dT[ch[0]]
        elif f.kind == "lever":  # a link's term through the chain's lever arm: position^power x (lag or dT)
            assert f.col is not None  # as above
            if f.tau and (ch[0], f.tau) in history:
                inner = np.asarray(history[(ch[0], f.tau)], dtype=float) - refs[ch[0]]
            else:  # dT, or a snapshot's settled lag
                inner = np.asarray(dT[ch[0]], dtype=float)
            acc = acc + c * q[:, f.col] ** f.power * inner
        elif f.kind == "gradient":  # eqs. 3.4-3.5: mean of one side less mean of the other
            a, b = ch[: f.power], ch[f.power :]
            const = const + c * (sum(dT[x] for x in a) / len(a) - sum(dT[x] for x in b) / len(b))
        else:  # structure mean (eq. 3.3)
            const = const + c * (sum(dT[x] for x in ch) / len(ch))
    value = acc + const
    for col, k in lin.items():
        value = value + k * q[:, col]
    return value


def fast_predict(doc: ModelDocument) -> Predict:
    """Return a predict callable equal to ``models.document.predict_element_errors`` for ``doc``, without pandas.

    Every feature kind of ``models.features`` is a product of at most one joint coordinate (or
    approach direction, of the axis its label names) and one linear combination of dT, so for a
    snapshot of temperatures each term is a short polynomial in the joint coordinates (the recast
    terms of ch. 6.4.2). Frames with a history and lagged terms go to the registry, which owns lags.
    """
    refs = {c: r.reference for c, r in doc.inputs.items()}
    terms = _fast_terms(doc)
    has_lag = any(f.kind == "lag" or (f.kind == "lever" and f.tau) for _, _, feats, _ in terms for f in feats)

    def predict(
        q: np.ndarray, temps: Temperatures, direction: np.ndarray | None, at: float | None = None
    ) -> kinematics.ElementErrors:
        """Return the (N, 6) errors of every modelled element at poses ``q`` (no term here depends on ``at``)."""
        n = q.shape[0]
        if isinstance(temps, pd.DataFrame) and has_lag and not temps.attrs.get("lagged"):
            if len(temps) > 1 and "time_s" in temps.columns:
                return documents.predict_element_errors(doc, temps, q, direction)
        dT, history = _snapshot_deltas(temps, refs, n)
        d = None if direction is None else np.asarray(direction, dtype=float)
        out: dict[str, np.ndarray] = {}
        for element, param, feats, coefs in terms:
            # (N, 6) held column by column: the chain reads each error component as one row
            arr = out.setdefault(element, np.zeros((6, n)).T)
            arr[:, param] += _term_value(feats, coefs, q, d, dT, history, refs)
        return out

    return predict


def _checked_predict(doc: ModelDocument) -> Predict:
    """Return ``fast_predict(doc)`` if it reproduces the registry on probe poses, else the registry itself."""
    try:
        fast = fast_predict(doc)
    except ValidationError:
        fast = None
    rng = np.random.default_rng(0)
    q = np.column_stack([rng.uniform(-300, 300, (6, 3)), rng.uniform(-1.2, 1.2, (6, 2))])
    direction = rng.choice([-1.0, 1.0], size=(6, 5))
    temps = {c: r.reference + 3.0 * (k % 3) - 2.0 for k, (c, r) in enumerate(doc.inputs.items())}

    def slow(
        q: np.ndarray, temps: Temperatures, direction: np.ndarray | None, at: float | None = None
    ) -> kinematics.ElementErrors:
        """Return the registry's prediction (time-dependent terms at ``at``, POSIX s; now when None)."""
        if at is None:
            return documents.predict_element_errors(doc, temps, q, direction)
        return documents.predict_element_errors(doc, temps, q, direction, at=at)

    if fast is not None:
        try:
            want = slow(q, temps, direction)
            got = fast(q, temps, direction)
            same = set(want) == set(got) and all(np.allclose(got[e], want[e], rtol=1e-9, atol=1e-12) for e in want)
        except ValidationError:
            same = False
        if same:
            return fast
    log.warning("model %s: using the registry's (slower) prediction", getattr(doc, "version", "?"))
    return slow


def retain_freed_memory() -> None:
    """Ask glibc's allocator to keep freed memory for reuse (no-op elsewhere).

    Compensating a large program makes many short-lived arrays of tens of MB; by default glibc
    returns them to the OS at once and every new one costs page faults again (about a third of
    the time of a million-block program on a virtual machine).
    """
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        if libc is not None and hasattr(libc, "mallopt"):
            libc.mallopt(-3, 1 << 30)  # M_MMAP_THRESHOLD: large blocks from the reusable heap
            libc.mallopt(-1, 1 << 34)  # M_TRIM_THRESHOLD: keep freed heap memory
    except OSError:
        pass


def resolution_units(program: Program, resolution_mm: float, resolution_deg: float) -> np.ndarray:
    """Return (5,) resolution per axis in the program's integer units; refuse a non-integral step."""
    steps = np.where(ROTARY, resolution_deg / program.scale, resolution_mm / program.scale)
    out = np.rint(steps).astype(np.int64)
    if np.any(out <= 0) or np.any(np.abs(steps - out) > 1e-6):
        raise ValidationError(
            f"resolution {resolution_mm} mm / {resolution_deg} deg is not a whole number of the "
            f"program's units (10^-{program.decimals[0]} mm, 10^-{program.decimals[1]} deg)"
        )
    return out


def decimals_for(resolution_mm: float, resolution_deg: float) -> tuple[int, int]:
    """Return the decimals needed to write positions at these resolutions (linear, rotary)."""

    def dec(x: float) -> int:
        e = Decimal(repr(float(x))).normalize().as_tuple().exponent
        return max(0, -int(e))

    return max(4, dec(resolution_mm)), max(3, dec(resolution_deg))


def quantise_carry(
    units: np.ndarray, state: np.ndarray | None = None, hysteresis: float = QUANTISER_HYSTERESIS
) -> np.ndarray:
    """Return the whole steps (P, 5) sent for desired corrections ``units`` (P, 5) in resolution steps.

    A step is sent only once the correction has moved more than ``0.5 + hysteresis`` steps away from
    what was sent before, and then as far as it takes to come back within that band; the remainder
    carries over (ch. 7.2). Per point: ``s = clip(s_prev, ceil(u - b), floor(u + b))`` with
    ``b = 0.5 + hysteresis``, so ``|u - s| <= b`` always: hysteresis 0 is rounding to the nearest
    step, and noise in the correction smaller than the hysteresis never toggles a step. ``state`` is
    the step count sent before the first point (default 0). ``hysteresis`` must be in [0, 0.5).

    Vectorised: the window ``[ceil(u - b), floor(u + b)]`` holds one or two whole steps (its width is
    under 2), so ``s`` keeps its previous value only while the window stays the same; whenever the
    window changes, ``s`` is forced to its lower end (window moved up) or upper end (moved down),
    whatever came before.
    """
    if not 0.0 <= hysteresis < 0.5:
        raise ValueError(f"the quantiser's hysteresis must be in [0, 0.5) steps, got {hysteresis}")
    u = np.asarray(units, dtype=float)
    n = u.shape[0]
    s0 = np.zeros(u.shape[1], dtype=np.int64) if state is None else np.asarray(state, dtype=np.int64)
    if n == 0:
        return np.empty(u.shape, dtype=np.int64)
    band = 0.5 + hysteresis
    lo = np.ceil(u - band).astype(np.int64)
    hi = np.floor(u + band).astype(np.int64)
    forced_value = np.where(lo[1:] >= hi[:-1], lo[1:], hi[1:])
    same = (lo[1:] == lo[:-1]) & (hi[1:] == hi[:-1]) & (hi[1:] > lo[1:])
    values = np.vstack([np.clip(s0, lo[0], hi[0])[None, :], forced_value])
    forced = np.vstack([np.ones((1, u.shape[1]), dtype=bool), ~same])
    idx = np.where(forced, np.arange(n)[:, None], 0)
    np.maximum.accumulate(idx, axis=0, out=idx)
    return np.take_along_axis(values, idx, axis=0)


def directions(nominal_int: np.ndarray, start_int: np.ndarray, initial: np.ndarray | None = None) -> np.ndarray:
    """Return (P, 5) approach direction +1/-1 of each point per axis (the last move's sign, carried)."""
    prev = np.vstack([start_int[None, :], nominal_int[:-1]])
    sgn = np.sign(nominal_int - prev).astype(np.int8)
    out = np.empty(sgn.shape, dtype=float)
    idx = np.arange(sgn.shape[0])
    init = np.ones(sgn.shape[1]) if initial is None else np.asarray(initial, dtype=float)
    for k in range(sgn.shape[1]):
        last = np.maximum.accumulate(np.where(sgn[:, k] != 0, idx, -1))
        out[:, k] = np.where(last >= 0, sgn[np.maximum(last, 0), k], init[k])
    return out


@dataclass(frozen=True)
class Correction:
    """The corrections of a run of points: desired (mm / rad), sent (integer units), diagnostics."""

    points: Points
    #: (P, 5) comp X, Y, Z (mm), comp theta_X, theta_Y (rad) from eqs. 4.23-4.26
    desired: np.ndarray
    #: (P, 5) whole resolution steps sent per axis
    steps: np.ndarray
    #: (P, 5) commanded pose in the program's integer units
    sent_int: np.ndarray
    #: (P,) poses near the A = 90 deg singularity (beta not compensated there)
    singular: np.ndarray
    #: (P,) roll about the spindle that five axes cannot cancel (rad)
    roll: np.ndarray
    #: (P, 5) approach direction +1/-1 per axis, as given to the model
    direction: np.ndarray

    def carry(self) -> Carry:
        """Return what these points hand the points after them."""
        return Carry(self.steps[-1], self.points.nominal_int[-1], self.direction[-1])


def rotary_lever(q: np.ndarray, dims: Mapping[str, Any], delta: np.ndarray) -> np.ndarray:
    """Return (N, 3) X, Y, Z offsets (mm) that cancel turning A, B by ``delta`` (N, 2) rad at poses ``q``.

    In the chain of eq. 4.12 a small turn of a rotary joint is a rotation of the part about that
    joint's axis, which passes through the joint's origin in the spindle frame: ``m`` for A (links
    T1..T4 plus X, Y, Z) and ``m + Rx(A) t5`` for B, whose axis is ``Rx(A) e_y``. The tool point
    (the spindle origin) then moves by ``-delta * axis x origin``; X, Y, Z move the part along the
    spindle axes, so the offsets are ``delta * axis x origin`` (first order in the small errors).
    """
    t = {
        k: np.asarray(dims[k], dtype=float) if k in dims else np.asarray(kinematics.TABLE_A1[k], dtype=float)
        for k in ("T1", "T2", "T3", "T4", "T5")
    }
    m = q[:, :3] + (t["T1"] + t["T2"] + t["T3"] + t["T4"])[None, :]
    ca, sa = np.cos(q[:, 3]), np.sin(q[:, 3])
    t5 = t["T5"]
    # Rx(A) t5 and Rx(A) e_y
    mb = m + np.column_stack([np.full_like(ca, t5[0]), ca * t5[1] - sa * t5[2], sa * t5[1] + ca * t5[2]])
    # the cross products written out: e_x x m = (0, -m_z, m_y); (0, c, s) x mb = (c mb_z - s mb_y, s mb_x, -c mb_x)
    da, db = delta[:, 0], delta[:, 1]
    out = np.empty_like(m)
    out[:, 0] = db * (ca * mb[:, 2] - sa * mb[:, 1])
    out[:, 1] = db * (sa * mb[:, 0]) - da * m[:, 2]
    out[:, 2] = da * m[:, 1] - db * (ca * mb[:, 0])
    return out


@dataclass(frozen=True)
class Grid:
    """How a program's points are made and sent: the machine's resolution (ch. 7.2) and the subdivision lengths."""

    resolution_mm: float = RESOLUTION_MM
    resolution_deg: float = RESOLUTION_DEG
    max_segment_mm: float = 5.0
    max_segment_deg: float = 5.0
    #: ``quantise_carry``'s hysteresis beyond half a step (steps)
    hysteresis_steps: float = QUANTISER_HYSTERESIS

    @classmethod
    def of(cls, options: Mapping[str, object]) -> Grid:
        """Return the grid named by keyword options (``resolution_mm`` ... ``max_segment_deg``; defaults otherwise)."""
        return with_options(cls(), options)

    @property
    def segment(self) -> tuple[float, float]:
        """Return the subdivision lengths (mm, deg)."""
        return self.max_segment_mm, self.max_segment_deg

    @property
    def decimals(self) -> tuple[int, int]:
        """Return the least decimals (linear, rotary) positions are written with at this resolution."""
        return decimals_for(self.resolution_mm, self.resolution_deg)


def with_options(base: _Options, options: Mapping[str, object]) -> _Options:
    """Return the frozen dataclass ``base`` with the fields ``options`` names replaced (other keys are ignored).

    How flat keyword options (``correct_points``, ``Streamer``) become the small dataclasses they group into.
    """
    return replace(base, **{f.name: options[f.name] for f in fields(base) if f.name in options})


@dataclass(frozen=True)
class Carry:
    """What a run of points hands the next, so a program corrected in pieces comes out as in one go.

    The whole steps sent per axis (``quantise_carry``'s state), the last nominal pose and the approach
    directions there; None before the first point (no steps, the program's start pose, +1).
    """

    steps: np.ndarray | None = None
    nominal: np.ndarray | None = None
    direction: np.ndarray | None = None


class CorrectKeywords(TypedDict, total=False):
    """The keyword options of :func:`correct_points` (see there)."""

    resolution_mm: float
    resolution_deg: float
    hysteresis_steps: float
    state: np.ndarray | None
    prev_nominal: np.ndarray | None
    prev_direction: np.ndarray | None
    at: float | None
    solved: tuple[np.ndarray, np.ndarray] | None


def correct_points(
    program: Program,
    points: Points,
    model: ErrorModel,
    temperatures: Temperatures,
    **options: Unpack[CorrectKeywords],
) -> Correction:
    """Return the quantised corrections of ``points`` for these temperatures (``correct`` with keyword options).

    ``state``, ``prev_nominal`` and ``prev_direction`` are the ``Carry`` of the points before,
    ``resolution_mm`` / ``resolution_deg`` the ``Grid``'s, ``at`` and ``solved`` as in ``correct``.
    """
    carry = Carry(options.get("state"), options.get("prev_nominal"), options.get("prev_direction"))
    grid = Grid.of(options)
    return correct(program, points, model, temperatures, carry, grid, options.get("at"), options.get("solved"))


def correct(
    program: Program,
    points: Points,
    model: ErrorModel,
    temperatures: Temperatures,
    carry: Carry = Carry(),
    grid: Grid = Grid(),
    at: float | None = None,
    solved: tuple[np.ndarray, np.ndarray] | None = None,
) -> Correction:
    """Return the quantised corrections of ``points`` for these temperatures (and time ``at``, POSIX s).

    ``carry`` is what the points before left (see ``Carry``), so a program can be corrected in pieces
    (streaming) with the same result as in one go. ``solved`` gives the axis commands (P, 5) and
    singular flags (P,) of eqs. 4.23-4.26 already solved for exactly these points, model and
    temperatures (the first pass's, ``KeptCommands``): they are used as they are (``Correction.roll``
    is then NaN, not kept).
    """
    q = program.to_q(points.nominal_int)
    start = program.start_int if carry.nominal is None else carry.nominal
    direction = directions(points.nominal_int, start, carry.direction)
    if solved is None:
        errors = (
            model.predict(q, temperatures, direction)
            if at is None
            else model.predict(q, temperatures, direction, at=at)
        )
        result = kinematics.compensate(q, errors, model.dims)
        q_cmd, singular, roll = result.q_cmd, result.singular, result.uncompensable_roll
    else:
        q_cmd, singular = solved
        roll = np.full(q.shape[0], np.nan)
    desired = q_cmd - q
    if not np.all(np.isfinite(desired)):
        raise ValidationError("the model predicts non-finite errors for these temperatures")
    s0 = np.zeros(5, dtype=np.int64) if carry.steps is None else np.asarray(carry.steps, dtype=np.int64)
    step_rad = float(np.deg2rad(grid.resolution_deg))
    # angles first (eq. 4.25): whole steps, the remainder carried over
    ang = desired[:, 3:] / step_rad
    whole = np.rint(ang)
    ang_steps = quantise_carry(np.where(np.abs(ang - whole) < 1e-6, whole, ang), s0[3:], grid.hysteresis_steps)
    # then translations (eq. 4.26), taking up what the angles on their grid leave at the tool
    xyz = desired[:, :3] + rotary_lever(q_cmd, model.dims, ang_steps * step_rad - desired[:, 3:])
    lin = xyz / grid.resolution_mm
    whole = np.rint(lin)
    xyz_steps = quantise_carry(np.where(np.abs(lin - whole) < 1e-6, whole, lin), s0[:3], grid.hysteresis_steps)
    steps = np.hstack([xyz_steps, ang_steps])
    step_int = resolution_units(program, grid.resolution_mm, grid.resolution_deg)
    sent = points.nominal_int + steps * step_int
    return Correction(points, desired, steps, sent, singular, roll, direction)


# ----------------------------------------------------------------------------- temperatures


@dataclass(frozen=True)
class TemperatureTable:
    """Thermocouple scans (bundle v1 temperatures.csv): times and one column per channel, gaps filled."""

    time_s: np.ndarray
    values: pd.DataFrame  # columns = channels, missing readings carried forward from the last scan
    #: tau -> (scans, channels) first-order lags of the readings over the whole table (``lag_history``)
    _lags: dict[float, np.ndarray] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def read_csv(cls, path: str | Path) -> TemperatureTable:
        """Return the table of a temperatures.csv; ValidationError ``FILE:ROW: problem`` otherwise."""
        path = Path(path)
        try:
            frame = pd.read_csv(path)
        except FileNotFoundError:
            raise ValidationError(f"{path}: no such file") from None
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
            raise ValidationError(f"{path}: not a temperatures CSV ({' '.join(str(exc).split())})") from None
        return cls.from_frame(frame, str(path))

    @classmethod
    def from_frame(cls, frame: pd.DataFrame, name: str = "temperatures") -> TemperatureTable:
        """Return the table of a frame with ``time_s`` and one column per channel."""
        if "time_s" not in frame.columns:
            raise ValidationError(f"{name}:1: no time_s column")
        if len(frame) == 0:
            raise ValidationError(f"{name}: no temperature rows")
        numeric = frame.apply(pd.to_numeric, errors="coerce")
        bad = numeric.isna() & frame.notna()
        if bad.to_numpy().any():
            row, col = np.argwhere(bad.to_numpy())[0]
            raise ValidationError(f"{name}:{row + 2}: {frame.columns[col]} is not a number ({frame.iat[row, col]!r})")
        t = numeric["time_s"].to_numpy(float)
        if not np.all(np.isfinite(t)):
            raise ValidationError(f"{name}:{int(np.flatnonzero(~np.isfinite(t))[0]) + 2}: time_s missing")
        back = np.flatnonzero(np.diff(t) < 0)
        if back.shape[0]:
            raise ValidationError(f"{name}:{int(back[0]) + 3}: time_s goes backwards")
        values = numeric.drop(columns=["time_s"]).ffill().reset_index(drop=True)
        return cls(time_s=t, values=values)

    def lag_history(self, taus_s: tuple[float, ...]) -> dict[tuple[str, float], np.ndarray]:
        """Return {(channel, tau): lag of its readings at every scan} over the whole table (ch. 5.3).

        The lag runs from the table's first scan (settled there, ``physics.lag.first_order_lag``), so
        a block's lagged temperature holds the history before it however the program is batched. A
        channel's lag starts at its first valid reading.
        """
        cols = list(self.values.columns)
        out: dict[tuple[str, float], np.ndarray] = {}
        for tau in taus_s:
            if tau not in self._lags:
                self._lags[tau] = first_order_lag(self.values.bfill().to_numpy(float), self.time_s, float(tau))
            out.update({(c, float(tau)): self._lags[tau][:, k] for k, c in enumerate(cols)})
        return out

    def latest(self, channels: tuple[str, ...] = (), taus_s: tuple[float, ...] = ()) -> dict[str, float]:
        """Return the latest reading of every channel (the last valid one where the last scan lacks it).

        With ``taus_s`` (a model's lag time constants) the readings carry their lags at the last scan
        (``physics.lag.LaggedReadings``).
        """
        row = self.values.iloc[-1]
        self._require(channels, row)
        readings = {c: float(v) for c, v in row.items()}
        if not taus_s:
            return readings
        return LaggedReadings(readings, {k: float(v[-1]) for k, v in self.lag_history(taus_s).items()})

    def nearest(
        self, times_s: np.ndarray, channels: tuple[str, ...] = (), taus_s: tuple[float, ...] = ()
    ) -> pd.DataFrame:
        """Return one row per time (the scan nearest to it), with ``time_s`` set to those times.

        With ``taus_s`` the frame carries the lags of those scans over the table's history in
        ``attrs["lagged"]`` ({(channel, tau): array}), which the model's lagged terms then take.
        """
        t = self.time_s
        i = np.clip(np.searchsorted(t, times_s), 1, max(len(t) - 1, 1))
        if len(t) > 1:
            i = np.where(np.abs(t[i - 1] - times_s) <= np.abs(t[i] - times_s), i - 1, i)
        else:
            i = np.zeros(len(times_s), dtype=np.int64)
        rows = self.values.iloc[i].reset_index(drop=True)
        self._require(channels, rows.iloc[-1] if len(rows) else self.values.iloc[-1])
        rows.insert(0, "time_s", np.asarray(times_s, dtype=float))
        if taus_s:
            rows.attrs["lagged"] = {k: v[i] for k, v in self.lag_history(taus_s).items()}
        return rows

    @staticmethod
    def _require(channels: tuple[str, ...], row: pd.Series) -> None:
        """Raise when a channel the model reads has no valid reading."""
        missing = [c for c in channels if c not in row.index]
        if missing:
            raise ValidationError(f"temperatures lack the model's channel(s) {', '.join(missing)}")
        empty = [c for c in channels if not np.isfinite(row[c])]
        if empty:
            raise ValidationError(f"no valid reading yet for channel(s) {', '.join(empty)}")


# ----------------------------------------------------------------------------- offline


class OfflineSummary(TypedDict):
    """The JSON summary of an :class:`OfflineResult`."""

    blocks: int
    points: int
    max_correction: dict[str, float]
    singular_points: int
    model: str
    temperatures: str
    extrapolated: NotRequired[dict[str, dict[str, float]]]  # only when something was


@dataclass(frozen=True)
class OfflineResult:
    """A compensated program and what was done to it."""

    text: bytes
    blocks: int
    points: int
    max_correction: dict[str, float]  # per axis, mm or deg, of what was sent
    singular: int
    model: str
    temperatures: str
    #: channels read beyond their fitted range by more than the margin (extrapolation allowed): see ``guard``
    extrapolated: dict[str, dict[str, float]] = field(default_factory=dict)

    def summary(self) -> OfflineSummary:
        """Return a JSON-ready summary (``extrapolated`` only when something was)."""
        out: OfflineSummary = {
            "blocks": self.blocks,
            "points": self.points,
            "max_correction": self.max_correction,
            "singular_points": self.singular,
            "model": self.model,
            "temperatures": self.temperatures,
        }
        if self.extrapolated:
            out["extrapolated"] = self.extrapolated
        return out


def compensate_program(
    program: Program,
    model: ErrorModel,
    temperatures: TemperatureTable | Temperatures,
    *,
    resolution_mm: float = RESOLUTION_MM,
    resolution_deg: float = RESOLUTION_DEG,
    max_segment_mm: float = 5.0,
    max_segment_deg: float = 5.0,
    chunk_points: int = 1 << 17,
) -> OfflineResult:
    """Return the program with every block corrected (long G1 segments subdivided first).

    With a ``TemperatureTable``: where the program carries times (``(T=...)`` comments) each
    point takes the scan nearest its block's time, otherwise the latest scan is used.
    """
    points = subdivide(program, max_segment_mm, max_segment_deg)
    times = program.line_time_s[program.block_line[points.block]]
    # the table each point takes its nearest scan from; None: every point takes ``fixed``
    per_point: TemperatureTable | None = None
    fixed: Temperatures | None
    if isinstance(temperatures, TemperatureTable):
        if points.n > 0 and bool(np.isfinite(times).all()):
            per_point = temperatures
        how = "nearest scan to each block's time" if per_point is not None else "latest scan"
        fixed = None if per_point is not None else temperatures.latest(model.channels, model.lag_taus)
    else:
        how, fixed = "given", temperatures
    sent = np.empty_like(points.nominal_int)
    singular = 0
    carry = Carry()
    grid = Grid(resolution_mm, resolution_deg)
    for s in range(0, points.n, chunk_points):
        sub = Points(points.block[s : s + chunk_points], points.nominal_int[s : s + chunk_points])
        temps = (
            per_point.nearest(times[s : s + chunk_points], model.channels, model.lag_taus)
            if per_point is not None
            else fixed
        )
        assert temps is not None
        corr = correct(program, sub, model, temps, carry, grid)
        sent[s : s + chunk_points] = corr.sent_int
        singular += int(corr.singular.sum())
        carry = corr.carry()
    if singular:
        log.warning("%d point(s) near A = +/-90 deg: beta cannot be compensated there", singular)
    text = emit_program(program, points, sent)
    diff = np.abs(sent - points.nominal_int) * program.scale if points.n else np.zeros((1, 5))
    mx = diff.max(axis=0) if points.n else np.zeros(5)
    return OfflineResult(
        text=text,
        blocks=program.n_blocks,
        points=points.n,
        max_correction={a: float(round(v, 6)) for a, v in zip("XYZAB", mx)},
        singular=singular,
        model=model.label,
        temperatures=how,
    )


#: the most points whose commands the first pass keeps for the second (48 bytes each, in a temporary file)
KEEP_MAX_POINTS = 1 << 23
#: bytes of program text parsed, corrected and written at a time by the streaming pipeline
STREAM_CHUNK_BYTES = 1 << 18
#: points corrected at once when every point takes the same temperatures (the result is the same
#: whatever the batch; the working set of a batch is about 1 kB per point)
SNAPSHOT_BATCH_POINTS = 1 << 14
#: the longest line accepted (a line is never split between two pieces)
MAX_LINE_BYTES = 1 << 20


def program_pieces(path: str | Path, chunk_bytes: int = STREAM_CHUNK_BYTES) -> Iterator[tuple[int, bytes]]:
    """Yield (lines before, text) of a program file in pieces of whole lines, reading ``chunk_bytes`` at a time.

    ValidationError for a file that cannot be read, is not a regular file, or has a line longer
    than MAX_LINE_BYTES.
    """
    path = Path(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise ValidationError(f"{path}: not a regular file")
        fh = path.open("rb")
    except FileNotFoundError:
        raise ValidationError(f"{path}: no such file") from None
    except OSError as exc:
        raise ValidationError(f"{path}: cannot read: {exc.strerror or exc}") from None
    lines = 0
    rest = b""
    with fh:
        while True:
            try:
                block = fh.read(chunk_bytes)
            except OSError as exc:
                raise ValidationError(f"{path}: cannot read: {exc.strerror or exc}") from None
            if not block:
                break
            text = rest + block
            cut = text.rfind(b"\n") + 1
            if cut == 0:
                if len(text) > MAX_LINE_BYTES:
                    raise ValidationError(
                        f"{path}:{lines + 1}: line longer than {MAX_LINE_BYTES} bytes; program not accepted"
                    )
                rest = text
                continue
            piece, rest = text[:cut], text[cut:]
            if len(rest) > MAX_LINE_BYTES:
                at = lines + piece.count(b"\n") + 1
                raise ValidationError(f"{path}:{at}: line longer than {MAX_LINE_BYTES} bytes; program not accepted")
            yield lines, piece
            lines += piece.count(b"\n")
        if rest:
            if len(rest) > MAX_LINE_BYTES:
                raise ValidationError(
                    f"{path}:{lines + 1}: line longer than {MAX_LINE_BYTES} bytes; program not accepted"
                )
            yield lines, rest


@dataclass(frozen=True)
class ProgramScan:
    """What the first pass over a streamed program learns: it parses, and the state pieces need."""

    decimals: tuple[int, int]
    eol: bytes
    first_time_s: float
    blocks: int
    lines: int
    #: the axis commands of every block solved by the first pass, when the second pass can use them as they are
    solved: KeptCommands | None = None
    #: the pieces the first pass parsed, when it kept them for the second pass (``Scanner``'s ``keep``)
    parsed: ParsedPieces | None = None

    def close(self) -> None:
        """Drop what the first pass kept for the second."""
        if self.solved is not None:
            self.solved.close()
        if self.parsed is not None:
            self.parsed.close()


def scan_program(
    path: str | Path,
    name: str,
    min_decimals: tuple[int, int],
    chunk_bytes: int = STREAM_CHUNK_BYTES,
    *,
    start: tuple[float, ...] | None = None,
    max_segment_mm: float = 5.0,
    max_segment_deg: float = 5.0,
    check: FirstPass | None = None,
) -> ProgramScan:
    """Check every line of a program file piece by piece (first pass); return what the second pass needs.

    Besides the syntax (``gcode.parse_program``: bad words, feeds <= 0, ...) every block's
    subdivision is counted (a segment needing more than 100000 points is refused here), and with
    ``check`` (``FirstPass``) every block's target and correction is checked against the machine
    envelope. Pieces are parsed from the pose, modal state and time stamp the lines before them
    leave (``start``: the pose before the program), so G91 blocks are checked where they really go.
    Nothing is kept but the state: memory does not grow with the program.
    """
    return Scanner(name, min_decimals, start, (max_segment_mm, max_segment_deg), check).scan(path, chunk_bytes)


class Scanner:
    """The first pass of ``scan_program``, a piece at a time; with ``keep`` the parsed pieces are kept on disk
    (``parsed.ParsedPieces``) for the second pass, which then neither reads nor parses the file again."""

    def __init__(
        self,
        name: str,
        min_decimals: tuple[int, int],
        start: tuple[float, ...] | None,
        segment: tuple[float, float],
        check: FirstPass | None = None,
        keep: ParsedPieces | None = None,
    ) -> None:
        self.name, self.min_decimals, self.segment, self.check, self.keep = name, min_decimals, segment, check, keep
        self.state = ParserState()
        self.pose = start
        self.first_time = float("nan")
        self.residuals: list[tuple[tuple[float, np.ndarray], tuple[float, np.ndarray]]] = []
        self.blocks = self.lines = 0

    def scan(self, path: str | Path, chunk_bytes: int) -> ProgramScan:
        """Check every piece of the file at ``path``; return what the second pass needs (the kept pieces with it)."""
        try:
            for offset, text in program_pieces(path, chunk_bytes):
                self.add(offset, text)
            return self.finish()
        except BaseException:
            if self.keep is not None:
                self.keep.close()
            raise

    def add(self, offset: int, text: bytes) -> None:
        """Parse and check the piece of ``text`` that starts after ``offset`` lines."""
        # each piece in its own decimals (the program's are known at the end), from the pose in mm / deg
        state = replace(self.state, line_offset=offset)
        piece = parse_program(text, self.name, self.pose, self.min_decimals, state=state, residuals=True)
        self.state = replace(piece.next_state(state), eol=piece.eol, pose_int=None)
        if not np.isfinite(self.first_time) and piece.n_lines and np.isfinite(piece.line_time_s).any():
            self.first_time = float(piece.line_time_s[np.flatnonzero(np.isfinite(piece.line_time_s))[0]])
        points = _check_piece(piece, self.check, self.segment)
        if piece.n_blocks:
            self.pose = tuple((piece.target_int[-1] * piece.scale).tolist())
        assert piece.residuals is not None
        self.residuals.append(piece.residuals)
        self.blocks += piece.n_blocks
        self.lines = offset + piece.n_lines
        if self.keep is not None and ParsedPieces.fits(piece):
            self.keep.write(replace(piece, residuals=None), points)
        elif self.keep is not None:  # too large to keep: the second pass reads and parses the file again
            self.keep.close()
            self.keep = None

    def finish(self) -> ProgramScan:
        """Return what the second pass needs: the program's decimals, line terminator, first time stamp, ..."""
        least = self.min_decimals
        decimals = (
            decimals_of([r[0] for r in self.residuals], least[0]),
            decimals_of([r[1] for r in self.residuals], least[1]),
        )
        if max(decimals) > MAX_DECIMALS:  # pragma: no cover - each piece has refused its own already
            raise ValidationError(f"{self.name}: more than {MAX_DECIMALS} decimals; program not accepted")
        solved = self.check.finish(decimals) if self.check is not None else None
        eol = self.state.eol or b"\n"
        return ProgramScan(decimals, eol, self.first_time, self.blocks, self.lines, solved, self.keep)


def _check_piece(piece: Program, check: FirstPass | None, segment: tuple[float, float]) -> int:
    """Refuse a piece whose targets leave the travel, whose segments need too many points, or whose corrections
    leave the envelope (targets first: a runaway is named as one; then the subdivision, then the corrections);
    return how many points it subdivides into."""
    try:
        if check is not None:
            check.targets(piece)
        points = count_points(piece, *segment)  # refuses a segment of too many points
    except ValidationError:
        if check is not None:
            check.finish()  # the blocks before this one are checked first: the first bad block is named
        raise
    if check is not None:
        check.corrections(piece, points, segment)
    return points


class KeptCommands:
    """The axis commands (eqs. 4.23-4.26) the first pass solved for every block, in order, for the second pass.

    Kept in an unnamed temporary file (48 bytes a block: five commands and the singular flag as
    float64), so memory does not grow with the program; ``read`` gives them back in order. They hold
    for the second pass only when every block is one point, the temperatures are the same for every
    point and each piece had the program's decimals (``FirstPass.finish`` decides).
    """

    def __init__(self) -> None:
        self.fh = tempfile.TemporaryFile()
        self.rows = 0

    def write(self, q_cmd: np.ndarray, singular: np.ndarray) -> None:
        """Append the commands (N, 5) and singular flags (N,) of the next blocks."""
        self.fh.write(np.column_stack([q_cmd, singular.astype(np.float64)]).tobytes())
        self.rows += q_cmd.shape[0]

    def read(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Return the next ``n`` blocks' commands (n, 5) and singular flags (n,) (from the start after ``rewind``)."""
        rows = np.frombuffer(self.fh.read(n * 48), dtype=np.float64).reshape(-1, 6)
        if rows.shape[0] != n:
            raise RuntimeError("the first pass kept fewer commands than the second pass reads")
        return rows[:, :5], rows[:, 5] > 0.5

    def rewind(self) -> None:
        """Read from the first block again."""
        self.fh.seek(0)

    def close(self) -> None:
        """Drop the file."""
        self.fh.close()


class FirstPass:
    """The envelope check of the first pass (``scan_program(check=...)``): targets, corrections, temperatures.

    Each block's correction is solved at its target (eqs. 4.23-4.26, not quantised) with the
    temperatures the second pass gives it: the scan nearest the block's time when a table and a
    timed block, else ``fixed`` (the latest scan, the given readings, or the streamer's first
    reading). The block's target and its corrected target must stay inside the travel and the
    correction under the largest plausible one; the temperatures used must not extrapolate.

    With ``keep`` (the offline path), while every block takes ``fixed``, blocks are solved in runs of
    ``kinematics.CHUNK`` counted over the whole program (where the second pass's batches fall, so each
    block's solution is the one the second pass would compute) and their commands are kept
    (``KeptCommands``): the second pass then does not solve them again. Each piece is checked once all its
    blocks are solved, and ``finish`` (at the end, and before any other refusal) checks the rest.
    """

    def __init__(
        self,
        guard: Guard,
        model: ErrorModel,
        temperatures: TemperatureTable | Temperatures,
        *,
        keep: bool = False,
        grid: Grid = Grid(),
    ) -> None:
        self.guard = guard
        self.model = model
        # the quantiser sends each point within 0.5 + hysteresis steps of its correction (quantise_carry):
        # a corrected target that close to the travel's ends is refused here, before the first byte
        band = 0.5 + grid.hysteresis_steps
        self.slack = band * np.where(ROTARY, grid.resolution_deg, grid.resolution_mm)
        self.table = temperatures if isinstance(temperatures, TemperatureTable) else None
        self.fixed: Temperatures = (
            self.table.latest(model.channels, model.lag_taus) if self.table is not None else temperatures
        )
        guard.check_temperatures(self.fixed)
        self.prev_direction: np.ndarray | None = None
        self.kept: KeptCommands | None = KeptCommands() if keep else None
        self._decimals: set[tuple[int, int]] = set()
        # blocks waiting to be solved: (piece, first block, q, direction); pieces waiting for their checks
        self._queue: list[tuple[Program, int, np.ndarray, np.ndarray]] = []
        self._queued = 0
        self._waiting: list[tuple[Program, Points, list[np.ndarray]]] = []

    def targets(self, piece: Program) -> None:
        """Refuse the first block of a piece whose target is outside the travel."""
        self.guard.check_positions(piece, np.arange(piece.n_blocks), piece.target_int * piece.scale, "target")

    def corrections(self, piece: Program, points: int | None = None, segment: tuple[float, float] = (5.0, 5.0)) -> None:
        """Refuse the first block of a piece whose correction, or corrected target, leaves the envelope.

        ``points``: how many points the piece subdivides into with ``segment`` (mm, deg); while commands
        are kept, every point is solved and checked (not only the blocks' targets).
        """
        if piece.n_blocks == 0:
            return
        times = piece.block_time_s()
        timed = self.table is not None and bool(np.isfinite(times).all())
        if self.kept is not None and (timed or self.kept.rows + self._queued + (points or 0) > KEEP_MAX_POINTS):
            self._drop_kept()  # temperatures per block, or too many points to keep: solved per piece
        if self.kept is not None:
            pts = subdivide(piece, *segment, count=points)
            self._decimals.add(piece.decimals)
            q = piece.to_q(pts.nominal_int)
            direction = directions(pts.nominal_int, piece.start_int, self.prev_direction)
            self.prev_direction = direction[-1]
            self._queue.append((piece, 0, q, direction))
            self._queued += pts.n
            self._waiting.append((piece, pts, []))
            if self._queued >= kinematics.CHUNK:
                self._solve(self._queued // kinematics.CHUNK * kinematics.CHUNK)
            return
        q = piece.to_q(piece.target_int)
        direction = directions(piece.target_int, piece.start_int, self.prev_direction)
        self.prev_direction = direction[-1]
        temps: Temperatures = self.fixed
        if timed:
            assert self.table is not None
            temps = self.table.nearest(times, self.model.channels, self.model.lag_taus)
            self.guard.check_temperatures(temps)
        solved = kinematics.compensate(q, self.model.predict(q, temps, direction), self.model.dims)
        self._check(piece, np.arange(piece.n_blocks), piece.target_int, solved.q_cmd - q)

    def finish(self, decimals: tuple[int, int] | None = None) -> KeptCommands | None:
        """Solve and check every block still waiting; return the kept commands when the second pass may use them.

        ``decimals``: the whole program's (the second pass parses with them); the commands hold only
        when every piece had them.
        """
        if self._queued:
            self._solve(self._queued)
        if self.kept is None or decimals is None:
            return None
        if self._decimals - {decimals}:
            self._drop_kept()
            return None
        self.kept.rewind()
        return self.kept

    def _drop_kept(self) -> None:
        """Stop keeping commands (solve what waits first): the second pass solves every point itself."""
        if self._queued:
            self._solve(self._queued)
        if self.kept is not None:
            self.kept.close()
            self.kept = None

    def _solve(self, n: int) -> None:
        """Solve the next ``n`` waiting blocks as one run, keep their commands, check the pieces they complete."""
        q = np.concatenate([e[2] for e in self._queue])
        direction = np.concatenate([e[3] for e in self._queue])
        solved = kinematics.compensate(q[:n], self.model.predict(q[:n], self.fixed, direction[:n]), self.model.dims)
        if self.kept is not None:
            self.kept.write(solved.q_cmd, solved.singular)
        correction = solved.q_cmd - q[:n]
        # hand each piece its rows; a piece is checked once all its blocks are solved
        rest: list[tuple[Program, int, np.ndarray, np.ndarray]] = []
        done = 0
        for piece, b0, pq, pdir in self._queue:
            take = min(pq.shape[0], n - done)
            if take:
                for waiting, _, rows in self._waiting:
                    if waiting is piece:
                        rows.append(correction[done : done + take])
                        break
            if take < pq.shape[0]:
                rest.append((piece, b0 + take, pq[take:], pdir[take:]))
            done += take
        self._queue = rest
        self._queued -= n
        while self._waiting and sum(r.shape[0] for r in self._waiting[0][2]) == self._waiting[0][1].n:
            piece, pts, rows = self._waiting.pop(0)
            self._check(piece, pts.block, pts.nominal_int, np.concatenate(rows))

    def _check(self, piece: Program, block: np.ndarray, pose_int: np.ndarray, correction: np.ndarray) -> None:
        """Refuse the first point (its block named) whose correction (N, 5; mm, rad) or corrected pose is outside."""
        correction = correction.copy()
        correction[:, 3:] = np.rad2deg(correction[:, 3:])
        if not np.all(np.isfinite(correction)):
            bad = int(np.flatnonzero(~np.isfinite(correction).all(axis=1))[0])
            line = piece.line_number(block[bad])
            raise ValidationError(f"{piece.name}:{line}: the model predicts non-finite errors; program not accepted")
        self.guard.check_corrections(piece, block, correction)
        self.guard.check_positions(piece, block, pose_int * piece.scale + correction, "corrected target", self.slack)


def parse_pieces(
    pieces: Iterable[tuple[int, bytes]],
    scan: ProgramScan,
    name: str,
    *,
    start: tuple[float, ...] | None = None,
    min_decimals: tuple[int, int] = (4, 3),
    max_segment_mm: float = 5.0,
    max_segment_deg: float = 5.0,
    max_points: int | None = None,
) -> Iterator[Program]:
    """Yield each piece of a program (``program_pieces``) parsed with the state the lines before it leave.

    The second pass of a streamed program, shared by the offline path (``compensate_stream``) and
    the machine link (``stream.Streamer``): every piece is parsed with the decimals, line terminator
    and first time stamp of the whole program (``scan``, the first pass) and starts from the pose,
    modal G0/G1 and G90/G91 and time stamp the previous piece ended with (``gcode.ParserState``), so
    its lines read exactly as they would in the whole program. Pieces are read one at a time, when the
    consumer asks for the next: memory holds the pieces the consumer keeps, not the program. With
    ``max_points`` a piece that would subdivide into more points is halved (by lines) until it does not.
    """
    state = ParserState(decimals=scan.decimals, time_s=scan.first_time_s, eol=scan.eol)
    reader = _PieceReader(name, start, min_decimals, (max_segment_mm, max_segment_deg), max_points)
    for offset, text in pieces:
        for piece in reader.parsed(text, replace(state, line_offset=offset)):
            state = piece.next_state(state)
            yield piece


def kept_pieces(scan: ProgramScan, parsed: ParsedPieces, reader: _PieceReader) -> Iterator[KeptPiece]:
    """Yield the pieces the first pass kept, as ``parse_pieces`` would parse them (the second pass, offline).

    A kept piece that does not read as the second pass parses it (``parsed.usable``), or would make too
    many points, is parsed again from its kept text with the state the pieces before it leave (and
    comes without its count of points: ``KeptPiece.points`` None).
    """
    state = ParserState(decimals=scan.decimals, time_s=scan.first_time_s, eol=scan.eol)
    for kept in parsed.read(reader.name, scan.eol):
        if usable(kept, state, reader.max_points):
            pieces: Iterable[KeptPiece] = (kept,)
        else:
            text = kept.program.data
            pieces = (
                KeptPiece(p, None) for p in reader.parsed(text, replace(state, line_offset=kept.program.first_line))
            )
        for piece in pieces:
            state = piece.program.next_state(state)
            yield piece


@dataclass(frozen=True)
class _PieceReader:
    """How ``parse_pieces`` parses a piece: name, start pose, least decimals, subdivision, most points."""

    name: str
    start: tuple[float, ...] | None
    min_decimals: tuple[int, int]
    segment: tuple[float, float]
    max_points: int | None

    def parsed(self, text: bytes, state: ParserState) -> Iterator[Program]:
        """Yield the piece parsed from ``state``, halved while it makes too many points (each half from the state
        the lines before it leave)."""
        piece = parse_program(text, self.name, self.start, self.min_decimals, state=state)
        if self.max_points is not None and piece.n_lines > 1 and count_points(piece, *self.segment) > self.max_points:
            mid = piece.n_lines // 2  # long segments subdivided: keep the points of a piece bounded
            cut = int(piece.line_start[mid])
            del piece
            first = None
            for first in self.parsed(text[:cut], state):
                yield first
            assert first is not None
            yield from self.parsed(text[cut:], first.next_state(state))
            return
        yield piece


class _Rows:
    """Array rows in order: pushed in runs, taken in runs of any length."""

    def __init__(self) -> None:
        self._parts: list[np.ndarray] = []
        self.n = 0

    def push(self, rows: np.ndarray) -> None:
        """Append ``rows``."""
        self._parts.append(rows)
        self.n += rows.shape[0]

    def take(self, n: int) -> np.ndarray:
        """Return the first ``n`` rows and drop them."""
        whole = np.concatenate(self._parts) if len(self._parts) > 1 else self._parts[0]
        head, rest = whole[:n], whole[n:]
        self._parts = [rest] if rest.shape[0] else []
        self.n -= n
        return head


class StreamCorrector:
    """The second pass of ``compensate_stream``: parsed pieces in, corrected text out, in constant memory.

    ``add`` takes the pieces in order; their points wait until a batch of ``chunk_points`` is
    corrected (counted over the whole program, as ``compensate_program`` does: with temperatures per
    point a model with lagged terms filters a batch's temperatures in time, so the batches must fall
    where they always did for the output to stay the same; with one set of temperatures for every
    point the result does not depend on the batches and smaller ones keep the working set small).
    A piece is written once all its points are corrected, with the quantisation remainder and the
    approach directions carried over (``Carry``). ``finish`` corrects the rest and returns what was done.
    """

    def __init__(
        self,
        model: ErrorModel,
        temperatures: TemperatureTable | Temperatures,
        out: BinaryIO,
        scan: ProgramScan,
        options: CorrectorOptions,
    ) -> None:
        self.model, self.out, self.options = model, out, options
        table = temperatures if isinstance(temperatures, TemperatureTable) else None
        timed = table is not None and scan.blocks > 0 and bool(np.isfinite(scan.first_time_s))
        #: the table each point takes its nearest scan from; None: every point takes ``fixed``
        self.per_point = table if timed else None
        self.fixed: Temperatures | None = None
        if table is not None:
            self.how = "nearest scan to each block's time" if timed else "latest scan"
            if not timed:
                self.fixed = table.latest(model.channels, model.lag_taus)
        else:
            self.how, self.fixed = "given", temperatures
        self.chunk_points = options.chunk_points if timed else min(options.chunk_points, SNAPSHOT_BATCH_POINTS)
        # the commands the first pass solved for every block (one point each, the same temperatures, solved
        # in runs of kinematics.CHUNK where these batches fall): used as they are, not solved again
        self.kept = scan.solved if not timed and self.chunk_points % kinematics.CHUNK == 0 else None
        self.scan = scan
        self.carry = Carry()
        self.result = _Totals()
        self._pending: deque[tuple[Program, Points]] = deque()  # pieces waiting for their points
        self._nominal, self._times, self._sent = _Rows(), _Rows(), _Rows()
        self._first: Program | None = None

    def add(self, piece: Program, count: int | None = None) -> None:
        """Take the next piece (``count``: its points, when the first pass counted them): queue its points,
        correct every full batch, write the pieces that are done."""
        points = subdivide(piece, *self.options.grid.segment, count=count)
        if self._first is None:
            self._first = piece
        if points.n:
            self._nominal.push(points.nominal_int)
            self._times.push(piece.line_time_s[piece.block_line[points.block]])
        self._pending.append((piece, points))
        while self._nominal.n >= self.chunk_points:
            self._correct(self.chunk_points)
        self._write()

    def finish(self) -> OfflineResult:
        """Correct and write what waits; return what was done."""
        if self._nominal.n:
            self._correct(self._nominal.n)
        self._write()
        assert not self._pending
        self.scan.close()
        return self.result.outcome(self)

    def _correct(self, n: int) -> None:
        """Correct the next ``n`` queued points as one batch."""
        assert self._first is not None
        nom, t = self._nominal.take(n), self._times.take(n)
        model = self.model
        temps = self.per_point.nearest(t, model.channels, model.lag_taus) if self.per_point is not None else self.fixed
        assert temps is not None
        solved = self.kept.read(n) if self.kept is not None else None
        points = Points(np.zeros(n, dtype=np.int64), nom)
        first = self._first
        carry = self.carry if self.carry.nominal is not None else replace(self.carry, nominal=first.start_int)
        corr = correct(first, points, model, temps, carry, self.options.grid, None, solved)
        self._sent.push(corr.sent_int)
        self.carry = corr.carry()
        self.result.singular += int(corr.singular.sum())

    def _write(self) -> None:
        """Write every waiting piece whose points are all corrected."""
        while self._pending and self._pending[0][1].n <= self._sent.n:
            piece, points = self._pending.popleft()
            if points.n == 0:
                self.out.write(piece.data)
                continue
            sent = self._sent.take(points.n)
            if self.options.guard is not None:
                self.options.guard.check_sent(piece, points.block, points.nominal_int, sent)
            self.out.write(emit(piece, points, sent, prev_sent=self.result.last_sent))
            self.result.add(piece, points, sent)


@dataclass
class _Totals:
    """What ``StreamCorrector`` has written: points, the largest correction sent, singular points."""

    points: int = 0
    singular: int = 0
    biggest: np.ndarray = field(default_factory=lambda: np.zeros(5, dtype=np.int64))
    last_sent: np.ndarray | None = None
    scale: np.ndarray | None = None

    def add(self, piece: Program, points: Points, sent: np.ndarray) -> None:
        """Count a written piece's points."""
        self.biggest = np.maximum(self.biggest, np.abs(sent - points.nominal_int).max(axis=0))
        self.last_sent = sent[-1]
        self.points += points.n
        self.scale = piece.scale

    def outcome(self, corrector: StreamCorrector) -> OfflineResult:
        """Return the result of the run."""
        if self.singular:
            log.warning("%d point(s) near A = +/-90 deg: beta cannot be compensated there", self.singular)
        mx = self.biggest * self.scale if self.scale is not None and self.points else np.zeros(5)
        guard = corrector.options.guard
        return OfflineResult(
            text=b"",
            blocks=corrector.scan.blocks,
            points=self.points,
            max_correction={a: float(round(v, 6)) for a, v in zip("XYZAB", mx)},
            singular=self.singular,
            model=corrector.model.label,
            temperatures=corrector.how,
            extrapolated=guard.report() if guard is not None else {},
        )


@dataclass(frozen=True)
class CorrectorOptions:
    """The options of ``StreamCorrector``: the grid, the batch size (points), the envelope guard."""

    grid: Grid = Grid()
    chunk_points: int = 1 << 17
    guard: Guard | None = None


class StreamOptions(TypedDict, total=False):
    """The keyword options of :func:`compensate_stream`, passed on unchanged by :func:`compensate_file`."""

    start: tuple[float, ...] | None
    resolution_mm: float
    resolution_deg: float
    hysteresis_steps: float
    max_segment_mm: float
    max_segment_deg: float
    chunk_bytes: int
    chunk_points: int
    scan: ProgramScan | None
    guard: Guard | None
    #: compensate_file only: comment lines written first (``compensator.header``), after a tape start
    header: Sequence[str]


def _first_pass(
    program_path: str | Path,
    model: ErrorModel,
    temperatures: TemperatureTable | Temperatures,
    options: StreamOptions,
) -> ProgramScan:
    """Return the first pass over a program file (``scan_program``, with the guard's envelope checks when given)."""
    guard = options.get("guard")
    grid = Grid.of(options)
    check = None if guard is None else FirstPass(guard, model, temperatures, keep=True, grid=grid)
    scanner = Scanner(str(program_path), grid.decimals, options.get("start"), grid.segment, check, ParsedPieces())
    return scanner.scan(program_path, options.get("chunk_bytes", STREAM_CHUNK_BYTES))


def compensate_stream(
    program_path: str | Path,
    model: ErrorModel,
    temperatures: TemperatureTable | Temperatures,
    out: BinaryIO,
    **options: Unpack[StreamOptions],
) -> OfflineResult:
    """Correct a program file into the binary stream ``out`` in constant memory; return what was done.

    Two passes over the file, each a generator of pieces of whole lines: the first checks every
    line and learns what the pieces share (the decimals of the whole program, its line terminator,
    its first time stamp); the second parses each piece with the state the lines before it left
    (pose, modal G0/G1 and G90/G91, time stamp), corrects its points carrying the quantisation
    remainder and approach directions, and writes it (``StreamCorrector``). The output is byte for
    byte that of ``compensate_program`` on the whole text (``OfflineResult.text`` stays empty).

    With a ``guard`` (``compensator.guard``) the first pass checks every block against the machine
    envelope before anything is written, and every point is checked again just before it is written.
    """
    scan = options.get("scan") or _first_pass(program_path, model, temperatures, options)
    grid = Grid.of(options)
    corrector = StreamCorrector(
        model,
        temperatures,
        out,
        scan,
        CorrectorOptions(grid, options.get("chunk_points", 1 << 17), options.get("guard")),
    )
    max_points = max(corrector.chunk_points // 2, 1)
    if scan.parsed is not None:  # the first pass kept what it parsed: the file is not read again
        reader = _PieceReader(str(program_path), options.get("start"), grid.decimals, grid.segment, max_points)
        for kept in kept_pieces(scan, scan.parsed, reader):
            corrector.add(kept.program, kept.points)
        return corrector.finish()
    pieces = parse_pieces(
        program_pieces(program_path, options.get("chunk_bytes", STREAM_CHUNK_BYTES)),
        scan,
        str(program_path),
        start=options.get("start"),
        min_decimals=grid.decimals,
        max_segment_mm=grid.max_segment_mm,
        max_segment_deg=grid.max_segment_deg,
        max_points=max_points,
    )
    for piece in pieces:
        corrector.add(piece)
    return corrector.finish()


def _regular_or_absent(path: Path) -> None:
    """Refuse an output path that exists and is not a regular file (a device, a FIFO, a symlink, a directory)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ValidationError(f"{path}: cannot write: {exc.strerror or exc}") from None
    if stat.S_ISLNK(st.st_mode):
        raise ValidationError(f"{path}: is a symbolic link; -o writes only a regular file (nothing written)")
    if not stat.S_ISREG(st.st_mode):
        kind = "a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device"
        raise ValidationError(f"{path}: is {kind}; -o writes only a regular file (nothing written)")


def compensate_file(
    program_path: str | Path,
    model: ErrorModel,
    temperatures: TemperatureTable | Temperatures,
    out_path: str | Path,
    **options: Unpack[StreamOptions],
) -> OfflineResult:
    """Parse, correct and write a program in constant memory (``compensate_stream`` with ``options``).

    The first pass (``scan_program``, with the ``guard``'s envelope checks) runs before ``OUT.part`` is
    opened; the text goes to ``OUT.part``, renamed to ``out_path`` only once the whole program is done:
    nothing is left behind when the program is refused or cannot be corrected.
    """
    out_path = Path(out_path)
    tmp = out_path.with_name(out_path.name + ".part")
    for path in (out_path, tmp):
        _regular_or_absent(path)  # before any work: -o never replaces a device, a FIFO or a symlink
    if options.get("scan") is None:  # the first pass, before the output is even opened
        options["scan"] = _first_pass(program_path, model, temperatures, options)
    try:
        header = options.pop("header", ())
        # O_NOFOLLOW | O_NONBLOCK: a symlink or FIFO put there since the check is refused, never followed or waited on
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_NONBLOCK, 0o666)
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise ValidationError(f"{tmp}: not a regular file; nothing written")
        with os.fdopen(fd, "wb") as fh:
            out = HeaderedOut(fh, header)
            result = compensate_stream(program_path, model, temperatures, out, **options)  # type: ignore[arg-type]
            out.close()
        tmp.replace(out_path)
    except OSError as exc:
        if tmp.is_file() and not tmp.is_symlink():
            tmp.unlink(missing_ok=True)
        raise ValidationError(f"{out_path}: cannot write: {exc.strerror or exc}; nothing written") from None
    except BaseException:
        if tmp.is_file() and not tmp.is_symlink():
            tmp.unlink(missing_ok=True)
        raise
    finally:
        scan = options["scan"]
        if scan is not None:
            scan.close()
    return result
