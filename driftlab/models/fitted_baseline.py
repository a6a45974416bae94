"""The diagnosis' baseline: the model ``driftlab fit`` registers, fitted on the training part only (issue 33).

Diagnosis judges the model the compensator loads, not a regression of its own: the bundle is fitted
by the fit's pipeline (``models.fitting.fit_bundles``: screening, allocation through the HTM chain,
per-link physical terms, joint adjustment, measuring-line corrections) with the time split of
``models.split`` - the same training rows the diagnosis decides on - and its prediction of every
reading, as the instrument reads it (zeroed sessions less their datum), is the baseline of each
(axis, term). The held-out figure the diagnosis states for a term is then the one ``driftlab fit``
states for it with the same split.

Where the bundle cannot be fitted through the chain (too few terms or samples for an allocation, no
stage the fit trains on), :func:`fit_baseline` says why and the diagnosis keeps its per-term model.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from driftlab.errors import DriftlabError
from driftlab.models.features import Feature
from driftlab.models.findings import Findings
from driftlab.models.fitting import FitOptions, FitResult, fit_bundles, predict_without
from driftlab.models.split import TIME_SPLIT
from driftlab.models.standard_model import BundleLike, PreparedBundle, TermData

log = logging.getLogger(__name__)


@dataclass
class FittedBaseline:
    """The fitted model of a bundle (training part only) and its prediction of every reading."""

    result: FitResult | None
    #: why there is no fitted model ('' when there is one)
    why: str = ""
    #: (axis, term) -> reading rows of the prediction frame, indexed by (time_s, position, direction)
    _by_term: dict[tuple[str, str], pd.DataFrame] = field(default_factory=dict)
    #: (axis, on its positioning term) -> the same without the catalogue effects the model carries there
    _without: dict[tuple[str, bool], dict[tuple[str, str], pd.DataFrame]] = field(default_factory=dict)

    @property
    def available(self) -> bool:
        """Return whether the bundle could be fitted through the chain."""
        return self.result is not None

    def covers(self, axis: str, term: str) -> bool:
        """Return whether the fitted model predicts the readings of (axis, term)."""
        return (axis, term) in self._by_term

    def predict(self, td: TermData) -> np.ndarray | None:
        """Return the fitted model's prediction at every row of ``td`` (None where it has none for a row)."""
        return _at(self._by_term.get((td.axis, td.term)), td)

    def predict_without_carried(self, td: TermData) -> np.ndarray | None:
        """Return the prediction at ``td``'s rows without the catalogue effects the model carries on its axis.

        Those are the terms the spec's standard model lacks and the fitted model may already hold
        along the moving axis: its approach direction (``dir[X]``: a reversal, on every term of the
        axis) and position x dT (``pos[X]*dT[k]``: the screw's expansion, eq. 3.2, on the axis' own
        positioning term X/dx). The diagnosis must earn them from the data like any other effect: its
        search starts without them, so that it names them (on the channel the residual follows) and
        states their held-out gain.
        """
        if self.result is None or self.result.steps is None:
            return None
        screw = positioning_term(td.axis) == td.term
        key = (td.axis, screw)
        if key not in self._without:
            steps = self.result.steps
            frame = predict_without(steps, lambda f: carried_on(f, td.axis, screw))
            self._without[key] = _by_term(frame)
        return _at(self._without[key].get((td.axis, td.term)), td)


def positioning_term(axis: str) -> str | None:
    """Return the translation along a linear axis (X/dx, Y/dy, Z/dz), where a screw's growth shows."""
    return {"X": "dx", "Y": "dy", "Z": "dz"}.get(axis)


def carried_on(f: Feature, axis: str, screw: bool) -> bool:
    """Return whether a fitted term is a catalogue effect along ``axis`` (its direction; position x dT of it)."""
    return f.label == axis and (f.kind == "direction" or (screw and f.kind == "pos_dT"))


def _at(frame: pd.DataFrame | None, td: TermData) -> np.ndarray | None:
    """Return a prediction frame's values at the rows of ``td`` (None unless every row has one)."""
    if frame is None:
        return None
    keys = pd.MultiIndex.from_arrays([td.t, td.pos, td.direction.astype(float)])
    pred = frame["predicted"].reindex(keys).to_numpy(float)
    return pred if np.all(np.isfinite(pred)) else None


def _by_term(pred: pd.DataFrame) -> dict[tuple[str, str], pd.DataFrame]:
    """Return the first campaign's predictions per (axis, term), indexed by (time_s, position, direction)."""
    out: dict[tuple[str, str], pd.DataFrame] = {}
    first = pred[pred["campaign"] == 0]
    for (axis, term), g in first.groupby(["axis", "term"], sort=False):
        idx = pd.MultiIndex.from_arrays([g["time_s"], g["position"], g["direction"].astype(float)])
        frame = pd.DataFrame({"predicted": g["predicted"].to_numpy(float)}, index=idx)
        out[(str(axis), str(term))] = frame[~frame.index.duplicated()]
    return out


#: the least a bundle must measure for the chain's allocation to tell links apart (ch. 4.3): lines of
#: several axes (a link is told from another by the axes that move it) and enough of them
MIN_AXES, MIN_LINES = 2, 6


def chain_fittable(prep: PreparedBundle) -> str:
    """Return why a prepared bundle cannot be fitted through the chain ('' when it can)."""
    lines = {(td.axis, td.term) for td in prep.terms}
    axes = {a for a, _ in lines}
    if len(axes) < MIN_AXES or len(lines) < MIN_LINES:
        return (
            f"the bundle measures {len(lines)} line(s) of {len(axes)} axis/axes: the chain's allocation needs "
            f"at least {MIN_LINES} lines of {MIN_AXES} axes (each term keeps its own model)"
        )
    return ""


def fit_baseline(
    bundle: BundleLike, holdout_fraction: float, prep: PreparedBundle | None = None, findings: Findings | None = None
) -> FittedBaseline:
    """Return the fitted baseline of a bundle: the fit's pipeline on the diagnosis' training rows, with ``findings``."""
    why = chain_fittable(prep) if prep is not None else ""
    if why:
        return FittedBaseline(None, why)
    opts = FitOptions(
        holdout_fraction=holdout_fraction,
        split=TIME_SPLIT,
        network=False,  # the neural comparison is a table of the fit's report, not part of the model
        virtual_sensors=False,  # the document's virtual sensors are for the compensator, not the prediction
        findings=findings,  # offered as candidates, as `driftlab fit --findings` does by default
    )
    try:
        result = fit_bundles([bundle], opts)
    except DriftlabError as exc:  # the chain cannot be fitted on this bundle: the per-term model stands
        log.info("diagnosis: no fitted baseline: %s", exc)
        return FittedBaseline(None, str(exc))
    pred = result.predictions
    if pred is None or pred.empty:
        return FittedBaseline(None, "the fit predicts no reading")
    return FittedBaseline(result, "", _by_term(pred))
