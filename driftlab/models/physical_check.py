"""Thesis table 6.3: fitted coefficients beside the physical ones of ch. 3.5, for the machine's stated geometry.

A physical coefficient is a length times the expansion coefficient alpha_c; the lengths are the
machine's, so they come from the geometry its campaigns state (``machine.geometry`` of
campaign.json, docs/bundle.md), never from the virtual machine's. Without a stated geometry there
is nothing to compare with and the check says so (status ``no geometry``) instead of inventing one.

Relationships (ch. 3.5):

- eq. 3.2, ballscrew of axis k: position x dT of its sites on the joint's own translation:
  alpha_c per mm of travel (L = position); the plain dT of its sites together: alpha_c l, l the
  non-travelled length (``screw_fixed_mm``);
- eqs. 3.1/3.3, a structure mean on the link it belongs to: alpha_c L, L the link's dimension along
  the translation (``links_mm``, Table A.1);
- eqs. 3.4/3.5, a gradient across a structure that bends (``bending``): alpha_c L/H on the angle it
  bends, alpha_c L^2/2H on the deflection at its tip.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, TypedDict, cast

import numpy as np
import pandas as pd

from driftlab.models.structures import SCREW_STRUCTURES, STRUCTURE_ELEMENT
from driftlab.physics.geometry import BENDING_SIDES, GEOMETRY_LINKS
from driftlab.physics.thermal import ALPHA_C
from driftlab.vocabulary import TRANSLATIONS

if TYPE_CHECKING:
    from driftlab.models.features import Feature
    from driftlab.models.standard_model import BundleLike
    from driftlab.physics.geometry import Geometry, GeometryRecord

STATUS_COMPARED = "compared"
STATUS_NO_GEOMETRY = "no geometry"
STATUS_CONFLICT = "conflicting geometry"

LINK_OF_NAME: Mapping[str, str] = GEOMETRY_LINKS
NAME_OF_LINK: Mapping[str, str] = {v: k for k, v in LINK_OF_NAME.items()}
#: the axis each translational joint drives
JOINT_AXIS: Mapping[str, str] = {"phi_x": "X", "phi_y": "Y", "phi_z": "Z"}
COLUMNS = [
    "term",
    "element",
    "param",
    "feature",
    "regression",
    "std_error",
    "physical",
    "unit",
    "relationship",
    "ratio",
    "status",
]


class PhysicalCheckRecord(TypedDict):
    """The JSON form of a :class:`PhysicalCheck`: table 6.3's status beside the table (report and document)."""

    status: str
    note: str
    geometry: GeometryRecord | None
    rows: int
    compared: int


@dataclass
class PhysicalCheck:
    """Table 6.3 and whether it could be made: ``compared``, ``no geometry`` or ``conflicting geometry``."""

    status: str
    table: pd.DataFrame
    geometry: GeometryRecord | None = None
    note: str = ""

    def to_dict(self) -> PhysicalCheckRecord:
        """Return the JSON summary kept beside the table (report and model document ``physical_check``)."""
        compared = int((self.table["status"] == STATUS_COMPARED).sum()) if len(self.table) else 0
        return {
            "status": self.status,
            "note": self.note,
            "geometry": self.geometry,
            "rows": int(len(self.table)),
            "compared": compared,
        }


def _plain(geometry: Geometry | Mapping[str, Any] | None) -> GeometryRecord | None:
    """Return a stated geometry as a plain JSON dict (pydantic model or mapping), None when absent."""
    if geometry is None:
        return None
    if hasattr(geometry, "model_dump"):
        return cast("GeometryRecord", geometry.model_dump(mode="json"))
    return json.loads(json.dumps(dict(geometry)))


def stated_geometries(bundles: Sequence[BundleLike]) -> dict[str, tuple[GeometryRecord, list[str]]]:
    """Return every distinct geometry the campaigns state (``machine.geometry``), keyed by its JSON.

    Each value is (the geometry as plain JSON, the names of the campaigns that state it). This is
    the one reader of stated geometry: the physical check and the fit's chain lengths both use it.
    """
    stated: dict[str, tuple[GeometryRecord, list[str]]] = {}
    for b in bundles:
        g = _plain(getattr(b.meta.machine, "geometry", None))
        if g is not None:
            key = json.dumps(g, sort_keys=True)
            stated.setdefault(key, (g, []))[1].append(str(getattr(b, "name", "?")))
    return stated


def machine_geometry(bundles: Sequence[BundleLike]) -> tuple[str, GeometryRecord | None, str]:
    """Return (status, geometry, note): the one geometry the campaigns of a machine state.

    Campaigns that state none are fine beside one that does; two different stated geometries are
    a conflict, reported as such (no comparison) rather than resolved by a guess.
    """
    stated = stated_geometries(bundles)
    machine = bundles[0].meta.machine.id if bundles else "?"
    if not stated:
        return (
            STATUS_NO_GEOMETRY,
            None,
            (
                f"no campaign of machine {machine} states its geometry (machine.geometry in campaign.json): "
                "the fitted coefficients are not compared with physical ones"
            ),
        )
    if len(stated) > 1:
        who = "; ".join(", ".join(names) for _, names in stated.values())
        return (
            STATUS_CONFLICT,
            None,
            (f"campaigns of machine {machine} state different geometries ({who}): nothing compared"),
        )
    g, names = next(iter(stated.values()))
    src = f" ({g['source']})" if g.get("source") else ""
    return STATUS_COMPARED, g, f"geometry stated by {', '.join(names)}{src}"


def _sides(f: Feature, locations: Mapping[str, str]) -> str | None:
    """Return the opposite sides ("upper-lower") a gradient spans, or None when they cannot be told."""
    if f.label and " " in f.label:
        return f.label.rsplit(" ", 1)[1]
    if len(f.channels) != 2:
        return None
    words = [set(locations.get(c, "").lower().split()) for c in f.channels]
    for pair in BENDING_SIDES:
        a, b = pair.split("-")
        if (a in words[0] and b in words[1]) or (b in words[0] and a in words[1]):
            return pair
    return None


class CoefficientModel(Protocol):
    """What table 6.3 reads of a fitted link or joint parameter (``fitting.ElementModel`` has it)."""

    @property
    def element(self) -> str: ...
    @property
    def param(self) -> str: ...
    @property
    def features(self) -> Sequence[Feature]: ...
    @property
    def coef(self) -> Sequence[float]: ...
    @property
    def std_errors(self) -> Sequence[float]: ...


@dataclass(frozen=True)
class _Physics:
    """The stated geometry as table 6.3 reads it, with the channels' structures, locations and the room."""

    alpha_c: float
    #: element -> its dimensions (mm, Table A.1)
    links: dict[str, tuple[float, ...]]
    #: axis -> the non-travelled length of its ballscrew (mm)
    screws: dict[str, float]
    #: structure -> how it bends (``length_mm``, ``height_mm``, ``across``, ``angle``, ``deflection``)
    bending: dict[str, Mapping[str, Any]]
    structures: Mapping[str, str]
    locations: Mapping[str, str]
    room: Sequence[str]


@dataclass(frozen=True)
class _Relation:
    """A physical coefficient of ch. 3.5 (NaN with ``missing``: the length it needs is not stated)."""

    physical: float
    unit: str
    relationship: str
    missing: str = ""


def _row(m: CoefficientModel, feature: str, fitted: tuple[float, float], rel: _Relation) -> dict[str, Any]:
    """Return one row of table 6.3: the fitted coefficient (value, std error) beside its physical value."""
    reg, se = fitted
    phys = rel.physical
    ok = not rel.missing and phys > 0
    return {
        "term": f"{m.element}.{m.param} {feature}",
        "element": m.element,
        "param": m.param,
        "feature": feature,
        "regression": float(reg),
        "std_error": float(se),
        "physical": float(phys) if ok else float("nan"),
        "unit": rel.unit,
        "relationship": rel.relationship,
        "ratio": abs(float(reg)) / phys if ok else float("nan"),
        "status": STATUS_COMPARED if ok else f"not stated: {rel.missing}",
    }


def _is_screw_dT(ph: _Physics, f: Feature, element: str, param: str) -> bool:
    """Return True for dT of a ballscrew site on its joint's own translation (eq. 3.2, the fixed part)."""
    own = JOINT_AXIS.get(element)
    return bool(
        f.kind == "dT"
        and own
        and param == "d" + own.lower()
        and ph.structures.get(f.channels[0], "") in SCREW_STRUCTURES.get(element, ())
    )


def _relation(ph: _Physics, f: Feature, element: str, param: str) -> _Relation | None:
    """Return the physical coefficient of ``f`` on (element, param) per ch. 3.5 (None: no relationship applies)."""
    own = JOINT_AXIS.get(element)
    if f.kind == "pos_dT" and own and param == "d" + own.lower() and f.label in ("", own):
        return _Relation(ph.alpha_c, "mm/mm/degC", "alpha_c dT L, L = position (eq. 3.2)")
    if f.kind == "mean" and param in TRANSLATIONS and STRUCTURE_ELEMENT.get(f.label) == element:
        if element not in ph.links:
            missing = f"links_mm.{NAME_OF_LINK.get(element, element)}"
            return _Relation(float("nan"), "mm/degC", "alpha_c dT L (eqs. 3.1, 3.3)", missing)
        L = abs(float(ph.links[element][TRANSLATIONS.index(param)]))
        if L > 0:  # no extent along this translation: the relationship does not apply
            return _Relation(ph.alpha_c * L, "mm/degC", f"alpha_c dT L, L = {L:.0f} mm (eqs. 3.1, 3.3)")
        return None
    if f.kind == "gradient" and not any(c in ph.room for c in f.channels):
        owners = {ph.structures.get(c, "") for c in f.channels}
        bent = ph.bending.get(owners.pop()) if len(owners) == 1 else None
        if bent is None or _sides(f, ph.locations) != bent.get("across", "upper-lower"):
            return None  # a structure that states no bending, or a gradient along another direction
        L, H = float(bent["length_mm"]), float(bent["height_mm"])
        if param == bent.get("angle"):
            return _Relation(ph.alpha_c * L / H, "rad/degC", f"alpha_c dT L/H, L = {L:.0f}, H = {H:.0f} mm (eq. 3.4)")
        if param == bent.get("deflection"):
            return _Relation(
                ph.alpha_c * L**2 / (2 * H), "mm/degC", f"alpha_c dT L^2/2H, L = {L:.0f}, H = {H:.0f} mm (eq. 3.5)"
            )
    return None


def _screw_relation(ph: _Physics, element: str) -> _Relation:
    """Return the physical coefficient of a joint's ballscrew sites' dT together (eq. 3.2: alpha_c l)."""
    own = JOINT_AXIS.get(element)
    if own in ph.screws:
        ell = float(ph.screws[own])
        return _Relation(ph.alpha_c * ell, "mm/degC", f"alpha_c dT l, l = {ell:.0f} mm non-travelled screw (eq. 3.2)")
    return _Relation(float("nan"), "mm/degC", "alpha_c dT l (eq. 3.2)", f"screw_fixed_mm.{own}")


def _model_rows(ph: _Physics, m: CoefficientModel) -> list[dict[str, Any]]:
    """Return the rows of table 6.3 of one fitted parameter (its ballscrew sites' dT summed into one)."""
    rows: list[dict[str, Any]] = []
    screw_sum, screw_se, screw_names = 0.0, 0.0, []
    for f, coef, se in zip(m.features, m.coef, m.std_errors):
        if _is_screw_dT(ph, f, m.element, m.param):
            screw_sum += coef
            screw_se = float(np.hypot(screw_se, se))
            screw_names.append(f.channels[0])
            continue
        rel = _relation(ph, f, m.element, m.param)
        if rel is not None:
            rows.append(_row(m, f.name, (coef, se), rel))
    if screw_names:
        name = "+".join(f"dT[{c}]" for c in screw_names)
        rows.append(_row(m, name, (screw_sum, screw_se), _screw_relation(ph, m.element)))
    return rows


def physical_table(
    models: Mapping[tuple[str, str], CoefficientModel],
    structures: Mapping[str, str],
    geometry: Geometry | Mapping[str, Any],
    *,
    locations: Mapping[str, str] | None = None,
    room: Sequence[str] = (),
) -> pd.DataFrame:
    """Return table 6.3 for a stated geometry: each recast coefficient beside its physical value (ch. 3.5).

    A row whose relationship applies but whose length the geometry does not state has ``physical``
    NaN and ``status`` "not stated: <what>".
    """
    g = _plain(geometry) or {}
    ph = _Physics(
        float(g.get("alpha_c_per_degC", ALPHA_C)),
        {LINK_OF_NAME[k]: tuple(v) for k, v in (g.get("links_mm") or {}).items() if k in LINK_OF_NAME},
        dict(g.get("screw_fixed_mm") or {}),
        dict(g.get("bending") or {}),
        structures,
        locations or {},
        room,
    )
    rows = [r for m in models.values() for r in _model_rows(ph, m)]
    return pd.DataFrame(rows, columns=COLUMNS)


def physical_check(
    models: Mapping[tuple[str, str], CoefficientModel],
    structures: Mapping[str, str],
    bundles: Sequence[BundleLike] = (),
    *,
    geometry: Geometry | Mapping[str, Any] | None = None,
    locations: Mapping[str, str] | None = None,
    room: Sequence[str] = (),
) -> PhysicalCheck:
    """Return table 6.3 for the geometry the campaigns state (or ``geometry``), or an explicit "no geometry"."""
    if geometry is not None:
        status, g, note = STATUS_COMPARED, _plain(geometry), "geometry given"
    else:
        status, g, note = machine_geometry(bundles)
    if g is None:
        return PhysicalCheck(status, pd.DataFrame(columns=COLUMNS), None, note)
    table = physical_table(models, structures, g, locations=locations, room=room)
    return PhysicalCheck(status, table, g, note)
