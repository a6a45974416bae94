"""Example campaign plans, virtual-machine scenarios and motion-code programs (shipped in the package as driftlab.examples)."""
