# The README's commands. Everything runs inside .venv, created on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
DEMO_STAMP := $(VENV)/.installed-demo
DEV_STAMP := $(VENV)/.installed-dev

.PHONY: demo test wheel-check docs bench lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# the demo needs magctl, its run-time dependencies and the view extra (report.html's charts, rig run --view), at
# the versions the committed results were produced with (constraints.txt, written by .ci/constraints.py)
$(DEMO_STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[view]'
	touch $@

# tests, lint, docs, notebooks, wheel building, and every optional extra
$(DEV_STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $@ $(DEMO_STAMP)

demo: $(DEMO_STAMP)
	$(BIN)/magctl reproduce --out out

# the coil board's firmware is compiled for this computer in the tests: a C compiler (Debian's gcc when missing);
# the view's pages are tested in a real headless browser: Debian's chromium when missing; the suite runs on every
# core (pytest-xdist): each test starts the servers, ports and folders it needs on its own
test: $(DEV_STAMP)
	@command -v cc >/dev/null 2>&1 || command -v gcc >/dev/null 2>&1 || \
		(apt-get update -qq && apt-get install -y -qq gcc >/dev/null)
	@command -v chromium >/dev/null 2>&1 || \
		(apt-get update -qq && apt-get install -y -qq chromium >/dev/null)
	$(BIN)/ruff check magctl analysis tests benchmarks docs/notebooks
	$(BIN)/mkdocs build --strict --quiet --site-dir site
	PYTHON=$(PYTHON) BUILD_PY=$(BIN)/python .ci/wheel-check
	$(BIN)/python -m pytest -q -n auto

wheel-check: $(DEV_STAMP)
	PYTHON=$(PYTHON) BUILD_PY=$(BIN)/python .ci/wheel-check

docs: $(DEV_STAMP)
	$(BIN)/mkdocs build --strict --site-dir site

bench: $(DEV_STAMP)
	$(BIN)/python benchmarks/run.py

lint: $(DEV_STAMP)
	$(BIN)/ruff check magctl analysis tests benchmarks docs/notebooks

clean:
	rm -rf $(VENV) .venv-wheel dist site out .pytest_cache
