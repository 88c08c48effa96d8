"""A scene layer means to a spec-following USD tool what it means to this project's Cycles.

Each test reads the authored attributes with plain pxr and applies the standard's definition
(UsdLux for lights, UsdGeom.Camera for exposure), then checks that the reader and Blender agree:
- a sun DistantLight authors inputs:normalize = true, so its intensity is the irradiance (W/m^2);
- an un-normalised DistantLight means radiance: irradiance = intensity x 2^exposure x pi sin^2(angle/2);
- the inspection SphereLight's intensity is its surface radiance; its power 4 pi^2 r^2 L is Blender's;
- the film exposure is UsdGeom.Camera's linear exposure scale, and editing fStop/time/iso changes the
  rendered brightness by exactly the standard factor;
- the Sun's disc is the station's DistantLight (drawn in camera rays), the Sun's sphere only a
  transparent mask label (class 1);
- light linking appears only on eclipse days.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdShade

from allo_usd.core.constants import SOLAR_CONSTANT
from allo_usd.core.geometry import look_at
from allo_usd.scene.spec import CameraSpec
from allo_usd.usd.read import read_scene
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import EXPOSURE, make_spec

SUN = "/World/Sky/SunLight"
SPOT = "/World/Camera/InspectionLight"
CAMERA = "/World/Camera"
UMBRA_DAY = 269          # 2030-09-27: the station in the Moon's umbra, the Earth sunlit


def _override(layer, prim_path: str, name: str, type_name, value) -> None:
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    spec = Sdf.CreatePrimInLayer(sdf, prim_path)
    old = spec.attributes.get(name)
    if old is not None:
        spec.RemoveProperty(old)
    Sdf.AttributeSpec(spec, name, type_name).default = value
    sdf.Save()


def _spec_irradiance(light: UsdLux.DistantLight) -> float:
    """UsdLux, computed from the attributes alone: the illuminance at normal incidence of a DistantLight
    (the OpenUSD usdLux documentation, "Normalizing Distant Lights")."""
    emission = light.GetIntensityAttr().Get() * 2.0 ** light.GetExposureAttr().Get()
    if light.GetNormalizeAttr().Get():
        return emission
    return emission * math.pi * math.sin(math.radians(light.GetAngleAttr().Get()) / 2.0) ** 2


def _penumbra_spec(fraction: float = 0.5):
    spec = make_spec()
    return replace(spec, sun=replace(spec.sun, irradiance=SOLAR_CONSTANT * fraction, lit_fraction=fraction,
                                     eclipse_state="penumbra", eclipse_body="moon"))


def test_sun_lamp_intensity_is_irradiance_under_the_spec(tiny_base, tmp_path):
    """Plain usd-core: normalize is authored true, so the Sun's spec irradiance is 1361 x lit fraction."""
    layer = write_scene_layer(_penumbra_spec(0.5), tmp_path / "s.usda", tiny_base)
    stage = Usd.Stage.Open(str(layer))
    light = UsdLux.DistantLight(stage.GetPrimAtPath(SUN))
    assert light.GetNormalizeAttr().HasAuthoredValue() and light.GetNormalizeAttr().Get() is True
    assert _spec_irradiance(light) == pytest.approx(SOLAR_CONSTANT * 0.5, rel=1e-6)
    assert read_scene(layer).sun.irradiance == pytest.approx(_spec_irradiance(light), rel=1e-6)
    for prim in stage.Traverse():  # every DistantLight the layer has (the bodies' lamps on this eclipse day)
        if prim.IsA(UsdLux.DistantLight):
            assert UsdLux.DistantLight(prim).GetNormalizeAttr().Get() is True, prim.GetPath()


def test_reader_follows_the_spec_for_an_unnormalised_distant_light(tiny_base, tmp_path):
    """A user's layer that turns normalize off means the same intensity as the disc's radiance: the
    reader (and so Cycles' sun strength) gets intensity x 2^exposure x pi sin^2(angle / 2)."""
    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    radiance = 2.0e7
    _override(layer, SUN, "inputs:normalize", Sdf.ValueTypeNames.Bool, False)
    _override(layer, SUN, "inputs:intensity", Sdf.ValueTypeNames.Float, radiance)
    _override(layer, SUN, "inputs:exposure", Sdf.ValueTypeNames.Float, 1.0)
    stage = Usd.Stage.Open(str(layer))
    light = UsdLux.DistantLight(stage.GetPrimAtPath(SUN))
    want = radiance * 2.0 * math.pi * math.sin(math.radians(0.533) / 2.0) ** 2
    assert _spec_irradiance(light) == pytest.approx(want, rel=1e-6)
    assert read_scene(layer).sun.irradiance == pytest.approx(want, rel=1e-6)
    assert 2700 < want < 2800  # the Sun's radiance over its disc, doubled by the exposure


@pytest.mark.render
def test_sphere_light_spec_power_is_what_blender_gets(tiny_base, tmp_path):
    """UsdLux: an un-normalised SphereLight's intensity is the radiance L of its surface, so it emits
    pi L per unit area over 4 pi r^2; a normalised one divides intensity by that area first. Blender's
    spot (a sphere lamp of the same radius, power in W) gets exactly that power."""
    import bpy

    from allo_usd.blender.build import build_scene

    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    for normalize in (False, True):
        _override(layer, SPOT, "inputs:normalize", Sdf.ValueTypeNames.Bool, normalize)
        stage = Usd.Stage.Open(str(layer))
        light = UsdLux.SphereLight(stage.GetPrimAtPath(SPOT))
        r, intensity = light.GetRadiusAttr().Get(), light.GetIntensityAttr().Get()
        radiance = intensity / (4 * math.pi * r ** 2) if normalize else intensity
        spec_power = math.pi * radiance * 4 * math.pi * r ** 2
        desc = read_scene(layer)
        assert desc.spot.intensity == pytest.approx(radiance, rel=1e-6)
        build_scene(desc)
        assert bpy.data.lights[SPOT].energy == pytest.approx(spec_power, rel=1e-6)
    assert spec_power == pytest.approx(math.pi * intensity, rel=1e-6)  # normalised: power pi x intensity


def test_film_exposure_is_the_cameras_standard_exposure_scale(tiny_base, tmp_path):
    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    stage = Usd.Stage.Open(str(layer))
    camera = UsdGeom.Camera(stage.GetPrimAtPath(CAMERA))
    assert camera.GetExposureAttr().HasAuthoredValue() and not stage.GetPrimAtPath("/Render/Settings").GetAttribute(
        "allo:render:exposure")
    assert camera.ComputeLinearExposureScale() == pytest.approx(EXPOSURE, rel=1e-6)
    assert read_scene(layer).render.exposure == pytest.approx(camera.ComputeLinearExposureScale(), rel=1e-6)
    for name, value in (("exposure:fStop", 2.8), ("exposure:time", 1 / 125), ("exposure:iso", 400.0),
                        ("exposure:responsivity", 0.7), ("exposure", -2.5)):
        _override(layer, CAMERA, name, Sdf.ValueTypeNames.Float, value)
        stage = Usd.Stage.Open(str(layer))
        camera = UsdGeom.Camera(stage.GetPrimAtPath(CAMERA))
        assert read_scene(layer).render.exposure == pytest.approx(camera.ComputeLinearExposureScale(), rel=1e-6), name
    assert camera.ComputeLinearExposureScale() == pytest.approx(1 / 125 * 4 / 2.8 ** 2 * 0.7 * 2 ** -2.5, rel=1e-6)


@pytest.mark.render
def test_editing_fstop_time_iso_scales_the_render_by_the_standard_factor(tiny_base, tmp_path):
    from allo_usd.blender.render import render_scene

    base = write_scene_layer(make_spec(samples=4), tmp_path / "a.usda", tiny_base)
    edited = write_scene_layer(make_spec(samples=4), tmp_path / "b.usda", tiny_base)
    # f/2 (1/4), 2 s (x2), ISO 50 (1/2): the standard scale falls to 1/4.
    for name, value in (("exposure:fStop", 2.0), ("exposure:time", 2.0), ("exposure:iso", 50.0)):
        _override(edited, CAMERA, name, Sdf.ValueTypeNames.Float, value)
    a, b = render_scene(read_scene(base)), render_scene(read_scene(edited))
    lit = (a.mask == 1) & (a.rgb.mean(axis=-1) > 0.01)
    assert lit.sum() > 50
    assert b.rgb[lit].sum() / a.rgb[lit].sum() == pytest.approx(0.25, rel=1e-3)


@pytest.mark.render
def test_the_sun_disc_is_the_lamp_and_the_sphere_only_labels_it(tiny_base, tmp_path):
    """Camera above the station aimed at the Sun: the disc is drawn (by the station's DistantLight), its
    pixels carry class 1, and the disc's light summed over its pixels is the lamp's irradiance. The Sun's
    sphere is cut out everywhere and emits nothing (a spec renderer sees one Sun)."""
    from allo_usd.blender.render import render_scene
    from allo_usd.core.geometry import camera_intrinsics

    spec = make_spec(resolution=(320, 180), samples=16)
    pos, d = np.array([0.0, 0.0, 30.0]), np.asarray(spec.sun.direction)
    spec = replace(spec, camera=CameraSpec(tuple(pos), look_at(pos, pos + d)))
    layer = write_scene_layer(spec, tmp_path / "s.usda", tiny_base)
    stage = Usd.Stage.Open(str(layer))
    surface = UsdShade.Material(stage.GetPrimAtPath("/World/Sky/Sun/Looks/Photosphere")).ComputeSurfaceSource()[0]
    # UsdPreviewSurface: drawn only where opacity >= opacityThreshold, so nowhere (a cut-out, not glass).
    assert surface.GetInput("opacity").Get() == 0.0 and surface.GetInput("opacityThreshold").Get() > 0.0
    assert not surface.GetInput("emissiveColor")
    desc = read_scene(layer)
    assert [s.path for s in desc.suns if s.camera_visible] == [SUN]
    result = render_scene(desc)
    w, h = spec.render.resolution
    f = camera_intrinsics(w, h)[0, 0]
    window = (slice(h // 2 - 4, h // 2 + 4), slice(w // 2 - 4, w // 2 + 4))
    assert (result.mask[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1] == 1).all()  # the disc is class 1
    # Radiance summed over the disc's pixels x one pixel's solid angle = irradiance (W/m^2).
    irradiance = result.rgb[window].mean(axis=-1).sum() / EXPOSURE / f ** 2
    assert irradiance == pytest.approx(SOLAR_CONSTANT, rel=0.1)
    assert np.median(result.rgb) == 0.0 and (result.mask == 0).mean() > 0.9  # black sky, unlabelled


def _active_lamps(stage) -> dict:
    return {str(p.GetPath()): p for p in stage.Traverse() if p.IsA(UsdLux.DistantLight)}


def test_a_normal_day_has_one_unlinked_sun_lamp(tiny_base, tmp_path):
    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    stage = Usd.Stage.Open(str(layer))
    lamps = _active_lamps(stage)
    assert list(lamps) == [SUN]
    link = UsdLux.LightAPI(lamps[SUN]).GetLightLinkCollectionAPI()
    assert link.GetIncludeRootAttr().Get() and not link.GetExcludesRel().GetTargets()
    desc = read_scene(layer)
    assert len(desc.suns) == 1 and desc.sun.link is None


def test_an_eclipse_day_keeps_the_three_linked_lamps(tiny_base, tmp_path):
    from allo_usd.scene.resolve import sun_and_bodies
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky

    sun, bodies = sun_and_bodies(compute_sky(default_epochs()), UMBRA_DAY)
    assert sun.lit_fraction == 0.0 and bodies["Earth"].light.lit_fraction == 1.0
    layer = write_scene_layer(replace(make_spec(), sun=sun, bodies=bodies), tmp_path / "s.usda", tiny_base)
    stage = Usd.Stage.Open(str(layer))
    lamps = _active_lamps(stage)
    assert sorted(lamps) == ["/World/Sky/EarthSunLight", "/World/Sky/MoonSunLight", SUN]
    excludes = UsdLux.LightAPI(lamps[SUN]).GetLightLinkCollectionAPI().GetExcludesRel().GetTargets()
    assert [str(t) for t in excludes] == ["/World/Sky/Earth", "/World/Sky/Moon"]
    desc = read_scene(layer)
    earth = {s.path: s for s in desc.suns}["/World/Sky/EarthSunLight"]
    assert desc.sun is None and earth.link.paths and not earth.link.exclude and not earth.camera_visible


def test_inspect_shows_the_lens_the_sensor_and_the_exposure(tiny_base, tmp_path):
    from allo_usd.usd.inspect import describe, format_description

    d = describe(write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base))
    cam = d["camera"]
    assert cam["focal_length_mm"] == pytest.approx(25.0) and cam["sensor_mm"] == pytest.approx((36.0, 20.25))
    e = cam["exposure"]
    assert e["ev"] == pytest.approx(math.log2(EXPOSURE), abs=1e-6) and e["linear_scale"] == pytest.approx(EXPOSURE)
    assert (e["f_stop"], e["time_s"], e["iso"], e["responsivity"]) == (1.0, 1.0, 100.0, 1.0)
    assert d["sun"]["normalize"] is True
    text = format_description(d)
    assert "focal length 25 mm" in text and "aperture 36 x 20.25 mm" in text and "-8.91096 EV" in text
    assert "normalize True" in text
