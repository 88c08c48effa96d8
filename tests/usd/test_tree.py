"""The layout of an authored tree is spelled once, in allo_usd.usd.tree: its path builders read back
what they write, an authored tree holds nothing but its names, the command line's messages name
its parts through it, and no other module of the package spells a tree name again."""

from __future__ import annotations

import ast
import re
from itertools import islice
from pathlib import Path

import pytest

import allo_usd
from allo_usd.usd import tree
from allo_usd.usd.tree import (COUNTS_CSV, GRANTED_DIRS, LAYER_DIRS, LAYER_FOLDER_DIRS, POSE_DIR, SCENE_DIR, SKIPPED_CSV, SKY_DIR,
                               STAGE_DIR, SUPPORT_DIRS, TREE_ENTRIES, TREE_LOCK, TREE_PLAN, existing_scene_ids,
                               pose_layer_path, scene_layer_path, sky_layer_path)

PACKAGE = Path(allo_usd.__file__).parent

# Every name of the layout: the module's string constants. LAYER_SUFFIX (".usda") is every USD
# layer's suffix, in a tree or not, so it is not a name only a tree has.
NAMES = {v for k, v in vars(tree).items() if k.isupper() and isinstance(v, str) and k != "LAYER_SUFFIX"}
# Names distinct enough to find in prose ("see counts.csv"): the tree's files, but base.usda, which
# messages also use for the shipped base stage and any other.
FILES = {n for n in NAMES if "." in n.lstrip(".")} - {tree.BASE_STAGE_FILE}
PROSE_DIRS = (SCENE_DIR, SKY_DIR, POSE_DIR, tree.HAZARD_DIR)       # "sky/, poses/" in a message

# The same strings spelled elsewhere with a meaning of their own, by module: (module, string) -> why.
ELSEWHERE = {
    ("core.provenance", "versions.json"): "TREE_VERSIONS, written there; core cannot import usd, tree re-exports it",
    ("core.paths", "stages"): "the package's own data folder (the shipped base stage), not a tree",
    ("core.paths", "base.usda"): "the shipped base stage, which the tree copies under the same name",
    ("core.paths", "stages/base.usda"): "the package's data marker",
    ("plan.model", "stages/base.usda"): "a plan's default base stage: the shipped one, or one in the working directory",
}


def module_name(path: Path, package: Path = PACKAGE) -> str:
    return ".".join(p for p in path.relative_to(package).with_suffix("").parts if p != "__init__")


def _docstrings(module: ast.Module) -> set[int]:
    ids = set()
    for node in ast.walk(module):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def _keys(module: ast.Module) -> set[int]:
    """String constants used as mapping keys (a dict display's keys, a subscript, .get/.pop/.setdefault's
    first argument): JSON fields such as a render record's "inputs", never a path."""
    ids = set()
    for node in ast.walk(module):
        if isinstance(node, ast.Dict):
            ids.update(id(k) for k in node.keys if k is not None)
        elif isinstance(node, ast.Subscript):
            ids.add(id(node.slice))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.args \
                and node.func.attr in ("get", "pop", "setdefault"):
            ids.add(id(node.args[0]))
    return ids


def spelled(text: str) -> str | None:
    """The tree name `text` spells, if any: the name itself, a path whose first part is one
    ("stages/base.usda", "/scenes"), or prose that names a tree file ("see counts.csv") or folder ("sky/, ...")."""
    if text in NAMES:
        return text
    if "/" in text and not any(c.isspace() for c in text):
        first = next((part for part in text.split("/") if part), "")
        if first in NAMES:
            return first
    for name in FILES:
        if re.search(rf"(?<![\w.-]){re.escape(name)}(?![\w-])", text):
            return name
    for name in PROSE_DIRS:
        if re.search(rf"(?<![\w/]){name}/(?![\w])", text):
            return name + "/"
    return None


def tree_names_outside(package: Path = PACKAGE) -> list[str]:
    found = []
    for path in sorted(package.rglob("*.py")):
        mod = module_name(path, package)
        if mod == "usd.tree":
            continue
        module = ast.parse(path.read_text())
        skip = _docstrings(module) | _keys(module)
        for node in ast.walk(module):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
                name = spelled(node.value)
                if name is not None and (mod, node.value) not in ELSEWHERE:
                    found.append(f"{path.relative_to(package.parent)}:{node.lineno}: {node.value!r} spells {name!r}")
    return found


# ---------------------------------------------------------------------------------------------
# Path builders


def _keys_of_a_plan():
    from allo_usd.plan.enumeration import iter_scenes, reserve_group
    from allo_usd.plan.model import paper_plan

    plan = paper_plan()
    keys = list(islice(iter_scenes(plan), 0, None, 2500))   # normal scenes of both splits, anomalous depths
    last = keys[-1]
    return plan, keys + reserve_group(plan, last.seed, last.asset, last.variant, 1)


def test_scene_layer_paths_read_back_as_their_scene_ids(tmp_path):
    _, keys = _keys_of_a_plan()
    assert {k.kind for k in keys} == {"normal", "anomaly"} and {k.split for k in keys} == {"train", "test"}
    assert any(k.reserve for k in keys)
    assert existing_scene_ids(tmp_path) == set()   # no scenes/ folder yet
    for k in keys:
        path = scene_layer_path(tmp_path, k.split, k.kind, k.scene_id)
        assert path.relative_to(tmp_path).parts == (SCENE_DIR, k.split, k.kind, f"{k.scene_id}.usda")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("")
    (tmp_path / SCENE_DIR / "train" / "normal" / "notes.txt").write_text("")   # not a layer: not a scene
    assert existing_scene_ids(tmp_path) == {k.scene_id for k in keys}


def test_sky_and_pose_layer_paths_name_their_day_and_sample(tmp_path):
    for day in (0, 7, 364, 1000):
        path = sky_layer_path(tmp_path, day)
        assert path.relative_to(tmp_path).parts == (SKY_DIR, f"d{day:03d}.usda")
        assert int(path.stem[1:]) == day
    _, keys = _keys_of_a_plan()
    for k in keys:
        path = pose_layer_path(tmp_path, k.seed, k.sample_id)
        rel = path.relative_to(tmp_path)
        assert rel.parts[:2] == (POSE_DIR, f"s{k.seed}") and len(rel.parts) == 3
        assert f"{rel.parts[1]}_{path.stem}" == k.sample_id   # the sample id read back from its path
    # the depths of one placement share their pose layer; reserve groups and placements do not share
    assert len({pose_layer_path(tmp_path, k.seed, k.sample_id) for k in keys}) == len({k.sample_id for k in keys})


def test_the_base_stage_schema_and_hazard_paths_are_the_trees(tmp_path):
    from allo_usd.usd import hazard

    assert tree.tree_base_stage(tmp_path) == tmp_path / STAGE_DIR / tree.BASE_STAGE_FILE
    assert tree.tree_schema(tmp_path) == tmp_path / tree.SCHEMA_DIR
    assert tree.hazard_asset_path(tmp_path, "bolt") == tmp_path / tree.HAZARD_DIR / "bolt" / "bolt.usda"
    assert hazard.hazard_asset_path is tree.hazard_asset_path and hazard.HAZARD_MARKER == tree.HAZARD_MARKER


# ---------------------------------------------------------------------------------------------
# The groups of names


def test_the_groups_are_names_of_the_tree():
    assert len(set(TREE_ENTRIES)) == len(TREE_ENTRIES)
    assert set(LAYER_DIRS) <= set(GRANTED_DIRS) <= set(TREE_ENTRIES) and set(SUPPORT_DIRS) <= set(TREE_ENTRIES)
    assert SCENE_DIR not in SUPPORT_DIRS and set(SUPPORT_DIRS) | {SCENE_DIR} == {*GRANTED_DIRS, tree.SCHEMA_DIR}
    # plan.toml is rewritten, not removed, by --replace; the lock belongs to the run, not to the layers
    assert TREE_PLAN not in TREE_ENTRIES and TREE_LOCK not in TREE_ENTRIES
    assert {COUNTS_CSV, SKIPPED_CSV, tree.RESERVES_CSV, tree.POSE_INPUTS, tree.TREE_VERSIONS} <= set(TREE_ENTRIES)


def test_names_spelled_elsewhere_agree_with_the_tree():
    from allo_usd.core import paths, provenance

    assert tree.TREE_VERSIONS == provenance.TREE_VERSIONS
    assert paths.BASE_STAGE.name == tree.BASE_STAGE_FILE   # copy_base_stage keeps the shipped stage's name


def test_the_safety_rules_and_the_dispatcher_take_their_folders_from_the_tree(tmp_path):
    from allo_usd.run import dispatch
    from allo_usd.usd import safety

    assert safety._tree_folders(tmp_path) == tuple(tmp_path / d for d in GRANTED_DIRS)
    assert dispatch.SUPPORT_DIRS is SUPPORT_DIRS
    assert not safety.is_authored_tree(tmp_path)
    (tmp_path / TREE_PLAN).write_text("")
    assert safety.is_authored_tree(tmp_path)


# ---------------------------------------------------------------------------------------------
# The command line names the tree's parts with the module's names


def test_the_replace_and_tree_options_name_the_trees_folders():
    import typer.main

    from allo_usd import cli

    command = typer.main.get_command(cli.app)
    replace = next(p for p in command.commands["author"].params if p.name == "replace")
    shown = re.findall(r"([\w.-]+)/", replace.help)
    assert shown and set(shown) <= set(TREE_ENTRIES), replace.help
    assert set(shown) == {SCENE_DIR, SKY_DIR, POSE_DIR, STAGE_DIR}
    authored, demo = cli.TREE_HELP.split("OUT/layers")
    granted = re.findall(r"([\w.-]+)/", authored)
    assert granted and set(granted) <= set(GRANTED_DIRS), cli.TREE_HELP
    assert set(re.findall(r"([\w.-]+)/", demo)) == set(LAYER_FOLDER_DIRS), cli.TREE_HELP


@pytest.mark.slow
def test_an_authored_tree_holds_only_the_modules_names_and_the_cli_names_them(tmp_path):
    from typer.testing import CliRunner

    from allo_usd import cli
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.plan.io import save_plan
    from allo_usd.plan.model import AnomalyChoice, Anomalies, Dates, Plan, Poses, Quality
    from allo_usd.run.author_tree import replace_tree

    plan = Plan(name="names", dates=Dates(days=1), poses=Poses(train=[1], test=[41]),
                anomalies=Anomalies(assets=[AnomalyChoice(id="power_drill")], depths=[0]),
                quality=Quality(resolution=(64, 36), samples=4), base_stage=str(BASE_STAGE))
    plan_file, out = save_plan(plan, tmp_path / "plan.toml"), tmp_path / "out"
    r = CliRunner().invoke(cli.app, ["author", str(plan_file), "--out", str(out), "--no-progress"])
    assert r.exit_code == 0, r.output
    assert f"under {out / SCENE_DIR};" in r.output and f"in {out / SKIPPED_CSV}," in r.output
    assert f"in {out / COUNTS_CSV}" in r.output
    top = {p.name for p in out.iterdir()}
    assert top <= {*TREE_ENTRIES, TREE_PLAN, TREE_LOCK}, top
    assert {SCENE_DIR, SKY_DIR, POSE_DIR, STAGE_DIR, tree.SCHEMA_DIR, COUNTS_CSV, SKIPPED_CSV, TREE_PLAN} <= top
    removed = replace_tree(out)
    assert set(removed) == top - {TREE_PLAN, TREE_LOCK}
    assert {p.name for p in out.iterdir()} == top & {TREE_PLAN, TREE_LOCK}


# ---------------------------------------------------------------------------------------------
# No other module spells a tree name


@pytest.mark.slow
def test_no_module_but_the_tree_spells_a_tree_name():
    found = tree_names_outside()
    assert not found, "tree names spelled outside allo_usd.usd.tree (import them from there):\n" + "\n".join(found)


def _planted(tmp_path: Path, statement: str) -> list[str]:
    """What the check finds in a package holding one module whose one function runs `statement`."""
    planted = tmp_path / "allo_usd" / "run" / "planted.py"
    planted.parent.mkdir(parents=True)
    planted.write_text(f"def f(out, seed, name, meta, x, rec, Path):\n    {statement}\n")
    return tree_names_outside(tmp_path / "allo_usd")


@pytest.mark.parametrize("statement", [
    'out / "scenes"',
    'Path(out, "sky", name)',
    'f"{out}/poses/{seed}"',
    'LOCK = ".allo-author.lock"',
    'raise ValueError(f"{out} has no plan.toml; fix: ...")',
    'print("layers in sky/, poses/ and stages/")',
    'x = ("counts.csv", "skipped.csv")',
])
def test_the_check_sees_a_name_spelled_again(tmp_path, statement):
    """The check is not vacuous: each way of spelling a name is found in a planted module."""
    assert len(_planted(tmp_path, statement)) >= 1


@pytest.mark.parametrize("statement", [
    'meta.get("inputs")',
    'row = {"inputs": sorted(x)}',
    'rec["inputs"]',
    'print("render: 3 scenes/h")',
    'DEFAULT = "out/sky"',
])
def test_the_check_leaves_other_meanings_alone(tmp_path, statement):
    """JSON keys, a rate and a default folder that only share a word with the tree are not names."""
    assert _planted(tmp_path, statement) == []
