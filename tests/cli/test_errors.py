"""Every error a user can cause prints one line naming the file and the fix, and exits 2 (no
traceback), before any render time is spent; a Ctrl-C ends a command with exit 130 and one line,
even while pxr is first imported."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from allo_usd.cli import _os_error_line
from allo_usd.core.paths import BASE_STAGE
from allo_usd.core.errors import AlloError
from allo_usd.core.files import ensure_output_dir, ensure_output_file


ROOT = Path(__file__).resolve().parents[2]


def env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT)}  # at call time: conftest sets the asset roots


def cli(*args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "from allo_usd.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, env=env(), timeout=300, **kw)


def one_line_error(r: subprocess.CompletedProcess, *words: str) -> str:
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


@pytest.fixture
def blocker(tmp_path) -> Path:
    f = tmp_path / "afile"
    f.write_text("not a directory")
    return f


def commands(out: Path, tmp_path: Path) -> dict[str, list]:
    layers = tmp_path / "layers"
    layers.mkdir(exist_ok=True)
    mesh = tmp_path / "m.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return {"render DIR": ["render", layers, "--out", out],
            "render LAYER": ["render", BASE_STAGE, "--out", out],
            "render PLAN": ["render", tmp_path / "plan.toml", "--out", out],
            "dataset": ["dataset", tmp_path, "--out", out],
            "author": ["author", tmp_path / "plan.toml", "--out", out],
            "sky": ["sky", "--out", out, "--days", "2"],
            "demo": ["demo", "--out", out],
            "asset import": ["asset", "import", mesh, "--out", out]}


@pytest.mark.slow
def test_an_out_that_is_a_file_is_one_line_and_exit_2(tmp_path, blocker):
    r = cli("plan", "--demo", "--out", tmp_path / "plan.toml")
    assert r.returncode == 0, r.stderr
    for name, args in commands(blocker, tmp_path).items():
        one_line_error(cli(*args), str(blocker), "not a directory")
    one_line_error(cli("plan", "--demo", "--out", blocker / "plan.toml"), str(blocker))
    one_line_error(cli("render", tmp_path / "layers", "--out", blocker / "sub"), str(blocker))


@pytest.fixture
def read_only_dir(small_tmpfs):
    """A read-only file system (root can write anywhere else)."""
    subprocess.run(["mount", "-o", "remount,ro", str(small_tmpfs)], check=True)
    return small_tmpfs


@pytest.mark.slow
def test_an_out_that_cannot_be_written_is_one_line_and_exit_2(tmp_path, read_only_dir):
    cli("plan", "--demo", "--out", tmp_path / "plan.toml")
    for name, args in commands(read_only_dir, tmp_path).items():
        one_line_error(cli(*args), str(read_only_dir), "cannot be written")
    for name, args in commands(read_only_dir / "sub", tmp_path).items():
        one_line_error(cli(*args), str(read_only_dir / "sub"), "cannot be created")
    one_line_error(cli("plan", "--demo", "--out", read_only_dir / "p.toml"), str(read_only_dir))


@pytest.mark.process
def test_bad_numbers_are_refused(tmp_path):
    (tmp_path / "layers").mkdir()
    for opt in ("--workers", "--threads", "--retries", "--timeout"):
        one_line_error(cli("render", tmp_path / "layers", "--out", tmp_path / "o", opt, "-1"), opt, "negative")


def test_ensure_output_dir_and_file(tmp_path):
    assert ensure_output_dir(tmp_path / "a" / "b").is_dir()
    assert not list((tmp_path / "a" / "b").iterdir())  # the probe is gone
    with pytest.raises(AlloError, match="is a directory"):
        ensure_output_file(tmp_path / "a")
    assert ensure_output_file(tmp_path / "c" / "p.toml") == tmp_path / "c" / "p.toml"
    assert (tmp_path / "c").is_dir()


def test_os_errors_from_paths_are_one_line_but_bugs_keep_their_traceback(tmp_path):
    line = _os_error_line(PermissionError(errno.EACCES, "Permission denied", "/data/x.png"))
    assert line.startswith("error: ") and "/data/x.png" in line and "permissions" in line
    assert "free space" in _os_error_line(OSError(errno.ENOSPC, "No space left on device"))
    assert _os_error_line(OSError(errno.EBADF, "Bad file descriptor", "x")) is None  # a bug, not the user
    assert _os_error_line(FileNotFoundError(errno.ENOENT, "No such file")) is None  # no path: a bug


INTERRUPT_DURING_PXR = textwrap.dedent("""
    import os, signal, sys

    class SigintWhilePxrLoads:
        '''Send SIGINT to this process when pxr's C++ loader imports pxr.Gf: where pxr's own loader
        would catch the KeyboardInterrupt and print it as a warning.'''
        fired = False

        def find_spec(self, name, path=None, target=None):
            if name == "pxr.Gf" and not self.fired:
                SigintWhilePxrLoads.fired = True
                os.kill(os.getpid(), signal.SIGINT)
            return None

    sys.meta_path.insert(0, SigintWhilePxrLoads())
    from allo_usd.cli import main
    main()
""")


@pytest.mark.process
def test_ctrl_c_while_pxr_is_first_imported_is_not_lost(tiny_base, tmp_path):
    from allo_usd.usd.scene_layer import write_scene_layer
    from tests.support.helpers import make_spec

    layer = write_scene_layer(make_spec(scene_id="k"), tmp_path / "k.usda", tiny_base)
    r = subprocess.run([sys.executable, "-c", INTERRUPT_DURING_PXR, "inspect", str(layer)], capture_output=True,
                       text=True, env=env(), timeout=300, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert r.returncode == 130, (r.returncode, r.stdout[-500:], r.stderr[-2000:])
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted"), r.stderr
    assert "Traceback" not in r.stderr and not r.stdout
