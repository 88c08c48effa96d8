"""A render's identity covers everything its composition read and the versions that affect pixels
(resume re-renders when any of it changes); output names are collision-free by construction."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from allo_usd.core.errors import LayerError
from allo_usd.core.files import sha256_file
from allo_usd.run.dispatch import dispatch, find_layers
from allo_usd.output.identity import render_identity, render_versions
from allo_usd.output.render_outputs import check_output_names, output_paths
from allo_usd.run.render_index import is_done, is_verified, load_manifest
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

ALL_OUTPUTS = ("color", "mask", "depth")
STEMS = st.lists(st.sampled_from(["a", "A", "b", "_", "-", "0", "mask", "MASK", "Mask", "depth", "DEPTH",
                                  "_mask", "_Depth", "x"]), min_size=1, max_size=4).map("".join)


def names(layer: Path) -> set[str]:
    """A layer's output names as a case-insensitive file system sees them."""
    return {p.name.lower() for p in output_paths(layer, Path("out"), ALL_OUTPUTS).values()}


@settings(max_examples=400, deadline=None)
@given(st.lists(STEMS, min_size=2, max_size=6))
@pytest.mark.slow
def test_output_names_of_accepted_layers_never_overlap(stems):
    layers = [Path(f"dir{i}") / f"{s}.usda" for i, s in enumerate(stems)]  # other folders, one output dir
    try:
        check_output_names(layers)
    except LayerError as exc:
        assert "rename" in str(exc)
        return
    for a, b in itertools.combinations(layers, 2):
        assert not names(a) & names(b), (a, b)


@pytest.mark.parametrize("stem", ["a_mask", "A_MASK", "scene_Depth", "x_depth"])
def test_a_stem_with_a_reserved_suffix_is_refused(stem):
    with pytest.raises(LayerError, match=rf"{stem}.usda: a layer named .*rename the layer"):
        check_output_names([Path(f"{stem}.usda")])
    with pytest.raises(LayerError, match="rename the layer"):
        output_paths(Path(f"{stem}.usda"), Path("out"), ALL_OUTPUTS)


def test_a_and_a_mask_are_refused_before_anything_renders(tiny_base, tmp_path):
    """a_mask.usda's RGB would be a.usda's class mask."""
    from allo_usd.run.job import render_layer

    for stem in ("a", "a_mask"):
        write_scene_layer(make_spec(scene_id=stem), tmp_path / "layers" / f"{stem}.usda", tiny_base)
    with pytest.raises(LayerError, match=r"a_mask.usda: a layer named \.\.\._mask .*a.usda's mask"):
        find_layers(tmp_path / "layers")
    with pytest.raises(LayerError, match="rename the layer"):
        dispatch(tmp_path / "layers", tmp_path / "out", workers=1, progress=False)
    with pytest.raises(LayerError, match="rename the layer"):
        render_layer(tmp_path / "layers" / "a_mask.usda", tmp_path / "out1")
    assert not (tmp_path / "out").exists() and not (tmp_path / "out1").exists()
    with pytest.raises(LayerError, match="differ only in case"):
        find_layers([tmp_path / "x" / "Scene.usda", tmp_path / "y" / "scene.usda"])


@pytest.fixture
def tree(tmp_path):
    """One authored scene (1 day, 1 pose, 64x36) over the tree's own copy of the base stage."""
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.plan.model import Anomalies, Dates, Plan, Poses, Quality
    from allo_usd.run.author import author_plan

    plan = Plan(name="identity", dates=Dates(days=1), poses=Poses(train=[1], test=[]),
                anomalies=Anomalies(assets=[]), quality=Quality(resolution=(64, 36), samples=2),
                base_stage=str(BASE_STAGE))
    [layer] = author_plan(plan, tmp_path / "tree", progress=False)
    return tmp_path / "tree", layer


@pytest.mark.render
def test_resume_renders_again_when_a_shared_sublayer_or_texture_changes(tree, tmp_path):
    root, layer = tree
    out = tmp_path / "out"
    assert dispatch(root, out, workers=1, progress=False).rendered == [layer.stem]
    meta = json.loads((out / f"{layer.stem}.json").read_text())
    row = load_manifest(out)[layer.stem]
    assert meta["identity"] == row["identity"] == render_identity(meta["inputs"])
    assert meta["versions"] == render_versions() and meta["versions"]["bpy"] != "not installed"
    assert {f"./{layer.name}", "../../../poses/s2030/d000_p01.usda", "../../../sky/d000.usda",
            "../../../stages/base.usda", "../../../stages/station/Station_geom.usdc",
            "../../../stages/station/textures/radiator.png"} <= set(meta["inputs"]), meta["inputs"]
    assert dispatch(root, out, workers=1, progress=False).skipped == [layer.stem]
    png = (out / f"{layer.stem}.png").read_bytes()

    sky = root / "sky" / "d000.usda"  # an edit of the shared sky: its sun intensity to 0
    sky.write_text(re.sub(r"inputs:intensity = [0-9.e+-]+", "inputs:intensity = 0", sky.read_text()))
    assert not is_done(layer, out) and not is_done(layer, out, load_manifest(out))
    summary = dispatch(root, out, workers=1, progress=False)
    assert summary.rendered == [layer.stem] and not summary.skipped
    assert (out / f"{layer.stem}.png").read_bytes() != png  # what a fresh render gives
    assert is_done(layer, out) and is_done(layer, out, load_manifest(out))

    texture = root / "stages" / "station" / "textures" / "radiator.png"
    texture.write_bytes(texture.read_bytes() + b"\0")  # a texture the stack uses
    assert not is_done(layer, out) and not is_done(layer, out, load_manifest(out))


@pytest.mark.render
def test_identity_covers_the_renderer_version(tree, tmp_path):
    """A render made with another bpy is not done: its recorded identity was made with that version."""
    from allo_usd.run.job import render_layer

    root, layer = tree
    out = tmp_path / "out"
    meta = render_layer(layer, out)
    assert is_done(layer, out)
    other = {**meta["versions"], "bpy": "4.2.0"}
    meta.update(identity=render_identity(meta["inputs"], other), versions=other)
    (out / f"{layer.stem}.json").write_text(json.dumps(meta))
    assert not is_done(layer, out)
    row = {"layer_sha256": meta["layer_sha256"], "identity": meta["identity"],
           "files": {p.name: sha256_file(p) for p in output_paths(layer, out).values()}}
    assert not is_verified(row, layer, out)
    assert render_layer(layer, out)["identity"] == render_identity(meta["inputs"])  # rendered again
