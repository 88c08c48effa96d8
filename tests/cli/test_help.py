"""`allo-usd --version`, and every command's `--help`: each option is described, and no option
shows a default that means nothing to a reader (a 0 that stands for "auto", a None)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from allo_usd.cli import app

ROOT = Path(__file__).resolve().parents[2]
SENTINELS = {"0", "0.0", "None", "-1", "", "''", '""'}
# (command, option) whose sentinel-looking default is meaningful; none today
MEANINGFUL: set[tuple[str, str]] = set()


def _commands(group, prefix: tuple[str, ...] = ()):
    for name, cmd in sorted(group.commands.items()):
        if hasattr(cmd, "commands"):  # a group (typer vendors its own click: duck-typed)
            yield from _commands(cmd, (*prefix, name))
        else:
            yield (*prefix, name), cmd


ROOT_COMMAND = typer.main.get_command(app)
COMMANDS = [((), ROOT_COMMAND), *_commands(ROOT_COMMAND)]


def _help(args: tuple[str, ...]) -> str:
    r = CliRunner().invoke(app, [*args, "--help"], env={"COLUMNS": "1000", "NO_COLOR": "1", "TERM": "dumb"})
    assert r.exit_code == 0, (args, r.output)
    return r.output


def _option_row(text: str, name: str) -> str:
    """The help row of option `name` (its names, metavar, help and default), on one line at this width."""
    rows = [line.strip("│ \n") for line in text.splitlines() if "│" in line]
    found = [row for row in rows if re.match(rf"(\*\s+)?{re.escape(name)}(\.\.\.)?(\s|$)", row)]
    assert len(found) == 1, (name, text)
    return found[0]


def test_the_commands_are_all_found():
    assert {" ".join(c) for c, _ in COMMANDS} >= {"render", "demo", "sky", "inspect", "diff", "dataset", "plan",
                                                  "author", "asset import"}


@pytest.mark.parametrize("path,cmd", COMMANDS, ids=[" ".join(c) or "allo-usd" for c, _ in COMMANDS])
def test_every_option_is_described_without_a_meaningless_default(path, cmd):
    text = _help(path)
    assert (cmd.help or "").strip(), f"{' '.join(path)} has no description"
    for param in cmd.params:
        if param.name == "help":
            continue
        option = param.param_type_name == "option"
        name = param.opts[0] if option else (param.metavar or param.name)
        row = _option_row(text, name)
        shown = re.findall(r"\[default: (.*?)\]", row)
        words = re.sub(r"\[(default|required)[^\]]*\]", "", row)
        words = re.sub(r"<[^>]*>", " ", re.sub(r"^\*\s+", "", words))
        for token in sorted({*param.opts, *param.secondary_opts, param.metavar or "", param.name}, key=len,
                            reverse=True):
            words = re.sub(rf"(?<!\S){re.escape(token)}(\.\.\.)?(?!\S)", " ", words)
        assert len(words.split()) >= 2, f"{' '.join(path)} {name} has no help text: {row!r}"
        assert (getattr(param, "help", None) or "").strip(), f"{' '.join(path)} {name}: no help="
        for default in shown:
            assert default.strip() not in SENTINELS or (" ".join(path), name) in MEANINGFUL, (
                f"{' '.join(path)} {name} shows the default {default!r}, which means nothing to a reader; say "
                f"what it does in the help text and hide it (show_default=False): {row!r}")


@pytest.mark.process
def test_version_prints_the_installed_distribution_without_bpy():
    code = ("import sys; from typer.testing import CliRunner; from allo_usd.cli import app; "
            "r = CliRunner().invoke(app, ['--version']); print(r.exit_code); print(r.output.strip()); "
            "print('bpy' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr
    exit_code, line, bpy_loaded = r.stdout.strip().splitlines()
    assert exit_code == "0", r.stdout
    assert line.startswith(f"allo-usd {version('allo-usd')} "), line
    assert f"bpy {version('bpy')}" in line and f"usd-core {version('usd-core')}" in line, line
    assert bpy_loaded == "False"


@pytest.mark.process
def test_version_through_the_entry_point():
    r = subprocess.run([sys.executable, "-c", "from allo_usd.cli import main; main()", "--version"],
                       capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0 and r.stdout.startswith(f"allo-usd {version('allo-usd')}"), (r.stdout, r.stderr)
