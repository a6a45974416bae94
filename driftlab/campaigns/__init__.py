"""Campaign store, bundle import/export, plans and the resumable scheduler."""
