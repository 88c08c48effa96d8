"""A plan's own camera (`[camera]`): validation, the UsdGeom.Camera values authored only for a
non-default lens, the reader's bounds on the aperture offsets, a render whose mask shows exactly what
rays through the recorded K and pose hit (and not with the offset's sign flipped), and placement
looking through the plan's camera."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from allo_usd.assets.mesh import fan_triangulate
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.errors import AlloError, LayerError, PlanError
from allo_usd.core.labels import ANOMALY
from allo_usd.plan.io import make_plan
from allo_usd.plan.model import paper_plan
from allo_usd.scene.raycast import RayScene, class_image
from allo_usd.usd.layout import CAMERA, SKY
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

# 50 mm lens, the sensor's height given (its width follows from 64x36: 32 mm), the principal point
# 6 px right and 4 px up of the image centre, a near plane at 0.5 m.
PLAN_CAMERA = {"focal_length_mm": 50.0, "sensor_height_mm": 18.0, "resolution": [64, 36],
               "clipping_range_m": [0.5, 1.0e12], "principal_point_offset_px": [6.0, -4.0]}
LENS_ATTRS = ("focalLength", "horizontalAperture", "verticalAperture", "clippingRange",
              "horizontalApertureOffset", "verticalApertureOffset")


def _plan(**camera):
    return make_plan({"name": "cam", "camera": camera})


def test_the_default_camera_is_table_one_and_every_existing_plan_keeps_it():
    lens, size = paper_plan().camera_model()
    assert lens == DEFAULT_CAMERA and size == (1920, 1080)
    assert (lens.focal_length_mm, lens.sensor_width_mm, lens.sensor_height_mm) == (25.0, 36.0, 20.25)
    assert make_plan({"name": "x"}).camera_model()[0] == DEFAULT_CAMERA


def test_plan_camera_resolves_the_other_sensor_side_and_the_resolution():
    lens, size = _plan(**PLAN_CAMERA).camera_model()
    assert size == (64, 36)
    assert lens == CameraModel(50.0, 32.0, 18.0, (0.5, 1.0e12), (6.0, -4.0))
    lens, size = make_plan({"name": "x", "camera": {"sensor_width_mm": 24.0},
                            "quality": {"resolution": [640, 480]}}).camera_model()
    assert (lens.sensor_width_mm, lens.sensor_height_mm, size) == (24.0, 18.0, (640, 480))


@pytest.mark.parametrize("size, height", [((1920, 1080), 20.25), ((160, 90), 20.25), ((2000, 1000), 18.0),
                                          ((1024, 1024), 36.0), ((854, 480), 36.0 * 480 / 854)])
def test_without_a_sensor_size_the_height_follows_the_images_aspect(size, height):
    """Table I's 36 mm width, and the height square pixels give: the layer's apertures then match its
    image, so UsdRender's aperture conforming leaves them as they are (a 16:9 image keeps 20.25 mm)."""
    lens, got = make_plan({"name": "x", "quality": {"resolution": list(size)}}).camera_model()
    assert got == size and lens.sensor_width_mm == 36.0 and lens.sensor_height_mm == height


@pytest.mark.parametrize("camera, quality, words", [
    ({"focal_length_mm": 0.5}, {}, ["camera.focal_length_mm", "fix:"]),
    ({"sensor_width_mm": 20000.0}, {}, ["camera.sensor_width_mm", "fix:"]),
    ({"sensor_height_mm": 0.1}, {}, ["camera.sensor_height_mm", "fix:"]),
    ({"sensor_width_mm": 36.0, "sensor_height_mm": 24.0}, {}, ["sensor_width_mm", "sensor_height_mm", "1920x1080",
                                                               "fix:"]),
    ({"resolution": [64, 36]}, {"resolution": [128, 72]}, ["camera.resolution [64, 36]",
                                                           "quality.resolution [128, 72]", "fix:"]),
    ({"resolution": [2, 2]}, {}, ["camera.resolution", "fix:"]),
    ({"clipping_range_m": [1.0, 0.5]}, {}, ["camera.clipping_range_m", "near < far", "fix:"]),
    ({"clipping_range_m": [1e-9, 10.0]}, {}, ["camera.clipping_range_m", "fix:"]),
    ({"principal_point_offset_px": [961.0, 0.0]}, {}, ["principal_point_offset_px", "outside", "fix:"]),
    ({"principal_point_offset_px": [0.0, float("nan")]}, {}, ["principal_point_offset_px", "fix:"]),
    ({"lens": 50}, {}, ["camera.lens", "fix:"]),
])
def test_plan_camera_errors_name_the_field_and_a_fix(camera, quality, words):
    with pytest.raises(PlanError) as err:
        make_plan({"name": "x", "camera": camera, **({"quality": quality} if quality else {})})
    for w in words:
        assert w in str(err.value)


def test_camera_resolution_fills_quality_and_the_same_in_both_is_fine():
    plan = _plan(resolution=[64, 36])
    assert plan.quality.resolution == (64, 36)
    again = make_plan(plan.model_dump(mode="json"))   # as saved and loaded
    assert again.camera_model() == plan.camera_model()


def test_aperture_offsets_follow_usd_and_square_pixels():
    lens = CameraModel(50.0, 32.0, 18.0, principal_point_offset_px=(6.0, -4.0))
    h, v = lens.aperture_offsets_mm(64)
    assert (h, v) == (-3.0, -2.0)                    # -dx * 32/64, +dy * 32/64
    k = lens.intrinsics(64, 36)
    assert (k[0, 2], k[1, 2], k[0, 0]) == (38.0, 14.0, 100.0)
    assert lens.intrinsics_opencv(64, 36)[0, 2] == 37.5


def test_usd_window_puts_the_optical_axis_on_the_principal_point():
    """GfCamera's own projection of the authored values: the optical axis lands at the principal point."""
    from pxr import Gf

    lens = CameraModel(50.0, 32.0, 18.0, principal_point_offset_px=(6.0, -4.0))
    h, v = lens.aperture_offsets_mm(64)
    cam = Gf.Camera(Gf.Matrix4d(1.0), Gf.Camera.Perspective, horizontalAperture=32.0, verticalAperture=18.0,
                    horizontalApertureOffset=h, verticalApertureOffset=v, focalLength=50.0)
    ndc = cam.frustum.ComputeProjectionMatrix().Transform(Gf.Vec3d(0, 0, -10))
    u, row = (ndc[0] + 1) / 2 * 64, (1 - ndc[1]) / 2 * 36
    assert (u, row) == pytest.approx(lens.principal_point(64, 36), abs=1e-6)


def _spec(lens: CameraModel, anomaly=True, **kw):
    return make_spec(anomaly=anomaly, lens=lens, **kw)


def _camera_specs(layer):
    from pxr import Sdf

    sdf = Sdf.Layer.FindOrOpen(str(layer))   # held: a prim spec does not keep its layer alive
    return {a.name for a in sdf.GetPrimAtPath(CAMERA).attributes}


def test_lens_is_authored_only_when_it_differs_from_table_one(tiny_base, tmp_path):
    default = write_scene_layer(_spec(DEFAULT_CAMERA), tmp_path / "d.usda", tiny_base)
    assert not set(LENS_ATTRS) & _camera_specs(default)
    lens = _plan(**PLAN_CAMERA).camera_model()[0]
    layer = write_scene_layer(_spec(lens), tmp_path / "c.usda", tiny_base)
    assert set(LENS_ATTRS) <= _camera_specs(layer)
    cam = read_scene(layer).camera
    assert (cam.focal_length_mm, cam.sensor_width_mm, cam.sensor_height_mm) == pytest.approx((50.0, 32.0, 18.0))
    assert (cam.horizontal_offset_mm, cam.vertical_offset_mm) == pytest.approx((-3.0, -2.0))
    assert cam.clip == pytest.approx((0.5, 1.0e12))


def test_validate_spec_refuses_a_lens_the_reader_would(tiny_base, tmp_path):
    for bad in (CameraModel(0.5), CameraModel(principal_point_offset_px=(40.0, 0.0)),
                CameraModel(clipping_range_m=(2.0, 1.0)), CameraModel(sensor_width_mm=float("nan"))):
        with pytest.raises(AlloError) as err:          # LayerError, or check_finite's AlloError
            write_scene_layer(_spec(bad), tmp_path / "bad.usda", tiny_base)
        assert "fix" in str(err.value)
        assert not (tmp_path / "bad.usda").exists()


@pytest.mark.parametrize("attr, value", [("horizontalApertureOffset", 0.181), ("verticalApertureOffset", -0.102),
                                         ("horizontalApertureOffset", float("inf"))])
def test_reader_refuses_out_of_range_aperture_offsets(tiny_base, tmp_path, attr, value):
    """Over half the aperture (36 mm, 20.25 mm: 0.18, 0.10125 scene units) the principal point leaves the image."""
    from pxr import Sdf

    layer = write_scene_layer(_spec(DEFAULT_CAMERA), tmp_path / "o.usda", tiny_base)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    prim = sdf.GetPrimAtPath(CAMERA)
    Sdf.AttributeSpec(prim, attr, Sdf.ValueTypeNames.Float).default = value
    sdf.Save()
    with pytest.raises(LayerError, match=attr):
        read_scene(layer)


def _ray_scene(desc):
    parts = []
    for m in desc.meshes:
        if m.path.startswith(SKY + "/"):
            continue  # the bodies are far away and not in this view
        pts = np.asarray(m.points, dtype=np.float64) @ m.matrix[:3, :3].T + m.matrix[:3, 3]
        parts.append((pts, fan_triangulate(m.face_counts, m.face_indices), m.class_id))
    return RayScene(parts)


def _classes_through(k: np.ndarray, w2c: np.ndarray, scene: RayScene, w: int, h: int) -> np.ndarray:
    """The class first hit by the ray through each pixel centre (OpenCV pixels) of K and the OpenCV pose."""
    rows, cols = np.mgrid[0:h, 0:w]
    cam = np.stack([(cols.ravel() - k[0, 2]) / k[0, 0], (rows.ravel() - k[1, 2]) / k[1, 1], np.ones(w * h)], 1)
    r, t = w2c[:3, :3], w2c[:3, 3]
    dirs = cam @ r                                   # camera -> world: R^T d
    origin = -r.T @ t
    owner, _ = scene.first_hit(np.broadcast_to(origin, dirs.shape), dirs)
    return owner.reshape(h, w)


@pytest.fixture(scope="module")
def rendered_lens(tiny_base, tmp_path_factory):
    from allo_usd.run.job import render_layer

    root = tmp_path_factory.mktemp("lens")
    lens = _plan(**PLAN_CAMERA).camera_model()[0]
    layer = write_scene_layer(_spec(lens, samples=2), root / "lens.usda", tiny_base)
    meta = render_layer(layer, root / "out")
    return layer, meta, root / "out"


@pytest.mark.render
def test_render_mask_is_what_rays_through_the_recorded_k_hit(rendered_lens):
    """The class mask of a 50 mm camera with a principal point offset equals, pixel for pixel (but for a
    few edge pixels), the classes the rays through the recorded K and pose meet; with the offset's sign
    flipped (the convention a wrong Blender shift or USD offset sign gives), far fewer agree."""
    layer, meta, out = rendered_lens
    mask = np.asarray(Image.open(out / meta["files"]["mask"]))
    h, w = mask.shape
    cam = meta["annotations"]["camera"]
    k, w2c = np.array(cam["K_px"]), np.array(cam["world_to_cam_opencv"])
    assert (k[0, 0], k[0, 2], k[1, 2]) == pytest.approx((100.0, 37.5, 13.5))
    scene = _ray_scene(read_scene(layer))
    seen = _classes_through(k, w2c, scene, w, h)
    assert (seen == ANOMALY).sum() > 20 and (seen == 1).sum() > 100     # the view shows both
    agree = (seen == mask).mean()
    assert agree > 0.97, agree                      # 1.0 at 64x36
    flipped = k.copy()
    flipped[0, 2], flipped[1, 2] = (w - 1) / 2 - 6.0, (h - 1) / 2 + 4.0
    assert (_classes_through(flipped, w2c, scene, w, h) == mask).mean() < agree - 0.2   # 0.62
    # and the anomaly box in the record matches the mask
    ys, xs = np.nonzero(mask == ANOMALY)
    assert meta["annotations"]["anomaly"]["bbox_xyxy_px"] == [xs.min(), ys.min(), xs.max(), ys.max()]


@pytest.mark.render
def test_blender_projection_has_the_principal_point_of_k(rendered_lens):
    import bpy

    from allo_usd.blender.build import build_scene

    layer, meta, _ = rendered_lens
    build_scene(read_scene(layer))
    scene = bpy.context.scene
    p = np.array(scene.camera.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=64, y=36))
    k = np.array(meta["annotations"]["camera"]["K_px"])
    # OpenGL clip space: x_ndc = (P00 x + P02 z) / -z, so the optical axis lands at x_ndc = -P02, y_ndc = -P12
    assert k[0, 2] == pytest.approx((1 - p[0, 2]) * 64 / 2 - 0.5, abs=1e-4)
    assert k[1, 2] == pytest.approx((1 + p[1, 2]) * 36 / 2 - 0.5, abs=1e-4)
    assert (scene.camera.data.shift_x, scene.camera.data.shift_y) == pytest.approx((-6 / 64, -4 / 64))


def test_placement_and_raycast_look_through_the_lens(tiny_base, tmp_path):
    """class_image through the plan's lens equals the OpenCV-K rays of the same lens (one convention),
    and differs from the default camera's."""
    lens = _plan(**PLAN_CAMERA).camera_model()[0]
    desc = read_scene(write_scene_layer(_spec(lens), tmp_path / "r.usda", tiny_base))
    scene = _ray_scene(desc)
    c2w = np.asarray(desc.camera.matrix)
    from allo_usd.output.annotations import world_to_cam_opencv

    via_k = _classes_through(lens.intrinsics_opencv(64, 36), world_to_cam_opencv(c2w), scene, 64, 36)
    mine = class_image(scene, c2w[:3, 3], c2w[:3, :3], 64, 36, lens)
    assert (mine == via_k).mean() > 0.99
    assert (class_image(scene, c2w[:3, 3], c2w[:3, :3], 64, 36) != mine).mean() > 0.1


def test_rig_scores_views_through_the_lens():
    from allo_usd.scene.rig import image_grid

    wide = image_grid(4, 2)
    assert np.array_equal(wide, image_grid(4, 2, DEFAULT_CAMERA, (1920, 1080)))   # no offset: the same rays
    lens = CameraModel(50.0, 32.0, 18.0, principal_point_offset_px=(6.0, -4.0))
    grid = image_grid(4, 2, lens, (64, 36))
    # the grid spans the lens's window: x/-z from -38/100 to 26/100, y/-z from 14/100 down to -22/100
    x, y = grid[:-1, 0] / -grid[:-1, 2], grid[:-1, 1] / -grid[:-1, 2]
    assert x.min() == pytest.approx(-0.38 + 0.08) and x.max() == pytest.approx(0.26 - 0.08)
    assert y.max() == pytest.approx(0.14 - 0.09) and y.min() == pytest.approx(-0.22 + 0.09)


@pytest.mark.render
def test_predicted_area_agrees_with_the_rendered_anomaly_for_a_plan_lens(tiny_base, tmp_path):
    """Place the crate with placement looking through a non-default lens; its predicted area fraction
    matches the anomaly pixels Blender renders through that lens (loosely: edges, sampling)."""
    from allo_usd.run.job import render_layer
    from allo_usd.scene.placement import place
    from allo_usd.scene.spec import AnomalySpec
    from allo_usd.usd.stage_geometry import scene_inputs

    lens = _plan(**{**PLAN_CAMERA, "resolution": [160, 90], "principal_point_offset_px": [15.0, -10.0],
                    "focal_length_mm": 35.0}).camera_model()[0]
    spec = _spec(lens, anomaly=False, resolution=(160, 90), samples=1)
    inputs = scene_inputs(tiny_base, None, spec.perilune_epoch)
    pts, tris, centre, obj = inputs.anomaly_scene("Crate", "red")
    station = RayScene(inputs.station_parts)
    rng = np.random.default_rng(3)
    placed = place(station, pts, tris, np.array(spec.camera.position), spec.camera.rotation, rng, 160, 90,
                   anomaly=obj, lens=lens, check_width=None)
    p = next(p for p in placed if p.position is not None)
    a = AnomalySpec("Crate", "red", tuple(map(float, p.position - p.rotation @ centre)), p.rotation,
                    p.depth_index, p.depth_offset, p.attempts, p.area_fraction)
    spec = replace(spec, anomaly=a)
    meta = render_layer(write_scene_layer(spec, tmp_path / "p.usda", tiny_base), tmp_path / "out")
    mask = np.asarray(Image.open(tmp_path / "out" / meta["files"]["mask"]))
    rendered = (mask == ANOMALY).mean()
    assert rendered > 0
    assert rendered == pytest.approx(p.area_fraction, rel=0.25), (rendered, p.area_fraction)


def test_inspect_shows_the_lens_and_where_it_comes_from(tiny_base, tmp_path):
    from allo_usd.usd.inspect import describe, format_description

    lens = _plan(**PLAN_CAMERA).camera_model()[0]
    plan_layer = write_scene_layer(_spec(lens), tmp_path / "plan_lens.usda", tiny_base)
    d = describe(plan_layer)["camera"]
    assert d["focal_length_mm"] == pytest.approx(50.0)
    assert d["aperture_offset_mm"] == pytest.approx((-3.0, -2.0))
    assert d["lens_from"] == "scene layer plan_lens.usda (plan camera)"
    assert "aperture offset (-3, -2) mm  from scene layer" in format_description(describe(plan_layer))
    default = describe(write_scene_layer(_spec(DEFAULT_CAMERA), tmp_path / "d.usda", tiny_base))["camera"]
    assert default["lens_from"] == "base stage base.usda (Table I default)"
    assert default["aperture_offset_mm"] == (0.0, 0.0) and default["focal_length_mm"] == pytest.approx(25.0)


@pytest.mark.render
def test_a_plan_with_its_own_camera_authors_and_renders_end_to_end(tmp_path, capsys):
    """Author a tiny plan with a 50 mm camera over the shipped base stage: every layer carries the lens,
    the rig poses that do not qualify under it are noted (one line each, not an error), and the
    anomalous scene renders with the anomaly where placement predicted (area within a loose bound)."""
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.run.author import author_plan
    from allo_usd.run.job import render_layer
    from allo_usd.usd.inspect import describe

    plan = make_plan({"name": "cam", "dates": {"days": 1}, "poses": {"train": [1], "test": [41, 42]},
                      "anomalies": {"assets": ["power_drill"], "depths": [0]}, "quality": {"samples": 2},
                      "base_stage": str(BASE_STAGE), "camera": PLAN_CAMERA})
    paths = author_plan(plan, tmp_path / "tree", progress=False)
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("note: base pose")]
    assert notes and all("does not qualify under the plan's camera" in line for line in notes)
    for p in paths:
        assert set(LENS_ATTRS) <= _camera_specs(p)
        assert describe(p)["camera"]["lens_from"].endswith("(plan camera)")
    anomalous = [p for p in paths if "/anomaly/" in str(p)]
    assert anomalous
    meta = render_layer(anomalous[0], tmp_path / "out")
    mask = np.asarray(Image.open(tmp_path / "out" / meta["files"]["mask"]))
    predicted = describe(anomalous[0])["anomaly"]["predicted_area_fraction"]
    assert (mask == ANOMALY).mean() == pytest.approx(predicted, rel=0.5, abs=2 / mask.size)


def test_bodies_in_view_uses_the_shifted_view_pyramid():
    """A body just inside the image's right edge with the principal point moved left (dx < 0 puts the
    image's centre right of the axis) is in view; the same body outside the centred pyramid is not."""
    from allo_usd.output.annotations import disc_in_view

    half_x, half_y = 0.32, 0.18
    d = np.array([0.40, 0.0, 1.0])                     # x/z = 0.40: beyond 0.32, within 0.10 + 0.32
    assert not disc_in_view(d, 1e-4, half_x, half_y)
    assert disc_in_view(d, 1e-4, half_x, half_y, (0.10, 0.0))
    assert not disc_in_view(np.array([-0.40, 0.0, 1.0]), 1e-4, half_x, half_y, (0.10, 0.0))   # left of -0.22
