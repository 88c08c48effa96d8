"""A tree's own folders that are symbolic links are refused for the tree's own layers exactly as
`--tree` refuses them. A tree's scene layers must not get `hazards/` (and sky/, poses/, stages/)
as roots after the link is followed: `hazards -> /` would let a scene read any file, and the render
would succeed and record the outside file among its inputs."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from allo_usd.core.errors import LayerError
from allo_usd.plan.model import Quality, demo_plan
from allo_usd.run.author import author_scene
from allo_usd.usd.tree import HAZARD_DIR, POSE_DIR, SCHEMA_DIR, SKY_DIR, STAGE_DIR
from allo_usd.usd.dependencies import walk

from tests.support.helpers import one_line_error, sandboxed_cli

SCENE = "s2030_d000_p01"   # the demo plan's first scene
CANARY = "tree-link-canary-5b1f0c"


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """One authored scene (the demo plan's first, at 64x36) in OUT, a file outside OUT holding the
    canary, and a layer inside OUT's scenes/ that reaches it through OUT/hazards/."""
    root = tmp_path_factory.mktemp("tree_links")
    plan = demo_plan().model_copy(update={"quality": Quality(preset="demo", resolution=(64, 36), samples=1)})
    out = root / "out"
    scene = author_scene(plan, SCENE, out)
    victim = root / "victim"
    victim.mkdir()
    (victim / "secret.usda").write_text(f'#usda 1.0\n(\n    doc = "{CANARY}"\n)\n')
    depth = len(scene.relative_to(out).parts) - 1            # scenes/SPLIT/KIND: three folders up to OUT
    up = "/".join([".."] * depth)
    evil = scene.with_name("evil.usda")
    evil.write_text(f'#usda 1.0\n(\n    subLayers = [\n        @./{scene.name}@,\n'
                    f'        @{up}/{HAZARD_DIR}/victim/secret.usda@\n    ]\n)\n')
    return out, scene, evil, root


@pytest.mark.process
def test_a_hazards_link_out_of_the_tree_is_refused_and_nothing_outside_is_read(tree, tmp_path):
    out, scene, evil, root = tree
    link = out / HAZARD_DIR
    assert not os.path.lexists(link)
    link.symlink_to(root)                                    # hazards -> a folder holding victim/secret.usda
    try:
        r = sandboxed_cli("render", evil, "--out", tmp_path / "r", "--device", "cpu")
    finally:
        link.unlink()
    one_line_error(r, f"{HAZARD_DIR}/", "symbolic link", str(root), "fix:", hidden=CANARY)
    written = list((tmp_path / "r").rglob("*")) if (tmp_path / "r").exists() else []
    assert not [p for p in written if p.suffix in (".json", ".png", ".exr")], written
    for p in written:
        if p.is_file():
            assert CANARY not in p.read_text(errors="replace"), p


@pytest.mark.parametrize("folder", [SKY_DIR, POSE_DIR, STAGE_DIR, SCHEMA_DIR, HAZARD_DIR])
def test_every_own_folder_that_is_a_link_is_refused_even_inside_the_tree(tree, folder):
    """Any link, even to a folder inside the tree, as `--tree` refuses it (safety.linked_folders)."""
    out, scene, _, _ = tree
    walk(scene)                                              # the tree as authored: its layers may be read
    real = out / folder
    moved = out / f".{folder}.real"
    had = real.exists()
    if had:
        real.rename(moved)
    else:
        moved.mkdir()
    real.symlink_to(moved)
    try:
        with pytest.raises(LayerError) as err:
            walk(scene)
    finally:
        real.unlink()
        if had:
            moved.rename(real)
        else:
            shutil.rmtree(moved)
    message = str(err.value)
    assert f"{folder}/ as a symbolic link" in message and "\n" not in message
    assert "; fix: replace the link" in message
    walk(scene)                                              # restored: read again


def test_tree_option_and_own_layers_refuse_the_same_links(tree):
    """`--tree OUT` (tree_roots) and a layer inside OUT (allowed_roots) agree on which trees grant nothing."""
    from allo_usd.usd.safety import linked_folders, tree_roots

    out, scene, _, root = tree
    assert linked_folders(Path(os.path.realpath(out))) == []
    tree_roots(out)
    link = out / HAZARD_DIR
    link.symlink_to(root)
    try:
        with pytest.raises(LayerError, match="symbolic link"):
            tree_roots(out)
        with pytest.raises(LayerError, match="symbolic link"):
            walk(scene)
    finally:
        link.unlink()
