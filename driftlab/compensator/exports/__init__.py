"""Compensation tables for real controllers, one module per family, one entry per controller generation.

Every writer takes an :class:`~driftlab.compensator.exports.grid.AxisTable` and returns an
:class:`Export`: the files' text and the settings the controller needs beside them (named in the
controller's own terms). :data:`CONTROLLERS` holds, per generation, what its manual allows: the
number of points of one table and the rule its spacing obeys. See docs/exports.md for the sources.
"""

from __future__ import annotations

from driftlab.compensator.exports.controllers import ALIASES, CONTROLLERS, FORMATS, Controller, Export, controller

__all__ = ["ALIASES", "CONTROLLERS", "FORMATS", "Controller", "Export", "controller"]
