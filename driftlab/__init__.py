"""driftlab: measure, learn and cancel thermal drift of five-axis machine tools."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"
__all__ = ["__version__", "connect"]

if TYPE_CHECKING:
    from driftlab.notebook import connect


def __getattr__(name: str) -> Any:
    """Return ``driftlab.connect`` (the notebook API, docs/notebook.md), imported on first use."""
    if name == "connect":
        # lazy: httpx and pandas stay off `import driftlab` and `driftlab --help`
        from driftlab.notebook import connect

        return connect
    raise AttributeError(f"module 'driftlab' has no attribute {name!r}")
