"""Build configuration that pyproject.toml cannot express: the top-level data folders mapped into the package.

``migrations/`` (Alembic) and ``examples/`` (plans, scenarios, programs) stay at the top of the source
tree, where contributors and alembic.ini expect them, and ship inside the wheel as the packages
``driftlab.migrations`` and ``driftlab.examples`` (found with importlib.resources, see
driftlab/resources.py). Their file lists (package-data) and everything else are in pyproject.toml.
"""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["driftlab", "driftlab.*"]), "driftlab.migrations", "driftlab.examples"],
    package_dir={"driftlab.migrations": "migrations", "driftlab.examples": "examples"},
)
