"""The public API: `import allo_usd` is cheap, every documented name resolves, and the names work
together from a plan to a read scene (rendering is covered by the render tests)."""

from __future__ import annotations

import subprocess
import sys

import pytest

import allo_usd


def test_import_loads_neither_pxr_nor_bpy():
    code = ("import sys, allo_usd; heavy = [m for m in ('pxr', 'bpy', 'skyfield', 'trimesh') if m in sys.modules]; "
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


@pytest.mark.parametrize("name", sorted(allo_usd._API))
def test_every_public_name_resolves(name):
    assert callable(getattr(allo_usd, name)) or isinstance(getattr(allo_usd, name), type)
    assert name in dir(allo_usd)


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        allo_usd.nope  # noqa: B018


def test_plan_to_description_through_the_api(tmp_path):
    plan = allo_usd.demo_plan()
    path = allo_usd.save_plan(plan, tmp_path / "plan.toml")
    assert allo_usd.load_plan(path) == plan
    keys = allo_usd.enumerate_scenes(plan)
    tree = allo_usd.author_plan(plan, tmp_path / "tree", limit=1, progress=False)
    assert [p.stem for p in tree.paths] == [keys[0].scene_id]
    desc = allo_usd.read_scene(tree.paths[0])
    assert isinstance(desc, allo_usd.SceneDescription)
    assert desc.meta["provenance"]["sceneId"] == keys[0].scene_id
    assert desc.render.resolution == tuple(plan.quality.resolution)


def test_author_scene_writes_one_scene_with_its_shared_layers(tmp_path):
    plan = allo_usd.demo_plan()
    keys = allo_usd.enumerate_scenes(plan)
    key = next(k for k in keys if k.kind == "anomaly")
    layer = allo_usd.author_scene(plan, key.scene_id, tmp_path / "tree")
    assert layer.stem == key.scene_id and layer.is_file()
    desc = allo_usd.read_scene(layer)
    assert desc.meta["provenance"]["sceneId"] == key.scene_id
    # the same scene authored as part of the whole plan is byte-identical
    full = allo_usd.author_plan(plan, tmp_path / "full", progress=False)
    twin = next(p for p in full.paths if p.stem == key.scene_id)
    assert twin.read_bytes() == layer.read_bytes()
    with pytest.raises(allo_usd.AlloError, match="no scene"):
        allo_usd.author_scene(plan, "s1_d000_p99", tmp_path / "tree")
