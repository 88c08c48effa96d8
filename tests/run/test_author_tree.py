"""An authored tree remembers its plan, one author run at a time writes it, and a broken base
stage is one clear error (the record is the truth)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from allo_usd.core.errors import LayerError, PlanError
from allo_usd.core.paths import BASE_STAGE
from allo_usd.plan.io import load_plan, save_plan
from allo_usd.run.author import author, author_scene

from tests.support.plans import small_plan

TREE_LOCK = ".allo-author.lock"   # allo_usd.usd.tree.TREE_LOCK
CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()"]


def layer_bytes(out: Path) -> dict[str, bytes]:
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*.usda"))}


def cli(*args, **popen) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600, **popen)


def error_line(r: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert "Traceback" not in r.stderr
    return lines[0]


# ---------------------------------------------------------------------------------------------
# The tree remembers its plan


@pytest.mark.slow
def test_a_changed_plan_is_refused_and_the_tree_keeps_its_record(tmp_path):
    out = tmp_path / "tree"
    author(small_plan((160, 90)), out, progress=False)
    before, record = layer_bytes(out), (out / "plan.toml").read_bytes()
    with pytest.raises(PlanError, match=r"quality\.resolution 160x90 in the tree, 480x270 in the plan given.*"
                                        r"fresh --out.*--replace"):
        author(small_plan((480, 270)), out, progress=False)
    assert layer_bytes(out) == before and (out / "plan.toml").read_bytes() == record
    assert load_plan(out / "plan.toml").quality.resolution == (160, 90)
    with pytest.raises(PlanError, match=r"dates\.days 1 in the tree, 2 in the plan given \(and 1 more: name \"tree\" in the tree, \"other\""):
        author(small_plan((160, 90), days=2).model_copy(update={"name": "other"}), out, progress=False)


@pytest.mark.slow
def test_the_same_plan_resumes_with_any_limit_and_from_its_own_file(tmp_path):
    out = tmp_path / "tree"
    plan = small_plan(train=(1, 2))
    first = author(plan, out, limit=1, progress=False)
    record = (out / "plan.toml").read_bytes()
    # the plan as read back from a file (another field order, defaults omitted or not) is the same plan
    again = load_plan(save_plan(plan, tmp_path / "copy.yaml"))
    whole = author(again, out, progress=False)
    assert set(first.paths) < set(whole.paths) and (out / "plan.toml").read_bytes() == record
    # the base stage named by another path (the tree checks its copy by content) is the same plan too
    author(plan.model_copy(update={"base_stage": os.path.relpath(BASE_STAGE)}), out, progress=False)


@pytest.mark.slow
def test_author_scene_refuses_a_tree_of_another_plan(tmp_path):
    from allo_usd.plan.enumeration import enumerate_scenes

    out = tmp_path / "tree"
    author(small_plan((160, 90)), out, limit=1, progress=False)
    other = small_plan((480, 270))
    key = enumerate_scenes(other)[0]
    with pytest.raises(PlanError, match=r"quality\.resolution 160x90 in the tree, 480x270"):
        author_scene(other, key.scene_id, out)
    layer = author_scene(other, key.scene_id, out, replace=True)
    assert "(480, 270)" in layer.read_text()
    assert load_plan(out / "plan.toml").quality.resolution == (480, 270)


@pytest.mark.process
def test_cli_replace_removes_the_old_layers_and_nothing_else(tmp_path):
    out, outside = tmp_path / "tree", tmp_path / "outside"
    old, new = save_plan(small_plan((160, 90)), tmp_path / "old.toml"), save_plan(small_plan((480, 270)),
                                                                                 tmp_path / "new.toml")
    r = cli("author", old, "--out", out, "--no-progress")
    assert r.returncode == 0, r.stderr
    (out / "notes.txt").write_text("mine")          # not the tree's: kept
    outside.mkdir()
    (outside / "keep.usda").write_text("#usda 1.0\n")
    (out / "reserves.csv").unlink(missing_ok=True)
    os.symlink(outside, out / "reserves.csv")       # a link is removed as a link, never followed
    line = error_line(cli("author", new, "--out", out, "--no-progress"))
    assert "quality.resolution 160x90 in the tree, 480x270 in the plan given" in line and "--replace" in line
    r = cli("author", new, "--out", out, "--no-progress", "--replace")
    assert r.returncode == 0, r.stderr
    scenes = sorted((out / "scenes").rglob("*.usda"))
    assert scenes and all("(480, 270)" in p.read_text() for p in scenes)
    assert not [p for p in out.iterdir() if p.name.startswith(".replaced.")]
    assert (out / "notes.txt").read_text() == "mine" and (outside / "keep.usda").is_file()
    assert load_plan(out / "plan.toml").quality.resolution == (480, 270)


def test_layers_without_a_plan_record_are_refused(tmp_path):
    out = tmp_path / "tree"
    (out / "scenes" / "train" / "normal").mkdir(parents=True)
    with pytest.raises(PlanError, match="no plan.toml"):
        author(small_plan(), out, progress=False)
    with pytest.raises(PlanError, match="not an authored tree"):   # --replace does not delete a stranger's folder
        author(small_plan(), out, progress=False, replace=True)
    assert (out / "scenes" / "train" / "normal").is_dir()


# ---------------------------------------------------------------------------------------------
# One author run at a time


@pytest.mark.process
def test_a_second_author_run_is_one_clear_error(tmp_path):
    from allo_usd.run.author_tree import tree_lock

    out = tmp_path / "tree"
    plan = save_plan(small_plan(), tmp_path / "plan.toml")
    out.mkdir()
    with tree_lock(out):   # another run holds the tree
        line = error_line(cli("author", plan, "--out", out, "--no-progress"))
    assert f"another author run (pid {os.getpid()}" in line and "wait for it" in line, line
    assert not (out / "plan.toml").exists() and not (out / "stages").exists()   # refused before touching it
    assert (out / TREE_LOCK).read_text() == ""   # released, and empty: the tree's bytes name no run


@pytest.mark.process
def test_two_concurrent_author_runs_into_one_folder(tmp_path):
    """Both started at once: the one that gets the lock authors, the other is refused in one line
    (never a traceback); a third run then resumes to the same tree as a run alone."""
    out = tmp_path / "tree"
    plan = save_plan(small_plan((64, 36), days=12, train=range(1, 41)), tmp_path / "plan.toml")
    def args(to: Path) -> list[str]:
        return [*CLI, "author", str(plan), "--out", str(to), "--no-progress", "--workers", "1"]

    a = subprocess.Popen(args(out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    b = subprocess.Popen(args(out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    results = [subprocess.CompletedProcess(p.args, p.wait(timeout=600), *p.communicate()) for p in (a, b)]
    for r in results:
        assert "Traceback" not in r.stderr and "Directory not empty" not in r.stderr, r.stderr
        assert r.returncode in (0, 2), r.stderr
    refused = [r for r in results if r.returncode == 2]
    for r in refused:
        assert "another author run (pid" in error_line(r)
    # the ordered case: B starts while A surely holds the tree (A is stopped while it holds the lock, so
    # it cannot finish and release it before B asks: a stopped process keeps its lock)
    out2 = tmp_path / "tree2"
    a = subprocess.Popen(args(out2), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not (out2 / TREE_LOCK).is_file() or not (out2 / TREE_LOCK).read_text():
        assert a.poll() is None and time.monotonic() < deadline, a.communicate()
        time.sleep(0.01)
    a.send_signal(signal.SIGSTOP)
    try:
        b = cli("author", plan, "--out", out2, "--no-progress")
    finally:
        a.send_signal(signal.SIGCONT)
    assert a.wait(timeout=600) == 0, a.communicate()
    assert "another author run (pid" in error_line(b)
    assert cli("author", plan, "--out", out, "--no-progress").returncode == 0
    assert layer_bytes(out) == layer_bytes(out2)


# ---------------------------------------------------------------------------------------------
# A broken base stage


def broken_stage(tmp_path: Path, how: str) -> Path:
    stage = tmp_path / f"stage_{how}"
    shutil.copytree(BASE_STAGE.parent, stage)
    base = stage / "base.usda"
    text = base.read_text()
    if how == "garbage":
        base.write_text("not a usd layer\n")
    elif how == "truncated":
        base.write_text(text[: len(text) // 2])
    elif how == "no-rig":
        base.write_text(text.replace("AlloCameraPoseAPI", "AlloCameraPosesAPI"))
    return base


@pytest.mark.parametrize("how", ["garbage", "truncated", "no-rig"])
@pytest.mark.process
def test_a_broken_base_stage_is_one_error_naming_it_and_the_fix(tmp_path, how):
    base = broken_stage(tmp_path, how)
    plan = save_plan(small_plan(base_stage=base), tmp_path / "plan.toml")
    out = tmp_path / "tree"
    line = error_line(cli("author", plan, "--out", out, "--no-progress"))
    assert f"base stage {base}" in line and "make stage" in line and "scripts/make_base_stage.py" in line, line
    assert not (out / "stages").exists() and not (out / "scenes").exists()   # no copy of a broken stage kept
    from allo_usd.plan.enumeration import enumerate_scenes

    with pytest.raises(LayerError, match="cannot be read"):
        author(small_plan(base_stage=base), out, progress=False)
    plan = small_plan(base_stage=base)
    with pytest.raises(LayerError, match="cannot be read"):
        author_scene(plan, enumerate_scenes(plan)[0].scene_id, out)
