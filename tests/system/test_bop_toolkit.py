"""The dataset's bop/CATEGORY/ evaluated as the BOP toolkit would (tests/support/bop_toolkit.py: its
load_ply, calc_pts_diameter, calc_gt_info, mssd, mspd, vsd, written from its definitions), on tiny renders
of the demo's anomalous scene as authored and with a user layer moving /World/Anomaly onto the image's
left edge, 1.5 m from the camera (a truncated anomaly): the first with the depth and amodal passes, the
second with depth alone (its full silhouette in the image from the render JSON's amodal_segmentation)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.support import bop_toolkit as bt
from tests.support.user_layers import DEMO_ANOMALY, demo_layers, override, render

pytestmark = pytest.mark.render

PASSES = ("rgb", "exr", "mask", "depth", "amodal")
NO_AMODAL = ("rgb", "exr", "mask", "depth")
NAME, SPLIT = "allo", "test"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from allo_usd.output.dataset import assemble
    from allo_usd.usd.read import read_scene

    root = tmp_path_factory.mktemp("bop_toolkit")
    scene = demo_layers(root) / f"{DEMO_ANOMALY}.usda"
    render(override(scene, root / "mine" / "authored.usda"), root / "renders", passes=PASSES)
    rec = json.loads((root / "renders" / "authored.json").read_text())
    k, a = np.array(rec["annotations"]["camera"]["K_px"]), rec["annotations"]["anomaly"]
    d = 1.5
    x, y = (0 - k[0, 2]) / k[0, 0] * d, (a["center_px"][1] - k[1, 2]) / k[1, 1] * d   # centred on the left edge
    p = (np.array(read_scene(scene).camera.matrix) @ [x, -y, -d, 1.0])[:3]
    body = 'over "World"\n{\n    over "Anomaly"\n    {\n        double3 xformOp:translate = (%r, %r, %r)\n    }\n}\n'
    render(override(scene, root / "mine" / "edge.usda", body % tuple(map(float, p))), root / "renders", passes=NO_AMODAL)
    out = root / "ds"
    assemble([root / "renders"], out)
    return out


def images(out: Path):
    """(scene_id, im_id, gt_id, gt, camera, model) of every ground-truth pose of the test split."""
    base = out / "bop" / NAME
    models = {int(k): bt.load_ply(base / "models" / f"obj_{int(k):06d}.ply")
              for k in json.loads((base / "models.json").read_text())}
    for scene_dir in sorted(p for p in (base / SPLIT).iterdir() if p.is_dir()):
        paths = bt.split_paths(out / "bop", NAME, SPLIT, int(scene_dir.name))
        gts, cams = bt.load_json(paths["scene_gt"], True), bt.load_json(paths["scene_camera"], True)
        infos = bt.load_json(paths["scene_gt_info"], True)
        for im_id, gt_list in gts.items():
            for gt_id, gt in enumerate(gt_list):
                gt = {**gt, "cam_R_m2c": np.reshape(gt["cam_R_m2c"], (3, 3)), "cam_t_m2c": np.reshape(gt["cam_t_m2c"], (3, 1))}
                yield (int(scene_dir.name), im_id, gt_id, gt, infos[im_id][gt_id], cams[im_id], models[gt["obj_id"]],
                       paths)


def depth_mm(paths, im_id, cam) -> np.ndarray:
    with Image.open(str(paths["depth"]).format(im_id=im_id)) as im:
        return np.asarray(im, dtype=np.float64) * cam["depth_scale"]


def test_every_file_the_toolkits_loader_reads_is_there_and_parses(dataset):
    base = dataset / "bop" / NAME
    cam = bt.load_json(base / "camera.json")   # inout.load_cam_params
    assert {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"} <= set(cam)
    obj_ids = sorted(int(k) for k in json.loads((base / "models.json").read_text()))
    for folder in ("models", "models_eval"):   # get_model_params: models[_TYPE]/obj_{obj_id:06d}.ply, models_info.json
        info = bt.load_json(base / folder / "models_info.json", True)
        assert sorted(info) == obj_ids
        for obj_id in obj_ids:
            model = bt.load_ply(base / folder / f"obj_{obj_id:06d}.ply")
            assert len(model["pts"]) and len(model["faces"]) and model["normals"].shape == model["pts"].shape
            assert {"diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"} <= set(info[obj_id])
    targets = bt.load_json(base / "test_targets_bop19.json")
    expected = []
    for scene_id, im_id, gt_id, gt, info, cam_im, _, paths in images(dataset):
        assert np.reshape(cam_im["cam_K"], (3, 3))[2].tolist() == [0, 0, 1]
        for key in ("rgb", "depth"):
            assert Path(str(paths[key]).format(im_id=im_id)).is_file()
        for key in ("mask", "mask_visib"):
            assert Path(str(paths[key]).format(im_id=im_id, gt_id=gt_id)).is_file()
        if info["visib_fract"] >= 0.1:   # enumerate_test_targets' min_visib_fract
            expected.append({"im_id": im_id, "inst_count": 1, "obj_id": gt["obj_id"], "scene_id": scene_id})
    assert targets == expected and len(expected) >= 1


def test_models_info_is_calc_model_infos(dataset):
    base = dataset / "bop" / NAME
    info = bt.load_json(base / "models" / "models_info.json", True)
    for obj_id, entry in info.items():
        pts = bt.load_ply(base / "models" / f"obj_{obj_id:06d}.ply")["pts"]
        assert entry["diameter"] == bt.calc_pts_diameter(pts)           # to the bit
        box = bt.calc_3d_bbox(pts)
        assert [entry[k] for k in ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z")] == box


def test_pose_errors_of_the_ground_truth_are_zero_and_a_1mm_shift_is_1mm(dataset):
    info = bt.load_json(dataset / "bop" / NAME / "models" / "models_info.json", True)
    for _, im_id, _, gt, _, cam, model, paths in images(dataset):
        R, t, K, pts = gt["cam_R_m2c"], gt["cam_t_m2c"], np.reshape(cam["cam_K"], (3, 3)), model["pts"]
        syms = bt.get_symmetry_transformations(info[gt["obj_id"]], 0.01)
        assert bt.mssd(R, t, R, t, pts, syms) == 0.0 and bt.mspd(R, t, R, t, K, pts, syms) == 0.0
        assert bt.vsd(R, t, R, t, depth_mm(paths, im_id, cam), K, 15.0, [0.05, 0.2, 0.5], info[gt["obj_id"]]["diameter"],
                      model) == [0.0, 0.0, 0.0]
        for axis in range(3):
            shift = np.eye(3)[axis].reshape(3, 1)
            assert bt.mssd(R, t + shift, R, t, pts, syms) == pytest.approx(1.0, abs=1e-9)


def test_the_models_vertices_in_the_gt_pose_cover_mask_visib(dataset):
    for _, im_id, gt_id, gt, _, cam, model, paths in images(dataset):
        K = np.reshape(cam["cam_K"], (3, 3))
        with Image.open(str(paths["mask_visib"]).format(im_id=im_id, gt_id=gt_id)) as im:
            visib = np.asarray(im) == 255
        h, w = visib.shape
        silhouette = bt.render_depth(model, gt["cam_R_m2c"], gt["cam_t_m2c"], K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h) > 0
        grown = silhouette.copy()   # a pixel's worth: Cycles' mask and a ray cast may differ on an edge pixel
        grown[1:] |= silhouette[:-1]; grown[:-1] |= silhouette[1:]
        grown[:, 1:] |= silhouette[:, :-1]; grown[:, :-1] |= silhouette[:, 1:]
        assert visib.any() and not (visib & ~grown).any(), (im_id, int((visib & ~grown).sum()))
        with Image.open(str(paths["mask"]).format(im_id=im_id, gt_id=gt_id)) as im:
            full = np.asarray(im) == 255   # the full silhouette in the image: the amodal pass's, or the recorded RLE's
        assert not (full & ~grown).any() and abs(int(full.sum()) - int(silhouette.sum())) <= edge_pixels(silhouette), im_id


def recomputed(dataset):
    for _, im_id, _, gt, written, cam, model, paths in images(dataset):
        K = np.reshape(cam["cam_K"], (3, 3))
        yield im_id, written, bt.calc_gt_info(depth_mm(paths, im_id, cam), K, gt, model)


def test_calc_gt_info_gives_the_visible_part_written(dataset):
    """px_count_visib and bbox_visib: the toolkit's depth test (delta 15 mm) on our depth and model."""
    for im_id, written, mine in recomputed(dataset):
        assert (written["px_count_visib"], written["bbox_visib"]) == (mine["px_count_visib"], mine["bbox_visib"]), im_id
        assert written["px_count_valid"] == mine["px_count_valid"]


def edge_pixels(mask: np.ndarray) -> int:
    inner = mask.copy()
    inner[1:-1, 1:-1] = mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
    return int((mask & ~inner).sum())


def test_calc_gt_info_truncation_full_silhouette(dataset):
    """px_count_all, bbox_obj and visib_fract on the toolkit's 3W x 3H canvas (within a pixel's worth: the
    silhouette's edge pixels, one pixel on a box side), the truncated anomaly included."""
    for im_id, written, mine in recomputed(dataset):
        assert abs(written["px_count_all"] - mine["px_count_all"]) <= edge_pixels(mine["mask_all"]), im_id
        assert all(abs(a - b) <= 1 for a, b in zip(written["bbox_obj"], mine["bbox_obj"])), (im_id, written, mine)
        slack = edge_pixels(mine["mask_all"]) / mine["px_count_all"]
        assert written["visib_fract"] == pytest.approx(mine["visib_fract"], abs=slack), im_id


def test_a_rerun_rewrites_only_a_changed_model(dataset):
    from allo_usd.output.dataset import assemble, read_manifest

    base = dataset / "bop" / NAME
    ply = base / "models" / "obj_000001.ply"
    good, before = ply.read_bytes(), os.stat(ply)
    renders = {Path(dataset / r["source"]).parent for r in read_manifest(dataset / "manifest.csv")}
    assemble(sorted(renders), dataset)
    after = os.stat(ply)
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)   # not rewritten
    ply.write_bytes(good[:-7])   # a stale model (or one cut short): rewritten whole
    assemble(sorted(renders), dataset)
    assert ply.read_bytes() == good == (base / "models_eval" / "obj_000001.ply").read_bytes()
    assert not [p for p in base.rglob("*") if ".tmp" in p.name or p.name.startswith(".")]
