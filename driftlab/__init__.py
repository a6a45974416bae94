"""driftlab: measure, learn and cancel thermal drift of five-axis machine tools."""

__version__ = "0.1.0"
