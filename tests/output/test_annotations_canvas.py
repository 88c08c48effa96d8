"""BOP's truncation convention (allo_usd.output.annotations, bop.gt_info): the full silhouette is
counted on the BOP toolkit's canvas (scripts/calc_gt_info.py: 3W x 3H, principal point shifted by
(W, H)), so px_count_all, visib_fract and bbox_obj include the part of the anomaly outside the image.
Each case is checked against an independent computation written here: numpy Moller-Trumbore of
every model triangle against the ray through every canvas pixel centre (no embree)."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.assets.mesh import fan_triangulate
from allo_usd.core.labels import ANOMALY
from allo_usd.output import bop
from allo_usd.output.annotations import camera_record, image_annotations
from allo_usd.plan.settings import RenderSpec
from allo_usd.scene.spec import CameraSpec
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import EXPOSURE, make_spec

W, H = 160, 90
CRATE = np.array([8.0, 4.0, 2.5])   # the tiny crate's place (0.6 x 0.4 x 0.3 m, axis-aligned)


def _camera_for(rotation: np.ndarray, cam_opencv: np.ndarray) -> CameraSpec:
    """A camera of `rotation` (camera-to-station, USD axes) placed so that the crate's centre is at
    `cam_opencv` in its OpenCV frame (x right, y down, z forward)."""
    usd = np.array([cam_opencv[0], -cam_opencv[1], -cam_opencv[2]])
    return CameraSpec(tuple(CRATE - rotation @ usd), rotation)


def toolkit_canvas(desc, width: int, height: int) -> np.ndarray:
    """(3H, 3W) bool: calc_gt_info's obj_mask_gt_large, independently: canvas pixel (c, r) holds the
    ray through image pixel centre (c - W, r - H) (the mask's rule: centres at integers), which
    meets some anomaly triangle in front of the camera (Moller-Trumbore, float64, both windings)."""
    cam = camera_record(desc, width, height)
    k, w2c = np.array(cam["K_px"]), np.array(cam["world_to_cam_opencv"])
    tris = []
    for m in desc.meshes:
        if m.class_id == ANOMALY:
            p = np.asarray(m.points, dtype=np.float64) @ np.asarray(m.matrix)[:3, :3].T + np.asarray(m.matrix)[:3, 3]
            p = p @ w2c[:3, :3].T + w2c[:3, 3]                       # OpenCV camera frame: rays from the origin
            tris.append(p[fan_triangulate(m.face_counts, m.face_indices)])
    rows, cols = np.mgrid[-height:2 * height, -width:2 * width]
    d = np.stack([(cols.ravel() - k[0, 2]) / k[0, 0], (rows.ravel() - k[1, 2]) / k[1, 1], np.ones(cols.size)], axis=1)
    hit = np.zeros(len(d), dtype=bool)
    for a, b, c in np.concatenate(tris):
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = p @ e1
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = -a                                                         # the origin minus a
        u = (p @ s) * inv
        q = np.cross(s, e1)
        v = (d @ q) * inv
        t = (q @ e2) * inv
        hit |= ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hit.reshape(3 * height, 3 * width)


def toolkit_info(canvas: np.ndarray, visible: np.ndarray) -> dict:
    """calc_gt_info's px_count_all, visib_fract, bbox_obj (misc.calc_2d_bbox of the canvas pixels
    shifted back by (W, H), unclipped; [-1]*4 when nothing is visible) for a visible mask."""
    height, width = visible.shape
    px_all, px_visib = int(canvas.sum()), int(visible.sum())
    box = [-1, -1, -1, -1]
    if px_visib > 0:
        ys, xs = canvas.nonzero()
        xs, ys = xs - width, ys - height
        box = [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]
    return {"px_count_all": px_all, "visib_fract": px_visib / px_all if px_all else 0.0, "bbox_obj": box}


def _rotation_looking(forward) -> np.ndarray:
    from allo_usd.core.geometry import look_at

    return look_at([0.0, 0.0, 0.0], np.asarray(forward, dtype=float))


def _cases():
    """name -> (crate centre in the OpenCV camera frame, expressed as a pixel and a depth, or metres)."""
    return {
        "left_edge": ("pixel", (-0.5, 60.0, 3.0)),
        "bottom_right_corner": ("pixel", (W - 0.5, H - 0.5, 3.0)),
        "around_the_lens": ("metres", (0.0, 0.25, 0.12)),     # 0.12 m in front of the lens, vertices behind it
        "top_edge": ("pixel", (70.0, 2.0, 6.0)),               # an ordinary scene, just cut by the top edge
    }


@pytest.fixture(scope="module")
def scenes(tiny_base, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("canvas")
    rot = _rotation_looking([-1.0, -0.5, -0.3])
    k = np.array(camera_record(_desc_at(tiny_base, tmp, "probe", CameraSpec((15.0, 8.0, 5.0), rot)), W, H)["K_px"])
    out = {}
    for name, (kind, where) in _cases().items():
        if kind == "pixel":
            u, v, z = where
            at = np.array([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z])
        else:
            at = np.array(where)
        out[name] = _desc_at(tiny_base, tmp, name, _camera_for(rot, at))
    return out


def _desc_at(tiny_base, tmp, name, camera):
    spec = make_spec(anomaly=True, render=RenderSpec((W, H), samples=1, exposure=EXPOSURE, seed=1, denoise=False),
                     camera=camera)
    return read_scene(write_scene_layer(spec, tmp / f"{name}.usda", tiny_base))


def _record(desc, visible: np.ndarray, amodal=None) -> dict:
    mask = np.where(visible, ANOMALY, 0).astype(np.uint8)
    return image_annotations(desc, mask, amodal)["anomaly"]


@pytest.mark.parametrize("name", list(_cases()))
def test_full_silhouette_is_counted_on_the_toolkits_canvas(scenes, name):
    desc = scenes[name]
    canvas = toolkit_canvas(desc, W, H)
    inside = canvas[H:2 * H, W:2 * W]
    assert inside.any() and canvas.sum() > inside.sum()   # truncated: part of it lies outside the image
    visible = inside.copy()
    visible[:, : W // 2] = False if name == "around_the_lens" else visible[:, : W // 2]   # hidden by something
    truth = toolkit_info(canvas, visible)
    for amodal in (None, np.where(inside, ANOMALY, 0).astype(np.uint8)):   # ray cast alone, or with the pass
        a = _record(desc, visible, amodal)
        assert a["visib_source"] == ("raycast" if amodal is None else "amodal_pass")
        assert abs(a["amodal_pixels_canvas"] - truth["px_count_all"]) <= max(2, 0.002 * truth["px_count_all"])
        assert a["visib_fract"] == pytest.approx(truth["visib_fract"], abs=0.005)
        assert a["visib_fract"] == a["pixels"] / a["amodal_pixels_canvas"]
        x0, y0, x1, y1 = a["bbox_amodal_canvas_xyxy_px"]
        assert np.abs(np.array(bop.bop_box([x0, y0, x1, y1])) - truth["bbox_obj"]).max() <= 1
        assert abs(a["amodal_pixels"] - inside.sum()) <= 2              # the in-image count stays the image's
        info = bop.gt_info(visible, None if amodal is None else inside, a, None)
        assert info["px_count_all"] == a["amodal_pixels_canvas"] and info["silhouette"] == "canvas"
        assert info["visib_fract"] == a["visib_fract"]
        assert info["bbox_obj"] == bop.bop_box(a["bbox_amodal_canvas_xyxy_px"])
        ys, xs = visible.nonzero()
        assert info["bbox_visib"] == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]


# ---------------------------------------------------------------- bop.gt_info's rules, without a scene
def _visible(box=(20, 10, 23, 12), shape=(36, 64)) -> np.ndarray:
    v = np.zeros(shape, dtype=bool)
    x0, y0, x1, y1 = box
    v[y0:y1 + 1, x0:x1 + 1] = True
    return v


CANVAS = {"amodal_pixels": 12, "bbox_amodal_xyxy_px": [20, 10, 23, 12], "amodal_pixels_canvas": 30,
          "bbox_amodal_canvas_xyxy_px": [-6, 10, 23, 12], "visib_source": "raycast"}


def test_gt_info_takes_the_canvas_count_and_an_unclipped_box():
    info = bop.gt_info(_visible(), None, CANVAS, None)
    assert info == {"px_count_visib": 12, "bbox_visib": [20, 10, 3, 2], "px_count_all": 30, "bbox_obj": [-6, 10, 29, 2],
                    "visib_fract": 12 / 30, "visib_source": "raycast", "silhouette": "canvas"}
    amodal = _visible((18, 10, 23, 12))   # the pass's pixels in the image: px_count_valid from them
    depth = np.where(amodal, 100, 0).astype(np.uint16)
    depth[10, 18] = 0
    info = bop.gt_info(_visible(), amodal, CANVAS, depth)
    assert (info["px_count_all"], info["px_count_valid"], info["visib_source"]) == (30, 17, "amodal_pass")


def test_gt_info_boxes_are_minus_one_when_nothing_is_visible():
    """calc_gt_info: bbox_obj and bbox_visib are [-1]*4 when px_count_visib is 0, whatever px_count_all."""
    info = bop.gt_info(np.zeros((36, 64), bool), None, CANVAS, None)
    assert info["bbox_obj"] == info["bbox_visib"] == [-1, -1, -1, -1]
    assert (info["px_count_all"], info["px_count_visib"], info["visib_fract"]) == (30, 0, 0.0)


def test_gt_info_of_an_older_render_keeps_the_image_values_and_says_so():
    old = {k: v for k, v in CANVAS.items() if "canvas" not in k}
    info = bop.gt_info(_visible(), None, old, None)
    assert (info["px_count_all"], info["bbox_obj"], info["visib_fract"], info["silhouette"]) == \
        (12, [20, 10, 3, 2], 1.0, "image")
    amodal = _visible((18, 10, 23, 12))
    info = bop.gt_info(_visible(), amodal, old, None)
    assert (info["px_count_all"], info["bbox_obj"], info["silhouette"]) == (18, [18, 10, 5, 2], "image")
    assert "silhouette" not in bop.gt_info(_visible(), None, {}, None)   # no full silhouette recorded at all


@pytest.mark.parametrize("change", [{"amodal_pixels_canvas": 5},                    # fewer than the visible pixels
                                    {"amodal_pixels_canvas": 10 ** 9},              # more than the canvas holds
                                    {"amodal_pixels_canvas": True},
                                    {"bbox_amodal_canvas_xyxy_px": [-65, 10, 23, 12]},   # off the canvas
                                    {"bbox_amodal_canvas_xyxy_px": [30, 10, 23, 12]},    # reversed
                                    {"bbox_amodal_canvas_xyxy_px": None},
                                    {"bbox_amodal_canvas_xyxy_px": [0.5, 10, 23, 12]}])
def test_gt_info_does_not_trust_impossible_canvas_values(change):
    info = bop.gt_info(_visible(), None, CANVAS | change, None)
    assert (info["px_count_all"], info["silhouette"]) == (12, "image")


def test_the_cache_check_takes_a_box_on_the_canvas_and_refuses_one_off_it():
    from allo_usd.output.annotation_files import _gt_problem

    info = bop.gt_info(_visible(), None, CANVAS, None)
    g = {"pose": None, "model": None, "info": info}
    assert not _gt_problem(g, 64, 36)
    for box in ([-65, 0, 3, 3], [100, 0, 28, 3], [0, 0, -2, 3], [-1, -1, -1, 0]):
        assert _gt_problem({**g, "info": info | {"bbox_obj": box}}, 64, 36)
    assert _gt_problem({**g, "info": info | {"bbox_visib": [-6, 10, 29, 2]}}, 64, 36)   # visible: in the image
    assert _gt_problem({**g, "info": info | {"silhouette": "elsewhere"}}, 64, 36)
    assert _gt_problem({**g, "info": info | {"px_count_all": 9 * 64 * 36 + 1}}, 64, 36)


@pytest.mark.parametrize("canvas", [False, True])
def test_the_dataset_says_how_many_renders_predate_the_canvas(tmp_path, canvas):
    import json
    import warnings

    from PIL import Image

    from allo_usd.output.dataset import assemble, summary_line

    d = tmp_path / "renders"
    d.mkdir()
    mask = np.ones((36, 64), np.uint8)
    mask[10:13, 20:24] = 2
    Image.fromarray(np.full((36, 64, 3), 90, np.uint8)).save(d / "a1.png")
    Image.fromarray(mask).save(d / "a1_mask.png")
    anomaly = (CANVAS if canvas else {k: v for k, v in CANVAS.items() if "canvas" not in k}) | {
        "pose": {"cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0.0, 0.0, 3000.0], "model_scale": [1.0] * 3},
        "model": {"asset": "crate", "variant": "blue", "model_id": "crate/blue", "path": None}}
    meta = {"layer": str(d / "a1.usda"), "layer_sha256": "1" * 64, "package_version": "0.1.0", "render_seconds": 0.1,
            "resolution": [64, 36], "class_pixels": {"background": 0, "station_and_bodies": 2292, "anomaly": 12},
            "anomaly_fraction": 12 / 2304, "effects": {}, "annotations": {"anomaly": anomaly, "anomalies": [anomaly]},
            "scene": {"sceneId": "a1", "split": "test", "variant": "anomaly", "pose": 1, "day": 0, "seed": 1,
                      "seedPath": "1/0/1/1", "provenance": {}, "anomaly": {"asset": "crate", "assetVariant": "blue"}},
            "files": {"rgb": "a1.png", "exr": "a1.exr", "mask": "a1_mask.png"}}
    (d / "a1.json").write_text(json.dumps(meta))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assemble([d], tmp_path / "ds")
    line = summary_line(tmp_path / "ds")
    assert "BOP poses 1 of 1" in line
    assert ("1 render(s) record the full silhouette inside the image only" in line) != canvas
    (info,) = json.loads(next((tmp_path / "ds" / "bop").rglob("scene_gt_info.json")).read_text()).values()
    assert info[0]["silhouette"] == ("canvas" if canvas else "image")
    assert info[0]["px_count_all"] == (30 if canvas else 12)
