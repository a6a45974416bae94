# Each target does its own set-up on a fresh machine: it creates .venv and installs
# driftlab with its dev extras (re-installed when pyproject.toml changes).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench setup clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/driftlab demo --out demo-out

# The code contracts of docs/architecture.md: lint, one format, types, the import layers, the module map.
LINTED := driftlab tests benchmarks docs migrations examples
lint: $(STAMP)
	$(BIN)/ruff check $(LINTED)
	$(BIN)/ruff format --check $(LINTED)
	$(BIN)/mypy
	$(BIN)/lint-imports
	$(BIN)/python docs/module_map.py --check

test: $(STAMP) lint
	DRIFTLAB_REQUIRE_PG=$${DRIFTLAB_REQUIRE_PG:-1} $(BIN)/python -m pytest -n 2 --dist loadfile -q

bench: $(STAMP)
	@for b in benchmarks/*.py; do echo "== $$b" >&2; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-out .pytest_cache

# Browser tests (tests/api/test_browser.py) drive Debian's headless Chromium; installed once when missing.
CHROMIUM := /usr/bin/chromium
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
$(CHROMIUM):
	$(SUDO) apt-get update -qq
	DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq chromium chromium-driver
setup test: $(CHROMIUM)

.PHONY: screenshots vendor-docs
screenshots: $(STAMP) $(CHROMIUM)  ## regenerate docs/img/*.png (live page, /docs, /redoc, reports)
	$(BIN)/python docs/screenshots.py

vendor-docs: $(STAMP)  ## fetch Swagger UI and ReDoc again from their npm packages (versions in VENDOR.json)
	$(BIN)/python -m driftlab.api.vendor refresh
