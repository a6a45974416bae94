"""`python -m driftlab`: the same entry point as the `driftlab` command."""

from driftlab.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
