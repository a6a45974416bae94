"""The machine envelope of a model document: where the axes may go and what a correction may be.

A model is safe to send to a machine only inside what it knows: the axes' travel (the controller's
soft limits, mm for X Y Z and degrees for A B), the largest correction per axis that a thermal
model can plausibly mean (thermal errors are tens of micrometres, ch. 1; a correction of metres is
a broken model or broken temperatures, never drift), and the temperatures each channel was fitted
on (``ModelDocument.inputs[c].min/max``) widened by a stated margin. The compensator refuses
anything outside it before the first byte is written or sent (``compensator.guard``).

The envelope travels with the document (``ModelDocument.envelope``) or comes from a machine file
(``driftlab compensate --machine-file``, JSON or YAML with the same keys); a file's values take
precedence over the document's, key by key.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

from pydantic import BaseModel, ConfigDict, Field, StrictFloat, field_validator

from driftlab.errors import ValidationError
from driftlab.vocabulary import AXES, Axis

#: the largest correction a thermal model may command per axis (mm for X Y Z, degrees for A B) unless stated
DEFAULT_MAX_CORRECTION: Final[Mapping[Axis, float]] = {"X": 1.0, "Y": 1.0, "Z": 1.0, "A": 0.1, "B": 0.1}
#: how far (degC) a reading may leave the range its channel was fitted on before it is refused
DEFAULT_EXTRAPOLATION_MARGIN_DEGC: Final = 5.0
#: the most an envelope may allow (issue 34): a thermal error is tens of micrometres (ch. 1), so a stated
#: largest correction above a few millimetres (or a degree) or a margin of more than tens of degC is a
#: typo or a guard switched off, not a machine: such documents and machine files are refused
MAX_CORRECTION_BOUND: Final[Mapping[str, float]] = {"X": 5.0, "Y": 5.0, "Z": 5.0, "A": 1.0, "B": 1.0}
MAX_MARGIN_DEGC: Final = 30.0


class Envelope(BaseModel):
    """Travel (soft limits) per axis, the largest plausible correction per axis, the extrapolation margin."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: (low, high) per axis: mm for X Y Z, degrees for A B; axes not listed are not limited
    travel: dict[Axis, tuple[StrictFloat, StrictFloat]] = Field(default_factory=dict)
    #: per axis (mm for X Y Z, degrees for A B)
    max_correction: dict[Axis, StrictFloat] = Field(default_factory=lambda: dict(DEFAULT_MAX_CORRECTION))
    extrapolation_margin_degC: StrictFloat = Field(
        default=DEFAULT_EXTRAPOLATION_MARGIN_DEGC, ge=0, le=MAX_MARGIN_DEGC, allow_inf_nan=False
    )
    #: where the envelope came from (a machine file, a plan), for messages
    source: str = Field(default="", max_length=200)

    @field_validator("travel")
    @classmethod
    def _travel(cls, value: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
        """Require finite limits, low below high."""
        for axis, (lo, hi) in value.items():
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"travel of {axis} must be two finite numbers, low < high (got {lo}, {hi})")
        return value

    @field_validator("max_correction")
    @classmethod
    def _max_correction(cls, value: dict[str, float]) -> dict[str, float]:
        """Require positive finite limits no larger than MAX_CORRECTION_BOUND."""
        for axis, v in value.items():
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"max_correction of {axis} must be a positive finite number (got {v})")
            bound = MAX_CORRECTION_BOUND[axis]
            if v > bound:
                unit = "deg" if axis in "AB" else "mm"
                raise ValueError(
                    f"max_correction of {axis} {v:g} {unit} is above {bound:g} {unit}: no thermal error is that large"
                )
        return value

    def limits(self) -> tuple[list[float], list[float], list[float]]:
        """Return (low, high, largest correction) per axis in AXES order (-inf, inf, inf where not stated)."""
        travel = {str(a): v for a, v in self.travel.items()}
        largest = {str(a): v for a, v in self.max_correction.items()}
        lo = [travel[a][0] if a in travel else -math.inf for a in AXES]
        hi = [travel[a][1] if a in travel else math.inf for a in AXES]
        mc = [largest.get(a, math.inf) for a in AXES]
        return lo, hi, mc


def envelope_from_mapping(data: Any, name: str = "machine file") -> Envelope:
    """Return the envelope of a mapping (``travel``, ``max_correction``, ``extrapolation_margin_degC``).

    Strict: a string or a boolean is not a number. ValidationError names the file and the problem.
    """
    if not isinstance(data, Mapping):
        raise ValidationError(f"{name}: expected a mapping with travel, max_correction, extrapolation_margin_degC")
    body = dict(data)
    try:
        if isinstance(body.get("max_correction"), Mapping):
            body["max_correction"] = {**DEFAULT_MAX_CORRECTION, **body["max_correction"]}
        body.setdefault("source", name)
        return Envelope.model_validate(body)
    except Exception as exc:  # pydantic.ValidationError -> one line
        if isinstance(exc, ValidationError):
            raise
        lines = [ln.strip().split(" [type=")[0] for ln in str(exc).splitlines()[1:3]]
        raise ValidationError(f"{name}: {': '.join(lines)}") from None


def merge(base: Envelope | None, override: Envelope | None) -> Envelope | None:
    """Return ``base`` with what ``override`` states taking precedence, key by key (None: neither)."""
    if base is None or override is None:
        return override or base
    given = override.model_fields_set
    return Envelope(
        travel={**base.travel, **override.travel},
        max_correction={**base.max_correction, **override.max_correction}
        if "max_correction" in given
        else base.max_correction,
        extrapolation_margin_degC=override.extrapolation_margin_degC
        if "extrapolation_margin_degC" in given
        else base.extrapolation_margin_degC,
        source=", ".join(s for s in (base.source, override.source) if s),
    )
