"""Property tests of the reader's bounds: a valid scene layer with random opinions over
its camera, lights, materials, render settings, sensor and transforms (finite, NaN, inf, huge, tiny,
negative numbers, and values of the wrong type) either reads into a description whose every value
lies inside the documented bounds (allo_usd.usd.reader_bounds, docs/reliability/reliability.md, section 2), or is refused
with a LayerError. Never another exception, never a value Blender would clamp."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pxr import Gf, Sdf

from allo_usd.core.errors import LayerError
from allo_usd.core.limits import MAX_SIDE_PX, MIN_SIDE_PX
from allo_usd.usd import reader_bounds as R
from allo_usd.usd.description import SceneDescription
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

T = Sdf.ValueTypeNames
CAMERA, SPOT, SUN = "/World/Camera", "/World/Camera/InspectionLight", "/World/Sky/SunLight"
ANOMALY, PAINT, SETTINGS = "/World/Anomaly", "/World/Anomaly/Looks/paint/PreviewSurface", "/Render/Settings"
MOON_SURFACE = "/World/Sky/Moon/Looks/Regolith/PreviewSurface"

SPECIAL = [0.0, -0.0, 1e-30, 1e-7, 1e-5, 0.5, 1.0, 90.0, 181.0, 1e6, 1e20, 1e30, 3.4e38, -1.0, -1e30,
           math.nan, math.inf, -math.inf]
NUMBER = st.one_of(st.sampled_from(SPECIAL), st.floats(allow_nan=True, allow_infinity=True, width=32))
INTEGER = st.one_of(st.sampled_from([0, 1, 3, 4, 64, 1024, 1025, 2 ** 31 - 1, -1, -(2 ** 31)]),
                    st.integers(-(2 ** 31), 2 ** 31 - 1))
WRONG = st.one_of(st.text(max_size=6), st.booleans())           # a string or a bool where a number belongs
SCALAR = st.one_of(NUMBER, INTEGER, WRONG)
TRIPLE = st.tuples(NUMBER, NUMBER, NUMBER)
PAIR = st.tuples(NUMBER, NUMBER)

# (prim, attribute, what it holds): every value the reader hands on towards Blender, and its sensor.
TARGETS = [
    (CAMERA, "focalLength", "scalar"), (CAMERA, "horizontalAperture", "scalar"),
    (CAMERA, "verticalAperture", "scalar"), (CAMERA, "clippingRange", "pair"),
    (SPOT, "inputs:intensity", "scalar"), (SPOT, "inputs:exposure", "scalar"), (SPOT, "inputs:radius", "scalar"),
    (SPOT, "inputs:shaping:cone:angle", "scalar"), (SPOT, "inputs:shaping:cone:softness", "scalar"),
    (SPOT, "inputs:color", "triple"),
    (SUN, "inputs:intensity", "scalar"), (SUN, "inputs:exposure", "scalar"), (SUN, "inputs:angle", "scalar"),
    (SUN, "inputs:color", "triple"),
    (PAINT, "inputs:metallic", "scalar"), (PAINT, "inputs:roughness", "scalar"), (PAINT, "inputs:ior", "scalar"),
    (PAINT, "inputs:diffuseColor", "triple"), (PAINT, "inputs:emissiveColor", "triple"),
    (MOON_SURFACE, "inputs:roughness", "scalar"),
    (SETTINGS, "allo:render:samples", "int"), (SETTINGS, "allo:render:seed", "int"),
    (SETTINGS, "allo:render:threads", "int"), (SETTINGS, "allo:render:maxBounces", "int"),
    (SETTINGS, "allo:render:adaptiveThreshold", "scalar"), (CAMERA, "exposure", "scalar"),
    (SETTINGS, "resolution", "int_pair"),
    (SETTINGS, "allo:effects:sensor:fullWell", "scalar"), (SETTINGS, "allo:effects:sensor:bitDepth", "int"),
    (SETTINGS, "allo:effects:sensor:quantumEfficiency", "scalar"),
]
TRANSFORMED = [CAMERA, SPOT, SUN, ANOMALY]


VECTORS = {"pair": (T.Float2, Gf.Vec2f), "int_pair": (T.Int2, Gf.Vec2i), "triple": (T.Color3f, Gf.Vec3f)}


def _typed(kind: str, value):
    """(Sdf type, value) to author `value` with: its natural type (a string as a string, and so on)."""
    if isinstance(value, bool):
        return T.Bool, value
    if isinstance(value, str):
        return T.String, value
    if isinstance(value, tuple):
        type_name, make = VECTORS[kind]
        return type_name, make(*value)
    if isinstance(value, int):
        return T.Int, value
    return T.Float, value


def _value(kind: str):
    return {"scalar": SCALAR, "int": st.one_of(INTEGER, NUMBER, WRONG),
            "pair": st.one_of(PAIR, WRONG), "int_pair": st.one_of(st.tuples(INTEGER, INTEGER), WRONG),
            "triple": st.one_of(TRIPLE, SCALAR)}[kind]


OPINION = st.sampled_from(TARGETS).flatmap(lambda t: st.tuples(st.just(t), _value(t[2])))
SCALE = st.tuples(st.sampled_from(TRANSFORMED), st.tuples(NUMBER, NUMBER, NUMBER))

_names = itertools.count()


@pytest.fixture(scope="module")
def valid_text(tiny_base, tmp_path_factory):
    from dataclasses import replace

    from allo_usd.plan.settings import EffectsSpec

    spec = make_spec(anomaly=True)
    spec = replace(spec, effects=EffectsSpec(sensor_noise=True))
    root = tmp_path_factory.mktemp("props") / "layers"
    return write_scene_layer(spec, root / "valid.usda", tiny_base)


def _set(layer, prim: str, name: str, type_name, value) -> None:
    spec = Sdf.CreatePrimInLayer(layer, prim)
    if name in spec.attributes:
        spec.RemoveProperty(spec.attributes[name])
    uniform = name in ("resolution", "xformOpOrder")
    attr = Sdf.AttributeSpec(spec, name, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
    attr.default = value


def _author(valid, opinions, scales=()):
    """A copy of the valid layer with `opinions` [((prim, name, kind), value)] and scales authored."""
    path = valid.with_name(f"case_{next(_names):05d}.usda")
    path.write_text(valid.read_text())
    layer = Sdf.Layer.FindOrOpen(str(path))
    for (prim, name, kind), value in opinions:
        _set(layer, prim, name, *_typed(kind, value))
    for prim, scale in scales:
        _set(layer, prim, "xformOp:scale", T.Double3, Gf.Vec3d(*scale))
        _set(layer, prim, "xformOpOrder", T.TokenArray, ["xformOp:translate", "xformOp:orient", "xformOp:scale"])
    layer.Save()
    return path


def _inside(value, bounds) -> bool:
    return bool(np.isfinite(value) and bounds[0] <= value <= bounds[1])


def _good_matrix(m) -> bool:
    if not np.isfinite(m).all():
        return False
    s = np.linalg.svd(m[:3, :3], compute_uv=False)
    return bool(R.MIN_SCALE <= s[-1] and s[0] <= R.MAX_SCALE)


def assert_within_bounds(desc: SceneDescription) -> None:
    c = desc.camera
    assert _inside(c.focal_length_mm, R.LENS_MM)
    assert _inside(c.sensor_width_mm, R.SENSOR_MM) and _inside(c.sensor_height_mm, R.SENSOR_MM)
    assert R.CLIP_M[0] <= c.clip[0] < c.clip[1] <= R.CLIP_M[1]
    assert _good_matrix(c.matrix)
    for m in desc.meshes:
        assert _good_matrix(m.matrix), m.path
    for sun in desc.suns:
        assert 0 < sun.irradiance <= R.MAX_LIGHT and _inside(sun.angle_deg, R.SUN_ANGLE_DEG)
        assert all(_inside(x, (0.0, R.MAX_COLOUR)) for x in sun.color)
        assert np.isfinite(sun.direction).all() and abs(np.linalg.norm(sun.direction) - 1) < 1e-9
    if desc.spot is not None:
        s = desc.spot
        assert _inside(s.intensity, (0.0, R.MAX_LIGHT)) and _inside(s.radius, R.SPOT_RADIUS_M)
        assert _inside(s.cone_angle_deg, R.SPOT_CONE_DEG) and _inside(s.softness, R.SPOT_SOFTNESS)
        assert all(_inside(x, (0.0, R.MAX_COLOUR)) for x in s.color) and _good_matrix(s.matrix)
        assert math.isfinite(4 * math.pi ** 2 * s.radius ** 2 * s.intensity)
    for mat in desc.materials.values():
        assert _inside(mat.metallic, R.UNIT_INTERVAL) and _inside(mat.roughness, R.UNIT_INTERVAL)
        assert _inside(mat.ior, R.IOR)
        assert all(_inside(x, (0.0, R.MAX_COLOUR)) for x in mat.base_color)
        assert all(_inside(x, (0.0, R.MAX_LIGHT)) for x in mat.emissive_color)
    r = desc.render
    assert all(MIN_SIDE_PX <= side <= MAX_SIDE_PX for side in r.resolution)
    assert _inside(r.samples, R.RENDER_SAMPLES) and _inside(r.seed, R.RENDER_SEED)
    assert _inside(r.threads, R.RENDER_THREADS) and _inside(r.max_bounces, R.RENDER_BOUNCES)
    assert _inside(r.adaptive_threshold, R.RENDER_ADAPTIVE) and 0 < r.exposure <= R.RENDER_EXPOSURE[1]
    if desc.effects.sensor is not None:
        desc.effects.sensor.validate()


def _read_or_refuse(path) -> None:
    try:
        desc = read_scene(path)
    except LayerError as exc:
        assert "fix" in str(exc) or "regenerate" in str(exc) or "restore" in str(exc), str(exc)
    else:
        assert_within_bounds(desc)
    finally:
        path.unlink()


PROPERTY = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@PROPERTY
@given(opinions=st.lists(OPINION, min_size=1, max_size=3))
@pytest.mark.slow
def test_random_values_read_within_bounds_or_are_refused(valid_text, opinions):
    _read_or_refuse(_author(valid_text, opinions))


@PROPERTY
@given(scales=st.lists(SCALE, min_size=1, max_size=2), opinions=st.lists(OPINION, max_size=1))
@pytest.mark.slow
def test_random_transforms_read_within_bounds_or_are_refused(valid_text, scales, opinions):
    _read_or_refuse(_author(valid_text, opinions, scales))


def test_the_valid_layer_reads_within_bounds(valid_text):
    assert_within_bounds(read_scene(valid_text))
