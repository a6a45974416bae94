"""The controllers driftlab writes tables for: one entry per generation, with what its manual allows.

:class:`Export` is what every writer returns (the files' text and the settings beside them, named in
the controller's own terms); :data:`CONTROLLERS` holds each generation's point limit and spacing rule.
See docs/exports.md for the sources.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from driftlab.errors import ValidationError


@dataclass(frozen=True)
class Export:
    """A controller table: its file(s) (suffix -> text, "" for the main file) and the settings beside them."""

    format: str
    files: dict[str, str]
    settings: dict[str, Any] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    @property
    def text(self) -> str:
        """Return the main file's text."""
        return self.files[""]


@dataclass(frozen=True)
class Controller:
    """One controller generation: its writer family, its table's point limit and its spacing rule."""

    name: str
    family: str  # linuxcnc, siemens, heidenhain, fanuc
    max_points: int  # points of one table (per direction where the directions have their own)
    spacing: str = "any"  # "any", "detection-unit" (an integer number of units), "power-of-two" (2^k x 0.1 um)
    title: str = ""


CONTROLLERS: dict[str, Controller] = {
    c.name: c
    for c in (
        # src/emc/motion/motion.h EMCMOT_COMP_SIZE: at most 256 entries per joint (command.c refuses more)
        Controller("linuxcnc", "linuxcnc", 256, title="LinuxCNC axis compensation file"),
        # MD38000 / MD18342 size the tables in the static user memory; no fixed limit known (docs/exports.md)
        Controller("840d-sl", "siemens", 4096, title="SINUMERIK 840D sl LEC + CEC"),
        # 828D: eight CEC tables of 200 points each, not extendable (FB K3 03/2013 p. 264)
        Controller("828d", "siemens", 200, title="SINUMERIK 828D LEC + CEC"),
        # 808D: LEC with up to 200 interpolation points, N = 0..199 (FM 01/2017 p. 106)
        Controller("808d", "siemens", 200, title="SINUMERIK 808D LEC + backlash"),
        # TNC 640 / 620 generation: AXISPOS column, any spacing; the table's size is not limited here
        Controller("tnc640", "heidenhain", 4096, title="HEIDENHAIN TNC 640 (620 generation) .COM"),
        # TNC 426/430 (and 407/415/425): at most 256 entries, spacing a power of two
        Controller("tnc426", "heidenhain", 256, "power-of-two", title="HEIDENHAIN TNC 426/430 .COM"),
        # Fanuc: compensation point numbers 0..1023 shared by all axes and both directions
        Controller("fanuc-0i", "fanuc", 1024, "detection-unit", title="FANUC Series 0i pitch error tape"),
        Controller("fanuc-30i", "fanuc", 1024, "detection-unit", title="FANUC Series 30i pitch error tape"),
    )
}

#: the names the command accepted before generations were told apart
ALIASES = {"siemens-cec": "840d-sl", "heidenhain": "tnc640", "fanuc": "fanuc-0i", "30i": "fanuc-30i"}
FORMATS = tuple(CONTROLLERS)


def controller(name: str) -> Controller:
    """Return the controller generation called ``name`` (or by one of its former format names)."""
    key = ALIASES.get(name.lower(), name.lower())
    if key not in CONTROLLERS:
        raise ValidationError(f"unknown controller {name!r}: one of {', '.join(CONTROLLERS)}")
    return CONTROLLERS[key]
