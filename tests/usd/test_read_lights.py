"""The reader's lights (allo_usd.usd.read_lights): every UsdLux light type Cycles can show, read with the
units UsdLux defines and each added to the others; everything else refused in one line naming the prim."""

from __future__ import annotations

import math

import numpy as np
import pytest

from allo_usd.core.errors import LayerError
from allo_usd.usd.description import AreaDesc, CylinderDesc, LampRays, SpotDesc
from allo_usd.usd.layout import INSPECTION_LIGHT
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec
from tests.support.user_layers import override


@pytest.fixture(scope="module")
def scene(tiny_base, tmp_path_factory):
    return write_scene_layer(make_spec(), tmp_path_factory.mktemp("lights") / "scene.usda", tiny_base)


def light(kind: str, name: str, *props: str, apis: str = "", parent: str = "") -> str:
    """usda text: a light `kind` named `name` (under `parent`) with `props`, for inside `over "World"`."""
    meta = f' (\n prepend apiSchemas = [{apis}]\n )' if apis else ""
    body = f'def {kind} "{name}"{meta}\n{{\n' + "\n".join(props) + "\n}"
    if parent:
        body = f'over "{parent}"\n{{\n{body}\n}}'
    return body + "\n"


def read(scene, tmp_path, *bodies: str, settings: str = ""):
    layer = override(scene, tmp_path / "mine.usda", 'over "World"\n{\n' + "\n".join(bodies) + "\n}\n")
    if settings:
        layer.write_text(layer.read_text().replace("int allo:render:samples", settings + "\n        int allo:render:samples"))
    return read_scene(layer)


def refused(scene, tmp_path, *bodies: str) -> str:
    with pytest.raises(LayerError) as exc:
        read(scene, tmp_path, *bodies)
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_a_second_sphere_light_is_added_and_keeps_the_inspection_spot(scene, tmp_path):
    desc = read(scene, tmp_path, light("SphereLight", "Lamp", "float inputs:radius = 0.2",
                                       "float inputs:intensity = 1000", "float inputs:exposure = 1"))
    assert desc.spot is not None and desc.spot.path == INSPECTION_LIGHT and desc.spot.shaped
    (lamp,) = desc.lights
    assert isinstance(lamp, SpotDesc) and lamp.path == "/World/Lamp" and not lamp.shaped
    assert lamp.intensity == pytest.approx(2000.0) and lamp.radius == pytest.approx(0.2)
    assert lamp.link is None and lamp.rays is None


def test_the_inspection_switch_turns_off_only_the_inspection_light(scene, tmp_path):
    off = "bool allo:effects:inspectionLight = false"
    desc = read(scene, tmp_path, light("SphereLight", "Lamp", "float inputs:intensity = 10"), settings=off)
    assert desc.spot is None and [x.path for x in desc.lights] == ["/World/Lamp"]


def test_a_disk_light_is_an_area_lamp_of_its_power(scene, tmp_path):
    r, L = 0.3, 500.0
    desc = read(scene, tmp_path, light("DiskLight", "Disk", f"float inputs:radius = {r}", f"float inputs:intensity = {L}"),
                light("DiskLight", "Normal", f"float inputs:radius = {r}", f"float inputs:intensity = {L}",
                      "bool inputs:normalize = true"))
    disk, normal = desc.lights
    assert isinstance(disk, AreaDesc) and disk.shape == "DISK" and disk.size == pytest.approx((2 * r, 2 * r))
    assert disk.power == pytest.approx(L * math.pi * r ** 2 * math.pi, rel=1e-6)  # radiance x area x pi
    assert normal.radiance == pytest.approx(L / (math.pi * r ** 2), rel=1e-6)
    assert normal.power == pytest.approx(L * math.pi, rel=1e-6)


def test_a_rect_light_counts_its_world_space_area(scene, tmp_path):
    desc = read(scene, tmp_path, light("RectLight", "Panel", "float inputs:width = 2", "float inputs:height = 0.5",
                                       "float inputs:intensity = 100", "double3 xformOp:scale = (2, 3, 1)",
                                       'uniform token[] xformOpOrder = ["xformOp:scale"]'))
    (rect,) = desc.lights
    assert rect.shape == "RECTANGLE" and rect.size == pytest.approx((2.0, 0.5))
    assert rect.power == pytest.approx(100.0 * (2 * 0.5 * 6) * math.pi, rel=1e-6)


def test_a_cylinder_light_reads_radius_length_and_radiance(scene, tmp_path):
    desc = read(scene, tmp_path, light("CylinderLight", "Tube", "float inputs:radius = 0.1", "float inputs:length = 2",
                                       "float inputs:intensity = 40", "bool inputs:normalize = true"))
    (tube,) = desc.lights
    assert isinstance(tube, CylinderDesc) and (tube.radius, tube.length) == pytest.approx((0.1, 2.0))
    assert tube.radiance == pytest.approx(40.0 / (2 * math.pi * 0.1 * 2.0), rel=1e-6)


def test_a_dome_light_is_the_background_radiance(scene, tmp_path):
    desc = read(scene, tmp_path, light("DomeLight", "Dome", "float inputs:intensity = 3", "float inputs:exposure = 2",
                                       "color3f inputs:color = (0.5, 1, 0.25)"))
    assert desc.dome.strength == pytest.approx(12.0) and desc.dome.color == pytest.approx((0.5, 1.0, 0.25))
    assert desc.lights == ()


def test_colour_temperature_multiplies_the_blackbody_colour(scene, tmp_path):
    from pxr import UsdLux

    desc = read(scene, tmp_path, light("RectLight", "Warm", "float inputs:intensity = 1", "color3f inputs:color = (1, 0.5, 1)",
                                       "bool inputs:enableColorTemperature = true",
                                       "float inputs:colorTemperature = 3000"))
    want = np.array([1.0, 0.5, 1.0]) * np.array(UsdLux.BlackbodyTemperatureAsRgb(3000.0))
    assert desc.lights[0].color == pytest.approx(tuple(want), rel=1e-6)
    assert want[0] > want[2]  # warm


def test_ray_switches_and_shadows(scene, tmp_path):
    desc = read(scene, tmp_path, light("SphereLight", "Lamp", "float inputs:intensity = 1", "float inputs:diffuse = 0",
                                       "bool inputs:shadow:enable = false", apis='"ShadowAPI"'))
    assert desc.lights[0].rays == LampRays(diffuse=False, specular=True, shadow=False)


def test_a_light_that_is_off_is_left_out(scene, tmp_path):
    desc = read(scene, tmp_path, *(light(k, k + "X", "float inputs:intensity = 0")
                                   for k in ("SphereLight", "RectLight", "DiskLight", "CylinderLight", "DomeLight")))
    assert desc.lights == () and desc.dome is None


def test_light_linking_applies_to_every_lamp(scene, tmp_path):
    desc = read(scene, tmp_path, light("DiskLight", "Disk", "float inputs:intensity = 1",
                                       "rel collection:lightLink:includes = </World/Station>",
                                       "uniform bool collection:lightLink:includeRoot = false"))
    (disk,) = desc.lights
    assert disk.link is not None and not disk.link.exclude and disk.link.paths
    assert all(p.startswith("/World/Station") for p in disk.link.paths)


@pytest.mark.parametrize("body, words", [
    (light("PortalLight", "Portal"), "/World/Portal: a PortalLight light is not rendered"),
    (light("GeometryLight", "Geo"), "/World/Geo: a GeometryLight light is not rendered"),
    (light("DomeLight_1", "Dome1"), "/World/Dome1: a DomeLight_1 light is not rendered"),
    (light("DomeLight", "A") + light("DomeLight", "B"), "/World/B: a second DomeLight"),
    (light("SphereLight", "F", "rel light:filters = </World/F>"), "/World/F: light filters"),
    (light("RectLight", "T", "asset inputs:texture:file = @t.png@"), "/World/T: inputs:texture:file on a RectLight"),
    (light("DomeLight", "T", "asset inputs:texture:file = @t.exr@", 'token inputs:texture:format = "mirroredBall"'),
     "/World/T: inputs:texture:format = 'mirroredBall' is not rendered"),
    (light("DomeLight", "M", "asset inputs:texture:file = @missing.exr@"),
     "DomeLight /World/M: texture @missing.exr@ does not resolve to a file"),
    (light("RectLight", "S", "float inputs:shaping:cone:angle = 30", apis='"ShapingAPI"'), "/World/S: ShapingAPI"),
    (light("SphereLight", "S", "float inputs:shaping:focus = 2", apis='"ShapingAPI"'), "/World/S: inputs:shaping:focus"),
    (light("SphereLight", "D", "float inputs:diffuse = 0.5"), "/World/D: inputs:diffuse = 0.5"),
    (light("SphereLight", "C", "color3f inputs:shadow:color = (1, 0, 0)", apis='"ShadowAPI"'),
     "/World/C: inputs:shadow:color"),
    (light("SphereLight", "L", "rel collection:shadowLink:excludes = </World/Station>"),
     "/World/L: collection:shadowLink leaves"),
    (light("DomeLight", "K", "rel collection:lightLink:excludes = </World/Station>"),
     "/World/K: collection:lightLink on a DomeLight"),
    (light("CylinderLight", "Z", "bool inputs:shadow:enable = false", apis='"ShadowAPI"'),
     "/World/Z: inputs:shadow:enable = false on a CylinderLight"),
    (light("RectLight", "E", "bool inputs:enableColorTemperature = true", "float inputs:colorTemperature = 50000"),
     "/World/E.inputs:colorTemperature"),
])
def test_what_cycles_cannot_show_is_refused_in_one_line(scene, tmp_path, body, words):
    assert words in refused(scene, tmp_path, body)
