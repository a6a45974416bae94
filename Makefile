# Each target does its own set-up on a fresh machine: it creates .venv and installs
# driftlab with its dev extras (re-installed when pyproject.toml changes).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench setup clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/driftlab demo --out demo-out

test: $(STAMP)
	DRIFTLAB_REQUIRE_PG=$${DRIFTLAB_REQUIRE_PG:-1} $(BIN)/python -m pytest -n 2 --dist loadfile -q

bench: $(STAMP)
	@for b in benchmarks/*.py; do echo "== $$b" >&2; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-out .pytest_cache
