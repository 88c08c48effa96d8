"""The anomaly's pose and visibility annotations (render side; conventions in
allo_usd/output/annotations.py) on real renders of a scene where the station's truss hides part of
the anomaly: the BOP pose reprojects the model file's triangles onto the `amodal` pass, visib_fract
is the mask counts' ratio (and the ray cast's without the pass), center_px and mask_centroid_px
are what they say, R is a rotation and the 3D box projects onto bbox3d_px. The `amodal` pass leaves
a warm session's scene as it found it."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from allo_usd.core.geometry import look_at, rot_x, rot_z
from allo_usd.core.labels import ANOMALY
from allo_usd.output.annotations import split_rotation_scale
from allo_usd.plan.settings import RenderSpec
from allo_usd.scene.spec import AnomalySpec, CameraSpec
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import EXPOSURE, make_spec

W, H = 160, 90
CAM = np.array([2.0, 0.3, 1.0])   # 3 m in front of the tiny station's truss (x in [-1, 1], z in [-1, 1])
# The crate sits behind the truss's top edge, tilted: the truss hides its lower third.
CRATE = AnomalySpec("Crate", "blue", (-1.6, 0.0, 1.05), rot_z(0.6) @ rot_x(0.4))


def _occluded_spec(passes, samples=1):
    spec = make_spec(anomaly=True, render=RenderSpec((W, H), samples=samples, exposure=EXPOSURE, seed=1,
                                                     denoise=False, passes=passes),
                     camera=CameraSpec(tuple(CAM), look_at(CAM, [-1.5, 0.0, 0.9])))
    return dataclasses.replace(spec, anomaly=CRATE)


@pytest.fixture(scope="module")
def occluded(tiny_base, tmp_path_factory):
    """The scene rendered with the amodal pass and without it: {"pass"|"raycast": (layer, meta, out)}."""
    from allo_usd.run.job import render_layer

    tmp = tmp_path_factory.mktemp("pose")
    out = {}
    for name, passes in (("pass", ("mask", "amodal")), ("raycast", ("mask",))):
        layer = write_scene_layer(_occluded_spec(passes), tmp / "layers" / f"occluded_{name}.usda", tiny_base)
        out[name] = (layer, render_layer(layer, tmp / name), tmp / name)
    return out


def _png(out: Path, meta: dict, key: str) -> np.ndarray:
    return np.asarray(Image.open(out / meta["files"][key]))


def _model_from_file(layer: Path, model: dict):
    """What a BOP user does: open the model file the record names (relative to the layer's folder), pick
    its variant and read its triangles in the file's own frame (metres)."""
    from pxr import Usd, UsdGeom

    from allo_usd.assets.mesh import fan_triangulate

    stage = Usd.Stage.Open(str((layer.parent / model["path"]).resolve()))
    root = stage.GetDefaultPrim()
    root.GetVariantSet("variant").SetVariantSelection(model["variant"])
    cache = UsdGeom.XformCache()
    pts, tris, n = [], [], 0
    for prim in Usd.PrimRange(root):
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)   # row vectors
            p = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
            pts.append(p @ m[:3, :3] + m[3, :3])
            tris.append(fan_triangulate(np.array(mesh.GetFaceVertexCountsAttr().Get()),
                                        np.array(mesh.GetFaceVertexIndicesAttr().Get())) + n)
            n += len(p)
    return np.concatenate(pts), np.concatenate(tris)


def _bop_project(anomaly: dict, k: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of model points through the record's BOP pose: x_mm = R (S x 1000) + t, u = K x / z."""
    pose = anomaly["pose"]
    r = np.array(pose["cam_R_m2c"]).reshape(3, 3)
    cam = (points_m * np.array(pose["model_scale"]) * 1000.0) @ r.T + np.array(pose["cam_t_m2c"])
    assert (cam[:, 2] > 0).all()
    return cam[:, :2] / cam[:, 2:3] * np.diag(k)[:2] + k[:2, 2]


def _rasterise(uv: np.ndarray, tris: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixel centres (c, r) inside some projected triangle (either winding)."""
    rows, cols = np.mgrid[0:height, 0:width]
    c, r = cols.ravel().astype(float), rows.ravel().astype(float)
    inside = np.zeros(c.size, dtype=bool)
    for a, b, d in uv[tris]:
        e = [(q[0] - p[0]) * (r - p[1]) - (q[1] - p[1]) * (c - p[0]) for p, q in ((a, b), (b, d), (d, a))]
        inside |= ((e[0] >= 0) & (e[1] >= 0) & (e[2] >= 0)) | ((e[0] <= 0) & (e[1] <= 0) & (e[2] <= 0))
    return inside.reshape(height, width)


@pytest.mark.render
def test_bop_pose_reprojects_the_model_file_onto_the_amodal_mask(occluded, tiny_base):
    layer, meta, out = occluded["pass"]
    a, k = meta["annotations"]["anomaly"], np.array(meta["annotations"]["camera"]["K_px"])
    assert a["model"] == {"asset": "Crate", "variant": "blue", "model_id": "Crate/blue",   # the layer's reference
                          "path": os.path.relpath(Path(tiny_base).parent / "anomalies" / "Crate.usda", layer.parent)}
    points, tris = _model_from_file(layer, a["model"])
    drawn = _rasterise(_bop_project(a, k, points), tris, W, H)
    amodal = _png(out, meta, "amodal") == ANOMALY
    assert amodal.sum() > 150
    iou = (drawn & amodal).sum() / (drawn | amodal).sum()
    assert iou >= 0.98, iou
    # the visible mask alone would not do: the truss hides a third of it
    assert (drawn & (_png(out, meta, "mask") == ANOMALY)).sum() / drawn.sum() < 0.8


@pytest.mark.render
def test_visib_fract_is_the_mask_counts_and_the_ray_cast_agrees(occluded):
    _, meta, out = occluded["pass"]
    a = meta["annotations"]["anomaly"]
    visible, amodal = _png(out, meta, "mask") == ANOMALY, _png(out, meta, "amodal")
    assert set(np.unique(amodal)) == {0, ANOMALY}   # STEM_mask.png's convention
    full = amodal == ANOMALY
    assert not (visible & ~full).any()              # every visible anomaly pixel is in the full silhouette
    assert a["visib_source"] == "amodal_pass"
    assert (a["pixels"], a["amodal_pixels"]) == (visible.sum(), full.sum())
    assert a["visib_fract"] == visible.sum() / full.sum()
    assert 0.3 < a["visib_fract"] < 0.9
    rows, cols = np.nonzero(full)
    assert a["bbox_amodal_xyxy_px"] == [cols.min(), rows.min(), cols.max(), rows.max()]
    assert a["bbox_amodal_xyxy_px"][3] > a["bbox_xyxy_px"][3]   # the hidden part is below the visible one
    assert meta["files"]["amodal"] == f"{Path(meta['layer']).stem}_amodal.png"
    # without the pass: the same keys, from the ray cast of the anomaly alone
    _, plain, plain_out = occluded["raycast"]
    b = plain["annotations"]["anomaly"]
    assert "amodal" not in plain["files"] and b["visib_source"] == "raycast"
    assert b["pixels"] == a["pixels"]
    assert abs(b["amodal_pixels"] - a["amodal_pixels"]) <= 2
    assert b["visib_fract"] == pytest.approx(a["visib_fract"], abs=0.01)
    # in the frame: the toolkit's canvas holds nothing more than the image
    assert (a["amodal_pixels_canvas"], a["bbox_amodal_canvas_xyxy_px"]) == (a["amodal_pixels"], a["bbox_amodal_xyxy_px"])
    assert (b["amodal_pixels_canvas"], b["bbox_amodal_canvas_xyxy_px"]) == (b["amodal_pixels"], b["bbox_amodal_xyxy_px"])
    amodal_keys = ("amodal_pixels", "visib_fract", "visib_source", "bbox_amodal_xyxy_px", "amodal_pixels_canvas",
                   "bbox_amodal_canvas_xyxy_px")
    assert {k: v for k, v in b.items() if k not in amodal_keys} == {k: v for k, v in a.items() if k not in amodal_keys}


@pytest.mark.render
def test_center_px_is_the_model_box_centre_and_mask_centroid_the_mean_pixel(occluded):
    layer, meta, out = occluded["pass"]
    a, k = meta["annotations"]["anomaly"], np.array(meta["annotations"]["camera"]["K_px"])
    points, _ = _model_from_file(layer, a["model"])
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    np.testing.assert_allclose(a["center_px"], _bop_project(a, k, centre[None])[0], atol=1e-6)
    x0, y0, x1, y1 = a["bbox_amodal_xyxy_px"]
    u, v = a["center_px"]
    assert x0 - 0.5 <= u <= x1 + 0.5 and y0 - 0.5 <= v <= y1 + 0.5
    cam = np.array(a["center_cam_opencv_m"])
    np.testing.assert_allclose(a["center_px"], cam[:2] / cam[2] * np.diag(k)[:2] + k[:2, 2], atol=1e-9)
    assert a["distance_m"] == pytest.approx(np.linalg.norm(cam))
    rows, cols = np.nonzero(_png(out, meta, "mask") == ANOMALY)
    assert a["mask_centroid_px"] == [cols.mean(), rows.mean()]
    # here the two differ: the truss hides the crate's lower part, so the visible centroid sits higher
    assert a["mask_centroid_px"][1] < v - 1


@pytest.mark.render
def test_r_is_a_rotation_and_the_3d_box_projects_onto_bbox3d_px(occluded):
    layer, meta, _ = occluded["pass"]
    a, k = meta["annotations"]["anomaly"], np.array(meta["annotations"]["camera"]["K_px"])
    r = np.array(a["pose"]["cam_R_m2c"]).reshape(3, 3)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(a["pose"]["model_scale"], [1, 1, 1], atol=1e-9)
    assert a["pose"]["model_units"] == "m"
    points, _ = _model_from_file(layer, a["model"])
    lo, hi = points.min(axis=0), points.max(axis=0)
    corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[n][2]] for i in (0, 1) for j in (0, 1)
                        for n in (0, 1)])   # index 4 ix + 2 iy + iz
    box = np.array(a["bbox3d_cam_m"])
    np.testing.assert_allclose(box * 1000, corners * 1000 @ r.T + np.array(a["pose"]["cam_t_m2c"]), atol=1e-6)
    np.testing.assert_allclose(a["bbox3d_px"], box[:, :2] / box[:, 2:] * np.diag(k)[:2] + k[:2, 2], atol=1e-9)
    x0, y0, x1, y1 = a["bbox_amodal_xyxy_px"]
    px = np.array(a["bbox3d_px"])   # the box's image holds the silhouette
    assert px[:, 0].min() <= x0 + 0.5 and x1 - 0.5 <= px[:, 0].max()
    assert px[:, 1].min() <= y0 + 0.5 and y1 - 0.5 <= px[:, 1].max()


def test_split_rotation_scale_returns_a_proper_rotation():
    rng = np.random.default_rng(5)
    for _ in range(50):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        s = rng.uniform(0.01, 100, size=3)
        r, got = split_rotation_scale(q @ np.diag(s))
        np.testing.assert_allclose(r, q, atol=1e-12)
        np.testing.assert_allclose(got, s, rtol=1e-12)
        r, got = split_rotation_scale(q @ np.diag(s * [1, 1, -1]))   # a mirror: a negative z scale
        assert np.linalg.det(r) == pytest.approx(1.0) and got[2] < 0
        np.testing.assert_allclose(r @ np.diag(got), q @ np.diag(s * [1, 1, -1]), atol=1e-9 * s.max())
    shear = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]])   # no rotation x scale split
    r, got = split_rotation_scale(shear)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


@pytest.mark.render
def test_the_amodal_render_leaves_a_warm_session_as_a_fresh_build(tiny_base, tmp_path):
    """A scene with the pass, then another through the same session: the second is byte for byte
    what a fresh build renders (every camera visibility and render setting was put back)."""
    from allo_usd.blender.render import render_scene
    from allo_usd.blender.session import Session
    from allo_usd.usd.read import read_scene

    first = read_scene(write_scene_layer(_occluded_spec(("rgb", "mask", "amodal"), samples=2),
                                         tmp_path / "first.usda", tiny_base))
    second = read_scene(write_scene_layer(make_spec(anomaly=True, samples=2), tmp_path / "second.usda", tiny_base))
    session = Session()
    with_pass = session.render(first, tmp_path)
    assert with_pass.amodal is not None and (with_pass.amodal == ANOMALY).sum() > (with_pass.mask == ANOMALY).sum()
    warm = session.render(second, tmp_path)
    assert not session.last.full_build
    fresh = render_scene(second, tmp_path)
    assert np.array_equal(warm.rgb, fresh.rgb) and np.array_equal(warm.mask, fresh.mask)
    assert warm.amodal is None
