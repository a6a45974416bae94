"""Test support shipped with the package: throwaway PostgreSQL clusters, small worlds, open-world bundles.

Outside the layers of docs/architecture.md: it may import any part of driftlab, and no part of
driftlab imports it (an import contract checks that). Tests and benchmarks use it.
"""
