"""One entry point for every controller's writer: ``write(name, table)`` picks the family's module.

The package itself holds only the controllers (light: the command line reads their names without
loading numpy); the writers, which evaluate the model on a grid, are imported here.
"""

from __future__ import annotations

from typing import Any

from driftlab.compensator.exports import fanuc, heidenhain, linuxcnc, siemens
from driftlab.compensator.exports.controllers import Export, controller
from driftlab.errors import ValidationError


def write(name: str, table: Any, **options: Any) -> Export:
    """Return the export of ``table`` for controller ``name`` (one of CONTROLLERS)."""
    ctl = controller(name)
    n = int(table.positions.size)
    if n > ctl.max_points:
        raise ValidationError(f"{ctl.name}: {n} points; a table holds at most {ctl.max_points} (use a coarser --step)")
    if ctl.family == "linuxcnc":
        return linuxcnc.write(table, ctl, **options)
    if ctl.family == "siemens":
        return siemens.write(table, ctl, **options)
    if ctl.family == "heidenhain":
        return heidenhain.write(table, ctl, **options)
    return fanuc.write(table, ctl, **options)
