"""Data shipped inside the package: the store's migrations and the example plans, scenarios and programs.

In the source tree they live at the top level (``migrations/``, ``examples/``); the build maps them
into the package as ``driftlab.migrations`` and ``driftlab.examples`` (setup.py), so an installed
wheel and an editable install both find them through ``importlib.resources``, from any directory.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def package_path(package: str) -> Path:
    """Return the directory of a data package of driftlab (``driftlab.migrations``, ``driftlab.examples``)."""
    return Path(str(resources.files(package)))


def examples_dir() -> Path:
    """Return the directory of the shipped examples (plans/, scenarios/, programs/)."""
    return package_path("driftlab.examples")


def migrations_dir() -> Path:
    """Return the Alembic script directory of the campaign store."""
    return package_path("driftlab.migrations")
