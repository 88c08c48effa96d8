# Two commands set up everything: `make run` renders a small real dataset, `make test` runs the tests
# (`make test-unit`: the unit tier alone, the inner loop).
# Both create .venv (Python 3.11: bpy 5.0.1 wheels exist for 3.11 only) and install what they need:
# exactly the versions in requirements.lock, checked against its sha256 hashes, then allo-usd itself
# (editable, no dependencies, no build isolation: nothing outside the lock is fetched).
# `make lock` regenerates requirements.lock from pyproject.toml (see the lock target).

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

LOCK   := requirements.lock
# The lock tool lives in its own venv inside .venv (never in .venv's own site-packages: not in the lock).
LOCKVENV   := $(VENV)/lock-tool
LOCK_INDEX ?= https://pypi.org/simple
LOCK_ARGS  ?=

.PHONY: run test test-unit env lock stage bench clean

# A changed lock or pyproject.toml reinstalls (a package dropped from the lock stays installed: rm -rf .venv for a clean one).
$(STAMP): $(LOCK) pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else "allo-usd needs Python 3.11 (bpy==5.0.1); set PYTHON=/path/to/python3.11")'
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --require-hashes --no-deps -r $(LOCK)
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

env: $(STAMP)

# Regenerate requirements.lock (pip-tools' pip-compile): every dependency of pyproject.toml and its `test`
# extra, transitive ones included, with setuptools and wheel (which `make env` builds allo-usd with), each
# pinned with the sha256 of every file PyPI holds for it. Existing pins are kept while they satisfy
# pyproject.toml; `make lock LOCK_ARGS=--upgrade` (or `--upgrade-package numpy`) moves them. It resolves
# for this interpreter, so it must run on Linux x86-64 with Python 3.11, and it reads PyPI only
# (LOCK_INDEX), never this machine's pip configuration: the lock is the same on every machine.
lock:
	@$(PYTHON) -c 'import platform, sys; sys.exit(0 if sys.version_info[:2] == (3, 11) and sys.platform == "linux" and platform.machine() == "x86_64" else "make lock resolves for Linux x86-64 with Python 3.11; run it there (set PYTHON=/path/to/python3.11)")'
	test -x $(LOCKVENV)/bin/pip-compile || ($(PYTHON) -m venv $(LOCKVENV) && $(LOCKVENV)/bin/pip install --quiet pip==26.3 pip-tools==7.6.2)
	env -u PIP_FIND_LINKS -u PIP_INDEX_URL -u PIP_EXTRA_INDEX_URL -u PIP_CONSTRAINT -u PIP_NO_INDEX \
	    PIP_CONFIG_FILE=/dev/null CUSTOM_COMPILE_COMMAND="make lock" \
	    $(LOCKVENV)/bin/pip-compile --quiet --generate-hashes --allow-unsafe --strip-extras --extra test \
	    --no-emit-index-url --no-emit-trusted-host --no-emit-find-links --index-url $(LOCK_INDEX) $(LOCK_ARGS) \
	    --output-file $(LOCK) pyproject.toml

run: $(STAMP)
	$(VENV)/bin/allo-usd demo --out out/demo
	@echo "renders in out/demo/renders, layers in out/demo/layers, contact sheet out/demo/contact_sheet.png"

# Two test processes (pytest-xdist), each taking whole files (--dist loadfile: a file's module and session
# fixtures are built once, in one process); TEST_WORKERS=1 runs them in this process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q $(if $(filter 1,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

# The inner loop: the unit tier (tests/conftest.py): no tests/system/, nothing marked render, slow, process or
# bpy; a test of the tier that starts a process or loads Blender fails. `make test` stays the gate (and CI's).
test-unit: $(STAMP)
	$(PY) -m pytest -q --unit $(if $(filter 1,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

stage: $(STAMP)
	$(PY) -m scripts.make_base_stage

bench: $(STAMP)
	$(PY) -m scripts.bench_sky

clean:
	rm -rf out .pytest_cache
