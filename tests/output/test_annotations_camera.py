"""Per-image camera and object record (allo_usd.output.annotations): K and pose land 3D points on
the pixels Blender's camera sees them at, the anomaly's box matches the rendered mask, bodies in
view agree with brute force, and the manifest flattens the record (missing keys: empty columns)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from allo_usd.assets.mesh import fan_triangulate
from allo_usd.core.labels import ANOMALY
from allo_usd.output.annotations import (USD_TO_OPENCV, annotation_columns, camera_record, disc_in_view,
                                         image_annotations, mask_bbox, project)
from allo_usd.plan.settings import RenderSpec
from allo_usd.scene.raycast import RayScene
from allo_usd.usd.layout import SKY
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import EXPOSURE, make_spec

FULL_HD = (1920, 1080)


def _desc(tiny_base, tmp_path, resolution, anomaly=True):
    spec = make_spec(anomaly=anomaly)
    spec = make_spec(anomaly=anomaly, render=RenderSpec(resolution, samples=1, exposure=EXPOSURE, seed=1,
                                                        denoise=False)) if resolution != (64, 36) else spec
    return read_scene(write_scene_layer(spec, tmp_path / f"s_{resolution[0]}.usda", tiny_base))


def _blender_pixel_rays(desc, cols, rows):
    """World rays through pixel centres (col + 0.5, row + 0.5 from the top-left corner) built from
    Blender's own camera (view_frame corners and matrix_world), independent of the recorded K."""
    import bpy

    from allo_usd.blender.build import build_scene

    build_scene(desc)
    scene = bpy.context.scene
    cam = scene.camera
    w, h = scene.render.resolution_x, scene.render.resolution_y
    frame = [np.array(v) for v in cam.data.view_frame(scene=scene)]   # camera-local corners
    tl = next(v for v in frame if v[0] < 0 and v[1] > 0)
    tr = next(v for v in frame if v[0] > 0 and v[1] > 0)
    bl = next(v for v in frame if v[0] < 0 and v[1] < 0)
    local = (tl + np.outer((np.asarray(cols) + 0.5) / w, tr - tl) + np.outer((np.asarray(rows) + 0.5) / h, bl - tl))
    m = np.array(cam.matrix_world)
    dirs = local @ m[:3, :3].T
    return np.broadcast_to(m[:3, 3], dirs.shape).copy(), dirs / np.linalg.norm(dirs, axis=1, keepdims=True), m


def _station_scene(desc):
    parts = []
    for m in desc.meshes:
        if m.path.startswith(SKY + "/"):
            continue  # the bodies: far away, and not what the check is about
        pts = np.asarray(m.points, dtype=np.float64) @ m.matrix[:3, :3].T + m.matrix[:3, 3]
        parts.append((pts, fan_triangulate(m.face_counts, m.face_indices), m.class_id))
    return RayScene(parts)


@pytest.mark.render
def test_station_points_project_onto_their_pixels_at_1080p(tiny_base, tmp_path):
    """Ray-cast the station through pixel centres of Blender's 1920x1080 camera, project each 3D hit
    back through the recorded K and world_to_cam_opencv: it lands on its pixel (OpenCV centres)."""
    desc = _desc(tiny_base, tmp_path, FULL_HD)
    rec = camera_record(desc, *FULL_HD)
    rows, cols = np.meshgrid(np.arange(0, 1080, 7), np.arange(0, 1920, 11), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    o, d, blender_world = _blender_pixel_rays(desc, cols, rows)
    owner, dist = _station_scene(desc).first_hit(o, d)
    hit = owner > 0
    assert hit.sum() > 1000  # the station fills part of the frame
    points = o[hit] + d[hit] * dist[hit, None]
    uv, z = project(np.array(rec["K_px"]), np.array(rec["world_to_cam_opencv"]), points)
    assert (z > 0).all()
    err = np.hypot(uv[:, 0] - cols[hit], uv[:, 1] - rows[hit])
    assert err.max() < 1.0, err.max()
    assert err.max() < 1e-3  # it is exact up to float error
    # the stage's camera matrix is Blender's (no axis change: both look down -Z, +Y up)
    np.testing.assert_allclose(np.array(rec["cam_to_world_usd"]), blender_world, atol=1e-6)


@pytest.mark.render
@pytest.mark.parametrize("resolution", [FULL_HD, (64, 36), (640, 360)])
def test_k_matches_blenders_projection(tiny_base, tmp_path, resolution):
    import bpy

    from allo_usd.blender.build import build_scene

    desc = _desc(tiny_base, tmp_path, resolution)
    build_scene(desc)
    scene = bpy.context.scene
    w, h = resolution
    p = np.array(scene.camera.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=w, y=h))
    k = np.array(camera_record(desc, w, h)["K_px"])
    # OpenGL clip space: x_ndc = P00 x / -z + P02; pixel u (OpenCV centres) = (x_ndc + 1) W / 2 - 0.5
    assert k[0, 0] == pytest.approx(p[0, 0] * w / 2, rel=1e-6)
    assert k[1, 1] == pytest.approx(p[1, 1] * h / 2, rel=1e-6)
    assert k[0, 2] == pytest.approx((p[0, 2] + 1) * w / 2 - 0.5, abs=1e-6)   # P02 = 0: no lens shift
    assert k[1, 2] == pytest.approx((p[1, 2] + 1) * h / 2 - 0.5, abs=1e-6)
    assert (k[0, 1], k[1, 0], k[2, 0], k[2, 1], k[2, 2]) == (0, 0, 0, 0, 1)


def test_pose_matrices_are_inverses_up_to_the_axis_flip(tiny_base, tmp_path):
    desc = _desc(tiny_base, tmp_path, (64, 36))
    rec = camera_record(desc, 64, 36)
    c2w, w2c = np.array(rec["cam_to_world_usd"]), np.array(rec["world_to_cam_opencv"])
    np.testing.assert_allclose(w2c @ c2w, np.diag([1.0, -1.0, -1.0, 1.0]), atol=1e-9)  # x kept, y and z flipped
    np.testing.assert_allclose(c2w[3], [0, 0, 0, 1])
    np.testing.assert_allclose(c2w[:3, 3], [15.0, 8.0, 5.0])  # helpers.CAM_POS: translation in the last column
    # the station's origin, which the camera looks at, lies straight ahead: OpenCV +z, at the image centre
    uv, z = project(np.array(rec["K_px"]), w2c, [0.0, 0.0, 0.0])
    assert z[0] == pytest.approx(np.linalg.norm([15.0, 8.0, 5.0]))
    np.testing.assert_allclose(uv[0], [31.5, 17.5], atol=1e-9)
    assert rec["clip_near_m"] == pytest.approx(desc.camera.clip[0]) and rec["clip_far_m"] > 1e9
    assert (rec["width"], rec["height"], rec["focal_length_mm"]) == (64, 36, pytest.approx(25.0))


def test_mask_bbox_is_inclusive():
    mask = np.zeros((36, 64), np.uint8)
    assert mask_bbox(mask) is None
    mask[5:9, 10:20] = ANOMALY
    mask[30, 2] = 1
    assert mask_bbox(mask) == [10, 5, 19, 8]


@pytest.mark.render
def test_render_json_anomaly_box_matches_the_mask(rendered, tiny_base, tmp_path):
    _, meta, d = rendered["anomaly"]
    mask = np.asarray(Image.open(d / meta["files"]["mask"]))
    rec = meta["annotations"]
    a = rec["anomaly"]
    ys, xs = np.nonzero(mask == ANOMALY)
    assert a["bbox_xyxy_px"] == [xs.min(), ys.min(), xs.max(), ys.max()]
    assert a["pixels"] == len(xs) == meta["class_pixels"]["anomaly"] > 0
    x0, y0, x1, y1 = a["bbox_xyxy_px"]
    u, v = a["center_px"]
    assert x0 - 0.5 <= u <= x1 + 0.5 and y0 - 0.5 <= v <= y1 + 0.5
    # the anomaly's vertices, projected, cover the mask's box (within a pixel of anti-aliasing)
    desc = _desc(tiny_base, tmp_path, (64, 36))
    pts = np.concatenate([np.asarray(m.points, float) @ m.matrix[:3, :3].T + m.matrix[:3, 3]
                          for m in desc.meshes if m.class_id == ANOMALY])
    uv, _ = project(np.array(rec["camera"]["K_px"]), np.array(rec["camera"]["world_to_cam_opencv"]), pts)
    assert uv[:, 0].min() - 1 <= x0 and x1 <= uv[:, 0].max() + 1
    assert uv[:, 1].min() - 1 <= y0 and y1 <= uv[:, 1].max() + 1
    centre = np.array(a["center_cam_opencv_m"])
    assert a["distance_m"] == pytest.approx(np.linalg.norm(centre)) and centre[2] > 0
    assert a["depth_offset_m"] == 0.0
    assert set(rec["in_view"]) == {"sun", "earth", "moon"}
    json.dumps(meta)  # plain JSON
    assert rendered["normal"][1]["annotations"]["anomaly"] is None


@pytest.mark.render
def test_rays_through_recorded_pixel_centres_reproduce_the_rendered_mask(rendered, tiny_base, tmp_path):
    """Invert the recorded K and pose: a ray through each pixel centre (OpenCV: (c, r)) hits what the
    render's class mask shows there, at every pixel; half a pixel off (the other centre convention)
    it does not."""
    _, meta, d = rendered["anomaly"]
    mask = np.asarray(Image.open(d / meta["files"]["mask"]))
    cam = meta["annotations"]["camera"]
    k, c2w = np.array(cam["K_px"]), np.linalg.inv(np.array(cam["world_to_cam_opencv"]))
    scene = _station_scene(_desc(tiny_base, tmp_path, (64, 36)))
    rows, cols = np.mgrid[0:36, 0:64]
    wrong = {}
    for shift in (0.0, 0.5):
        x = (cols.ravel() + shift - k[0, 2]) / k[0, 0]
        y = (rows.ravel() + shift - k[1, 2]) / k[1, 1]
        dirs = np.stack([x, y, np.ones_like(x)], axis=1) @ c2w[:3, :3].T
        owner, _ = scene.first_hit(np.broadcast_to(c2w[:3, 3], dirs.shape), dirs)
        wrong[shift] = int((owner.reshape(36, 64) != mask).sum())
    assert (mask == ANOMALY).any() and (mask == 1).any()
    assert wrong[0.0] <= 2, wrong      # exact here; a pixel or two of float ties allowed
    assert wrong[0.5] > 20, wrong


def _brute_in_view(direction, radius, half_x, half_y, n=801):
    """Smallest angle from `direction` to a dense grid of view rays (edges included), and the grid step."""
    x, y = np.meshgrid(np.linspace(-half_x, half_x, n), np.linspace(-half_y, half_y, n))
    rays = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    d = np.asarray(direction) / np.linalg.norm(direction)
    step = 2 * half_x / (n - 1)
    return float(np.arccos(np.clip(rays @ d, -1, 1)).min()), step


@pytest.mark.slow
def test_disc_in_view_agrees_with_brute_force():
    rng = np.random.default_rng(3)
    half_x, half_y = 0.72, 0.405
    assert disc_in_view([0, 0, 1], 1e-4, half_x, half_y)
    assert not disc_in_view([0, 0, -1], 0.5, half_x, half_y)
    edge = math.atan(half_x)
    beside = [math.sin(edge + 0.01), 0.0, math.cos(edge + 0.01)]   # 0.01 rad right of the frame
    assert disc_in_view(beside, 0.011, half_x, half_y) and not disc_in_view(beside, 0.009, half_x, half_y)
    checked = 0
    for _ in range(300):
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.3
        radius = float(rng.uniform(0.001, 0.3))
        angle, step = _brute_in_view(d, radius, half_x, half_y)
        if abs(angle - radius) < 2 * step:
            continue   # too close to the edge for the grid to decide
        assert disc_in_view(d, radius, half_x, half_y) == (angle < radius), (d, radius, angle)
        checked += 1
    assert checked > 250


def test_in_view_of_a_scene(tiny_base, tmp_path):
    """helpers' scene: the camera at (15, 8, 5) looks at the station's origin; the Moon, 7,000 km
    straight below with a 1,737 km radius, fills a 28 deg wide cone that the 72 deg frame meets;
    looking up instead, it is not in view."""
    desc = _desc(tiny_base, tmp_path, (64, 36), anomaly=False)
    seen = image_annotations(desc, np.zeros((36, 64), np.uint8))["in_view"]
    k = camera_record(desc, 64, 36)
    below = np.array([0.0, 0.0, -7.0e6]) - np.array([15.0, 8.0, 5.0])
    w2c = np.array(k["world_to_cam_opencv"])
    angle, step = _brute_in_view(w2c[:3, :3] @ below, math.asin(1.7374e6 / np.linalg.norm(below)),
                                 32 / k["K_px"][0][0], 18 / k["K_px"][1][1])
    assert seen["moon"] == (angle < math.asin(1.7374e6 / np.linalg.norm(below)))
    from dataclasses import replace

    from allo_usd.core.geometry import look_at

    up = np.eye(4)
    up[:3, :3] = look_at([15.0, 8.0, 5.0], [15.0, 8.0, 100.0])
    up[:3, 3] = [15.0, 8.0, 5.0]
    looking_up = replace(desc, camera=replace(desc.camera, matrix=up))
    assert image_annotations(looking_up, np.zeros((36, 64), np.uint8))["in_view"]["moon"] is False


def test_manifest_columns_flatten_the_record_and_leave_missing_keys_empty():
    rec = {"camera": {"width": 64, "height": 36, "K_px": [[44.4, 0, 31.5], [0, 44.4, 17.5], [0, 0, 1]],
                      "focal_length_mm": 25.0, "sensor_width_mm": 36.0, "sensor_height_mm": 20.25,
                      "clip_near_m": 0.05, "clip_far_m": 1e12, "cam_to_world_usd": np.eye(4).tolist(),
                      "world_to_cam_opencv": USD_TO_OPENCV.tolist()},
           "anomaly": {"bbox_xyxy_px": [1, 2, 3, 4], "pixels": 9, "center_cam_opencv_m": [0.5, -0.25, 12.0],
                       "distance_m": 12.01, "center_px": [2.0, 3.0], "depth_offset_m": 0.0},
           "in_view": {"sun": False, "earth": True, "moon": None}}
    meta = {"annotations": rec, "station_fraction": 0.25,
            "bodies": {"sun": {"pixels": 0}, "earth": {"pixels": 17}, "moon": {"pixels": 3}}}
    row = annotation_columns(meta)
    assert (row["fx"], row["cx"], row["cy"], row["width"], row["clip_far"]) == (44.4, 31.5, 17.5, 64, 1e12)
    assert json.loads(row["world_to_cam_opencv"]) == USD_TO_OPENCV.tolist()
    assert " " not in row["K_px"]
    assert [row[f"bbox_{k}"] for k in ("x_min", "y_min", "x_max", "y_max")] == [1, 2, 3, 4]
    assert (row["anomaly_pixels"], row["anomaly_cam_z"], row["anomaly_distance_m"]) == (9, 12.0, 12.01)
    assert (row["station_fraction"], row["sun_pixels"], row["earth_pixels"], row["moon_pixels"]) == (0.25, 0, 17, 3)
    assert (row["sun_in_view"], row["earth_in_view"], row["moon_in_view"]) == (False, True, "")
    # the other passes' keys absent, or a hostile record: empty columns, never an error
    empty = annotation_columns({"annotations": {"camera": {"K_px": [["x"]], "width": float("nan")},
                                                "anomaly": None, "in_view": "yes"}})
    assert all(v == "" for v in empty.values()), empty
    odd = annotation_columns({"annotations": {"camera": [1], "anomaly": [2], "in_view": {"sun": "yes"}},
                              "station_fraction": 10 ** 400, "bodies": {"sun": {"pixels": 2.5}}})
    assert all(v == "" for v in odd.values()), odd
    assert all(v == "" for v in annotation_columns({}).values())
