"""Compensation tables for real controllers, one module per format, from the model's correction of one axis.

Every writer takes an :class:`~driftlab.compensator.exports.grid.AxisTable` and returns an
:class:`Export`: the file's text and the settings the controller needs beside the file (named in
the controller's own terms). See docs/exports.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Export:
    """A controller table: the file's text and the controller settings that go with it."""

    format: str
    text: str
    settings: dict[str, Any] = field(default_factory=dict)


FORMATS = ("linuxcnc", "siemens-cec", "heidenhain", "fanuc")


def write(fmt: str, table: Any, **options: Any) -> Export:
    """Return the export of ``table`` in format ``fmt`` (one of FORMATS)."""
    from driftlab.errors import ValidationError

    if fmt == "linuxcnc":
        from driftlab.compensator.exports import linuxcnc as mod
    elif fmt == "siemens-cec":
        from driftlab.compensator.exports import siemens as mod  # type: ignore[no-redef]
    elif fmt == "heidenhain":
        from driftlab.compensator.exports import heidenhain as mod  # type: ignore[no-redef]
    elif fmt == "fanuc":
        from driftlab.compensator.exports import fanuc as mod  # type: ignore[no-redef]
    else:
        raise ValidationError(f"unknown format {fmt!r}: one of {', '.join(FORMATS)}")
    return mod.write(table, **options)
