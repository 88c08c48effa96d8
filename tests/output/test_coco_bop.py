"""The dataset's COCO and BOP files and its pass folders, on real tiny Cycles renders.

A normal train scene, a normal test scene and an anomalous test scene are rendered at 64x36 with
the depth, normal and instance passes (and `amodal` once the renderer has it); `allo-usd dataset`'s
assemble then writes annotations/, bop/, depth/, normal/, instance/ and instances.json. The COCO and
BOP snippets of docs/formats/coco_bop.md are run here as they are written (README_SNIPPETS)."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from allo_usd.core.paths import ROOT
from allo_usd.output.annotation_files import read_depth_exr
from allo_usd.output.dataset import summary_line
from allo_usd.output.bop import DEPTH_SCALE
from allo_usd.output.dataset import assemble, read_manifest
from allo_usd.output.pass_files import PASS_COLUMNS
from allo_usd.run.job import render_layer
from allo_usd.output.render_outputs import PASS_FILES
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

pytestmark = pytest.mark.render

AMODAL = "amodal" in PASS_FILES   # the render side's `amodal` pass, once it exists
PASSES = ("rgb", "exr", "mask", "depth", "normal", "instance") + (("amodal",) if AMODAL else ())
SCENES = {"d000_p01": dict(day=0, pose=1, seed=21),
          "d002_p41": dict(day=2, pose=41, split="test", seed=23),
          "d003_p41_crate_z0": dict(day=3, pose=41, split="test", seed=24, anomaly=True)}


def pixels(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


@pytest.fixture(scope="module")
def renders(tiny_base, tmp_path_factory):
    root = tmp_path_factory.mktemp("coco_render")
    for name, kw in SCENES.items():
        spec = make_spec(scene_id=name, samples=2, **kw)
        spec = replace(spec, render=replace(spec.render, passes=PASSES))
        render_layer(write_scene_layer(spec, root / "layers" / f"{name}.usda", tiny_base), root / "renders")
    return root / "renders"


@pytest.fixture(scope="module")
def tree(renders, tmp_path_factory):
    out = tmp_path_factory.mktemp("coco_ds") / "ds"
    assemble([renders], out)
    return out, summary_line(out)


def rows_by_name(out: Path) -> dict[str, dict]:
    return {r["name"]: r for r in read_manifest(out / "manifest.csv")}


def test_coco_round_trip_is_exact(tree):
    from pycocotools import mask as mask_utils
    from pycocotools.coco import COCO

    out, _ = tree
    rows = rows_by_name(out)
    test = COCO(str(out / "annotations" / "instances_test.json"))
    assert [c["name"] for c in test.loadCats(test.getCatIds())] == ["Crate"]     # one per asset, no station
    by_file = {img["file_name"]: img for img in test.loadImgs(test.getImgIds())}
    assert set(by_file) == {r["image"] for r in rows.values() if r["split"] == "test"}
    for file_name, img in by_file.items():
        row = next(r for r in rows.values() if r["image"] == file_name)
        assert (out / file_name).is_file() and (img["width"], img["height"]) == (64, 36)
        anns = test.loadAnns(test.getAnnIds(imgIds=img["id"]))
        if row["kind"] == "good":
            assert anns == []                      # normal images are present with no annotation
            continue
        (ann,) = anns
        visible = pixels(out / row["allo_mask"]) == 2
        assert visible.any() and np.array_equal(test.annToMask(ann).astype(bool), visible)
        x0, y0, x1, y1 = (int(row[f"bbox_{k}"]) for k in ("x_min", "y_min", "x_max", "y_max"))
        assert ann["bbox"] == [x0, y0, x1 - x0 + 1, y1 - y0 + 1] == list(mask_utils.toBbox(ann["segmentation"]))
        assert ann["area"] == int(visible.sum()) == int(row["anomaly_pixels"]) and ann["iscrowd"] == 0
    train = COCO(str(out / "annotations" / "instances_train.json"))
    assert len(train.getImgIds()) == 1 and train.getAnnIds() == []


def test_bop_files_have_bops_keys_and_agree_with_the_masks(tree):
    out, summary = tree
    rows = rows_by_name(out)
    row = rows["d003_p41_crate_z0"]
    im = int(row["index"])
    scene = out / "bop" / "allo" / "test" / "000000"
    camera = json.loads((scene / "scene_camera.json").read_text())
    gt = json.loads((scene / "scene_gt.json").read_text())
    info = json.loads((scene / "scene_gt_info.json").read_text())
    assert set(camera) == set(gt) == set(info) == {r["index"] for r in rows.values() if r["split"] == "test"}
    cam = camera[str(im)]
    assert set(cam) == {"cam_K", "depth_scale", "cam_R_w2c", "cam_t_w2c"} and cam["depth_scale"] == DEPTH_SCALE
    assert np.allclose(np.reshape(cam["cam_K"], (3, 3)), json.loads(row["K_px"]))
    w2c = np.array(json.loads(row["world_to_cam_opencv"]))
    assert np.allclose(np.reshape(cam["cam_R_w2c"], (3, 3)), w2c[:3, :3])
    assert np.allclose(cam["cam_t_w2c"], w2c[:3, 3] * 1000.0)       # mm
    visible = pixels(out / row["allo_mask"]) == 2
    mask_visib = pixels(scene / "mask_visib" / f"{im:06d}_000000.png")
    assert np.array_equal(mask_visib == 255, visible) and set(np.unique(mask_visib)) <= {0, 255}
    assert (scene / "rgb" / f"{im:06d}.png").samefile(out / row["image"])
    meta = json.loads((out / row["source"]).read_text())
    if (meta["annotations"]["anomaly"] or {}).get("pose") is None:     # the render side has not landed yet
        assert gt[str(im)] == info[str(im)] == [] and "BOP poses 0 of 1" in summary and "re-render" in summary
        return
    (entry,), (gi,) = gt[str(im)], info[str(im)]
    assert "BOP poses 1 of 1" in summary and ("amodal masks 1 of 1" in summary) == AMODAL
    assert set(entry) >= {"obj_id", "cam_R_m2c", "cam_t_m2c"} and isinstance(entry["obj_id"], int)
    r = np.reshape(entry["cam_R_m2c"], (3, 3))
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(r), 1.0)
    models = json.loads((out / "bop" / "allo" / "models.json").read_text())
    assert models[str(entry["obj_id"])]["asset"] == "Crate"
    ys, xs = np.nonzero(visible)
    assert gi["bbox_visib"] == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
    assert gi["px_count_visib"] == visible.sum() and 0 < gi["visib_fract"] <= 1
    assert gi["visib_fract"] == pytest.approx(gi["px_count_visib"] / gi["px_count_all"])
    if AMODAL:
        amodal = pixels(scene / "mask" / f"{im:06d}_000000.png") == 255
        assert gi["px_count_all"] >= amodal.sum() and not (visible & ~amodal).any()   # the canvas: outside too
        assert gi["silhouette"] == "canvas" and gi["px_count_all"] == meta["annotations"]["anomaly"]["amodal_pixels_canvas"]


def test_every_pass_is_in_the_dataset_and_the_manifest(tree, renders):
    out, _ = tree
    for row in rows_by_name(out).values():
        meta = json.loads((out / row["source"]).read_text())
        for name in PASS_COLUMNS:
            assert row[name] == f"{name}/{Path(row['image']).with_suffix(Path(meta['files'][name]).suffix)}"
            assert (out / row[name]).samefile(renders / meta["files"][name])   # placed as the images are
        depth = read_depth_exr(out / row["depth"])
        assert np.array_equal(depth, read_depth_exr(renders / meta["files"]["depth"]))
        chunk = out / "bop" / "allo" / row["split"] / "000000"
        units = pixels(chunk / "depth" / f"{int(row['index']):06d}.png")
        assert units.dtype == np.uint16
        valid = np.isfinite(depth) & (depth > 0) & (depth * 1000 / DEPTH_SCALE <= 65535)
        assert valid.any() and (~valid).any()               # station pixels, and the black sky (0: BOP's invalid)
        assert np.all(np.abs(units[valid] * DEPTH_SCALE - depth[valid] * 1000) <= DEPTH_SCALE / 2 + 1e-3)
        assert not units[~valid].any()
        tables = json.loads((out / "instances.json").read_text())["images"]
        assert tables[row["image"]] == {"instance": row["instance"], "objects": meta["instances"]}
        assert pixels(out / row["instance"]).max() <= len(meta["instances"])


def fabricate(src: Path, name: str, dst: Path, new: str, **scene) -> Path:
    """A copy of a real render record and all its files under another scene name."""
    meta = json.loads((src / f"{name}.json").read_text())
    dst.mkdir(parents=True, exist_ok=True)
    files = {}
    for key, file in meta["files"].items():
        files[key] = file.replace(name, new)
        if key != "meta":
            shutil.copyfile(src / file, dst / files[key])
    meta["files"], meta["layer_sha256"] = files, "f" * 64
    meta["scene"].update(sceneId=new, **scene)
    (dst / f"{new}.json").write_text(json.dumps(meta))
    return dst


REDRAWN = ("manifest.csv", "manifest.parquet", "contact_sheets/")   # rewritten by every run


def stats(out: Path) -> dict[str, tuple[int, int]]:
    return {p.relative_to(out).as_posix(): (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.rglob("*")
            if p.is_file() and not p.relative_to(out).as_posix().startswith(REDRAWN)}


def test_a_rerun_adding_scenes_leaves_earlier_files_untouched(renders, tmp_path):
    out = tmp_path / "ds"
    assemble([renders], out)
    before = stats(out)
    assemble([renders], out)
    assert stats(out) == before                             # nothing new: no file rewritten, COCO and BOP included
    more = fabricate(renders, "d002_p41", tmp_path / "more", "d009_p44", day=9, pose=44)
    assemble([renders, more], out)
    after = stats(out)
    rewritten = {"annotations/instances_test.json", "annotations/records.json", "instances.json",
                 "bop/allo/test/000000/scene_camera.json", "bop/allo/test/000000/scene_gt.json",
                 "bop/allo/test/000000/scene_gt_info.json"}
    for path, stat in before.items():
        if path not in rewritten:
            assert after[path] == stat, f"{path} was rewritten"
    assert after["annotations/instances_train.json"] == before["annotations/instances_train.json"]
    new = rows_by_name(out)["d009_p44"]
    assert all((out / new[k]).is_file() for k in PASS_COLUMNS)
    assert (out / "bop" / "allo" / "test" / "000000" / "depth" / f"{int(new['index']):06d}.png").is_file()


def readme_snippet(first_line: str) -> str:
    """The python block of docs/formats/coco_bop.md that starts with `first_line`."""
    text = (ROOT / "docs" / "formats" / "coco_bop.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    return next(b for b in blocks if b.startswith(first_line))


def test_readme_coco_and_bop_snippets_run(tree, monkeypatch):
    out, _ = tree
    monkeypatch.chdir(out.parent)
    for first in ("# COCO:", "# BOP:"):
        code = readme_snippet(first).replace('"out/demo/dataset"', repr(str(out)))
        namespace: dict = {}
        exec(compile(code, f"docs/formats/coco_bop.md {first}", "exec"), namespace)   # noqa: S102 - the README's own code
        if first == "# BOP:" and namespace.get("covered") is not None:
            assert namespace["covered"] >= 0.98   # the model's projected vertices cover the visible mask
