# Two commands set up everything: `make run` renders a small real dataset, `make test` runs the tests.
# Both create .venv (Python 3.11: bpy 5.0.1 wheels exist for 3.11 only) and install what they need.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: run test env stage bench clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else "allo-usd needs Python 3.11 (bpy==5.0.1); set PYTHON=/path/to/python3.11")'
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

env: $(STAMP)

run: $(STAMP)
	$(VENV)/bin/allo-usd demo --out out/demo
	@echo "renders in out/demo/renders, layers in out/demo/layers, contact sheet out/demo/contact_sheet.png"

test: $(STAMP)
	$(PY) -m pytest -q

stage: $(STAMP)
	$(PY) scripts/make_base_stage.py

bench: $(STAMP)
	$(PY) scripts/bench_sky.py

clean:
	rm -rf out .pytest_cache
