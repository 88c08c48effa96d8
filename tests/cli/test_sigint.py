"""Ctrl-C is honoured at any time: `allo-usd author` of a plan with a mesh
hazard, stopped by SIGINT at several moments (one of them while trimesh imports scipy, where
trimesh's `except BaseException` swallowed the KeyboardInterrupt and the run went on to exit 0),
always ends with exit 130 and one line, and a re-run of the same command finishes the tree with
the same bytes as a run never interrupted. Also the hold itself (allo_usd.core.interrupts): a
SIGINT inside it is delivered after the block, to the handler that was there."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from allo_usd.core.interrupts import Held, import_held, interrupt_held

ROOT = Path(__file__).resolve().parents[2]
BRACKET = ROOT / "examples" / "bring_your_own" / "bracket.obj"

PLAN = """name = "sigint"
seeds = [7]

[dates]
start = 2030-03-20
days = 1

[poses]
train = [1]
test = [41]

[[anomalies.assets]]
id = "bracket"
file = "bracket.obj"
units = "mm"
up_axis = "y"

[counts]
anomalous_test = 2

[quality]
preset = "draft"
resolution = [64, 36]
"""


def _command() -> list[str]:
    """`allo-usd` as a user starts it: the console script beside this Python (else `python -m`)."""
    script = Path(sys.executable).parent / "allo-usd"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "allo_usd.cli"]


def _start(plan_dir: Path, out: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([*_command(), "author", "plan.toml", "--out", str(out), "--no-progress"], cwd=plan_dir,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _inside_scipy(proc: subprocess.Popen, deadline: float) -> bool:
    """Wait until the process has mapped a scipy extension (trimesh imports scipy in its own import,
    under `except BaseException`); False if it ended or the deadline passed first."""
    maps = Path(f"/proc/{proc.pid}/maps")
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if "/scipy/" in maps.read_text():
                return True
        except OSError:
            return False
        time.sleep(0.005)
    return False


def _files(tree: Path) -> dict[str, bytes]:
    return {p.relative_to(tree).as_posix(): p.read_bytes() for p in sorted(tree.rglob("*")) if p.is_file()}


@pytest.fixture
def plan_dir(tmp_path) -> Path:
    d = tmp_path / "plan"
    d.mkdir()
    (d / "plan.toml").write_text(PLAN)
    (d / "bracket.obj").write_bytes(BRACKET.read_bytes())
    return d


@pytest.mark.process
def test_a_sigint_at_any_time_ends_author_with_130_and_a_resume_gives_the_same_tree(plan_dir, tmp_path):
    """The moments are fractions of an uninterrupted run's wall time (0.3 to 2 s on an idle machine,
    later on a loaded one), and one is "while scipy loads", inside trimesh's own import."""
    t0 = time.monotonic()
    clean = _start(plan_dir, tmp_path / "clean")
    stdout, stderr = clean.communicate(timeout=300)
    whole = time.monotonic() - t0
    assert clean.returncode == 0, stderr

    out = tmp_path / "tree"
    fresh = tmp_path / "tree_scipy"   # the scipy moment on a tree of its own: one the timed moments left
    for when in [0.07, 0.2, 0.35, 0.5, "scipy"]:   # finished (their signals came late) has nothing to import
        proc = _start(plan_dir, fresh if when == "scipy" else out)
        if when == "scipy":
            if not _inside_scipy(proc, time.monotonic() + 120):
                proc.kill()
                proc.communicate()
                pytest.fail("author never imported scipy (through trimesh, for the plan's mesh hazard)")
        else:
            time.sleep(when * whole)
        if proc.poll() is not None:   # a resumed run that finished before its moment: no signal was sent
            assert proc.returncode == 0 and when != "scipy", (when, proc.stderr.read())
            continue
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
        if proc.returncode == 0 and when != "scipy":   # it finished as the signal came, its summary printed: a
            assert "scene layers" in stdout and "Traceback" not in stderr, (when, stdout, stderr)   # complete run
            continue
        assert proc.returncode == 130, (when, whole, proc.returncode, stdout[-500:], stderr[-2000:])
        lines = [x for x in stderr.splitlines() if x.strip()]
        assert lines and lines[-1].startswith("interrupted"), (when, stderr)
        assert "Traceback" not in stderr, (when, stderr)

    want = _files(tmp_path / "clean")
    for tree in (out, fresh):
        resumed = _start(plan_dir, tree)
        stdout, stderr = resumed.communicate(timeout=300)
        assert resumed.returncode == 0, stderr
        got = _files(tree)
        assert sorted(got) == sorted(want)   # no temporary, lock or partial file left by the interrupted runs
        assert [name for name in want if got[name] != want[name]] == []


def test_a_sigint_inside_the_hold_is_delivered_after_it():
    """The hold notes a SIGINT and hands it to the previous handler when the block ends: Python's
    default raises KeyboardInterrupt there (not inside, where a library would swallow it)."""
    reached = []
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)   # pytest may run with SIGINT ignored
    try:
        with pytest.raises(KeyboardInterrupt):
            with interrupt_held():
                signal.raise_signal(signal.SIGINT)
                try:   # what trimesh does around its optional imports
                    reached.append("inside")
                except BaseException:  # noqa: BLE001
                    reached.append("swallowed")
                reached.append("end of block")
        assert reached == ["inside", "end of block"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


def test_the_hold_hands_a_sigint_to_a_custom_handler_and_nests():
    seen = []
    previous = signal.signal(signal.SIGINT, lambda sig, frame: seen.append(sig))
    try:
        with interrupt_held():
            with interrupt_held():
                signal.raise_signal(signal.SIGINT)
            assert seen == []   # the inner block handed it to the outer hold
        assert seen == [signal.SIGINT]
        held = Held().start()
        signal.raise_signal(signal.SIGINT)
        assert held.release(deliver=False) is True and seen == [signal.SIGINT]   # noted, not delivered
        assert import_held("json").dumps([1]) == "[1]"
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.process
def test_a_sigint_after_the_work_ends_with_130_or_0_never_by_the_signal(plan_dir, tmp_path):
    """A Ctrl-C sent the moment the summary is printed lands in the command's exit. Python's own
    shutdown (about 0.3 s with USD and numpy loaded) used to run with the default SIGINT action,
    so it killed the process by the signal (status -2, no message); the console script now ends with
    SIGINT held (cli._exit_held): 130 with the one line if it came in time, else 0."""
    seen = []
    for k in range(4):
        proc = _start(plan_dir, tmp_path / f"t{k}")
        for line in proc.stdout:
            if "test/anomaly:" in line:                       # the summary's last line
                proc.send_signal(signal.SIGINT)
                break
        stdout, stderr = proc.communicate(timeout=120)
        assert proc.returncode in (0, 130), (proc.returncode, stderr[-2000:])
        if proc.returncode == 130:
            assert [x for x in stderr.splitlines() if x.strip()][-1].startswith("interrupted"), stderr
        seen.append(proc.returncode)
    assert seen
