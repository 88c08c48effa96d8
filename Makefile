# Two commands set up everything: `make run` renders a small real dataset, `make test` runs the tests
# (`make test-unit`: the unit tier alone, the inner loop).
# Both create .venv (Python 3.11: bpy 5.0.1 wheels exist for 3.11 only) and install what they need:
# exactly the versions in requirements.lock, wheels only, each checked against the lock's sha256 hashes,
# then allo-usd itself (editable, no dependencies, no build isolation: nothing outside the lock is fetched).
# A .venv built from another lock is built again from scratch, never trusted (scripts/install_env.py).
# `make lock` regenerates requirements.lock from pyproject.toml (see the lock target).

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
LOCK   := requirements.lock
PROJECT := .

# The lock tool lives in a venv of its own (not in .venv: not in the lock, and .venv is rebuilt when the lock changes).
LOCKVENV   := .lock-tool
LOCK_INDEX ?= https://pypi.org/simple
LOCK_ARGS  ?=

.PHONY: run test test-unit env lock stage bench clean

# Every time (a no-op while .venv/.installed-stamp records this lock's and pyproject.toml's sha256): a changed
# lock, or a .venv without that record, builds .venv again from scratch with
#   pip install --require-hashes --only-binary :all: --no-deps --force-reinstall -r $(LOCK)
# (a wheel whose hash is not in the lock fails, naming the package; nothing is built from source); a changed
# pyproject.toml installs allo-usd again. VENV, LOCK and PROJECT may be set (tests/system/test_lock.py does).
env:
	@$(PYTHON) -m scripts.install_env --venv $(VENV) --lock $(LOCK) --project $(PROJECT)

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

run: env
	$(VENV)/bin/allo-usd demo --out out/demo
	@echo "renders in out/demo/renders, layers in out/demo/layers, contact sheet out/demo/contact_sheet.png"

# Two test processes (pytest-xdist), each taking whole files (--dist loadfile: a file's module and session
# fixtures are built once, in one process); TEST_WORKERS=1 runs them in this process.
TEST_WORKERS ?= 2
test: env
	$(PY) -m pytest -q $(if $(filter 1,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

# The inner loop: the unit tier (tests/conftest.py): no tests/system/, nothing marked render, slow, process or
# bpy; a test of the tier that starts a process or loads Blender fails. `make test` stays the gate (and CI's).
test-unit: env
	$(PY) -m pytest -q --unit $(if $(filter 1,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

stage: env
	$(PY) -m scripts.make_base_stage

bench: env
	$(PY) -m scripts.bench_sky

clean:
	rm -rf out .pytest_cache
