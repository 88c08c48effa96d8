"""A user's own lights over a demo scene (docs/usd/what_renders.md, lights): each UsdLux light type adds
light where it shines, never replacing another; the lights add up in linear EXR; the dome is the
background; the mask and the amodal pass are not changed by lights. Plus Blender's own measurements:
an area lamp's energy radiance x area x pi gives the irradiance a Lambertian emitter gives, and Blender's
USD importer shows each light type as the lamp this renderer makes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.support.user_layers import DEMO_ANOMALY, DEMO_NORMAL, demo_layers, override, render

pytestmark = pytest.mark.render

SAMPLES = 48        # enough that the sums below agree within 2 % (Monte-Carlo noise at 96 x 54)


def lamp(kind: str, name: str, *props: str, apis: str = "") -> str:
    """A light's usda; _render puts it under the camera (its -Z is the view direction), a dome under /World."""
    meta = f' (\n prepend apiSchemas = [{apis}]\n )' if apis else ""
    return f'def {kind} "{name}"{meta}\n{{\n' + "\n".join(props) + "\n}\n"


SPHERE = lamp("SphereLight", "Lamp", "float inputs:radius = 0.05", "float inputs:intensity = 1e7",
              "double3 xformOp:translate = (0, 0.3, 0)", 'uniform token[] xformOpOrder = ["xformOp:translate"]')
RECT = lamp("RectLight", "Panel", "float inputs:width = 0.5", "float inputs:height = 0.5",
            "float inputs:intensity = 4e5", "color3f inputs:color = (1, 0.3, 0.3)")
DISK = lamp("DiskLight", "Disk", "float inputs:radius = 0.3", "float inputs:intensity = 3e5")
CYLINDER = lamp("CylinderLight", "Tube", "float inputs:radius = 0.05", "float inputs:length = 1",
                "float inputs:intensity = 2e6", "double3 xformOp:translate = (0, 0, -1)",
                'uniform token[] xformOpOrder = ["xformOp:translate"]')
DOME_COLOUR, DOME_STRENGTH = (0.2, 0.4, 1.0), 300.0
DOME = 'def DomeLight "Dome"\n{\nfloat inputs:intensity = 300\ncolor3f inputs:color = (0.2, 0.4, 1.0)\n}\n'
NO_INSPECTION = "bool allo:effects:inspectionLight = false"


@pytest.fixture(scope="module")
def layers(tmp_path_factory):
    return demo_layers(tmp_path_factory.mktemp("lights"))


def _exr(rendered) -> np.ndarray:
    from allo_usd.blender.render import read_multilayer_exr

    ch = read_multilayer_exr(rendered.file("exr"))
    return np.stack([next(v for k, v in ch.items() if k.endswith(c)) for c in "RGB"], -1).astype(np.float64)


def _render(layers, name: str, *bodies: str, scene: str = DEMO_NORMAL, settings: str = "", samples: int = 8,
            **options):
    world = "".join(b for b in bodies if b.startswith("def DomeLight"))
    camera = "".join(b for b in bodies if not b.startswith("def DomeLight"))
    layer = override(layers / f"{scene}.usda", layers / f"mine_{name}.usda",
                     f'over "World"\n{{\n{world}over "Camera"\n{{\n{camera}}}\n}}\n', samples=samples)
    if settings:
        layer.write_text(layer.read_text().replace("int allo:render:samples", settings + "\n        int allo:render:samples"))
    return render(layer, layers.parent / "out" / name, **options)


@pytest.fixture(scope="module")
def sums(layers):
    """Linear EXR renders at SAMPLES: the base, each light alone, two lights together, the dome."""
    out = {name: _render(layers, name, *bodies, samples=SAMPLES)
           for name, bodies in (("base", ()), ("sphere", (SPHERE,)), ("rect", (RECT,)), ("disk", (DISK,)),
                                ("cylinder", (CYLINDER,)), ("rect+sphere", (RECT, SPHERE)), ("dome", (DOME,)))}
    return out


@pytest.mark.parametrize("name", ["sphere", "rect", "disk", "cylinder", "dome"])
def test_each_light_adds_light_and_leaves_the_mask(sums, name):
    base, lit = sums["base"], sums[name]
    assert _exr(lit).sum() > 1.05 * _exr(base).sum(), name
    np.testing.assert_array_equal(lit.mask, base.mask)  # a light is never a labelled object
    assert lit.mask.max() == base.mask.max() == 1


def test_the_lights_add_up(sums):
    base = _exr(sums["base"]).sum(axis=(0, 1))
    a, b, ab = ((_exr(sums[k]).sum(axis=(0, 1)) - base) for k in ("rect", "sphere", "rect+sphere"))
    np.testing.assert_allclose(ab, a + b, rtol=0.02)
    assert (a > 0).all() and (b > 0).all()


def test_the_dome_is_the_background_and_lights_the_station(sums):
    lit, base = _exr(sums["dome"]), _exr(sums["base"])
    background = (sums["dome"].mask == 0) & (base.max(axis=-1) < 1e-6)  # black space without it (away from edges)
    assert background.mean() > 0.2
    pixel = lit[background].mean(axis=0)
    np.testing.assert_allclose(pixel / pixel[2], np.array(DOME_COLOUR) / DOME_COLOUR[2], rtol=5e-3)  # its colour (half-float EXR)
    from allo_usd.usd.read import read_scene

    exposure = read_scene(sums["dome"].out.parent.parent / "layers" / "mine_dome.usda").render.exposure
    np.testing.assert_allclose(pixel, np.array(DOME_COLOUR) * DOME_STRENGTH * exposure, rtol=0.01)  # its radiance
    station = sums["dome"].mask == 1
    assert lit[station].sum() > 1.05 * base[station].sum()


def test_a_second_sphere_light_keeps_the_inspection_light(layers, sums):
    from allo_usd.usd.read import read_scene

    desc = read_scene(layers / "mine_sphere.usda")
    assert desc.spot is not None and [x.path for x in desc.lights] == ["/World/Camera/Lamp"]
    off = _render(layers, "off", settings=NO_INSPECTION)
    off_sphere = _render(layers, "off_sphere", SPHERE, settings=NO_INSPECTION)
    assert read_scene(layers / "mine_off_sphere.usda").spot is None
    assert off_sphere.rgb.astype(float).sum() > 1.05 * off.rgb.astype(float).sum()  # the user's lamp still lights


def test_lights_leave_the_amodal_pass(layers):
    passes = ("rgb", "mask", "amodal")
    plain = _render(layers, "amodal_plain", scene=DEMO_ANOMALY, passes=passes)
    lit = _render(layers, "amodal_lit", SPHERE, RECT, CYLINDER, DOME, scene=DEMO_ANOMALY, passes=passes)
    from PIL import Image

    a, b = (np.asarray(Image.open(r.file("amodal"))) for r in (plain, lit))
    assert a.max() == 2
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(plain.mask, lit.mask)


@pytest.mark.parametrize("shape", ["DISK", "RECTANGLE"])
def test_an_area_lamp_gives_the_irradiance_of_a_lambertian_emitter(shape):
    """A one-sided Lambertian emitter of radiance L, on axis at distance d over a white diffuse plane,
    gives it irradiance E = L x its projected solid angle; the plane's radiance is E / pi. Built with
    build.build_area (energy = L x area x pi) and measured in Cycles' linear render."""
    import bpy

    from allo_usd.blender.build import build_area, reset
    from allo_usd.usd.description import AreaDesc

    L, d, half = 10.0, 1.0, 0.3
    reset()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.use_denoising, scene.cycles.max_bounces = 128, False, 0
    scene.render.resolution_x = scene.render.resolution_y = 8
    me = bpy.data.meshes.new("plane")
    me.from_pydata([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], [], [(0, 1, 2, 3)])
    mat = bpy.data.materials.new("white")
    tree = mat.node_tree
    for n in [n for n in tree.nodes if n.type != "OUTPUT_MATERIAL"]:
        tree.nodes.remove(n)
    diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (1, 1, 1, 1)
    tree.links.new(diffuse.outputs[0], next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL").inputs[0])
    me.materials.append(mat)
    scene.collection.objects.link(bpy.data.objects.new("plane", me))
    cam = bpy.data.cameras.new("cam")
    cam.type, cam.ortho_scale = "ORTHO", 0.02
    cam_obj = bpy.data.objects.new("cam", cam)
    cam_obj.location = (0, 0, 0.5)
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    world = bpy.data.worlds.new("black")
    next(n for n in world.node_tree.nodes if n.type == "BACKGROUND").inputs["Strength"].default_value = 0.0
    scene.world = world
    m = np.eye(4)
    m[2, 3] = d  # facing down: the lamp emits along its -Z
    if shape == "DISK":
        area, projected = math.pi * half ** 2, math.pi * half ** 2 / (half ** 2 + d ** 2)
    else:
        x = half / math.sqrt(1 + half ** 2)  # a square 2 half x 2 half: 4 corner rectangles (view factor)
        area, projected = 4 * half ** 2, 4 * 2 * x * math.atan(x) / 2.0
    build_area(AreaDesc("/Lamp", m, shape, (2 * half, 2 * half), L, L * area * math.pi, (1.0, 1.0, 1.0)))
    bpy.ops.render.render()
    result = bpy.data.images["Render Result"]
    viewer = scene.render
    viewer.image_settings.file_format = "OPEN_EXR"
    import tempfile
    from pathlib import Path

    from allo_usd.blender.render import read_multilayer_exr

    path = Path(tempfile.mkdtemp()) / "plane.exr"
    result.save_render(str(path))
    red = next(v for k, v in read_multilayer_exr(path).items() if k.endswith("R"))
    assert float(np.mean(red)) == pytest.approx(L * projected / math.pi, rel=0.01)


def test_blenders_importer_shows_each_light_type(tmp_path):
    """Blender's USD import makes the lamp this renderer makes for each type (a CylinderLight, which
    Blender has no lamp for, becomes its POINT lamp; a DomeLight no object: the known exception)."""
    import bpy

    path = tmp_path / "lights.usda"
    lights = {"Sphere": ("SphereLight", "", ("POINT", None)), "Spot": ("SphereLight", "ShapingAPI", ("SPOT", None)),
              "Rect": ("RectLight", "", ("AREA", "RECTANGLE")), "Disk": ("DiskLight", "", ("AREA", "DISK")),
              "Sun": ("DistantLight", "", ("SUN", None)), "Tube": ("CylinderLight", "", ("POINT", None)),
              "Dome": ("DomeLight", "", None)}
    body = "".join(f'def {kind} "{name}"' + (f' (\nprepend apiSchemas = ["{api}"]\n)' if api else "")
                   + ("\n{\nfloat inputs:shaping:cone:angle = 30\n}\n" if api else "\n{\n}\n")
                   for name, (kind, api, _) in lights.items())
    path.write_text(f'#usda 1.0\n(\nupAxis = "Z"\nmetersPerUnit = 1\n)\ndef Xform "W"\n{{\n{body}}}\n')
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=str(path))
    got = {o.name: (o.data.type, getattr(o.data, "shape", None) if o.data.type == "AREA" else None)
           for o in bpy.context.scene.objects if o.type == "LIGHT"}
    assert got == {name: want for name, (_, _, want) in lights.items() if want is not None}


# A lat-long dome image of 4 x 2 blocks of saturated colours (longitude quarters x hemispheres).
BLOCKS = np.array([[[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]],
                   [[1, 0, 1], [0, 1, 1], [1, 0.5, 0], [0.5, 0, 1]]], dtype=np.float64)


def _spec_block(d_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UsdLux DomeLight's lat-long map (the OpenEXR convention), written out from the spec: pole +Y,
    longitude 0 towards +Z and pi/2 towards +X; the image's left column is longitude +pi, its top row
    latitude +pi/2. (block row, block column) of each dome-frame direction, and its distance in radians
    to the nearest block edge."""
    d = d_local / np.linalg.norm(d_local, axis=-1, keepdims=True)
    lon, lat = np.arctan2(d[..., 0], d[..., 2]), np.arcsin(np.clip(d[..., 1], -1, 1))
    x = (np.pi - lon) / (2 * np.pi) * 4          # block columns of 90 degrees
    y = (np.pi / 2 - lat) / np.pi * 2            # block rows of 90 degrees, top first
    col, row = np.clip(np.floor(x), 0, 3).astype(int), np.clip(np.floor(y), 0, 1).astype(int)
    edge = np.minimum(np.abs(x - np.round(x)) * np.pi / 2 * np.cos(lat), np.abs(y - np.round(y)) * np.pi / 2)
    return np.stack([row, col], -1), edge


def test_a_textured_dome_is_the_lat_long_map_the_spec_describes(layers, tmp_path):
    """Every background pixel shows the block of the dome's image that UsdLux's lat-long convention puts
    in that pixel's direction, with the dome turned by its own rotation (here its pole tipped onto the
    stage's +Z and turned 30 degrees about it)."""
    from PIL import Image

    image = np.kron(BLOCKS, np.ones((16, 16, 1)))          # 64 x 128 pixels, 2:1
    Image.fromarray((image * 255).astype(np.uint8)).save(layers / "dome_blocks.png")
    dome = ('def DomeLight "Dome"\n{\nfloat inputs:intensity = 300\nasset inputs:texture:file = @dome_blocks.png@\n'
            'token inputs:texture:format = "latlong"\ndouble3 xformOp:rotateXYZ = (90, 0, 30)\n'
            'uniform token[] xformOpOrder = ["xformOp:rotateXYZ"]\n}\n')
    lit = _render(layers, "dome_texture", dome, settings=NO_INSPECTION, samples=4)
    rgb = _exr(lit)
    cam = lit.record["annotations"]["camera"]
    k, c2w = np.array(cam["K_px"]), np.linalg.inv(np.array(cam["world_to_cam_opencv"]))
    h, w = lit.mask.shape
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones((h, w))], -1) @ c2w[:3, :3].T
    rx, rz = np.radians(90.0), np.radians(30.0)   # rotateXYZ: X first, then Z (column vectors: Rz @ Rx)
    r_x = np.array([[1, 0, 0], [0, np.cos(rx), -np.sin(rx)], [0, np.sin(rx), np.cos(rx)]])
    r_z = np.array([[np.cos(rz), -np.sin(rz), 0], [np.sin(rz), np.cos(rz), 0], [0, 0, 1]])
    block, edge = _spec_block(rays @ (r_z @ r_x))        # world -> dome frame: R^T d, as rows: d @ R
    space = lit.mask == 0
    for _ in range(3):   # 3 pixels clear of the station: its edge pixels blend in through the pixel filter
        space = space & np.roll(space, 1, 0) & np.roll(space, -1, 0) & np.roll(space, 1, 1) & np.roll(space, -1, 1)
    sky = space & (edge > np.radians(3))
    assert sky.sum() > 200 and len({tuple(b) for b in block[sky]}) >= 2   # at least two blocks in view
    want = BLOCKS[block[sky][:, 0], block[sky][:, 1]]
    got = rgb[sky] / rgb[sky].max(axis=-1, keepdims=True)
    srgb_want = np.where(want > 0, want, 0)             # 0, 0.5 and 1 in sRGB: 0.5 is 0.214 linear
    srgb_want = np.where(np.isclose(srgb_want, 0.5), 0.2140, srgb_want)
    np.testing.assert_allclose(got, srgb_want, atol=0.05)


def test_a_lamp_without_diffuse_and_specular_adds_no_light(layers, sums):
    """inputs:diffuse = 0 and inputs:specular = 0 (UsdLux multipliers) turn off the lamp's diffuse and
    glossy contributions: what it adds to the station is gone, within Monte-Carlo noise."""
    off = lamp("RectLight", "Panel", "float inputs:width = 0.5", "float inputs:height = 0.5",
               "float inputs:intensity = 4e5", "color3f inputs:color = (1, 0.3, 0.3)", "float inputs:diffuse = 0",
               "float inputs:specular = 0")
    dark = _exr(_render(layers, "rect_off", off, samples=SAMPLES))
    base, lit = _exr(sums["base"]), _exr(sums["rect"])
    station = sums["base"].mask == 1
    added = lit[station].sum() - base[station].sum()
    assert added > 0.05 * base[station].sum()
    assert abs(dark[station].sum() - base[station].sum()) < 0.02 * added + 0.01 * base[station].sum()
