"""What `make run` does, at 64x36: real scenes over the committed stage, rendered and valid."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from allo_usd.run.demo import run_demo

from tests.support.plans import plain_usd_report
from tests.support.validation import validation_errors

pytestmark = pytest.mark.render


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    run_demo(out, resolution=(64, 36), samples=2)
    return out


def test_demo_renders_two_normal_and_two_anomalous(demo_dir):
    metas = [json.loads(p.read_text()) for p in sorted((demo_dir / "renders").glob("*.json"))]
    assert len(metas) == 4
    kinds = sorted(m["scene"]["variant"] for m in metas)
    assert kinds == ["anomaly", "anomaly", "normal", "normal"]
    for m in metas:
        mask = np.asarray(Image.open(demo_dir / "renders" / m["files"]["mask"]))
        assert mask.shape == (36, 64)
        assert (mask == 1).any(), "every demo pose looks at the station"
        assert ((mask == 2).any()) == (m["scene"]["variant"] == "anomaly")
        assert m["scene"]["provenance"]["seed"] == m["scene"]["seed"]
    sheet = Image.open(demo_dir / "contact_sheet.png")
    assert sheet.size[0] > 128 and sheet.size[1] > 4 * 36
    splits = sorted((m["scene"]["split"], m["scene"]["variant"]) for m in metas)
    assert splits == [("test", "anomaly"), ("test", "anomaly"), ("test", "normal"), ("train", "normal")]


def test_demo_dataset_has_every_mvtec_folder(demo_dir):
    """The demo's dataset: train/good, a non-empty test/good, and one test/ and ground_truth/ folder
    per anomaly asset, each image listed in the manifest; a re-run at another size starts it anew."""
    from allo_usd.output.dataset import read_manifest
    from allo_usd.run.demo import demo_dataset

    cat = demo_dir / "dataset" / "allo"
    folders = {f"{p.parent.name}/{p.name}": len(list(p.glob("*.png"))) for p in cat.glob("*/*")}
    assert folders == {"train/good": 1, "test/good": 1, "test/power_drill": 1, "test/mli_blanket": 1,
                       "ground_truth/power_drill": 1, "ground_truth/mli_blanket": 1}, folders
    rows = read_manifest(demo_dir / "dataset" / "manifest.csv")
    assert sorted(r["image"].split("/")[2] for r in rows) == ["good", "good", "mli_blanket", "power_drill"]
    assert sorted((demo_dir / "dataset" / "contact_sheets").iterdir())
    other = demo_dir / "other_size"
    demo_dataset(demo_dir / "renders", other, (64, 36))
    first = other / read_manifest(other / "manifest.csv")[0]["image"]
    first.unlink()                                   # (a hard link to the render: not written into)
    Image.new("RGB", (32, 18)).save(first)           # as if an earlier demo ran at 32x18
    demo_dataset(demo_dir / "renders", other, (64, 36))   # assemble alone refuses to mix sizes
    assert Image.open(first).size == (64, 36) and len(read_manifest(other / "manifest.csv")) == 4


def test_every_demo_layer_validates(demo_dir):
    layers = sorted((demo_dir / "layers").glob("*.usda"))
    assert len(layers) == 4
    for layer in layers:
        assert layer.stat().st_size <= 4096  # a scene layer's own file is at most 4 KB
        assert validation_errors(layer) == [], layer.name
    shared = sorted(p for d in ("sky", "poses") for p in (demo_dir / "layers" / d).rglob("*.usda"))
    assert [p.parent.name for p in shared].count("sky") == 4 and len(shared) == 8
    for layer in shared:
        assert validation_errors(layer) == [], layer.name


def test_demo_composes_like_a_plan_inside_its_own_tree(demo_dir, tmp_path, monkeypatch):
    """Scene layers stack shared pose and sky layers over the tree's own base stage copy, with
    relative paths only; the tree, moved elsewhere, opens with usd-core alone and renders."""
    import shutil

    from pxr import Sdf

    from allo_usd.run.job import render_layer
    from allo_usd.core.paths import STAGES

    tree = demo_dir / "layers"
    for path in sorted(tree.glob("*.usda")):
        layer = Sdf.Layer.FindOrOpen(str(path))
        subs = list(layer.subLayerPaths)
        assert subs[0].startswith("./poses/s2030/") and subs[1].startswith("./sky/d"), subs
        assert subs[2] == "./stages/base.usda"
        camera = layer.GetPrimAtPath("/World/Camera")  # only the image's exposure (UsdGeom.Camera), not the pose
        assert camera is None or set(camera.attributes.keys()) == {"exposure"}
    assert (tree / "stages" / "base.usda").read_bytes() == (STAGES / "base.usda").read_bytes()
    moved = tmp_path / "x" / "y" / "layers"
    shutil.copytree(tree, moved)
    report = plain_usd_report(moved, sorted(moved.glob("*.usda")))
    assert len(report["layers"]) == 4
    for path, r in report["layers"].items():
        assert r["composition_errors"] == [] and r["outside"] == [] and r["validation_errors"] == [], (path, r)
    from allo_usd.usd.safety import ENV_ROOTS

    monkeypatch.delenv(ENV_ROOTS, raising=False)  # the layer's own directory is an allowed root
    meta = render_layer(moved / "d045_p42_power_drill_z0.usda", tmp_path / "renders")
    assert meta["class_pixels"]["anomaly"] > 0
    original = json.loads((demo_dir / "renders" / "d045_p42_power_drill_z0.json").read_text())
    assert meta["class_pixels"] == original["class_pixels"]


def test_demo_rerun_renders_only_changed_layers_with_a_progress_bar(demo_dir, capsys):
    before = {p.name: p.stat().st_mtime_ns for p in (demo_dir / "renders").glob("*.json")}
    run_demo(demo_dir, resolution=(64, 36), samples=2)
    assert {p.name: p.stat().st_mtime_ns for p in (demo_dir / "renders").glob("*.json")} == before
    err = capsys.readouterr().err
    assert "demo: 100%" in err and "4/4 [" in err  # counts, then elapsed<remaining (the ETA)
