"""The unit tier (`pytest --unit`, `make test-unit`, tests/conftest.py) keeps its promise: a test
of the tier that starts a process or imports bpy, in its body or in a fixture it sets up, fails and
names the mark to give it; a marked test is left out; anything else runs. Run on a test file of
its own, with the project's conftest loaded as a plugin."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

CASES = '''
import subprocess, sys
import pytest

@pytest.fixture
def spawned():
    subprocess.run([sys.executable, "-c", "pass"])

def test_spawns():
    subprocess.run([sys.executable, "-c", "pass"])

def test_spawns_in_a_fixture(spawned):
    pass

def test_forks():
    import multiprocessing
    multiprocessing.get_context("fork").Process(target=print).start()

def test_imports_bpy():
    import bpy  # noqa: F401

@pytest.mark.process
def test_marked_process():
    subprocess.run([sys.executable, "-c", "pass"])

@pytest.mark.render
def test_marked_render():
    import bpy  # noqa: F401

def test_plain():
    assert sum(range(4)) == 6
'''


@pytest.mark.process
def test_the_unit_tier_refuses_processes_and_bpy_and_leaves_marked_tests_out(tmp_path):
    (tmp_path / "test_cases.py").write_text(CASES)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider", "-p", "tests.conftest",
                        "--unit", "--rootdir", str(tmp_path), str(tmp_path / "test_cases.py")],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    out = r.stdout
    assert r.returncode == 1, out
    outcome = {name: word for word, name in re.findall(r"^(PASSED|FAILED|ERROR) \S*test_cases\.py::(\w+)", out, re.M)}
    assert outcome == {"test_spawns": "FAILED", "test_forks": "FAILED", "test_imports_bpy": "FAILED",
                       "test_spawns_in_a_fixture": "ERROR", "test_plain": "PASSED"}, out[-3000:]
    assert re.search(r"\b2 deselected\b", out), out[-3000:]
    assert "mark it @pytest.mark.process" in out and "imports bpy" in out, out[-3000:]
