"""The 50 thermocouple sites of the virtual machine (thesis Table 5.1) and their thermal response.

Each site is a first-order node of the thermal network (``driftlab.physics.thermal``): it follows
its local air (a mix of the ceiling and floor room channels T49/T50, by height) plus a steady
rise per unit of each heat source, with its own time constant: minutes near a motor, hours for
the Z column and the base (ch. 3.5, 5.3, 6.3: "time constants ... on the order of three hours").
Heat sources (ch. 5.2, 6.3): the spindle (by rpm), each axis motor by feed, each linear motor
holding position under servo, the electronics cabinet (always on with the machine; it sits on the
back of the Z column, ch. 5.4) - and the room air itself.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from driftlab.vocabulary import AXES

#: heat sources of the network, in the column order of the source matrix
SOURCES: tuple[str, ...] = (
    "spindle",
    "feed_x",
    "feed_y",
    "feed_z",
    "feed_a",
    "feed_b",
    "hold_x",
    "hold_y",
    "hold_z",
    "cabinet",
)
#: exogenous drives: the hall air near the ceiling and near the floor (daily cycle)
EXOGENOUS: tuple[str, ...] = ("hall_ceiling", "hall_floor")
#: source normalisation: u = rpm / SPINDLE_REF_RPM, u = feed / FEED_REF_MM_MIN (deg/min for A/B)
SPINDLE_REF_RPM = 10000.0
FEED_REF_MM_MIN = 4000.0


@dataclass(frozen=True)
class Site:
    """One thermocouple site: name, Table 5.1 location, structure, thermal response."""

    name: str
    location: str
    structure: str
    tau_min: float
    ceiling_weight: float  # share of the ceiling air (T49) in the site's ambient; rest is floor (T50)
    gains: Mapping[str, float] = field(default_factory=dict)  # steady degC rise per unit source
    exogenous: Mapping[str, float] = field(default_factory=dict)  # room sites only


def _s(n: int, loc: str, struct: str, tau_min: float, w: float, **gains: float) -> Site:
    return Site(f"T{n}", loc, struct, tau_min, w, MappingProxyType(dict(gains)))


# Table 5.1 locations; gains/time constants chosen so that the spindle motor site swings by about
# 20 degC (ch. 5.3, Fig. 5.4), the arm's upper/lower gradient reaches ~3.5 degC (Fig. 5.16), and
# slow structures move by 1-2 degC over hours.
_TABLE: tuple[Site, ...] = (
    _s(1, "X axis front left corner", "x_table", 85, 0.5, feed_x=1.2, hold_x=0.1, cabinet=0.2, feed_a=0.2),
    _s(2, "X axis back left corner", "x_table", 90, 0.5, feed_x=1.0, hold_x=0.1, cabinet=0.3, feed_a=0.2),
    _s(3, "X axis back right corner", "x_table", 95, 0.5, feed_x=0.9, hold_x=0.1, cabinet=0.3, feed_b=0.2),
    _s(4, "X axis front right corner", "x_table", 80, 0.5, feed_x=1.3, hold_x=0.1, cabinet=0.2, feed_b=0.2),
    _s(
        5,
        "X-Y carriage front left corner",
        "xy_carriage",
        70,
        0.4,
        feed_x=1.5,
        feed_y=0.8,
        hold_x=0.15,
        hold_y=0.15,
        cabinet=0.2,
    ),
    _s(
        6,
        "X-Y carriage back left corner",
        "xy_carriage",
        75,
        0.4,
        feed_x=1.3,
        feed_y=1.0,
        hold_x=0.15,
        hold_y=0.2,
        cabinet=0.3,
    ),
    _s(
        7,
        "X-Y carriage back right corner",
        "xy_carriage",
        85,
        0.4,
        feed_x=1.1,
        feed_y=1.1,
        hold_x=0.1,
        hold_y=0.2,
        cabinet=0.3,
    ),
    _s(
        8,
        "X-Y carriage front right corner",
        "xy_carriage",
        80,
        0.4,
        feed_x=1.6,
        feed_y=0.7,
        hold_x=0.2,
        hold_y=0.1,
        cabinet=0.2,
    ),
    _s(9, "X axis ballscrew nut", "x_screw", 25, 0.4, feed_x=5.0, hold_x=0.4),
    _s(10, "X axis motor", "x_motor", 12, 0.4, feed_x=8.0, hold_x=1.5),
    _s(11, "X axis ballscrew end bearing", "x_screw", 40, 0.4, feed_x=3.0, hold_x=0.3),
    _s(12, "Lower left front corner of base", "base", 330, 0.2, cabinet=0.3, feed_y=0.15, spindle=0.05),
    _s(13, "Upper left front corner of base", "base", 280, 0.4, cabinet=0.35, feed_y=0.2, feed_x=0.2, spindle=0.1),
    _s(14, "Upper left back corner of base", "base", 270, 0.4, cabinet=0.6, feed_y=0.25, spindle=0.1),
    _s(15, "Lower left back corner of base", "base", 320, 0.2, cabinet=0.55, feed_y=0.2, spindle=0.05),
    _s(16, "Lower right front corner of base", "base", 340, 0.2, cabinet=0.25, feed_x=0.1, spindle=0.05),
    _s(17, "Upper right front corner of base", "base", 290, 0.4, cabinet=0.3, feed_x=0.25, spindle=0.1),
    _s(18, "Upper right back corner of base", "base", 260, 0.4, cabinet=0.65, feed_y=0.2, spindle=0.1),
    _s(19, "Lower right back corner of base", "base", 310, 0.2, cabinet=0.5, feed_y=0.15, spindle=0.05),
    _s(20, "Y axis ballscrew nut", "y_screw", 25, 0.3, feed_y=5.0, hold_y=0.4),
    _s(21, "Y axis motor", "y_motor", 12, 0.2, feed_y=8.0, hold_y=1.5),
    # the Y motor sits at the bottom of the Z column and warms it from below (ch. 4.3)
    _s(22, "Lower left front of Z column", "z_column", 200, 0.3, feed_y=1.0, spindle=0.3, feed_z=0.2, cabinet=0.8),
    _s(23, "Upper left front of Z column", "z_column", 180, 0.7, feed_y=0.4, spindle=0.6, feed_z=0.4, cabinet=0.7),
    _s(24, "Upper right front of Z column", "z_column", 185, 0.7, feed_y=0.35, spindle=0.65, feed_z=0.4, cabinet=0.8),
    _s(25, "Lower right front of Z column", "z_column", 205, 0.3, feed_y=0.9, spindle=0.3, feed_z=0.2, cabinet=0.9),
    # the electronics panel is mounted on the back of the column (ch. 5.4)
    _s(26, "Lower left back of Z column", "z_column", 230, 0.3, feed_y=0.8, spindle=0.2, cabinet=2.0),
    _s(27, "Upper left back of Z column", "z_column", 215, 0.7, feed_y=0.3, spindle=0.4, cabinet=1.7),
    _s(28, "Upper right back of Z column", "z_column", 220, 0.7, feed_y=0.3, spindle=0.4, cabinet=1.8),
    _s(29, "Lower right back of Z column", "z_column", 240, 0.3, feed_y=0.7, spindle=0.2, cabinet=2.1),
    _s(30, "Z axis ballscrew", "z_screw", 25, 0.7, feed_z=5.0, hold_z=0.5, spindle=0.5),
    _s(31, "Z axis motor", "z_motor", 12, 0.8, feed_z=7.0, hold_z=1.5, spindle=0.3),
    _s(32, "Lower left spindle support arm", "spindle_arm", 35, 0.8, spindle=2.5, feed_z=0.3),
    _s(33, "Upper left spindle support arm", "spindle_arm", 28, 0.85, spindle=6.0, feed_z=0.4),
    _s(34, "Upper right spindle support arm", "spindle_arm", 30, 0.85, spindle=6.5, feed_z=0.4),
    _s(35, "Lower right spindle support arm", "spindle_arm", 38, 0.8, spindle=2.3, feed_z=0.3),
    _s(36, "Main spindle bearing and chilling line", "spindle", 8, 0.7, spindle=1.5),
    _s(37, "Main spindle motor", "spindle", 20, 0.8, spindle=20.0),
    _s(38, "Front left corner of rotary base", "rotary_base", 95, 0.3, feed_a=1.5, feed_b=0.5, feed_x=0.4, cabinet=0.1),
    _s(
        39, "Back left corner of rotary base", "rotary_base", 105, 0.3, feed_a=1.3, feed_b=0.6, feed_x=0.3, cabinet=0.15
    ),
    _s(
        40,
        "Back right corner of rotary base",
        "rotary_base",
        110,
        0.3,
        feed_a=1.2,
        feed_b=0.7,
        feed_x=0.3,
        cabinet=0.15,
    ),
    _s(
        41, "Front right corner of rotary base", "rotary_base", 90, 0.3, feed_a=1.6, feed_b=0.4, feed_x=0.4, cabinet=0.1
    ),
    _s(42, "A Axis motor and gear train", "a_drive", 20, 0.3, feed_a=6.0, feed_b=0.3),
    _s(43, "Left side of B axis table", "b_table", 55, 0.45, feed_b=2.0, feed_a=0.6),
    _s(44, "Right side of B axis table", "b_table", 60, 0.45, feed_b=1.8, feed_a=0.7),
    _s(45, "Lower side of B axis table", "b_table", 65, 0.35, feed_b=2.2, feed_a=0.5),
    _s(46, "Top side of B axis table", "b_table", 50, 0.55, feed_b=1.5, feed_a=0.6),
    _s(47, "Left B axis bearing", "b_table", 30, 0.4, feed_b=3.0),
    _s(48, "B axis motor and gear train", "b_drive", 18, 0.4, feed_b=6.0, feed_a=0.5),
    # room thermocouples: air near the top and the floor (ch. 5.3); the machine warms its air a little
    Site(
        "T49",
        "Room temperature at top of machine",
        "room",
        40,
        0.0,
        MappingProxyType({"spindle": 0.3, "cabinet": 0.5}),
        MappingProxyType({"hall_ceiling": 1.0}),
    ),
    Site(
        "T50",
        "Room temperature at floor",
        "room",
        60,
        0.0,
        MappingProxyType({"cabinet": 0.2}),
        MappingProxyType({"hall_floor": 1.0}),
    ),
)

SITES: tuple[Site, ...] = _TABLE
CHANNELS: tuple[str, ...] = tuple(s.name for s in SITES)
SITE_INDEX: Mapping[str, int] = MappingProxyType({s.name: i for i, s in enumerate(SITES)})
ROOM_CHANNELS: tuple[str, ...] = ("T49", "T50")


def structure_channels(structure: str) -> tuple[str, ...]:
    """Return the channels of Table 5.1 that sit on ``structure``."""
    return tuple(s.name for s in SITES if s.structure == structure)


def channel_map() -> dict[str, dict[str, str]]:
    """Return the campaign.json ``channels`` object: channel -> {location, structure}."""
    return {s.name: {"location": s.location, "structure": s.structure} for s in SITES}


#: the thesis' 18 selected thermocouples (ch. 5.4) plus the other two arm corners
THESIS_SELECTION: tuple[str, ...] = (
    "T7",
    "T9",
    "T10",
    "T13",
    "T19",
    "T20",
    "T21",
    "T24",
    "T26",
    "T30",
    "T31",
    "T32",
    "T33",
    "T34",
    "T35",
    "T37",
    "T42",
    "T45",
    "T49",
    "T50",
)
#: the model channels written to campaign.json (the user's sensor selection per axis). Every axis's
#: measurement carries every element's errors at home, so each list holds every driver; Z leaves
#: out the Y motor T21, whose heat reaching the column is the catalogue's unmapped_channel story (ch. 4.3)
MODEL_CHANNELS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {ax: tuple(c for c in THESIS_SELECTION if not (ax == "Z" and c == "T21")) for ax in AXES}
)
