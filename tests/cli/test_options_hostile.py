"""Hostile command-line options: every number a command takes
is a finite number in its range, and a bad one is one line that prints what was given;
`--timeout nan` does not turn the per-scene limit off and a 0.5 s limit is reported as 0.5 s;
a malformed `--scheduler` is one line at once and an unreachable one within 10 s; `--save-blend`
never overwrites a file without `--force`, never writes through a link or into a device, FIFO
or directory, wants `.blend`, says so before anything renders, and writes atomically."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from allo_usd.cli import app
from allo_usd.core.errors import AlloError

from tests.support.helpers import one_line_error, sandboxed_cli


def _refused(args: list, *words: str) -> str:
    """The command refuses `args` with an AlloError (cli.main prints it as one line, exit 2) holding `words`."""
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert isinstance(result.exception, AlloError), (args, result.exit_code, result.output, result.exception)
    message = str(result.exception)
    assert "\n" not in message and ("fix:" in message or "; " in message), message
    for w in words:
        assert w in message, (w, message)
    return message


# ---------------------------------------------------------------- numbers

NUMBERS = {
    "render": [("--workers", ["nan", "-1", "1025", "1e3", "2.5", "inf"]), ("--threads", ["nan", "-1", "99999"]),
               ("--retries", ["-1", "101", "many"]),
               ("--timeout", ["nan", "NaN", "inf", "-inf", "-1", "0", "-0", "1e400", "abc", ""]),
               ("--target-psnr", ["nan", "-inf", "-1", "100.5", "1e9", "1e308", "forty", ""]),
               ("--time-limit", ["nan", "inf", "-1", "1e7", "an hour"])],
    "author": [("--workers", ["0", "-3", "nan"]), ("--limit", ["-1", "nan", "1.5"])],
    "demo": [("--width", ["0", "3", "8193", "nan"]), ("--height", ["-270", "1e9"]), ("--samples", ["0", "65537", "x"]),
             ("--target-psnr", ["nan", "-3", "101"]), ("--time-limit", ["-1", "nan"])],
    "sky": [("--year", ["1899", "2054", "99999", "nan"]), ("--days", ["0", "56321", "100000000", "-5"])],
}
CASES = [(cmd, opt, value) for cmd, table in NUMBERS.items() for opt, values in table for value in values]


@pytest.mark.parametrize("command,option,value", CASES, ids=[f"{c} {o} {v!r}" for c, o, v in CASES])
def test_a_bad_number_is_one_line_that_prints_what_was_given(command, option, value, tmp_path):
    (tmp_path / "layers").mkdir()
    (tmp_path / "plan.toml").write_text('name = "x"\n')
    where = {"render": [tmp_path / "layers"], "author": [tmp_path / "plan.toml"], "demo": [], "sky": []}[command]
    message = _refused([command, *where, "--out", tmp_path / "o", option, value], f"{option} {value}")
    if value.startswith("-") and value not in ("-0", "-inf"):
        assert "negative" in message
    assert not (tmp_path / "o").exists()   # refused before anything was made


@pytest.mark.process
def test_the_one_line_reaches_the_terminal_and_the_default_limit_keeps_its_meaning(tmp_path):
    (tmp_path / "layers").mkdir()
    r = sandboxed_cli("render", tmp_path / "layers", "--out", tmp_path / "o", "--timeout", "nan")
    one_line_error(r, "--timeout nan is not a number of seconds > 0", "fix:", hidden="Traceback")
    for given in ([], ["--timeout", "0.5"]):   # accepted: the run goes on to find no scene layer
        _refused(["render", tmp_path / "layers", "--out", tmp_path / "o", *given], "no scene layers")


def test_a_time_limit_is_reported_as_given_and_nan_never_turns_it_off(tmp_path):
    from allo_usd.core.timefmt import seconds_text
    from allo_usd.run.dispatch import TIMEOUT_BASE_S, _timeout_reason, check_timeout, dispatch, time_limit

    assert "time limit of 0.5 s;" in _timeout_reason(0.5)
    assert [seconds_text(s) for s in (0.5, 0.25, 25, 600.0, 120.2304, 0.001)] == \
        ["0.5 s", "0.25 s", "25 s", "600 s", "120.2 s", "0.001 s"]
    layer = tmp_path / "l.usda"
    layer.write_text("#usda 1.0\n")
    assert time_limit(layer, 0.5) == 0.5 and time_limit(layer, None) >= TIMEOUT_BASE_S
    assert check_timeout(0) is None   # the API's 0 still means the default
    for bad in (math.nan, math.inf, -1.0, "10", True):
        with pytest.raises(AlloError, match="not a number of seconds > 0"):
            check_timeout(bad)
        with pytest.raises(AlloError, match="not a number of seconds > 0"):
            time_limit(layer, bad)
        with pytest.raises(AlloError, match="not a number of seconds > 0"):
            dispatch(tmp_path, tmp_path / "out", timeout=bad)
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- --scheduler

@pytest.mark.parametrize("address", ["nonsense", "tcp://", "tcp://host:notaport", "http://x:1", "tcp://h:0",
                                     "tcp://:8786", "inproc://x"])
def test_a_malformed_scheduler_address_is_one_line(address, tmp_path):
    (tmp_path / "layers").mkdir()
    _refused(["render", tmp_path / "layers", "--out", tmp_path / "o", "--scheduler", address],
             f"--scheduler {address!r}", "fix:")


@pytest.mark.process
def test_an_unreachable_scheduler_is_one_line_within_10_s(tmp_path):
    """Timed against a malformed address (the same start-up, imports and checks, no connection),
    so a loaded machine's slow start does not count against the connection's 10 s."""
    (tmp_path / "layers").mkdir()
    args = ["render", tmp_path / "layers", "--out", tmp_path / "o", "--scheduler"]
    t0 = time.monotonic()
    one_line_error(sandboxed_cli(*args, "tcp://host:notaport"), "not a scheduler address", hidden="Traceback")
    start_up = time.monotonic() - t0
    for address in ("tcp://127.0.0.1:1", "tcp://10.255.255.1:8786"):
        t0 = time.monotonic()
        r = sandboxed_cli(*args, address)
        spent = time.monotonic() - t0
        one_line_error(r, f"--scheduler {address}", "no Dask scheduler answered", "fix:", hidden="Traceback")
        assert spent - start_up < 10, (address, spent, start_up)


# ---------------------------------------------------------------- --save-blend

@pytest.fixture
def layer(tmp_path) -> Path:
    """A file named as a layer: every refusal below comes before the layer is even read."""
    path = tmp_path / "layers" / "s.usda"
    path.parent.mkdir()
    path.write_text("#usda 1.0\n")
    return path


def _save_blend(layer: Path, out: Path, target, *more: str) -> list:
    return ["render", layer, "--out", out, "--save-blend", target, *more]


def test_save_blend_never_loses_a_file_or_writes_through_a_link(layer, tmp_path):
    out = tmp_path / "o"
    precious = tmp_path / "old.blend"
    precious.write_bytes(b"a scene of my own")
    _refused(_save_blend(layer, out, precious), f"--save-blend {precious} exists", "--force")
    victim = tmp_path / "victim.txt"
    victim.write_text("system file")
    link = tmp_path / "link.blend"
    link.symlink_to(victim)
    dangling = tmp_path / "dangling.blend"
    dangling.symlink_to(tmp_path / "nowhere.blend")
    for target in (link, dangling):
        for more in ([], ["--force"]):
            _refused(_save_blend(layer, out, target, *more), f"{target} is a symbolic link", "never writes through")
    assert precious.read_bytes() == b"a scene of my own" and victim.read_text() == "system file"
    assert not (tmp_path / "nowhere.blend").exists() and not out.exists()


@pytest.mark.process
def test_save_blend_refuses_what_is_not_a_new_or_regular_blend_file(layer, tmp_path):
    out = tmp_path / "o"
    fifo = tmp_path / "pipe.blend"
    os.mkfifo(fifo)
    folder = tmp_path / "folder.blend"
    folder.mkdir()
    for target, words in ((Path("/dev/null"), "not a regular file"), (fifo, "not a regular file"),
                          (folder, "is a directory"), (tmp_path / "scene.txt", "does not end in .blend"),
                          (tmp_path / "scene", "does not end in .blend")):
        for more in ([], ["--force"]):
            _refused(_save_blend(layer, out, target, *more), str(target), words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.blend", "layers", "pipe.blend"]
    r = sandboxed_cli(*_save_blend(layer, out, "/dev/null", "--force"))   # as a user sees it
    one_line_error(r, "/dev/null exists and is not a regular file", "fix:", hidden="Traceback")


@pytest.mark.render
def test_save_blend_replaces_with_force_atomically_and_leaves_no_backup(tiny_base, tmp_path):
    """With --force an existing .blend is replaced by the whole new scene (Blender would keep the
    old one as FILE.blend1 had it saved over it: nothing but FILE is left); without --force the API
    refuses it too, before anything renders."""
    from allo_usd.run.job import render_layer
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    layer = write_scene_layer(make_spec(samples=1), tmp_path / "layers" / "s.usda", tiny_base)
    saved = tmp_path / "debug" / "s.blend"
    saved.parent.mkdir()
    saved.write_bytes(b"yesterday's scene")
    with pytest.raises(AlloError, match="exists"):
        render_layer(layer, tmp_path / "api", save_blend=saved)
    assert saved.read_bytes() == b"yesterday's scene" and not (tmp_path / "api" / "s.png").exists()

    r = subprocess.run([sys.executable, "-m", "allo_usd.cli", "render", str(layer), "--out", str(tmp_path / "o"),
                        "--save-blend", str(saved), "--force"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    head = saved.read_bytes()[:8]
    assert head.startswith(b"BLENDER") or head.startswith(b"\x28\xb5\x2f\xfd"), head   # plain or zstd
    assert [p.name for p in saved.parent.iterdir()] == ["s.blend"]   # no .blend1 backup, no temporary
    assert (tmp_path / "o" / "s.png").is_file()


def test_a_target_override_is_for_one_layer_or_a_plan_and_a_time_limit_needs_a_target(tmp_path):
    """--target-psnr / --time-limit replace the target of a single layer (or a plan's, authored with it); a
    directory's layers keep their own, and a time limit with no target (the demo's) limits nothing."""
    (tmp_path / "layers").mkdir()
    for option in (["--target-psnr", "40"], ["--time-limit", "60"]):
        _refused(["render", tmp_path / "layers", "--out", tmp_path / "o", *option],
                 "--target-psnr and --time-limit override the target of a single layer", "quality.target_psnr")
    _refused(["demo", "--out", tmp_path / "o", "--time-limit", "60"], "--time-limit 60 is given without --target-psnr")
    assert not (tmp_path / "o").exists()
