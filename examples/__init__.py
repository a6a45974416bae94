"""Example campaign plans, virtual-machine scenarios and motion-code programs.

Shipped in the package as driftlab.examples.
"""
