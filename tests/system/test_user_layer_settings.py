"""Camera and render settings of a layer of one's own over a demo scene (docs/usd/what_renders.md,
camera and render settings): each UsdGeom.Camera / UsdRender attribute is rendered as USD says (its
effect asserted in the image or in what the reader hands Blender) or refused in one line."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from allo_usd.core.errors import LayerError
from tests.support.user_layers import DEMO_ANOMALY, demo_layers, override, render


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    from allo_usd.usd.safety import trees_granted

    layers = demo_layers(tmp_path_factory.mktemp("settings"))
    with trees_granted([layers]):   # the demo's layer folder, as `--tree` grants it
        yield layers


def camera(body: str) -> str:
    return f'over "World"\n{{\n    over "Camera"\n    {{\n{body}\n    }}\n}}\n'


SETTINGS_MARK, RENDER_MARK = "\x00settings\x00", "\x00render\x00"


def settings(body: str) -> str:
    """Lines for /Render/Settings (merged into the override's own `over "Settings"`)."""
    return SETTINGS_MARK + body + SETTINGS_MARK


def render_prims(body: str) -> str:
    """Prim specs under /Render (merged into the override's own `over "Render"`)."""
    return RENDER_MARK + body + RENDER_MARK


def layer(tree, name: str, body: str = "", **kw):
    """override() of the demo's anomalous scene, with settings()/render_prims() parts of `body` put
    into the override's own /Render/Settings and /Render specs."""
    parts = {}
    for mark in (SETTINGS_MARK, RENDER_MARK):
        pieces = body.split(mark)
        body, parts[mark] = "".join(pieces[0::2]), "\n".join(pieces[1::2])
    path = override(tree / f"{DEMO_ANOMALY}.usda", tree.parent / "mine" / f"{name}.usda", body, **kw)
    text = path.read_text()
    text = text.replace('over "Settings"\n    {\n', 'over "Settings"\n    {\n' + parts[SETTINGS_MARK] + "\n", 1)
    text = text.replace('over "Render"\n{\n', 'over "Render"\n{\n' + parts[RENDER_MARK] + "\n", 1)
    path.write_text(text)
    return path


def read(tree, name: str, body: str = "", **kw):
    from allo_usd.usd.read import read_scene

    return read_scene(layer(tree, name, body, **kw))


def refused(tree, name: str, body: str, *words: str, **kw) -> str:
    with pytest.raises(LayerError) as info:
        read(tree, name, body, **kw)
    line = str(info.value)
    assert "\n" not in line and "fix" in line, line
    for w in words:
        assert w in line, (w, line)
    return line


def lens(cam) -> list:
    """A CameraDesc's fields but its matrix."""
    return [getattr(cam, f.name) for f in dataclasses.fields(cam) if f.name != "matrix"]


def same_view(a, b) -> bool:
    """Two renders of one view: their masks agree but for a few edge pixels (each render's own
    sample pattern), their colours on average within 2 levels."""
    return (a.mask != b.mask).mean() < 0.01 and np.abs(a.rgb.astype(float) - b.rgb.astype(float)).mean() < 2


def sharpness(rgb: np.ndarray) -> float:
    g = rgb.astype(float).mean(-1)
    return float(np.abs(np.diff(g, axis=0)).mean() + np.abs(np.diff(g, axis=1)).mean())


def test_honoured_values_reach_the_camera(tree):
    base = read(tree, "plain").camera
    assert (base.f_stop, base.focus_distance_m) == (0.0, 0.0)   # fStop 0: no depth of field
    assert read(tree, "focal", camera("float focalLength = 0.5")).camera.focal_length_mm == pytest.approx(50.0)
    assert read(tree, "clip", camera("float2 clippingRange = (0.5, 1000)")).camera.clip == pytest.approx((0.5, 1000))
    dof = read(tree, "dof", camera("float fStop = 2.8\nfloat focusDistance = 4")).camera
    assert (dof.f_stop, dof.focus_distance_m) == pytest.approx((2.8, 4.0))
    off = read(tree, "dof_off", camera("float fStop = 2.8\nfloat focusDistance = 4") +
               settings("uniform bool disableDepthOfField = 1")).camera
    assert (off.f_stop, off.focus_distance_m) == (0.0, 0.0)


@pytest.mark.parametrize("body", [
    camera('uniform token stereoRole = "left"'), camera("float shutter:open = -0.25\nfloat shutter:close = 0.25"),
    settings("uniform bool instantaneousShutter = 1\nuniform bool disableMotionBlur = 1"),
    settings('uniform token renderingColorSpace = "lin_rec709_scene"'),
    settings('uniform token[] materialBindingPurposes = ["full", ""]'),
], ids=["stereoRole", "shutter", "instantaneousShutter", "renderingColorSpace", "materialBindingPurposes"])
def test_settings_that_change_nothing_in_one_instant_render_as_without(tree, body):
    """A stereo role names which eye this camera is (one image is rendered from it); a shutter
    interval blurs nothing when nothing moves (time samples are refused); lin_rec709_scene and
    ["full", ""] are what the render does anyway."""
    a, b = read(tree, "edit", body).camera, read(tree, "plain").camera
    assert np.array_equal(a.matrix, b.matrix) and lens(a) == lens(b)


def test_aperture_is_conformed_to_the_image_by_the_policy(tree):
    square = "float horizontalAperture = 0.36\nfloat verticalAperture = 0.36"   # 36 x 36 mm for a 96x54 image
    wide = 36 * 96 / 54
    for policy, width in (("expandAperture", wide), ("cropAperture", 36.0), ("adjustApertureWidth", wide),
                          ("adjustApertureHeight", 36.0)):
        cam = read(tree, policy, camera(square) + settings(f'uniform token aspectRatioConformPolicy = "{policy}"')).camera
        assert cam.sensor_width_mm == pytest.approx(width, rel=1e-5), policy
    refused(tree, "pixel", camera(square) + settings('uniform token aspectRatioConformPolicy = "adjustPixelAspectRatio"'),
            "square pixels")
    assert read(tree, "default_policy", camera(square)).camera.sensor_width_mm == pytest.approx(wide, rel=1e-5)


def test_render_settings_prim_path_and_camera_relationship(tree):
    """renderSettingsPrimPath names the settings read; a RenderSettings prim it does not name is not
    read; the settings' camera relationship picks the camera, a user's own included."""
    own = ('def RenderSettings "Mine"\n{\n    uniform int2 resolution = (64, 48)\n'
           '    rel camera = </World/Camera>\n    rel products = </Render/Products/Image>\n}\n')
    named = read(tree, "named", render_prims(own), metadata='    renderSettingsPrimPath = "/Render/Mine"\n')
    assert named.render.resolution == (64, 48)
    assert read(tree, "unnamed", render_prims(own)).render.resolution == (96, 54)
    refused(tree, "not_settings", "", "not a RenderSettings prim", metadata='    renderSettingsPrimPath = "/World"\n')
    base = read(tree, "plain").camera
    mine = read(tree, "my_camera", _own_camera(base, focal=0.5) + settings("rel camera = </World/MyCamera>")).camera
    assert mine.path == "/World/MyCamera" and mine.focal_length_mm == pytest.approx(50.0)
    assert np.allclose(mine.matrix, base.matrix)


def demo_exposure(tree) -> float:
    from pxr import Usd

    stage = Usd.Stage.Open(str(tree / f"{DEMO_ANOMALY}.usda"))
    return stage.GetPrimAtPath("/World/Camera").GetAttribute("exposure").Get()


def _own_camera(base, focal: float, exposure: float = 0.0) -> str:
    """A camera of one's own at `base`'s place with its aperture, at `focal` (tenths of a scene
    unit) and `exposure` (EV)."""
    m = np.asarray(base.matrix, dtype=float)   # column vectors: USD's row-vector matrix is its transpose
    rows = ", ".join("(" + ", ".join(f"{v:.17g}" for v in row) + ")" for row in m.T)
    return (f'over "World"\n{{\n    def Camera "MyCamera"\n    {{\n        float focalLength = {focal}\n'
            f'        float exposure = {exposure!r}\n'
            f'        float horizontalAperture = {base.sensor_width_mm / 100}\n'
            f'        float verticalAperture = {base.sensor_height_mm / 100}\n'
            f'        float2 clippingRange = ({base.clip[0]}, {base.clip[1]})\n'
            f'        matrix4d xformOp:transform = ({rows})\n'
            f'        uniform token[] xformOpOrder = ["xformOp:transform"]\n    }}\n}}\n')


REFUSED = {
    "orthographic": (camera('token projection = "orthographic"'), "perspective cameras only"),
    "clippingPlanes": (camera("float4[] clippingPlanes = [(0, 0, 1, 0)]"), "clippingPlanes"),
    "stereoRole": (camera('uniform token stereoRole = "both"'), "stereoRole"),
    "fStop_without_focus": (camera("float fStop = 2"), "focusDistance"),
    "time_samples": (camera("double3 xformOp:translate.timeSamples = {0: (0, 0, 0), 1: (1, 0, 0)}"),
                     "time samples", "default time code"),
    "pixelAspectRatio": (settings("uniform float pixelAspectRatio = 2"), "square pixels"),
    "dataWindowNDC": (settings("uniform float4 dataWindowNDC = (0, 0, 0.5, 0.5)"), "whole image"),
    "materialBindingPurposes": (settings('uniform token[] materialBindingPurposes = ["preview"]'),
                                "materialBindingPurposes"),
    "renderingColorSpace": (settings('uniform token renderingColorSpace = "srgb_rec709_scene"'), "linear Rec.709"),
    "two_cameras": (settings("rel camera = [</World/Camera>, </World/Camera/InspectionLight>]"), "one camera"),
    "second_product": (render_prims('over "Products"\n{\n    def RenderProduct "Other"\n    {\n    }\n}\n') + settings("rel products = [</Render/Products/Image>, "
                                                             "</Render/Products/Other>]"), "one, /Render/Products/Image"),
    "productName": (render_prims('over "Products"\n{\n    over "Image"\n    {\n        token productName = "beauty"\n'
                                 '    }\n}\n'), "productName"),
    "product_resolution": (render_prims('over "Products"\n{\n    over "Image"\n    {\n'
                                        '        uniform int2 resolution = (10, 10)\n    }\n}\n'), "for itself"),
    "unknown_var": (render_prims('over "Vars"\n{\n    def RenderVar "Albedo"\n    {\n    }\n}\n'
                                 'over "Products"\n{\n    over "Image"\n    {\n'
                                 '        rel orderedVars = [</Render/Vars/Color>, </Render/Vars/Albedo>]\n    }\n}\n'),
                    "does not write"),
    "var_sourceName": (render_prims('over "Vars"\n{\n    over "Color"\n    {\n        uniform string sourceName = "normal"\n'
                                    '    }\n}\n'), "sourceName"),
}


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_refused_in_one_line(tree, name):
    body, *words = REFUSED[name]
    refused(tree, name, body, *words)


@pytest.mark.render
def test_depth_of_field_and_conformed_aperture_in_the_image(tree, tmp_path):
    plain = render(layer(tree, "r_plain"), tmp_path / "plain")
    dof = render(layer(tree, "r_dof", camera("float fStop = 1.4\nfloat focusDistance = 0.3")),
                 tmp_path / "dof")
    # the lens focused 0.3 m away at f/1.4: the station metres away is blurred (measured ~0.4x the edges)
    assert sharpness(dof.rgb) < 0.7 * sharpness(plain.rgb), (sharpness(dof.rgb), sharpness(plain.rgb))
    # the mask is of what the lens' rays hit: the same objects, its edges spread by the blur
    assert 0 < (dof.mask != plain.mask).mean() < 0.1 and set(np.unique(dof.mask)) == set(np.unique(plain.mask))
    # a square aperture expanded to the 16:9 image renders as the 64 x 36 mm aperture it becomes
    square = render(layer(tree, "r_square",
                             camera("float horizontalAperture = 0.36\nfloat verticalAperture = 0.36")), tmp_path / "sq")
    wide = render(layer(tree, "r_wide",
                           camera(f"float horizontalAperture = {0.36 * 96 / 54!r}\nfloat verticalAperture = 0.36")),
                  tmp_path / "wide")
    assert same_view(square, wide)
    assert (square.mask != plain.mask).mean() > 0.05   # and it is another view than 36 mm wide


@pytest.mark.render
def test_a_users_own_camera_renders_from_it(tree, tmp_path):
    """The settings' camera relationship to a camera of one's own renders from that camera: the
    same image as the scene's camera given the same lens."""
    from allo_usd.usd.read import read_scene

    base = read_scene(layer(tree, "c_plain")).camera
    own = render(layer(tree, "c_own", _own_camera(base, 0.5, demo_exposure(tree)) +
                          settings("rel camera = </World/MyCamera>")), tmp_path / "own")
    zoomed = render(layer(tree, "c_zoom", camera("float focalLength = 0.5")), tmp_path / "zoom")
    assert same_view(own, zoomed)
    assert (own.mask != render(layer(tree, "c_plain"), tmp_path / "plain").mask).mean() > 0.05


# A fresh Blender: USD-import a layer into an empty factory scene; report each camera's lens and depth of field.
CAMERA_PROBE = r"""
import bpy, json, sys
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=sys.argv[1])
print("PROBE " + json.dumps({o.name: {"lens": o.data.lens, "dof": o.data.dof.use_dof,
                                      "fstop": o.data.dof.aperture_fstop, "focus": o.data.dof.focus_distance}
                             for o in bpy.context.scene.objects if o.type == "CAMERA"}))
"""


@pytest.mark.process
@pytest.mark.bpy
@pytest.mark.parametrize("row", ["own_camera", "depth_of_field"])
def test_blenders_importer_shows_it_too(tree, row):
    """Blender's own USD importer, the outside client, shows the rendered camera rows: a camera of
    one's own is a camera object with its lens; fStop and focusDistance are its depth of field."""
    import json
    import subprocess
    import sys

    from allo_usd.usd.read import read_scene

    base = read_scene(layer(tree, "i_plain")).camera
    body = (_own_camera(base, 0.5) if row == "own_camera" else camera("float fStop = 1.4\nfloat focusDistance = 0.3"))
    path = layer(tree, f"i_{row}", body)
    r = subprocess.run([sys.executable, "-c", CAMERA_PROBE, str(path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    cams = json.loads(r.stdout.split("PROBE ", 1)[1].splitlines()[0])
    if row == "own_camera":
        assert cams["MyCamera"]["lens"] == pytest.approx(50.0, rel=1e-4), cams
    else:
        assert cams["Camera"]["dof"] and cams["Camera"]["fstop"] == pytest.approx(1.4, rel=1e-4), cams
        assert cams["Camera"]["focus"] == pytest.approx(0.3, rel=1e-4), cams


def test_a_full_purpose_binding_is_the_one_rendered(tree):
    """materialBindingPurposes ["full", ""] (the fallback): a mesh's full-purpose binding wins over
    its all-purpose one (UsdShade ComputeBoundMaterial("full"))."""
    plain = read(tree, "plain")
    mesh = next(m for m in plain.meshes if m.material)
    parts = mesh.path.strip("/").split("/")
    opening = "".join(f'{"    " * i}over "{p}"\n{"    " * i}{{\n' for i, p in enumerate(parts[:-1]))
    inner = "    " * (len(parts) - 1)
    closing = "".join(f'{"    " * i}}}\n' for i in reversed(range(len(parts) - 1)))
    body = (opening + f'{inner}over "{parts[-1]}" (\n{inner}    prepend apiSchemas = ["MaterialBindingAPI"]\n{inner})\n'
            f'{inner}{{\n{inner}    rel material:binding:full = </MyRed>\n{inner}}}\n' + closing +
            'def Material "MyRed"\n{\n    token outputs:surface.connect = </MyRed/Surface.outputs:surface>\n'
            '    def Shader "Surface"\n    {\n        uniform token info:id = "UsdPreviewSurface"\n'
            '        color3f inputs:diffuseColor = (0.8, 0.05, 0.05)\n        token outputs:surface\n    }\n}\n')
    red = read(tree, "full_binding", body)
    assert {m.path: m.material for m in red.meshes}[mesh.path] == "/MyRed"
    assert mesh.material != "/MyRed"
