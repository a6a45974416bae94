"""Instrument setups of a campaign plan: what is mounted, which error terms it delivers, over what range.

Table 5.3 of the thesis says how each of the thirty motion-error terms (five axes x six terms) was
measured: a laser interferometer for position, straightness and the two angles it can see (linear
optics, straightness optics, angular optics: figs. 5.7-5.9), proximity sensors on reference
surfaces for the roll of a linear axis (two parallel reference lines, fig. 5.11) and for the
run-outs and tilts of a rotary axis (arcs/cylinders centred on its axis, figs. 5.12-5.13, the
ISO 230-7 reference cylinder or sphere), and a reference artefact for squareness. A setup is one
such mounting; it stays for a stage and may change between stages, as on a real machine.

What a setup delivers (``deliverable``):

====================  ==========================  ===================================================
instrument            optics / fixture            terms of its axis
====================  ==========================  ===================================================
laser                 linear                      the axis' own position (X/dx, Y/dy, Z/dz)
laser                 straightness                one perpendicular translation at a time (fig. 5.8)
laser                 angular                     pitch or yaw of a linear axis; a rotary axis' own
                                                  angle within the optics' +-10 deg (fig. 5.9), the
                                                  full travel with the counter-rotating table (5.10)
proximity             reference_edge              roll of a linear axis (X/alpha, Y/beta, Z/gamma)
proximity             cylinder, sphere            rotary axis: three run-outs and the two tilts
probe                 reference_square            squareness to another linear axis (ch. 5.5)
probe                 sphere                      location of a rotary axis' centre (ch. 5.5, 3 points)
probe                 spindle_bar                 spindle growth: Z/dx, Z/dy, Z/dz at five points
====================  ==========================  ===================================================

The laser optics see one quantity per alignment (a straightness or angular optic is turned to the
other direction by remounting it), so a laser setup delivers one term; a proximity array delivers
every term its sensors resolve. A laser is zeroed when it is set up: its readings are relative to
the first reading of the setup (``datum: session``); proximity sensors and the probe read against a
stable artefact (``datum: absolute``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from driftlab.vocabulary import AXES, OWN_ROTATION, OWN_TRANSLATION, ROTATIONS, TRANSLATIONS, Axis, Term
from driftlab.vocabulary import LINEAR_AXES as LINEAR
from driftlab.vocabulary import ROTARY_AXES as ROTARY

#: the coverage table's column order: translations first
TERMS: tuple[str, ...] = (*TRANSLATIONS, *ROTATIONS)

#: Table 5.3: the angular optics see the two angles other than the roll of a linear axis
LASER_ANGLES = {ax: tuple(t for t in ("alpha", "beta", "gamma") if t != OWN_ROTATION[ax]) for ax in LINEAR}
#: Table 5.3: the straightness optics see the two translations perpendicular to a linear axis
STRAIGHTNESS = {ax: tuple(t for t in ("dx", "dy", "dz") if t != OWN_TRANSLATION[ax]) for ax in LINEAR}
#: Table 5.3 (Prox / Ref.): a rotary axis' run-outs (three translations) and tilts (the other two angles)
ROTARY_PROXIMITY = {
    ax: ("dx", "dy", "dz", *(t for t in ("alpha", "beta", "gamma") if t != OWN_ROTATION[ax])) for ax in ROTARY
}
#: fig. 5.9: the angular optics lose the beam beyond +-10 deg of rotation (degrees)
ANGULAR_OPTICS_RANGE_DEG = 10.0
#: squareness pairs (ch. 5.5, Table 5.3 "Reference"): stored as the angle error of the axis that carries
#: it in the chain T1 PhiZ T2 PhiY T3 PhiX (eq. 4.12): Y-Z in T2 (Y/alpha), X-Z and X-Y in T3 (X/beta, X/gamma)
SQUARENESS = {"YZ": ("Y", "alpha"), "XZ": ("X", "beta"), "XY": ("X", "gamma")}
#: location of a rotary axis (ch. 5.5: three points on a reference surface, the arc's centre): the two
#: offsets of the centre perpendicular to the axis, stored as that axis' translations at its zero
LOCATION = {"A": ("dy", "dz"), "B": ("dx", "dz")}
#: spindle growth with the touch probe on the spindle bar (five points): the tool point at home
SPINDLE_BAR = ("dx", "dy", "dz")

LaserOptics = Literal["linear", "straightness", "angular"]
Fixture = Literal["reference_edge", "cylinder", "sphere", "reference_square", "spindle_bar"]


def cell(axis: str, term: str) -> str:
    """Return the coverage-table name of an (axis, term) pair, e.g. ``X/dx``."""
    return f"{axis}/{term}"


def all_cells() -> list[str]:
    """Return the thirty motion-error terms of the five-axis model (ch. 4), axis-major."""
    return [cell(a, t) for a in AXES for t in TERMS]


def deliverable(instrument: str, kind: str | None, axis: str) -> tuple[str, ...]:
    """Return the terms of ``axis`` an instrument with these optics/fixture can deliver (empty: none)."""
    if instrument == "laser":
        if kind == "linear":
            return (OWN_TRANSLATION[axis],) if axis in LINEAR else ()
        if kind == "straightness":
            return STRAIGHTNESS.get(axis, ())
        if kind == "angular":
            return LASER_ANGLES[axis] if axis in LINEAR else (OWN_ROTATION[axis],)
        return ()
    if instrument == "proximity":
        if kind == "reference_edge":
            return (OWN_ROTATION[axis],) if axis in LINEAR else ()
        if kind in ("cylinder", "sphere"):
            return ROTARY_PROXIMITY.get(axis, ())
        return ()
    if instrument == "probe":
        if kind == "reference_square":
            return tuple(t for ax, t in SQUARENESS.values() if ax == axis)
        if kind == "sphere":
            return LOCATION.get(axis, ())
        if kind == "spindle_bar":
            return SPINDLE_BAR if axis == "Z" else ()
    return ()


class Setup(BaseModel):
    """One instrument mounting: the instrument, its optics or fixture, the axis it measures and its terms."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    instrument: Literal["laser", "proximity", "probe"]
    optics: LaserOptics | None = Field(default=None, description="laser optics (figs. 5.7-5.9)")
    fixture: Fixture | None = Field(default=None, description="proximity reference surface or probe artefact")
    axis: Axis
    terms: list[Term] = Field(min_length=1, description="the error terms of `axis` this setup is read for")
    counter_rotating: bool = Field(
        default=False, description="angular optics on the counter-rotating table (fig. 5.10): full rotary travel"
    )
    pose: dict[Axis, float] = Field(
        default_factory=dict, description="where the other axes stand while this setup measures (mm, deg; default 0)"
    )
    reference: dict[str, Any] = Field(
        default_factory=dict, description="where the instrument sat, the artefact, its stated uncertainty"
    )

    @model_validator(mode="after")
    def _consistent(self) -> Setup:
        """Check the setup can deliver its terms (Table 5.3) and names what is mounted."""
        kind = self.kind
        if self.instrument == "laser" and (self.optics is None or self.fixture is not None):
            raise ValueError("a laser setup names its optics (linear, straightness or angular), not a fixture")
        if self.instrument != "laser" and (self.fixture is None or self.optics is not None):
            raise ValueError(f"a {self.instrument} setup names its fixture, not optics")
        can = deliverable(self.instrument, kind, self.axis)
        if not can:
            raise ValueError(f"{self.instrument} with {kind} measures nothing on the {self.axis} axis (table 5.3)")
        bad = [t for t in self.terms if t not in can]
        if bad:
            raise ValueError(
                f"{self.instrument} with {kind} cannot deliver {', '.join(cell(self.axis, t) for t in bad)} "
                f"(it delivers {', '.join(cell(self.axis, t) for t in can)}; table 5.3)"
            )
        if len(set(self.terms)) != len(self.terms):
            raise ValueError("a term is listed twice")
        if self.instrument == "laser" and len(self.terms) != 1:
            raise ValueError("laser optics see one term per alignment: use one setup per term (figs. 5.7-5.9)")
        if self.axis in self.pose:
            raise ValueError(f"pose gives the other axes; {self.axis} is the one this setup moves")
        if self.counter_rotating and not (self.optics == "angular" and self.axis in ROTARY):
            raise ValueError("counter_rotating applies to angular optics on a rotary axis (fig. 5.10)")
        return self

    @property
    def kind(self) -> str:
        """Return the optics (laser) or the fixture (proximity, probe)."""
        return str(self.optics if self.instrument == "laser" else self.fixture)

    @property
    def datum(self) -> str:
        """Return 'session' (zeroed when set up: the laser) or 'absolute' (read against an artefact)."""
        return "session" if self.instrument == "laser" else "absolute"

    def cells(self) -> list[str]:
        """Return the coverage cells this setup delivers, e.g. ['X/dx']."""
        return [cell(self.axis, t) for t in self.terms]

    def range_deg(self) -> float | None:
        """Return the rotary range the setup sees either side of 0 (None: the whole travel)."""
        if (
            self.instrument == "laser"
            and self.optics == "angular"
            and self.axis in ROTARY
            and not self.counter_rotating
        ):
            return ANGULAR_OPTICS_RANGE_DEG
        return None

    def full_pose(self, position: float) -> dict[str, float]:
        """Return the commanded pose x, y, z (mm), a, b (deg) with this setup's axis at ``position``."""
        pose = {ax.lower(): float(self.pose.get(ax, 0.0)) for ax in AXES}  # type: ignore[call-overload]
        pose[self.axis.lower()] = float(position)
        return pose

    def bundle_entry(self) -> dict[str, Any]:
        """Return the campaign.json ``setups`` entry of bundle v2."""
        out: dict[str, Any] = {
            "instrument": self.instrument,
            "axis": self.axis,
            "terms": self.cells(),
            "datum": self.datum,
        }
        out["optics" if self.instrument == "laser" else "fixture"] = self.kind
        if self.counter_rotating:
            out["counter_rotating"] = True
        ref = dict(self.reference)
        if self.pose:
            ref.setdefault("pose", {k: float(v) for k, v in self.pose.items()})
        if ref:
            out["reference"] = ref
        return out


def default_laser_setup(axis: str, term: str) -> Setup:
    """Return the laser setup that measures ``term`` of ``axis`` (plans written before setups existed)."""
    if axis in LINEAR:
        optics = (
            "linear" if term == OWN_TRANSLATION[axis] else ("straightness" if term in STRAIGHTNESS[axis] else "angular")
        )
    else:
        optics = "angular"
    return Setup(instrument="laser", optics=optics, axis=axis, terms=[term])  # type: ignore[arg-type,list-item]


def coverage(measured: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    """Return cell -> the stage names that measure it, for all thirty cells (empty list: not measured)."""
    out: dict[str, list[str]] = {c: [] for c in all_cells()}
    for c, stage in measured:
        if stage not in out[c]:
            out[c].append(stage)
    return out


def coverage_table(cov: Mapping[str, Sequence[str]]) -> list[list[str]]:
    """Return the coverage as rows axis x terms (a cell: the first stage that measures it, '-' for none)."""
    rows = [["axis", *TERMS]]
    for a in AXES:
        row = [a]
        for t in TERMS:
            stages = cov.get(cell(a, t), [])
            row.append(stages[0] + (f" +{len(stages) - 1}" if len(stages) > 1 else "") if stages else "-")
        rows.append(row)
    return rows
