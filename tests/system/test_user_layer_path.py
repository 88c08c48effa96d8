"""Layers of one's own on the first path (docs/guide/layering.md): `--tree` grants the demo's layer
folder as it grants an authored tree, a folder of one's own override layers renders with
`render DIR` (no customLayerData needed), and a layer USD cannot parse is answered about the layer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from allo_usd.core.errors import LayerError
from allo_usd.usd.safety import ENV_ROOTS, tree_roots, trees_granted
from tests.support.helpers import sandboxed_cli
from tests.support.user_layers import DEMO_ANOMALY, DEMO_NORMAL, demo_layers, override


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    """root/layers (the demo's layer folder) and root/mine (two override layers over two demo scenes,
    and a helper layer that is no scene)."""
    root = tmp_path_factory.mktemp("path")
    layers = demo_layers(root)
    override(layers / f"{DEMO_ANOMALY}.usda", root / "mine" / "drill_view.usda")
    override(layers / f"{DEMO_NORMAL}.usda", root / "mine" / "sunlit_view.usda")
    (root / "mine" / "shared.usda").write_text('#usda 1.0\n(\n    defaultPrim = "World"\n)\n\nover "World"\n{\n}\n')
    return root


@pytest.fixture
def no_roots(monkeypatch):
    monkeypatch.delenv(ENV_ROOTS, raising=False)


def read(layer):
    from allo_usd.usd.read import read_scene

    return read_scene(layer)


def test_tree_grants_the_demos_layer_folder_and_nothing_else(demo, no_roots, tmp_path):
    layers, mine = demo / "layers", demo / "mine" / "drill_view.usda"
    granted = {p.relative_to(layers).as_posix() for p in tree_roots(layers)}
    assert granted == {"sky", "poses", "stages", "schema", *(p.name for p in layers.glob("*.usda"))}
    with pytest.raises(LayerError, match=rf"name that tree with `--tree {layers}`"):
        read(mine)
    with trees_granted([layers]):
        assert read(mine).meta["sceneId"] == DEMO_ANOMALY
    private = layers / "private"
    private.mkdir(exist_ok=True)
    (private / "x.usda").write_text((layers / f"{DEMO_NORMAL}.usda").read_text())
    sneaky = override(private / "x.usda", tmp_path / "sneaky.usda")
    with trees_granted([layers]), pytest.raises(LayerError) as info:
        read(sneaky)
    line = str(info.value)
    assert "grants only its scene layers" in line and "not private" in line and "--tree OUT" not in line, line


def test_tree_that_is_no_tree_says_what_it_lacks(demo, no_roots, tmp_path):
    with pytest.raises(LayerError, match="holds neither plan.toml nor stages/base.usda"):
        tree_roots(tmp_path)
    # a real tree given, the layer's file in none: the message says so, not "name its tree with --tree"
    loose = tmp_path / "loose"
    loose.mkdir()
    (loose / "scene.usda").write_text((demo / "layers" / f"{DEMO_NORMAL}.usda").read_text())
    layer = override(loose / "scene.usda", tmp_path / "mine" / "v.usda")
    with trees_granted([demo / "layers"]), pytest.raises(LayerError) as info:
        read(layer)
    line = str(info.value)
    assert "no tree granted" in line and "--tree OUT" not in line, line


def test_a_layer_over_a_scene_layer_is_a_scene_of_its_own(demo):
    from allo_usd.usd.sniff import is_scene_layer

    with trees_granted([demo / "layers"]):
        assert is_scene_layer(demo / "mine" / "drill_view.usda")
        assert not is_scene_layer(demo / "mine" / "shared.usda")
        pose = next((demo / "layers" / "poses").rglob("*.usda"))
        assert not is_scene_layer(pose)   # a pose layer sublayers a sky layer, no scene


@pytest.mark.process
@pytest.mark.render
def test_render_dir_renders_ones_own_override_layers(demo, tmp_path):
    out = tmp_path / "out"
    r = sandboxed_cli("render", "mine", "--tree", "layers", "--out", out, cwd=demo)
    assert r.returncode == 0 and "2 rendered" in r.stdout, (r.stdout, r.stderr)
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert sorted((row["scene"], row["scene_id"]) for row in rows) == [("drill_view", "drill_view"),
                                                                        ("sunlit_view", "sunlit_view")]
    for stem, scene in (("drill_view", DEMO_ANOMALY), ("sunlit_view", DEMO_NORMAL)):
        record = json.loads((out / f"{stem}.json").read_text())
        assert record["scene"]["sceneId"] == scene   # the scene it is composed over
        assert (out / f"{stem}.png").is_file()


def test_a_syntax_error_is_answered_about_the_layer(demo, tmp_path):
    good = (demo / "mine" / "drill_view.usda").read_text()
    mine = demo / "mine" / "broken.usda"
    mine.write_text(good.replace("int allo:render:samples = 8", "int allo:render:samples = 8 8"))
    with trees_granted([demo / "layers"]), pytest.raises(LayerError) as info:
        read(mine)
    line = str(info.value)
    assert f"{mine}:" in line and "USD cannot parse line" in line and "fix the layer's syntax" in line, line
    assert "re-author" not in line
    mine.unlink()
    # the project's own scene layer, broken: restore it by authoring again
    authored = tmp_path / f"{DEMO_NORMAL}.usda"
    authored.write_text((demo / "layers" / f"{DEMO_NORMAL}.usda").read_text() + "\ndef Xform (\n")
    with pytest.raises(LayerError, match="re-author it with `allo-usd author`"):
        read(authored)
