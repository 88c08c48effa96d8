"""Opening a scene in outside tools, and in Blender.

Outside tools: a composed scene offers exactly one camera, the one that renders it (/World/Camera). The
base stage's 50 rig poses are Xforms with AlloCameraPoseAPI (which records their lens), not
UsdGeom.Camera prims, so usdview's camera menu (every UsdGeom.Camera on the stage) and Blender's
importer (`bpy.ops.wm.usd_import`, one camera object per UsdGeom.Camera) see one camera (with the
rig as cameras the importer would make 51).

The importer tests also measure what the importer leaves behind (README "Other USD tools"): it
sets no active camera and reads none of the layer's render settings, so the resolution, engine,
view transform and exposure stay Blender's defaults.

Blender: `allo-usd render LAYER --save-blend FILE` is the faithful route to a .blend. A fresh Python
process with bpy opens the file, renders it without changing anything, and gets the project's image:
the render's linear values, rounded to half, are the project's EXR bit for bit, and the project's
own 8-bit encoding of them is its PNG byte for byte. The PNG Blender itself writes from that
render (the .blend's output format: 8-bit PNG, Standard view transform) differs by at most one
level, and only where the exact sRGB value lies within 0.01 level of a rounding boundary: Blender's
OpenColorIO sRGB transform is not rounded exactly as the project's threshold table
(allo_usd.output.writers.linear_to_srgb8). Measured: 2 of 6,912 values in the glare scene below,
none in the plain one.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from allo_usd.usd import layout

# A fresh Blender: USD-import a layer into the factory startup scene, emptied ("empty") or as a user
# gets it (its Cube, Light and Camera, that camera active), and report what the importer left behind.
IMPORT_PROBE = r"""
import bpy, json, sys

def probe(layer, empty):
    bpy.ops.wm.read_factory_settings(use_empty=empty)
    before = {o.name for o in bpy.context.scene.objects}
    result = bpy.ops.wm.usd_import(filepath=layer)
    s = bpy.context.scene
    return {"result": sorted(result),
            "cameras": sorted(o.name for o in s.objects if o.type == "CAMERA" and o.name not in before),
            "active": s.camera.name if s.camera else None,
            "resolution": [s.render.resolution_x, s.render.resolution_y, s.render.resolution_percentage],
            "engine": s.render.engine, "view_transform": s.view_settings.view_transform,
            "view_exposure": s.view_settings.exposure, "film_exposure": s.cycles.film_exposure}

print("PROBE " + json.dumps({"empty": probe(sys.argv[1], True), "startup": probe(sys.argv[1], False)}))
"""

# A fresh Blender: open a saved .blend and render it untouched. The Render Result is then saved twice:
# in the .blend's own output format (what F12 and "Save As" give), and as 32-bit linear EXR (only the
# file format of the save changes, after the render; nothing the render used).
RENDER_PROBE = r"""
import bpy, sys
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
assert "FINISHED" in bpy.ops.render.render()
result = bpy.data.images["Render Result"]
result.save_render(sys.argv[2])
settings = bpy.context.scene.render.image_settings
settings.file_format, settings.color_depth, settings.color_mode = "OPEN_EXR", "32", "RGB"
result.save_render(sys.argv[3])
"""


def _python(code: str, *args) -> str:
    r = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout


@pytest.fixture(scope="module")
def demo_layer(tmp_path_factory) -> Path:
    """The demo plan's first scene layer, over its tree's byte copy of the committed base stage."""
    from allo_usd.plan.model import demo_plan
    from allo_usd.run.author import author

    out = tmp_path_factory.mktemp("blender_import") / "tree"
    tree = author(demo_plan(), out, limit=1, progress=False, workers=1)
    return tree.paths[0]


def test_composed_scene_offers_one_camera(demo_layer):
    """usdview's camera menu lists every UsdGeom.Camera of the composed stage: only /World/Camera. The
    rig's 50 poses are there, as Xforms that record their lens."""
    from pxr import Usd, UsdGeom

    from allo_usd.core.camera_model import DEFAULT_CAMERA
    from allo_usd.usd import read, stage_geometry

    stage = read.open_stage(demo_layer)
    cameras = [str(p.GetPath()) for p in Usd.PrimRange(stage.GetPseudoRoot()) if p.IsA(UsdGeom.Camera)]
    assert cameras == [layout.CAMERA]
    rig = stage.GetPrimAtPath(layout.RIG).GetChildren()
    assert len(rig) == 50 and all(p.IsA(UsdGeom.Xform) and p.HasAPI("AlloCameraPoseAPI") for p in rig)
    base = demo_layer.parents[3] / "stages" / "base.usda"
    assert [p.index for p in stage_geometry.read_rig(base)] == list(range(1, 51))
    assert stage_geometry.read_rig_lens(base) == DEFAULT_CAMERA   # the lens the rig's views were chosen through (Table I)


def test_blenders_importer_brings_in_one_camera(demo_layer):
    """Blender's own importer on a composed scene layer creates exactly one camera object, the render
    camera. It makes none active: an empty scene then has no camera ("Cannot render, no camera"), and
    the startup scene keeps its own Camera active (the imported one is "Camera.001"). It reads none of
    the layer's render settings: resolution, engine, view transform and exposure stay Blender's
    defaults (README "Other USD tools" says so; update it if this changes)."""
    got = json.loads(_python(IMPORT_PROBE, demo_layer).split("PROBE ", 1)[1])
    name = layout.CAMERA.rsplit("/", 1)[1]
    empty, startup = got["empty"], got["startup"]
    assert empty["result"] == ["FINISHED"] and empty["cameras"] == [name], empty
    assert empty["active"] is None, empty
    assert startup["cameras"] == [f"{name}.001"] and startup["active"] == name, startup
    for left in (empty, startup):   # the layer asks for 480x270, Cycles, Standard, exposure -8.911 EV
        assert left["resolution"] == [1920, 1080, 100], left
        assert left["engine"] == "BLENDER_EEVEE" and left["view_transform"] == "AgX", left
        assert left["view_exposure"] == 0.0 and left["film_exposure"] == 1.0, left


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.parts[0].channels
        return np.stack([np.asarray(ch[c].pixels) for c in "RGB"], axis=-1)


@pytest.mark.render
@pytest.mark.parametrize("case", ["plain", "glare_denoised"])
def test_saved_blend_renders_the_projects_image(tiny_base, tmp_path, case):
    """`allo-usd render LAYER --save-blend FILE`; a fresh bpy opens FILE and renders it untouched: the
    same linear image as the project's render (EXR bit for bit), the same PNG through the project's
    encoding, and Blender's own PNG within one level, only at rounding boundaries (module doc)."""
    import dataclasses

    from PIL import Image

    from allo_usd.output.writers import linear_to_srgb8
    from allo_usd.plan.settings import EffectsSpec
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    spec = make_spec(anomaly=True, samples=2 if case == "plain" else 4)
    if case == "glare_denoised":   # the compositor (Glare node) and OIDN are in the .blend too
        spec = dataclasses.replace(spec, render=dataclasses.replace(spec.render, denoise=True),
                                   effects=EffectsSpec(glare=True))
    layer = write_scene_layer(spec, tmp_path / "layers" / "s.usda", tiny_base)
    blend, out = tmp_path / "s.blend", tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "allo_usd.cli", "render", str(layer), "--out", str(out),
                        "--save-blend", str(blend)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    own_png, linear = tmp_path / "fresh.png", tmp_path / "fresh.exr"
    _python(RENDER_PROBE, blend, own_png, linear)

    fresh = _read_exr(linear)
    project_exr, project_png = _read_exr(out / "s.exr"), np.asarray(Image.open(out / "s.png"))
    assert fresh.shape == (36, 64, 3) and fresh.dtype == np.float32
    assert np.array_equal(fresh.astype(np.float16), project_exr)       # the same render, bit for bit
    assert np.array_equal(linear_to_srgb8(fresh), project_png)          # so the same PNG, byte for byte
    blender_png = np.asarray(Image.open(own_png))
    assert blender_png.shape == (36, 64, 4) and (blender_png[..., 3] == 255).all()   # RGBA, opaque
    diff = np.abs(blender_png[..., :3].astype(int) - project_png.astype(int))
    assert diff.max() <= 1, diff.max()
    if diff.any():   # only where the exact value sits on a rounding boundary (within 0.01 level)
        c = np.clip(fresh[diff > 0].astype(np.float64), 0.0, 1.0)
        level = 255 * np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)   # IEC 61966-2-1
        assert np.abs(level - np.floor(level) - 0.5).max() < 0.01, level


def test_rig_records_the_lens_its_views_were_chosen_through(tmp_path):
    """A rig written with another lens (a model-built stage scored through a plan's camera) records it on
    every pose, principal-point offset included, and read_rig_lens gives it back (to float32 precision)."""
    from pxr import Usd, UsdGeom

    from allo_usd.core.camera_model import CameraModel
    from allo_usd.core.geometry import look_at
    from allo_usd.scene.spec import CameraPose
    from allo_usd.usd import schema
    from allo_usd.usd.base_stage import define_rig
    from allo_usd.usd.stage_geometry import read_rig, read_rig_lens

    schema.register()
    lens = CameraModel(50.0, 24.0, 13.5, (0.5, 1e9), (6.0, -4.0))
    poses = [CameraPose(i, "train", np.array([10.0, i, 2.0]), look_at(np.array([10.0, i, 2.0]), [0, 0, 0]))
             for i in (1, 2)]
    stage = Usd.Stage.CreateNew(str(tmp_path / "rig.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    define_rig(stage, poses, lens, (640, 360))
    stage.GetRootLayer().Save()
    assert [p.index for p in read_rig(tmp_path / "rig.usda")] == [1, 2]
    got = read_rig_lens(tmp_path / "rig.usda", 640)
    assert got.focal_length_mm == 50.0 and (got.sensor_width_mm, got.sensor_height_mm) == (24.0, 13.5)
    assert got.clipping_range_m == (0.5, 1e9)
    assert got.principal_point_offset_px == pytest.approx((6.0, -4.0), rel=1e-6)
