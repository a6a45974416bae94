"""Campaign store, bundle import/export, plans and acquisition records (the daemon runs them: driftlab.daemon)."""
