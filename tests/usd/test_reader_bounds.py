"""The reader bounds every value Blender would clamp or choke on, and broken input fails
with one clear LayerError (naming the attribute, the value, the allowed range and the fix).

Each layer here is a valid scene layer with one opinion overridden through Sdf (an `over` in the
scene layer itself), so the rest of the scene stays valid and only the named value is at fault.
"""

from __future__ import annotations

import pytest
from pxr import Gf, Sdf, Vt

from allo_usd.core.errors import LayerError
from allo_usd.core.limits import MAX_SIDE_PX, MIN_SIDE_PX
from allo_usd.usd import reader_bounds
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

CAMERA = "/World/Camera"
SPOT = "/World/Camera/InspectionLight"
SUN = "/World/Sky/SunLight"
ANOMALY = "/World/Anomaly"
BODY = "/World/Anomaly/Geom/Body"
PAINT = "/World/Anomaly/Looks/paint/PreviewSurface"
MOON_TEXTURE = "/World/Sky/Moon/Looks/Regolith/BaseColorTexture"
SETTINGS = "/Render/Settings"
T = Sdf.ValueTypeNames


@pytest.fixture
def layer(tiny_base, tmp_path):
    return write_scene_layer(make_spec(anomaly=True), tmp_path / "s.usda", tiny_base)


def override(layer, prim_path: str, name: str, type_name, value, uniform: bool = False) -> None:
    """Author `name` = value (of Sdf type `type_name`) over prim_path in the scene layer itself."""
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    spec = Sdf.CreatePrimInLayer(sdf, prim_path)
    old = spec.attributes.get(name)
    if old is not None:
        spec.RemoveProperty(old)
    attr = Sdf.AttributeSpec(spec, name, type_name,
                             Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
    attr.default = value
    sdf.Save()


def add_scale(layer, prim_path: str, scale, order=("xformOp:translate", "xformOp:orient")) -> None:
    override(layer, prim_path, "xformOp:scale", T.Double3, Gf.Vec3d(*scale))
    override(layer, prim_path, "xformOpOrder", T.TokenArray, Vt.TokenArray([*order, "xformOp:scale"]), uniform=True)


def refused(layer, *needles: str) -> str:
    with pytest.raises(LayerError) as info:
        read_scene(layer)
    message = str(info.value)
    for needle in needles:
        assert needle in message, message
    assert "fix" in message or "regenerate" in message or "restore" in message, message
    return message


# ----------------------------------------------------------------------------- camera

@pytest.mark.parametrize("clip", [(float("nan"), float("nan")), (0.0, 100.0), (5.0, 1.0), (1.0, 1.0),
                                  (0.05, float("inf")), (0.05, 1e20), (-1.0, 10.0)])
@pytest.mark.slow
def test_camera_clipping_range_is_finite_ordered_and_within_blender(layer, clip):
    override(layer, CAMERA, "clippingRange", T.Float2, Gf.Vec2f(*clip))
    refused(layer, f"{CAMERA}.clippingRange")


@pytest.mark.parametrize("name,value,needle", [
    ("exposure", float("nan"), "exposure"), ("exposure", float("inf"), "exposure"), ("exposure", 100.0, "exposure"),
    ("exposure", 40.0, "linear exposure scale"), ("exposure:fStop", 0.0, "exposure:fStop"),
    ("exposure:iso", -100.0, "exposure:iso"), ("exposure:time", float("nan"), "exposure:time"),
    ("exposure:responsivity", 0.0, "exposure:responsivity"), ("exposure:fStop", 1e-7, "linear exposure scale")])
def test_camera_exposure_is_finite_positive_and_within_film_exposure(layer, name, value, needle):
    """The film exposure comes from UsdGeom.Camera's exposure attributes: each is bounded, and so is
    the linear scale they make (Cycles film_exposure takes 0..2^32)."""
    override(layer, CAMERA, name, T.Float, value)
    refused(layer, f"{CAMERA}", needle)


@pytest.mark.parametrize("name,value", [("focalLength", 1e-30), ("focalLength", 1e30), ("focalLength", 0.005),
                                        ("horizontalAperture", 1e-30), ("verticalAperture", 1e30)])
def test_camera_lens_values_within_blenders_limits(layer, name, value):
    override(layer, CAMERA, name, T.Float, value)
    refused(layer, f"{CAMERA}.{name}", "mm")


def test_camera_projection_must_be_perspective(layer):
    override(layer, CAMERA, "projection", T.Token, "orthographic")
    refused(layer, "projection")


@pytest.mark.parametrize("prim,scale,order", [
    (CAMERA, (0, 0, 0), ("xformOp:translate", "xformOp:orient")),
    (CAMERA, (1, 1, 1e-9), ("xformOp:translate", "xformOp:orient")),
    (ANOMALY, (1, 0, 1), ("xformOp:translate", "xformOp:orient")),       # a mesh scaled to nothing vanishes
    (SPOT, (0, 0, 0), ("xformOp:translate", "xformOp:orient")),
    (SUN, (1, 1, 0), ("xformOp:translate", "xformOp:orient")),
    (ANOMALY, (1e13, 1, 1), ("xformOp:translate", "xformOp:orient")),
])
def test_degenerate_transform_is_refused(layer, prim, scale, order):
    add_scale(layer, prim, scale, order)
    refused(layer, prim, "degenerate", "xformOp:scale")


def test_a_valid_scale_still_reads(layer):
    add_scale(layer, ANOMALY, (2, 0.5, 1e-3))
    desc = read_scene(layer)
    assert {m.path for m in desc.meshes} >= {BODY}


# ----------------------------------------------------------------------------- lights

@pytest.mark.parametrize("name,type_name,value", [
    ("inputs:shaping:cone:angle", T.Float, 120.0), ("inputs:shaping:cone:angle", T.Float, 0.1),
    ("inputs:shaping:cone:softness", T.Float, 2.0), ("inputs:radius", T.Float, 1e30),
    ("inputs:intensity", T.Float, 1e30), ("inputs:color", T.Color3f, Gf.Vec3f(-1, 1, 1)),
    ("inputs:color", T.Color3f, Gf.Vec3f(1, float("nan"), 1)), ("inputs:exposure", T.Float, 60.0),
])
def test_spot_values_within_blenders_limits(layer, name, type_name, value):
    override(layer, SPOT, name, type_name, value)
    refused(layer, f"{SPOT}.{name}")


@pytest.mark.parametrize("name,type_name,value", [
    ("inputs:angle", T.Float, 181.0), ("inputs:angle", T.Float, -1.0), ("inputs:intensity", T.Float, -5.0),
    ("inputs:intensity", T.Float, 1e30), ("inputs:color", T.Color3f, Gf.Vec3f(1, -0.5, 1)),
    ("inputs:color", T.Color3f, Gf.Vec3f(1, 1, 1e30)),
])
def test_sun_values_within_blenders_limits(layer, name, type_name, value):
    override(layer, SUN, name, type_name, value)
    refused(layer, f"{SUN}.{name}")


def test_a_type_mismatch_in_a_light_is_a_layer_error(layer):
    override(layer, SPOT, "inputs:color", T.String, "warm")
    refused(layer, f"{SPOT}.inputs:color")


# ----------------------------------------------------------------------------- materials

@pytest.mark.parametrize("name,type_name,value", [
    ("inputs:metallic", T.String, "shiny"), ("inputs:metallic", T.Float, 2.0), ("inputs:metallic", T.Float, -0.1),
    ("inputs:roughness", T.Float, float("nan")), ("inputs:roughness", T.Float, 1.5),
    ("inputs:diffuseColor", T.Color3f, Gf.Vec3f(float("nan"), 0, 0)),
    ("inputs:diffuseColor", T.Color3f, Gf.Vec3f(-1, 0, 0)), ("inputs:diffuseColor", T.Float, 0.5),
    ("inputs:diffuseColor", T.String, "red"), ("inputs:emissiveColor", T.Color3f, Gf.Vec3f(0, -1, 0)),
    ("inputs:emissiveColor", T.Color3f, Gf.Vec3f(0, float("inf"), 0)), ("inputs:ior", T.String, "glass"),
    ("inputs:ior", T.Float, 0.5),
])
def test_shader_inputs_are_type_checked_and_bounded(layer, name, type_name, value):
    override(layer, PAINT, name, type_name, value)
    refused(layer, f"{PAINT}.{name}")


# ----------------------------------------------------------------------------- textures

def _use_texture(layer, path) -> None:
    override(layer, MOON_TEXTURE, "inputs:file", T.Asset, Sdf.AssetPath(str(path)))


def _png_bytes() -> bytes:
    import io

    import numpy as np
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_texture_that_is_missing_or_a_directory_is_refused(layer, tmp_path):
    _use_texture(layer, tmp_path / "gone.png")
    refused(layer, "gone.png")
    (tmp_path / "adir.png").mkdir()
    _use_texture(layer, tmp_path / "adir.png")
    refused(layer, "adir.png", "not a regular file")


def test_texture_that_is_not_an_image_is_refused(layer, tmp_path):
    fake = tmp_path / "notes.png"
    fake.write_text("this is a text file renamed .png\n")
    _use_texture(layer, fake)
    message = refused(layer, "notes.png", "not an image")
    assert "this is" not in message, message   # a refusal never shows the file's bytes


def test_truncated_png_is_refused(layer, tmp_path):
    cut = tmp_path / "cut.png"
    cut.write_bytes(_png_bytes()[:40])
    _use_texture(layer, cut)
    refused(layer, "cut.png", "cut short")


def test_huge_texture_is_refused(layer, tmp_path):
    huge = tmp_path / "huge.png"
    with open(huge, "wb") as f:  # sparse: takes no disk space
        f.write(_png_bytes())
        f.truncate(reader_bounds.MAX_TEXTURE_BYTES + 1)
    _use_texture(layer, huge)
    refused(layer, "huge.png", "MiB")


def test_a_good_texture_still_reads(layer, tmp_path):
    ok = tmp_path / "ok.png"
    ok.write_bytes(_png_bytes())
    _use_texture(layer, ok)
    desc = read_scene(layer)
    assert any(m.base_color_texture == str(ok) for m in desc.materials.values())


# ----------------------------------------------------------------------------- meshes

@pytest.mark.parametrize("counts", [[-1, 5, 4, 4, 4, 4, 4], [2, 2, 4, 4, 4, 4, 4], [0, 4, 4, 4, 4, 4, 4],
                                    [4, 4, 4, 4, 4, 4, 4]])
def test_face_counts_are_at_least_three_and_sum_to_the_indices(layer, counts):
    override(layer, BODY, "faceVertexCounts", T.IntArray, Vt.IntArray(counts))
    refused(layer, BODY, "faceVertexCounts")


def test_missing_topology_is_a_layer_error(layer):
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    spec = Sdf.CreatePrimInLayer(sdf, BODY)
    attr = Sdf.AttributeSpec(spec, "faceVertexCounts", T.IntArray)
    attr.default = Sdf.ValueBlock()
    sdf.Save()
    refused(layer, BODY, "faceVertexCounts")


def test_wrongly_typed_topology_is_a_layer_error(layer):
    override(layer, BODY, "faceVertexCounts", T.FloatArray, Vt.FloatArray([4.5] * 6))
    refused(layer, BODY, "faceVertexCounts")


def test_st_and_normals_counts_match_their_interpolation(layer):
    override(layer, BODY, "primvars:st", T.TexCoord2fArray, Vt.Vec2fArray([(0, 0)] * 23))
    refused(layer, BODY, "primvars:st")


def test_normals_count_matches_interpolation(layer):
    override(layer, BODY, "normals", T.Normal3fArray, Vt.Vec3fArray([(0, 0, 1)] * 5))
    refused(layer, BODY, "normals")


def test_points_beyond_the_bound_are_refused(layer):
    override(layer, BODY, "points", T.Point3fArray, Vt.Vec3fArray([(0, 0, 0)] * 23 + [(1e30, 0, 0)]))
    refused(layer, BODY, "points")


def test_a_mesh_beyond_the_point_budget_is_refused(layer, monkeypatch):
    # A 2 GB mesh is refused by the same check: the bound is lowered here, not the mesh made huge.
    monkeypatch.setattr(reader_bounds, "MAX_MESH_POINTS", 10)
    refused(layer, "points", "at most 10")


# ----------------------------------------------------------------------------- hierarchy

def _nest(layer, under: str, depth: int) -> None:
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    path = Sdf.Path(under)
    for i in range(depth):
        path = path.AppendChild(f"N{i}")
    Sdf.CreatePrimInLayer(sdf, path)
    while path != Sdf.Path(under):
        spec = sdf.GetPrimAtPath(path)
        spec.specifier, spec.typeName = Sdf.SpecifierDef, "Xform"
        path = path.GetParentPath()
    sdf.Save()


def test_deep_nesting_is_refused_before_the_slow_part(layer):
    _nest(layer, "/World/Station", reader_bounds.MAX_DEPTH + 10)
    refused(layer, "nested", str(reader_bounds.MAX_DEPTH))


def test_nesting_within_the_bound_reads(layer):
    _nest(layer, "/World/Station", reader_bounds.MAX_DEPTH - 10)
    assert read_scene(layer).meshes


def test_too_many_prims_is_refused(layer, monkeypatch):
    monkeypatch.setattr(reader_bounds, "MAX_PRIMS", 20)
    refused(layer, "prims", "20")


def test_world_matrix_checks_each_ancestor_once(layer):
    """The ancestor walk stops at prims already checked (it was quadratic in the nesting depth)."""
    from pxr import Usd, UsdGeom

    _nest(layer, "/World/Station", 50)
    stage = Usd.Stage.Open(str(layer))
    deep = [p for p in stage.Traverse() if p.GetName().startswith("N") and p.GetPath().HasPrefix("/World/Station")]
    cache, checked = UsdGeom.XformCache(), set()
    visits = []
    original = reader_bounds._check_op_values

    def counting(prim):
        visits.append(prim.GetPath())
        original(prim)
    reader_bounds._check_op_values = counting
    try:
        for p in deep:
            reader_bounds.world_matrix(cache, p, checked=checked)
    finally:
        reader_bounds._check_op_values = original
    assert len(visits) == len(set(visits)) == len(deep) + 2  # + /World/Station and /World


# ----------------------------------------------------------------------------- stage

@pytest.mark.parametrize("default", [None, "Nope", "Render"])
def test_missing_or_wrong_default_prim_is_a_layer_error(layer, default):
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    if default is None:
        sdf.ClearDefaultPrim()
    else:
        sdf.defaultPrim = default
    sdf.Save()
    refused(layer, "defaultPrim")


# ----------------------------------------------------------------------------- render settings

@pytest.mark.parametrize("name,type_name,value", [
    ("allo:render:seed", T.Int, -1), ("allo:render:seed", T.Int64, 2 ** 31),
    ("allo:render:threads", T.Int, 2000),
])
def test_render_settings_within_blenders_limits(layer, name, type_name, value):
    override(layer, SETTINGS, name, type_name, value)
    refused(layer, name)


@pytest.mark.parametrize("name,type_name,value,needle", [
    ("allo:render:targetPsnr", T.Float, float("nan"), "nan is outside 0..100"),
    ("allo:render:targetPsnr", T.Float, -1.0, "-1 is outside 0..100"),
    ("allo:render:targetPsnr", T.Float, 1e9, "1e+09 is outside 0..100"),
    ("allo:render:targetPsnr", T.Float, float("inf"), "inf is outside 0..100"),
    ("allo:render:targetPsnr", T.String, "forty dB, please", "is not a number (a str)"),
    ("allo:render:targetPsnr", T.Bool, True, "is not a number (a bool)"),
    ("allo:render:timeLimit", T.Float, float("nan"), "nan is outside 0..1e+06"),
    ("allo:render:timeLimit", T.Float, -5.0, "-5 is outside 0..1e+06"),
    ("allo:render:timeLimit", T.Double, 1e9, "1e+09 is outside 0..1e+06"),
    ("allo:render:timeLimit", T.String, "an hour", "is not a number (a str)"),
])
def test_a_hostile_target_or_time_limit_is_one_line_naming_the_attribute(layer, name, type_name, value, needle):
    override(layer, SETTINGS, "allo:render:targetPsnr", T.Float, 40.0)   # a valid target beside the time limit
    override(layer, SETTINGS, name, type_name, value)
    message = refused(layer, name, needle, "fix the layer")
    assert "\n" not in message and "please" not in message and "hour" not in message   # never quotes the file


def test_a_time_limit_without_a_target_is_refused_and_a_valid_target_reads(layer):
    override(layer, SETTINGS, "allo:render:timeLimit", T.Float, 60.0)
    refused(layer, "allo:render:timeLimit is authored without allo:render:targetPsnr")
    override(layer, SETTINGS, "allo:render:targetPsnr", T.Float, 40.0)
    render = read_scene(layer).render
    assert (render.target_psnr, render.time_limit) == (40.0, 60.0)


def test_a_layer_without_a_target_reads_as_fixed_samples(layer):
    render = read_scene(layer).render
    assert (render.target_psnr, render.time_limit) == (0.0, 0.0)


def test_resolution_below_blenders_minimum_is_refused(layer):
    override(layer, SETTINGS, "resolution", T.Int2, Gf.Vec2i(2, 2), uniform=True)
    refused(layer, "resolution")


# ----------------------------------------------------------------------------- the bounds are Blender's

@pytest.mark.bpy
def test_reader_bounds_lie_within_blenders_hard_limits():
    """Every range the reader allows ends inside the hard limits of the bpy RNA property it sets,
    so Blender never clamps a recorded value (read from bpy, not copied by hand)."""
    import math

    import bpy

    def limits(rna_type, name):
        p = rna_type.bl_rna.properties[name]
        return p.hard_min, p.hard_max

    def inside(bounds, rna_type, name, scale=1.0):
        lo, hi = limits(rna_type, name)
        assert lo <= bounds[0] * scale and bounds[1] * scale <= hi, (name, bounds, (lo, hi))

    inside(reader_bounds.LENS_MM, bpy.types.Camera, "lens")
    assert reader_bounds.LENS_MM[0] == limits(bpy.types.Camera, "lens")[0]  # Blender's own minimum: 1 mm
    inside(reader_bounds.SENSOR_MM, bpy.types.Camera, "sensor_width")
    inside(reader_bounds.SENSOR_MM, bpy.types.Camera, "sensor_height")
    inside(reader_bounds.CLIP_M, bpy.types.Camera, "clip_start")
    inside(reader_bounds.CLIP_M, bpy.types.Camera, "clip_end")
    inside(reader_bounds.SUN_ANGLE_DEG, bpy.types.SunLight, "angle", math.pi / 180)
    inside(reader_bounds.SPOT_CONE_DEG, bpy.types.SpotLight, "spot_size", 2 * math.pi / 180)  # a full cone of 2 x half angle
    inside(reader_bounds.SPOT_SOFTNESS, bpy.types.SpotLight, "spot_blend")
    inside(reader_bounds.SPOT_RADIUS_M, bpy.types.SpotLight, "shadow_soft_size")
    for rna in (bpy.types.SunLight, bpy.types.SpotLight):
        inside((0.0, reader_bounds.MAX_COLOUR), rna, "color")
        # the spot's power 4 pi^2 r^2 L, at the largest radius and radiance, is still a finite float32
        inside((0.0, 4 * math.pi ** 2 * reader_bounds.SPOT_RADIUS_M[1] ** 2 * reader_bounds.MAX_LIGHT), rna, "energy")
    cycles = bpy.context.scene.cycles.bl_rna
    render = bpy.context.scene.render.bl_rna

    def inside_of(rna, name, bounds):
        p = rna.properties[name]
        assert p.hard_min <= bounds[0] and bounds[1] <= p.hard_max, (name, bounds, (p.hard_min, p.hard_max))

    inside_of(cycles, "seed", reader_bounds.RENDER_SEED)
    inside_of(cycles, "samples", reader_bounds.RENDER_SAMPLES)
    inside_of(cycles, "max_bounces", reader_bounds.RENDER_BOUNCES)
    inside_of(cycles, "adaptive_threshold", reader_bounds.RENDER_ADAPTIVE)
    inside_of(cycles, "film_exposure", reader_bounds.RENDER_EXPOSURE)
    inside_of(render, "threads", (1, reader_bounds.RENDER_THREADS[1]))  # 0 is AUTO, not a thread count
    inside_of(render, "resolution_x", (MIN_SIDE_PX, MAX_SIDE_PX))
    inside_of(render, "resolution_y", (MIN_SIDE_PX, MAX_SIDE_PX))
    mat = bpy.data.materials.new("bounds")
    try:
        bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
        for socket in ("Metallic", "Roughness"):
            p = bsdf.inputs[socket].bl_rna.properties["default_value"]
            assert (p.hard_min, p.hard_max) == reader_bounds.UNIT_INTERVAL
        for socket in ("Base Color", "Emission Color"):
            p = bsdf.inputs[socket].bl_rna.properties["default_value"]
            assert p.hard_min <= 0.0 and reader_bounds.MAX_COLOUR <= p.hard_max
    finally:
        bpy.data.materials.remove(mat)


# ----------------------------------------------------------------------------- Blender's side

def _garbled_png(path) -> None:
    """A PNG that passes every cheap check (signature, IEND at its end) but whose pixels are garbage."""
    data = bytearray(_png_bytes())
    start = data.index(b"IDAT") + 4
    data[start:start + 16] = b"\x00" * 16
    path.write_bytes(bytes(data))


@pytest.mark.render
def test_a_texture_blender_cannot_decode_fails_the_build(layer, tmp_path):
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.session import Session

    bad = tmp_path / "garbled.png"
    _garbled_png(bad)
    _use_texture(layer, bad)
    desc = read_scene(layer)  # the cheap checks pass: only decoding finds it
    with pytest.raises(LayerError, match="garbled.png.*not an image Blender can decode"):
        build_scene(desc)
    with pytest.raises(LayerError, match="garbled.png"):
        Session().render(desc)


@pytest.mark.render
def test_build_refuses_a_value_blender_would_clamp(layer):
    """A description made without the reader (the Python API) meets the same bounds in the builder."""
    from dataclasses import replace

    import bpy

    from allo_usd.blender.build import build_scene

    desc = read_scene(layer)
    with pytest.raises(LayerError, match=r"focal length \(mm\) = 1e-30 would become 1.0 in Blender"):
        build_scene(replace(desc, camera=replace(desc.camera, focal_length_mm=1e-30)))
    with pytest.raises(LayerError, match="cone"):
        build_scene(replace(desc, spot=replace(desc.spot, cone_angle_deg=120.0)))
    with pytest.raises(LayerError, match="render seed"):
        build_scene(replace(desc, render=replace(desc.render, seed=-5)))
    build_scene(desc)
    assert bpy.context.scene.camera.data.lens == pytest.approx(desc.camera.focal_length_mm)


# ----------------------------------------------------------------------------- inspect

def test_inspect_says_a_foreign_layer_is_not_ours(tmp_path, tiny_base):
    from typer.testing import CliRunner

    from allo_usd.cli import app
    from allo_usd.usd.inspect import describe

    foreign = tmp_path / "foreign.usda"
    foreign.write_text('#usda 1.0\n(\n    defaultPrim = "Thing"\n    metersPerUnit = 1\n    upAxis = "Z"\n)\n\n'
                       'def Xform "Thing"\n{\n    def Cube "Box"\n    {\n    }\n}\n')
    with pytest.raises(LayerError, match=r"foreign.usda is not a scene layer authored by allo-usd: its default prim "
                                         r"/Thing has no AlloSceneAPI"):
        describe(foreign)
    with pytest.raises(LayerError, match="base.usda is not a scene layer authored by allo-usd"):
        describe(tiny_base)  # the base stage is ours, but not a scene
    result = CliRunner().invoke(app, ["inspect", str(foreign)])
    assert result.exit_code != 0 and "None" not in result.output


def test_a_target_beside_lens_glare_is_refused(layer):
    """The target mode denoises after the render, where Blender composites the glare: a layer with both
    would lose its glare, so it is refused in one line naming both attributes and the fix."""
    override(layer, SETTINGS, "allo:render:targetPsnr", T.Float, 40.0)
    override(layer, SETTINGS, "allo:effects:glare", T.Bool, True)
    refused(layer, "allo:render:targetPsnr and allo:effects:glare are both on", "fix: turn lens glare off")
