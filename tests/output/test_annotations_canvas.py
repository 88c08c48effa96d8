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
