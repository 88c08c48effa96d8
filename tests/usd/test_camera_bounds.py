"""A plan's [camera] bounds and the layer reader's agree after the float32 round trip, at every edge:
a plan at each edge authors a layer the reader accepts, reading back the edge itself; just outside
each edge the plan refuses, naming the field. focal_length_mm = 1.0 (inside the plan's 1..100,000 mm)
is stored as 0.0099999998 scene units, and the reader accepts it."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core.camera_model import CLIP_M, LENS_MM, MAX_SHIFT, SENSOR_MM
from allo_usd.core.errors import LayerError, PlanError
from allo_usd.plan.io import make_plan
from allo_usd.usd.layout import CAMERA
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec


def _plan(resolution=(64, 36), **camera):
    return make_plan({"name": "edges", "quality": {"resolution": list(resolution)}, "camera": camera})


def _read_back(plan, tiny_base, path):
    """The plan's lens authored into a scene layer (write_scene_layer, as author does) and read back."""
    lens, size = plan.camera_model()
    layer = write_scene_layer(make_spec(resolution=size, lens=lens), path, tiny_base)
    return read_scene(layer).camera


# (camera table, resolution, the values the reader must give back: the edge itself where its float32 falls
# outside the bound (1 mm is stored as 0.0099999998 units), else that float32, which lies inside)
EDGES = [
    ({"focal_length_mm": LENS_MM[0]}, (64, 36), {"focal_length_mm": LENS_MM[0]}),
    ({"focal_length_mm": LENS_MM[1]}, (64, 36), {"focal_length_mm": LENS_MM[1]}),
    ({"sensor_width_mm": SENSOR_MM[0]}, (64, 64), {"sensor_width_mm": SENSOR_MM[0], "sensor_height_mm": SENSOR_MM[0]}),
    ({"sensor_width_mm": SENSOR_MM[1]}, (64, 64), {"sensor_width_mm": SENSOR_MM[1], "sensor_height_mm": SENSOR_MM[1]}),
    ({"sensor_height_mm": SENSOR_MM[0]}, (64, 36), {"sensor_height_mm": SENSOR_MM[0]}),
    ({"sensor_height_mm": SENSOR_MM[1]}, (36, 64), {"sensor_height_mm": SENSOR_MM[1]}),
    ({"clipping_range_m": list(CLIP_M)}, (64, 36), {"clip": CLIP_M}),
    ({"clipping_range_m": [CLIP_M[0], 2 * CLIP_M[0]]}, (64, 36), {"clip": (CLIP_M[0], 2 * CLIP_M[0])}),
    ({"clipping_range_m": [1e12, CLIP_M[1]]}, (64, 36), {"clip": (1e12, CLIP_M[1])}),
]


@pytest.mark.parametrize("camera, resolution, expect", EDGES, ids=lambda v: str(v) if isinstance(v, dict) else None)
def test_a_plan_at_each_edge_reads_back_as_that_edge(camera, resolution, expect, tiny_base, tmp_path):
    cam = _read_back(_plan(resolution, **camera), tiny_base, tmp_path / "edge.usda")
    for field, value in expect.items():
        if field == "clip":
            for got, want in zip(cam.clip, value):
                assert CLIP_M[0] <= got <= CLIP_M[1] and got == _stored(want, CLIP_M), (cam.clip, value)
        else:
            bounds = LENS_MM if field == "focal_length_mm" else SENSOR_MM
            got = getattr(cam, field)
            assert bounds[0] <= got <= bounds[1] and got == _stored(want := value / 100, (bounds[0] / 100,
                                                                                         bounds[1] / 100)) * 100, \
                (field, got, want)


def _stored(value: float, bounds) -> float:
    """What the reader gives for `value` stored as a float32: the bound itself if the float32 fell outside."""
    f = float(np.float32(value))
    return min(max(f, bounds[0]), bounds[1])


@pytest.mark.parametrize("sx, sy", [(1, 1), (-1, -1), (1, -1), (-1, 1)])
@pytest.mark.parametrize("resolution, sensor", [((64, 36), {}), ((640, 480), {"sensor_width_mm": 7.7}),
                                                ((1919, 1081), {"sensor_height_mm": 13.3}),
                                                ((333, 777), {"sensor_width_mm": 1.0})])
def test_a_principal_point_on_the_image_edge_reads_back_inside_the_bound(sx, sy, resolution, sensor, tiny_base,
                                                                          tmp_path):
    w, h = resolution
    plan = _plan(resolution, principal_point_offset_px=[sx * w / 2, sy * h / 2], **sensor)
    cam = _read_back(plan, tiny_base, tmp_path / "offset.usda")
    assert abs(cam.horizontal_offset_mm) <= MAX_SHIFT * cam.sensor_width_mm
    assert abs(cam.vertical_offset_mm) <= MAX_SHIFT * cam.sensor_height_mm
    assert cam.horizontal_offset_mm == pytest.approx(-sx * cam.sensor_width_mm / 2, rel=1e-6)
    assert cam.vertical_offset_mm == pytest.approx(sy * cam.sensor_height_mm / 2, rel=1e-6)


def test_sensor_sides_given_both_within_the_plans_aspect_tolerance_read_back(tiny_base, tmp_path):
    """The plan accepts a width and height whose aspect is up to 1e-6 off the image's; a principal point
    on the image's corner with such a sensor still reads back."""
    w, h = 64, 36
    sw = 36.0
    sh = sw * h / w * (1 + 0.9e-6)
    plan = _plan((w, h), sensor_width_mm=sw, sensor_height_mm=sh, principal_point_offset_px=[-w / 2, h / 2])
    cam = _read_back(plan, tiny_base, tmp_path / "aspect.usda")
    assert abs(cam.vertical_offset_mm) <= MAX_SHIFT * cam.sensor_height_mm


OUTSIDE = [
    ({"focal_length_mm": np.nextafter(LENS_MM[0], 0)}, (64, 36), "focal_length_mm"),
    ({"focal_length_mm": LENS_MM[1] * (1 + 1e-9)}, (64, 36), "focal_length_mm"),
    ({"sensor_width_mm": np.nextafter(SENSOR_MM[0], 0)}, (64, 64), "sensor_width_mm"),
    ({"sensor_width_mm": SENSOR_MM[1] * (1 + 1e-9)}, (64, 64), "sensor_width_mm"),
    ({"sensor_height_mm": np.nextafter(SENSOR_MM[0], 0)}, (64, 36), "sensor_height_mm"),
    ({"sensor_height_mm": SENSOR_MM[1] * (1 + 1e-9)}, (36, 64), "sensor_height_mm"),
    ({"clipping_range_m": [np.nextafter(CLIP_M[0], 0), 1.0]}, (64, 36), "clipping_range_m"),
    ({"clipping_range_m": [1.0, CLIP_M[1] * (1 + 1e-9)]}, (64, 36), "clipping_range_m"),
    ({"clipping_range_m": [1.0, 1.00000001]}, (64, 36), "32-bit floats"),   # one float32: near == far in the layer
]


@pytest.mark.parametrize("camera, resolution, words", OUTSIDE, ids=lambda v: str(v) if isinstance(v, dict) else None)
def test_just_outside_each_edge_the_plan_refuses_naming_the_field(camera, resolution, words):
    with pytest.raises(PlanError) as err:
        _plan(resolution, **{k: (list(map(float, v)) if isinstance(v, list) else float(v)) for k, v in camera.items()})
    message = str(err.value)
    assert words in message and "fix:" in message, message


@pytest.mark.parametrize("dx, dy", [(32.001, 0), (0, -18.001)])
def test_a_principal_point_just_outside_the_image_is_refused_by_the_plan(dx, dy):
    with pytest.raises(PlanError, match="principal_point_offset_px.*outside the 64x36 image"):
        _plan((64, 36), principal_point_offset_px=[dx, dy]).camera_model()


@pytest.mark.parametrize("attr, value", [("focalLength", np.nextafter(np.float32(0.01), np.float32(0))),
                                         ("focalLength", np.nextafter(np.float32(1000), np.float32(np.inf))),
                                         ("horizontalAperture", np.nextafter(np.float32(0.01), np.float32(0)))])
def test_the_reader_still_refuses_a_float32_beyond_the_stored_edge(attr, value, tiny_base, tmp_path):
    """Only the edge's own float32 is read as the edge: the next float32 outward is refused."""
    from pxr import Sdf

    from allo_usd.core.camera_model import DEFAULT_CAMERA

    layer = write_scene_layer(make_spec(lens=DEFAULT_CAMERA), tmp_path / "beyond.usda", tiny_base)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    Sdf.AttributeSpec(sdf.GetPrimAtPath(CAMERA), attr, Sdf.ValueTypeNames.Float).default = float(value)
    sdf.Save()
    with pytest.raises(LayerError, match=attr):
        read_scene(layer)


@pytest.mark.render
def test_a_plan_at_the_lens_and_clipping_edges_renders(tiny_base, tmp_path):
    """The smallest focal length and near plane reach Blender as the edges themselves (build.assign reads
    every value back: a clamped one would be a LayerError)."""
    from allo_usd.run.job import render_layer

    lens, size = _plan((64, 36), focal_length_mm=LENS_MM[0], clipping_range_m=[CLIP_M[0], CLIP_M[1]]).camera_model()
    layer = write_scene_layer(make_spec(resolution=size, lens=lens, samples=1), tmp_path / "wide.usda", tiny_base)
    meta = render_layer(layer, tmp_path / "out")
    assert (tmp_path / "out" / "wide.png").is_file()
    cam = meta["annotations"]["camera"]
    assert cam["focal_length_mm"] == LENS_MM[0] and cam["clip_near_m"] == CLIP_M[0], cam
