"""The campaign store's Alembic migrations (shipped in the package as driftlab.migrations)."""
