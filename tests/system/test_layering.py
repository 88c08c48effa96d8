"""A layer of one's own on top of an authored tree (README, "Your own layer on top"), run as the
README writes it: its .usda text and its render command are read from the README. The layer
lives outside the tree, sublayers one of its scene layers, moves the camera 2 m, turns the
inspection light off and halves the sun; `render --tree OUT` renders it with no ALLO_ASSET_ROOTS,
and --tree grants an authored tree's four folders and nothing else."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd

from tests.support.helpers import one_line_error as _one_line_error, sandboxed_cli
from allo_usd.core.errors import LayerError
from allo_usd.plan.model import Quality, demo_plan
from allo_usd.run.author import author_scene
from allo_usd.usd import layout
from allo_usd.usd.safety import ENV_ROOTS, trees_granted

ROOT = Path(__file__).resolve().parents[2]
SCENE = "s2030_d000_p01"  # the demo plan's first scene, which the README's layer sublayers
CANARY = "CANARY-7c1f9e: private text that no message may show"


def readme_recipe() -> tuple[str, list[str]]:
    """(the .usda text, the `allo-usd render ...` arguments) of the README's recipe section."""
    text = (ROOT / "docs" / "guide" / "layering.md").read_text()
    section = text.split("\n## Your own layer on top\n", 1)[1].split("\n## ", 1)[0]
    usda = re.findall(r"```usda\n(.*?)```", section, re.S)
    renders = [line for block in re.findall(r"```sh\n(.*?)```", section, re.S) for line in block.splitlines()
               if line.startswith("allo-usd render ")]
    assert len(usda) == 1 and len(renders) == 1, "the recipe has one .usda layer and one render command"
    words = shlex.split(renders[0].split("#")[0])
    assert words[:2] == ["allo-usd", "render"]
    return usda[0], words[2:]


def option(args: list[str], name: str) -> str:
    return args[args.index(name) + 1]


def without(args: list[str], name: str) -> list[str]:
    i = args.index(name)
    return args[:i] + args[i + 2:]


def cli(*args, cwd: Path) -> subprocess.CompletedProcess:
    return sandboxed_cli(*args, cwd=cwd)


def one_line_error(r: subprocess.CompletedProcess, *words: str) -> str:
    return _one_line_error(r, *words, hidden=CANARY)


@pytest.fixture(scope="module")
def recipe(tmp_path_factory):
    """A folder laid out as the README's: the demo plan's first scene authored into the tree the
    render command names (at 64x36), the README's layer where the command names it."""
    usda, args = readme_recipe()
    root = tmp_path_factory.mktemp("layering")
    plan = demo_plan()
    plan = plan.model_copy(update={"quality": Quality(preset="demo", resolution=(64, 36), samples=16)})
    tree = root / option(args, "--tree")
    scene = author_scene(plan, SCENE, tree)
    mine = root / args[0]
    mine.parent.mkdir(parents=True, exist_ok=True)
    mine.write_text(usda)
    return root, args, tree, scene, mine


def variant(mine: Path, name: str, edit) -> Path:
    """A copy of the README's layer beside it (same sublayer path), edited with Sdf."""
    layer = Sdf.Layer.FindOrOpen(str(mine))
    out = Sdf.Layer.CreateNew(str(mine.with_name(name)))
    out.TransferContent(layer)
    edit(out)
    out.Save()
    return Path(out.realPath)


def _remove(layer, path: str) -> None:
    edit = Sdf.BatchNamespaceEdit()
    edit.Add(path, Sdf.Path.emptyPath)
    assert layer.Apply(edit), path


def moved_only(layer) -> None:  # only the camera move: the lights as the scene has them
    _remove(layer, layout.INSPECTION_LIGHT)
    _remove(layer, layout.SKY)


def spot_at_zero(layer) -> None:  # the other natural way to turn a light off
    spec = layer.GetPrimAtPath(layout.INSPECTION_LIGHT)
    spec.ClearInfo("active")
    Sdf.AttributeSpec(spec, "inputs:intensity", Sdf.ValueTypeNames.Float).default = 0.0


def test_the_readme_layer_moves_the_camera_2m_and_halves_the_sun(recipe):
    _, _, _, scene, mine = recipe
    before, after = Usd.Stage.Open(str(scene)), Usd.Stage.Open(str(mine))  # plain usd-core composes it
    assert after.GetRootLayer().subLayerPaths[0].endswith(f"scenes/train/normal/{SCENE}.usda")
    cam0, cam1 = before.GetPrimAtPath(layout.CAMERA), after.GetPrimAtPath(layout.CAMERA)
    t0 = np.array(cam0.GetAttribute("xformOp:translate").Get())
    t1 = np.array(cam1.GetAttribute("xformOp:translate").Get())
    assert np.allclose(t1 - t0, (0, 0, 2), atol=1e-3), (
        f"the README's camera translate {tuple(t1)} is not the scene's {tuple(t0)} moved 2 m up: update the README")
    assert cam1.GetAttribute("xformOp:orient").Get() == cam0.GetAttribute("xformOp:orient").Get()
    sun0 = before.GetPrimAtPath(layout.STATION_SUN).GetAttribute("inputs:intensity").Get()
    sun1 = after.GetPrimAtPath(layout.STATION_SUN).GetAttribute("inputs:intensity").Get()
    assert sun1 == pytest.approx(sun0 / 2, rel=1e-6), (
        f"the README's sun intensity {sun1} is not half the scene's {sun0}: update the README")
    for name in ("inputs:normalize", "inputs:exposure"):  # whatever they are, the override leaves them
        a, b = (s.GetPrimAtPath(layout.STATION_SUN).GetAttribute(name) for s in (before, after))
        assert (a.Get() if a else None) == (b.Get() if b else None)
    assert before.GetPrimAtPath(layout.INSPECTION_LIGHT).IsActive()
    assert not after.GetPrimAtPath(layout.INSPECTION_LIGHT).IsActive()


def test_the_reader_sees_the_override_through_tree(recipe, monkeypatch):
    from allo_usd.usd.read import read_scene

    _, _, tree, scene, mine = recipe
    monkeypatch.delenv(ENV_ROOTS, raising=False)
    with pytest.raises(LayerError, match=rf"--tree {re.escape(str(tree.resolve()))}"):
        read_scene(mine)
    zero = variant(mine, "zero_reader.usda", spot_at_zero)
    with trees_granted([tree]):
        assert ENV_ROOTS in os.environ
        original, mine_desc, zero_desc = read_scene(scene), read_scene(mine), read_scene(zero)
    assert ENV_ROOTS not in os.environ  # granted for the block only
    assert original.spot is not None and original.spot.intensity > 0
    assert mine_desc.spot is None  # an inactive spotlight is no spotlight
    assert zero_desc.spot is None or zero_desc.spot.intensity == 0
    moved = mine_desc.camera.matrix[:3, 3] - original.camera.matrix[:3, 3]
    assert np.linalg.norm(moved) == pytest.approx(2.0, abs=1e-3)
    assert np.allclose(mine_desc.camera.matrix[:3, :3], original.camera.matrix[:3, :3])
    sun0, sun1 = ({s.path: s for s in d.suns}[layout.STATION_SUN] for d in (original, mine_desc))
    assert sun1.irradiance == pytest.approx(sun0.irradiance / 2, rel=1e-6)


def test_without_tree_the_layer_is_refused_naming_the_fix(recipe):
    root, args, tree, _, _ = recipe
    line = one_line_error(cli("render", *without(args, "--tree"), cwd=root), "resolves outside the allowed roots")
    assert f"--tree {tree.resolve()}" in line, line
    one_line_error(cli("inspect", args[0], cwd=root), f"--tree {tree.resolve()}")
    assert cli("inspect", args[0], "--tree", option(args, "--tree"), "--json", cwd=root).returncode == 0


def test_tree_must_be_an_authored_tree_and_grants_only_its_folders(recipe, tmp_path):
    root, args, tree, _, mine = recipe
    layer = args[0]
    not_a_tree = root / "not_a_tree"
    not_a_tree.mkdir(exist_ok=True)
    (not_a_tree / "scenes").mkdir(exist_ok=True)
    private = tree / "private"
    private.mkdir(exist_ok=True)
    (private / "secret.usda").write_text(f'#usda 1.0\n(\n    doc = "{CANARY}"\n)\n')
    for bad in (not_a_tree, private, tree / "scenes", root / "missing"):
        one_line_error(cli("render", layer, "--tree", bad, "--out", tmp_path / "r", cwd=root), f"--tree {bad}")
    # a tree does not grant its private/ folder, even to a layer that names it
    sneaky = mine.with_name("sneaky.usda")
    sneaky.write_text(mine.read_text().replace("subLayers = [\n", "subLayers = [\n        @../" +
                                               os.path.relpath(private / "secret.usda", root) + "@,\n", 1))
    one_line_error(cli("render", sneaky.relative_to(root), "--tree", option(args, "--tree"), "--out", tmp_path / "r",
                       cwd=root), "secret.usda resolves outside the allowed roots")
    # a tree whose folder links outside it grants nothing
    linked = root / "linked_tree"
    linked.mkdir(exist_ok=True)
    (linked / "plan.toml").write_text((tree / "plan.toml").read_text())
    if not (linked / "stages").is_symlink():
        (linked / "stages").symlink_to(not_a_tree)
    one_line_error(cli("render", layer, "--tree", linked, "--out", tmp_path / "r", cwd=root), "symbolic link")
    # a link to a tree is that tree (symbolic links resolve)
    link = root / "tree_link"
    if not link.is_symlink():
        link.symlink_to(tree)
    assert cli("inspect", layer, "--tree", link, "--json", cwd=root).returncode == 0
    assert not (tmp_path / "r").exists() or not any((tmp_path / "r").glob("*.png"))


def _exr(path: Path) -> np.ndarray:
    import OpenEXR
    import Imath

    f = OpenEXR.InputFile(str(path))
    dw = f.header()["dataWindow"]
    w, h = dw.max.x - dw.min.x + 1, dw.max.y - dw.min.y + 1
    return np.stack([np.frombuffer(f.channel(c, Imath.PixelType(Imath.PixelType.FLOAT)), np.float32).reshape(h, w)
                     for c in "RGB"], -1)


def _outputs(out: Path, stem: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from PIL import Image

    return (_exr(out / f"{stem}.exr"), np.asarray(Image.open(out / f"{stem}.png")).astype(float)[..., :3],
            np.asarray(Image.open(out / f"{stem}_mask.png")))


@pytest.mark.render
def test_the_readme_render_command_renders_the_override(recipe):
    root, args, tree, scene, mine = recipe
    r = cli("render", *args, cwd=root)  # exactly the README's command, with no ALLO_ASSET_ROOTS
    assert r.returncode == 0, (r.stdout, r.stderr)
    out = root / option(args, "--out")
    assert cli("render", scene, "--out", root / "original", cwd=root).returncode == 0
    moved = variant(mine, "moved.usda", moved_only)
    r = cli("render", moved.relative_to(root), "--tree", tree, "--out", root / "moved", "--workers", "1", cwd=root)
    assert r.returncode == 0 and "1 rendered" in r.stdout, (r.stdout, r.stderr)  # the pool's workers got the tree
    zero = variant(mine, "zero.usda", spot_at_zero)
    assert cli("render", zero.relative_to(root), "--tree", tree, "--out", root / "zero", cwd=root).returncode == 0

    lin, srgb, mask = _outputs(out, mine.stem)
    lin0, _, mask0 = _outputs(root / "original", SCENE)
    lin_m, srgb_m, mask_m = _outputs(root / "moved", "moved")
    lin_z, _, _ = _outputs(root / "zero", "zero")
    station = mask > 0
    # the camera moved: the view changed; the lights do not change what is seen
    assert (mask != mask0).mean() > 0.05 and np.abs(lin - lin0).mean() > 0.01
    assert np.array_equal(mask, mask_m) and station.mean() > 0.2
    # half the sun and no spotlight: the station about half as bright as from the same place, lit as the scene is
    ratio = lin[station].mean() / lin_m[station].mean()
    assert 0.4 < ratio < 0.55, ratio
    assert srgb[station].mean() < 0.85 * srgb_m[station].mean()
    # the spotlight turned off by intensity 0 or by active = false: the same image
    assert lin_z[station].mean() == pytest.approx(lin[station].mean(), rel=0.01)

    meta = json.loads((out / f"{mine.stem}.json").read_text())
    assert meta["layer"] == str(mine.resolve())
    inputs = {os.path.realpath(os.path.join(mine.parent, k)) for k in meta["inputs"]}
    assert str(mine.resolve()) in inputs and str(scene.resolve()) in inputs
    assert any(k.endswith("stages/base.usda") for k in meta["inputs"]) and meta["identity"]
