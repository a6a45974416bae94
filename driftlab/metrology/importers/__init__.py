"""Instrument exports -> campaign bundles: Renishaw laser ``.rtx`` and CSV export, and any CSV through a column mapping.

Every importer turns its file into error readings (time_s, axis, term, position, direction, value in
the bundle's units) plus the temperatures the file recorded, and :func:`common.write_readings`
writes them through the bundle writer and validates the result with the bundle loader before the
directory appears. Problems are one line, ``FILE:ROW: problem`` where a row is involved.
"""

from __future__ import annotations

FORMATS = ("rtx", "renishaw-csv", "generic")
