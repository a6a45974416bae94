"""Build configuration that pyproject.toml cannot express: the top-level data folders mapped into the package.

``migrations/`` (Alembic) and ``examples/`` (plans, scenarios, programs, machines) stay at the top of the
source tree, where contributors and alembic.ini expect them, and ship inside the wheel as the packages
``driftlab.migrations`` and ``driftlab.examples`` (found with importlib.resources, see
driftlab/resources.py). Their file lists (package-data) and everything else are in pyproject.toml.

Every folder that holds shipped data is listed as a package of its own (``driftlab.api.static.vendor``,
``driftlab.examples.plans``, ...): setuptools warns ("Package would be ignored") about a data folder
with an importable name that is not listed, once per folder and build step (issue 35.10). Folders
whose names are not importable (``swagger-ui``) are not packages and are carried by package-data.
"""

from pathlib import Path

from setuptools import find_packages, setup

HERE = Path(__file__).resolve().parent


def data_packages(package: str, directory: str) -> list[str]:
    """Return ``package`` and one package per importable sub-folder of ``directory`` (data folders)."""
    root = HERE / directory
    names = [package]
    for sub in sorted(p for p in root.rglob("*") if p.is_dir()):
        parts = sub.relative_to(root).parts
        if all(part.isidentifier() for part in parts) and "__pycache__" not in parts:
            names.append(".".join((package, *parts)))
    return names


code = find_packages(include=["driftlab", "driftlab.*"])
setup(
    packages=sorted(
        {
            *code,
            *data_packages("driftlab.api.static", "driftlab/api/static"),
            *data_packages("driftlab.migrations", "migrations"),
            *data_packages("driftlab.examples", "examples"),
        }
    ),
    package_dir={"driftlab.migrations": "migrations", "driftlab.examples": "examples"},
)
