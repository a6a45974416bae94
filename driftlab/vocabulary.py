"""The words every layer shares: axes, error terms, units, channel names.

Defined once here; every module that spells an axis or a term list imports it from this module.

* Axes are the machine's five joints (ch. 4.2): three linear X, Y, Z and two rotary A (about X)
  and B (about Y).
* Error terms are the six components of an error vector in the order of the small-angle HTM of
  eq. 4.8: ``(alpha, beta, gamma, dx, dy, dz)`` = rotations about X, Y, Z then translations.
* Units inside driftlab: lengths in mm, angles in rad, temperatures in degC, times in s.
  People read um and urad (``labels.display_unit``). Rotary positions in files are degrees.
* Heat sources of a stage (:data:`HEAT_SOURCES`), one word each for the daemon, the simulator and
  every reader: ``off`` (machine off), ``idle`` (powered, no heat source), ``spindle``, ``feed`` (an
  axis oscillating), ``combined`` (spindle and axis), ``motor_hold``. Campaigns stored before the
  words were one used ``none``, ``axis``, ``spindle+axis``: :func:`heat_source` reads both.
* Channels (thermocouples, bundle columns, instrument setup ids) are named by
  :data:`CHANNEL_NAME`: a letter or digit, then letters, digits, ``_ . -``, at most 64 in all.
"""

from __future__ import annotations

import re
from typing import Literal

Axis = Literal["X", "Y", "Z", "A", "B"]
LinearAxis = Literal["X", "Y", "Z"]
Term = Literal["alpha", "beta", "gamma", "dx", "dy", "dz"]
Rotation = Literal["alpha", "beta", "gamma"]
Translation = Literal["dx", "dy", "dz"]

#: the five joints of the machine (ch. 4.2)
AXES: tuple[str, ...] = ("X", "Y", "Z", "A", "B")
LINEAR_AXES: tuple[str, ...] = ("X", "Y", "Z")
ROTARY_AXES: tuple[str, ...] = ("A", "B")

#: the error vector's components in the order of eq. 4.8 (rad, rad, rad, mm, mm, mm)
TERMS: tuple[str, ...] = ("alpha", "beta", "gamma", "dx", "dy", "dz")
ROTATIONS: tuple[str, ...] = ("alpha", "beta", "gamma")
TRANSLATIONS: tuple[str, ...] = ("dx", "dy", "dz")

#: each linear axis's own translation and each axis's own rotation (positioning and roll)
OWN_TRANSLATION: dict[str, str] = {"X": "dx", "Y": "dy", "Z": "dz"}
OWN_ROTATION: dict[str, str] = {"X": "alpha", "Y": "beta", "Z": "gamma", "A": "alpha", "B": "beta"}

#: units of the stored values
LENGTH_UNIT = "mm"
ANGLE_UNIT = "rad"

#: the heat source of a stage (ISO 230-3's tests are chosen by it: off/idle ETVE, spindle, feed)
HEAT_SOURCES: tuple[str, ...] = ("off", "idle", "spindle", "feed", "combined", "motor_hold")
#: the plan's heat kinds (spindle, axis, motor_hold) and the spellings of campaigns stored before
_HEAT_KIND = {"none": "idle", "": "idle", "axis": "feed", "spindle": "spindle", "motor_hold": "motor_hold"}


def heat_source(label: str | None) -> str:
    """Return the one word for a stage's heat source, from either spelling ("spindle+axis" -> "combined")."""
    text = str(label or "").strip().lower()
    if text in HEAT_SOURCES:
        return text
    kinds = {_HEAT_KIND.get(k.strip(), k.strip()) for k in text.split("+")} - {"idle"}
    if not kinds:
        return "idle"
    if len(kinds) == 1:
        return kinds.pop()
    return "combined"


#: a channel's (or instrument setup's) name
CHANNEL_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")


def is_angle(term: str) -> bool:
    """Return True for a rotation term (rad), False for a translation (mm)."""
    return term in ROTATIONS


def term_unit(term: str) -> str:
    """Return the stored unit of a term: rad for rotations, mm for translations."""
    return ANGLE_UNIT if is_angle(term) else LENGTH_UNIT


def valid_channel_name(name: str) -> bool:
    """Return True when ``name`` may name a channel (and is not the reserved ``time_s``)."""
    return bool(CHANNEL_NAME.match(name)) and name != "time_s"


#: the effect catalogue of the bundle spec (sections 3 and 4): every kind a diagnosis may report, in
#: the spec's order (``models.effects`` screens them, ``models.findings`` reads them back, the
#: diagnosis cites each one's thesis sections)
EFFECT_KINDS: tuple[str, ...] = (
    "reversal",
    "screw_expansion",
    "unmapped_channel",
    "thermal_lag",
    "sensor_fault",
    "drift",
    "quadratic",
    "operating_condition",
    "sensor_drift",
    "datum_shift",
    "unsensed_source",
    "direction_thermal",
)
