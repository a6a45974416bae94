"""A machine's stated geometry: the lengths of the physical relationships of ch. 3.5 (thesis table 6.3).

Stated in campaign.json as ``machine.geometry`` (docs/bundle.md), in a scenario's or a plan's
``machine`` block, and kept in the model document beside the table it was used for. A leaf
module (pydantic only): bundles, plans, the virtual machine and the models all read it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Literal, TypedDict, cast

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from driftlab.physics.thermal import ALPHA_C
from driftlab.vocabulary import LinearAxis, Rotation, Translation

#: the fixed links of Table A.1 by the name a geometry block gives them (the HTM chain's T1..T6, ch. 4)
GEOMETRY_LINKS: Mapping[str, str] = {
    "spindle_head": "T1",
    "column": "T2",
    "carriage": "T3",
    "table": "T4",
    "rotary_support": "T5",
    "part_table": "T6",
}
LinkName = Literal["spindle_head", "column", "carriage", "table", "rotary_support", "part_table"]
#: opposite sides of a structure a bending gradient may span (the words of the sites' locations)
BENDING_SIDES = ("upper-lower", "top-bottom", "front-back", "left-right")
#: the largest length a geometry may state (mm): a larger one is a units mistake
MAX_GEOMETRY_MM = 1e5
_MAX_TEXT = 200
_CONTROL = re.compile(r"[\x00-\x1f\x7f\ud800-\udfff]")


class BendingRecord(TypedDict):
    """The JSON form of a :class:`Bending`."""

    length_mm: float
    height_mm: float
    across: str
    angle: Rotation | None
    deflection: Translation | None


class GeometryRecord(TypedDict, total=False):
    """The JSON form of a :class:`Geometry` (campaign.json's ``machine.geometry``, the model document's).

    Not total: a geometry given as a plain mapping is read as it stands.
    """

    source: str
    alpha_c_per_degC: float
    links_mm: dict[str, list[float]]  # (a, b, c) per link name
    screw_fixed_mm: dict[str, float]
    bending: dict[str, BendingRecord]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Bending(_Strict):
    """A structure that bends under a gradient across it: a cantilever of length L and height H (eqs. 3.4-3.5)."""

    length_mm: float = Field(gt=0, le=MAX_GEOMETRY_MM, allow_inf_nan=False)
    height_mm: float = Field(gt=0, le=MAX_GEOMETRY_MM, allow_inf_nan=False)
    #: the pair of opposite sides (site location words) the gradient spans, across the height H
    across: Literal["upper-lower", "top-bottom", "front-back", "left-right"] = "upper-lower"
    #: the rotation the gradient bends the structure by (eq. 3.4) and the deflection at its tip (eq. 3.5)
    angle: Rotation | None = None
    deflection: Translation | None = None


class Geometry(_Strict):
    """The machine's stated dimensions for the physical relationships of ch. 3.5 (thesis table 6.3).

    Every part is optional: a relationship whose length is not stated is not compared.
    """

    source: str = Field(default="", max_length=_MAX_TEXT)
    #: expansion coefficient of the castings (eq. 3.1: 12.1e-6 /degC for cast iron and steel)
    alpha_c_per_degC: float = Field(default=ALPHA_C, gt=0, le=1e-4, allow_inf_nan=False)
    #: fixed links of the chain (Table A.1): (a, b, c) in mm along X, Y, Z
    links_mm: dict[LinkName, tuple[float, float, float]] = Field(default_factory=dict)
    #: non-travelled length l of each ballscrew, motor to nut at position 0 (eq. 3.2)
    screw_fixed_mm: dict[LinearAxis, float] = Field(default_factory=dict)
    #: structures that bend under a gradient (eqs. 3.4-3.5), by the ``structure`` name of their channels
    bending: dict[str, Bending] = Field(default_factory=dict)

    @field_validator("links_mm")
    @classmethod
    def _links(cls, value: dict[str, tuple[float, float, float]]) -> dict[str, tuple[float, float, float]]:
        """Require finite link dimensions within the plausible range."""
        for name, abc in value.items():
            if not all(math.isfinite(v) and abs(v) <= MAX_GEOMETRY_MM for v in abc):
                raise ValueError(f"link {name}: dimensions must be finite mm within +-{MAX_GEOMETRY_MM:g}")
        return value

    @field_validator("screw_fixed_mm")
    @classmethod
    def _screws(cls, value: dict[str, float]) -> dict[str, float]:
        """Require positive, finite, plausible non-travelled lengths."""
        for axis, v in value.items():
            if not (math.isfinite(v) and 0 < v <= MAX_GEOMETRY_MM):
                raise ValueError(f"screw_fixed_mm.{axis}: a length in mm, > 0 and <= {MAX_GEOMETRY_MM:g}")
        return value

    @field_validator("bending")
    @classmethod
    def _bending(cls, value: dict[str, Bending]) -> dict[str, Bending]:
        """Require structure names of plain text and a bending that states what it bends."""
        for name, b in value.items():
            if not name or len(name) > _MAX_TEXT or _CONTROL.search(name):
                raise ValueError(f"bending: {name[:40]!r} is not a structure name")
            if b.angle is None and b.deflection is None:
                raise ValueError(f"bending.{name}: state the angle (eq. 3.4) or the deflection (eq. 3.5) it causes")
        return value

    @model_validator(mode="after")
    def _something(self) -> Geometry:
        """Refuse a geometry that states no length at all (state none instead)."""
        if not (self.links_mm or self.screw_fixed_mm or self.bending):
            raise ValueError("a geometry states at least one of links_mm, screw_fixed_mm, bending")
        return self

    def document(self) -> GeometryRecord:
        """Return the JSON form (as campaign.json and the model document hold it)."""
        return cast("GeometryRecord", self.model_dump(mode="json"))
