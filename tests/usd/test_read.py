"""The reader turns a composed stage into plain data, with pxr only."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.core.labels import ANOMALY, STATION
from allo_usd.core.errors import LayerError
from allo_usd.usd.read import read_scene

from tests.support.helpers import EXPOSURE, make_spec


def test_reader_describes_the_scene(tiny_base, tmp_path):
    spec = make_spec(anomaly=True)
    desc = read_scene(write_scene_layer(spec, tmp_path / "s.usda", tiny_base))
    by_path = {m.path: m for m in desc.meshes}
    assert by_path["/World/Station/Geom/Truss"].class_id == STATION
    assert by_path["/World/Sky/Moon/Geom/Surface"].class_id == STATION
    assert by_path["/World/Anomaly/Geom/Body"].class_id == ANOMALY
    assert by_path["/World/Sky/Sun/Geom/Surface"].ray_visibility == "cameraOnly"
    assert by_path["/World/Sky/Moon/Geom/Surface"].ray_visibility == "noShadow"
    assert by_path["/World/Station/Geom/Truss"].ray_visibility == "all"
    np.testing.assert_allclose(by_path["/World/Anomaly/Geom/Body"].matrix[:3, 3], spec.anomaly.position)
    np.testing.assert_allclose(by_path["/World/Sky/Moon/Geom/Surface"].matrix[0, 0], 1.7374e6)
    assert desc.camera.focal_length_mm == pytest.approx(25.0)
    assert desc.camera.sensor_width_mm == pytest.approx(36.0)
    assert desc.sun.irradiance == pytest.approx(1361.0)
    np.testing.assert_allclose(desc.sun.direction, spec.sun.direction, atol=1e-7)
    assert desc.render.resolution == (64, 36) and desc.render.exposure == pytest.approx(EXPOSURE)
    assert desc.render.outputs == ("rgb", "exr", "mask")
    assert desc.meta["seed"] == 7 and desc.meta["anomaly"]["assetVariant"] == "blue"
    blue = desc.materials[by_path["/World/Anomaly/Geom/Body"].material]
    assert blue.base_color[2] > blue.base_color[0]
    moon = desc.materials[by_path["/World/Sky/Moon/Geom/Surface"].material]
    assert moon.base_color_texture and moon.base_color_texture.endswith(".png")


def test_umbra_turns_the_station_sun_off_not_the_bodies_suns(tiny_base, tmp_path):
    from dataclasses import replace

    from allo_usd.scene.spec import SunSpec

    spec = make_spec(sun=SunSpec((0.0, 0.0, 1.0), 0.0, 1361.0, 0.533, 1.5e11, 0.0, "umbra", "moon"))
    desc = read_scene(write_scene_layer(spec, tmp_path / "s.usda", tiny_base))
    assert desc.sun is None
    # A spec without body lamps lights each body with the station's Sun, unoccluded.
    assert [(s.path, s.irradiance) for s in desc.suns] == [("/World/Sky/EarthSunLight", 1361.0),
                                                          ("/World/Sky/MoonSunLight", 1361.0)]
    off = SunSpec((0.0, 1.0, 0.0), 0.0, 1300.0, 0.53, 1.5e11, 0.0, "umbra", "earth")  # a total lunar eclipse
    spec = replace(spec, bodies={**spec.bodies, "Moon": replace(spec.bodies["Moon"], light=off)})
    desc = read_scene(write_scene_layer(spec, tmp_path / "t.usda", tiny_base))
    assert [s.path for s in desc.suns] == ["/World/Sky/EarthSunLight"]


def test_reader_resolves_light_linking_from_the_collections(tiny_base, tmp_path):
    from dataclasses import replace

    from allo_usd.usd.description import LightLink
    from allo_usd.scene.spec import SunSpec

    moon_sun = SunSpec((0.0, 0.6, 0.8), 1300.0, 1370.0, 0.53, 1.49e11, 0.95, "penumbra", "earth")
    spec = make_spec(anomaly=True)
    spec = replace(spec, bodies={**spec.bodies, "Moon": replace(spec.bodies["Moon"], light=moon_sun)})
    layer = write_scene_layer(spec, tmp_path / "s.usda", tiny_base)
    desc = read_scene(layer)
    suns = {s.path: s for s in desc.suns}
    earth, moon = "/World/Sky/Earth/Geom/Surface", "/World/Sky/Moon/Geom/Surface"
    assert list(suns) == ["/World/Sky/SunLight", "/World/Sky/EarthSunLight", "/World/Sky/MoonSunLight"]
    assert suns["/World/Sky/SunLight"].link == LightLink(True, (moon, earth))  # all but the bodies
    assert suns["/World/Sky/EarthSunLight"].link == LightLink(False, (earth,))
    assert suns["/World/Sky/MoonSunLight"].link == LightLink(False, (moon,))
    assert suns["/World/Sky/MoonSunLight"].irradiance == pytest.approx(1300.0)
    np.testing.assert_allclose(suns["/World/Sky/MoonSunLight"].direction, moon_sun.direction, atol=1e-7)
    assert suns["/World/Sky/MoonSunLight"].angle_deg == pytest.approx(0.53)
    # The membership is USD's, not a naming convention: exclude the station from the station's sun
    # and it lights only the Sun's disc and the anomaly.
    from pxr import Sdf, Usd, UsdLux

    stage = Usd.Stage.Open(str(layer))
    UsdLux.LightAPI(stage.GetPrimAtPath("/World/Sky/SunLight")).GetLightLinkCollectionAPI() \
        .GetExcludesRel().AddTarget(Sdf.Path("/World/Station"))
    stage.GetRootLayer().Save()
    link = {s.path: s for s in read_scene(layer).suns}["/World/Sky/SunLight"].link
    assert link == LightLink(False, ("/World/Sky/Sun/Geom/Surface", "/World/Anomaly/Geom/Body"))
    # A lamp whose collection holds nothing lights nothing: it is left out like a lamp that is off.
    UsdLux.LightAPI(stage.GetPrimAtPath("/World/Sky/MoonSunLight")).GetLightLinkCollectionAPI() \
        .GetIncludesRel().SetTargets([])
    stage.GetRootLayer().Save()
    assert "/World/Sky/MoonSunLight" not in {s.path for s in read_scene(layer).suns}


@pytest.mark.process
def test_reader_never_imports_bpy(tiny_base, tmp_path):
    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    code = ("import sys; from allo_usd.usd.read import read_scene; read_scene(sys.argv[1]); "
            "assert 'bpy' not in sys.modules, 'read imported bpy'")
    subprocess.run([sys.executable, "-c", code, str(layer)], check=True)


def test_malformed_layer_gives_clear_error(tmp_path):
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\n( defaultPrim = \"World\"\n over \"World\" {")
    with pytest.raises(LayerError, match="bad.usda"):
        read_scene(bad)
    with pytest.raises(LayerError, match="does not exist"):
        read_scene(tmp_path / "missing.usda")


def test_missing_sublayer_is_named(tiny_base, tmp_path):
    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    text = layer.read_text().replace("base.usda", "gone.usda")
    broken = tmp_path / "broken.usda"
    broken.write_text(text)
    with pytest.raises(LayerError):
        read_scene(broken)


def test_denoiser_settings_round_trip_and_bad_token_is_named(tiny_base, tmp_path):
    from dataclasses import replace

    spec = make_spec()
    spec = replace(spec, render=replace(spec.render, denoise=True, denoise_prefilter="ACCURATE", denoise_quality="HIGH"))
    layer = write_scene_layer(spec, tmp_path / "s.usda", tiny_base)
    render = read_scene(layer).render
    assert (render.denoise_prefilter, render.denoise_quality) == ("ACCURATE", "HIGH")
    layer.write_text(layer.read_text().replace('denoisePrefilter = "ACCURATE"', 'denoisePrefilter = "SHARP"'))
    with pytest.raises(LayerError, match=r"denoisePrefilter = 'SHARP' is not one of NONE, FAST, ACCURATE"):
        read_scene(layer)
