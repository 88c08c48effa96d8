"""Scene-layer authoring: layer specs, composed values, determinism, bad input."""

from __future__ import annotations

import re

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

from allo_usd import __version__
from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.core.errors import AlloError, LayerError
from allo_usd.scene.spec import CameraSpec, SunSpec

from tests.support.helpers import make_spec


def test_layer_holds_only_scene_opinions(tiny_base, tmp_path):
    path = write_scene_layer(make_spec(anomaly=True), tmp_path / "s.usda", tiny_base)
    layer = Sdf.Layer.FindOrOpen(str(path))
    assert layer.subLayerPaths[0].endswith("base.usda") and not layer.subLayerPaths[0].startswith("/")
    assert layer.defaultPrim == "World"
    assert layer.customLayerData["allo"]["seed"] == 7
    assert layer.customLayerData["allo"]["packageVersion"] == __version__
    # Station geometry is never copied into the scene layer.
    assert layer.GetPrimAtPath("/World/Station") is None
    assert layer.GetPrimAtPath("/World/Camera").specifier == Sdf.SpecifierOver
    assert layer.GetPrimAtPath("/World/Anomaly").specifier == Sdf.SpecifierDef
    # A self-contained layer (sky and pose included) with an anomaly: three sun lamps of ~600 bytes.
    assert path.stat().st_size < 5120


def test_composed_values(tiny_base, tmp_path):
    spec = make_spec(anomaly=True)
    stage = Usd.Stage.Open(str(write_scene_layer(spec, tmp_path / "s.usda", tiny_base)))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    cam = stage.GetPrimAtPath("/World/Camera")
    m = np.array(UsdGeom.Xformable(cam).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    np.testing.assert_allclose(m[:3, 3], spec.camera.position)
    np.testing.assert_allclose(m[:3, :3], spec.camera.rotation, atol=1e-12)
    world = stage.GetPrimAtPath("/World")
    assert world.GetAttribute("allo:seed").Get() == 7
    assert world.GetAttribute("allo:variant").Get() == "anomaly"
    assert stage.GetPrimAtPath("/Render/Settings").GetAttribute("resolution").Get() == (64, 36)
    anomaly = stage.GetPrimAtPath("/World/Anomaly")
    assert anomaly.GetVariantSets().GetVariantSelection("variant") == "blue"
    assert stage.GetPrimAtPath("/World/Anomaly/Geom/Body").IsA(UsdGeom.Mesh)
    sun = stage.GetPrimAtPath("/World/Sky/SunLight")
    sm = np.array(UsdGeom.Xformable(sun).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    np.testing.assert_allclose(sm[:3, 2], spec.sun.direction, atol=1e-12)


def test_same_spec_same_bytes(tiny_base, tmp_path):
    a = write_scene_layer(make_spec(anomaly=True), tmp_path / "a" / "s.usda", tiny_base)
    b = write_scene_layer(make_spec(anomaly=True), tmp_path / "b" / "s.usda", tiny_base)
    assert a.read_bytes() == b.read_bytes()
    c = write_scene_layer(make_spec(anomaly=True, seed=8), tmp_path / "c" / "s.usda", tiny_base)
    assert c.read_bytes() != a.read_bytes()


@pytest.mark.parametrize("bad", [
    {"camera": CameraSpec((np.nan, 0.0, 0.0), np.eye(3))},
    {"sun": SunSpec((0.0, 0.0, np.inf), 1361.0, 1361.0, 0.533, 1.5e11)},
    {"split": "validation"},
])
def test_bad_spec_writes_nothing(tiny_base, tmp_path, bad):
    target = tmp_path / "bad.usda"
    with pytest.raises(AlloError):
        write_scene_layer(make_spec(**bad), target, tiny_base)
    assert list(tmp_path.iterdir()) == []


def test_missing_base_stage_is_named(tmp_path):
    with pytest.raises(LayerError, match="base stage"):
        write_scene_layer(make_spec(), tmp_path / "s.usda", tmp_path / "nope.usda")


def test_unknown_anomaly_asset(tiny_base, tmp_path):
    from allo_usd.scene.spec import AnomalySpec

    from dataclasses import replace

    spec = replace(make_spec(), anomaly=AnomalySpec("NoSuchThing", "x", (1.0, 1.0, 1.0), np.eye(3)))
    with pytest.raises(LayerError, match="NoSuchThing"):
        write_scene_layer(spec, tmp_path / "s.usda", tiny_base)
    assert not (tmp_path / "s.usda").exists()


def test_each_body_has_a_sun_lamp_that_lights_only_it(tiny_base, tmp_path):
    """The station's sun lights all but the Earth and Moon; each body's own lamp lights only it (UsdLux
    light linking), with the Sun's direction and irradiance at that body and its own eclipse."""
    from dataclasses import replace

    from pxr import UsdLux

    from allo_usd.scene.spec import SunSpec

    spec = make_spec()
    moon_sun = SunSpec((0.0, 0.6, 0.8), 651.0, 1370.0, 0.53, 1.49e11, 0.475, "penumbra", "earth")
    spec = replace(spec, bodies={**spec.bodies, "Moon": replace(spec.bodies["Moon"], light=moon_sun)})
    stage = Usd.Stage.Open(str(write_scene_layer(spec, tmp_path / "s.usda", tiny_base)))

    def members(path):
        query = UsdLux.LightAPI(stage.GetPrimAtPath(path)).GetLightLinkCollectionAPI().ComputeMembershipQuery()
        return {p: query.IsPathIncluded(Sdf.Path(p)) for p in
                ("/World/Station", "/World/Sky/Earth/Geom/Surface", "/World/Sky/Moon/Geom/Surface", "/World/Sky/Sun")}

    assert members("/World/Sky/SunLight") == {"/World/Station": True, "/World/Sky/Earth/Geom/Surface": False,
                                              "/World/Sky/Moon/Geom/Surface": False, "/World/Sky/Sun": True}
    assert [k for k, v in members("/World/Sky/EarthSunLight").items() if v] == ["/World/Sky/Earth/Geom/Surface"]
    assert [k for k, v in members("/World/Sky/MoonSunLight").items() if v] == ["/World/Sky/Moon/Geom/Surface"]
    moon = stage.GetPrimAtPath("/World/Sky/MoonSunLight")
    assert moon.HasAPI("AlloEclipseAPI")
    values = {n: moon.GetAttribute(f"allo:{n}").Get() for n in
              ("litFraction", "eclipseState", "eclipseBody", "irradianceUnoccluded", "sunDistance")}
    assert values == {"litFraction": 0.475, "eclipseState": "penumbra", "eclipseBody": "earth",
                      "irradianceUnoccluded": 1370.0, "sunDistance": 1.49e11}
    assert UsdLux.DistantLight(moon).GetIntensityAttr().Get() == pytest.approx(651.0)
    m = np.array(UsdGeom.Xformable(moon).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    np.testing.assert_allclose(m[:3, 2], moon_sun.direction, atol=1e-12)
    # No lamp given for the Earth: it gets the station's Sun, unoccluded and unshadowed.
    earth = stage.GetPrimAtPath("/World/Sky/EarthSunLight")
    assert UsdLux.DistantLight(earth).GetIntensityAttr().Get() == pytest.approx(spec.sun.irradiance_unoccluded)
    assert earth.GetAttribute("allo:litFraction").Get() == 1.0


def test_bad_body_lamp_writes_nothing(tiny_base, tmp_path):
    from dataclasses import replace

    spec = make_spec()
    bad = SunSpec((0.0, 0.0, 1.0), 1361.0, 1361.0, 0.533, 1.5e11, 1.5)  # lit fraction above 1
    spec = replace(spec, bodies={**spec.bodies, "Earth": replace(spec.bodies["Earth"], light=bad)})
    with pytest.raises(LayerError, match="Earth's sun lamp"):
        write_scene_layer(spec, tmp_path / "bad.usda", tiny_base)
    assert list(tmp_path.iterdir()) == []


def test_inspect_shows_every_sun_lamp_and_what_it_lights(tiny_base, tmp_path):
    from dataclasses import replace

    from allo_usd.usd.inspect import describe, format_description

    # A normal day (every lit fraction 1): one normalised lamp lights everything, no light linking.
    d = describe(write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base))
    assert d["sun"]["path"] == "/World/Sky/SunLight" and d["sun"]["normalize"] is True
    assert d["sun"]["light_link"] == {"include_root": True, "includes": [], "excludes": []}
    assert d["body_suns"] == [] and "lights all" in format_description(d)
    # An eclipse day (the station half lit, the bodies fully): the three linked lamps.
    spec = make_spec()
    eclipse = replace(spec, sun=replace(spec.sun, irradiance=680.5, lit_fraction=0.5, eclipse_state="penumbra",
                                        eclipse_body="moon"))
    d = describe(write_scene_layer(eclipse, tmp_path / "e.usda", tiny_base))
    assert d["sun"]["light_link"] == {"include_root": True, "includes": [],
                                      "excludes": ["/World/Sky/Earth", "/World/Sky/Moon"]}
    assert [(s["path"], s["light_link"]["includes"], s["lit_fraction"]) for s in d["body_suns"]] == [
        ("/World/Sky/EarthSunLight", ["/World/Sky/Earth"], 1.0), ("/World/Sky/MoonSunLight", ["/World/Sky/Moon"], 1.0)]
    text = format_description(d)
    assert "lights all but /World/Sky/Earth, /World/Sky/Moon" in text
    assert "MoonSunLight" in text and "lights only /World/Sky/Moon" in text


def test_a_sun_token_outside_the_schema_is_refused_before_writing(tiny_base, tmp_path):
    from dataclasses import replace

    from allo_usd.core.errors import LayerError

    spec = make_spec()
    bad = replace(spec, sun=replace(spec.sun, eclipse_body="Earth"))  # the schema's token is "earth"
    with pytest.raises(LayerError, match="eclipse_body 'Earth' is not one of none, moon, earth"):
        write_scene_layer(bad, tmp_path / "bad.usda", tiny_base)
    assert not (tmp_path / "bad.usda").exists()


def test_film_exposure_and_sensor_squares_are_machine_free():
    """The film exposure is fixedmath.exp2 of the authored EV (exact for a power of two; not Python's
    `2.0 ** EV`, glibc's pow, which rounds by CPU), and the sensor's squares are products (not `** 2`)."""
    from allo_usd.core import fixedmath as fm
    from allo_usd.core.sensor import PHOTON_ENERGY_J, SensorParams, photons_per_radiance
    from allo_usd.usd.base_stage import camera_ev
    from allo_usd.usd.scene_layer import film_exposure

    for k in range(-20, 21):
        assert film_exposure(2.0 ** k) == 2.0 ** k
    rng = np.random.default_rng(20300104)
    for e in rng.uniform(0.01, 100.0, 500):
        assert film_exposure(float(e)) == fm.exp2(camera_ev(float(e)))
    for pitch, f in zip(rng.uniform(1e-6, 2e-5, 5000), rng.uniform(1.0, 22.0, 5000)):
        p = SensorParams(pixel_pitch_m=float(pitch), f_number=float(f))
        want = (np.pi / 4.0) * p.transmission * (p.pixel_pitch_m * p.pixel_pitch_m) * 1.0 / (
            p.f_number * p.f_number * PHOTON_ENERGY_J)
        assert photons_per_radiance(p, 1.0) == want


def test_a_target_is_authored_only_when_set(tiny_base, tmp_path):
    """allo:render:targetPsnr / timeLimit appear only with a target: a spec without one writes the bytes it
    wrote before the target mode (no attribute, not even a 0), one with one records both (the time limit
    only when > 0)."""
    from dataclasses import replace

    spec = make_spec(anomaly=True)
    fixed = write_scene_layer(spec, tmp_path / "fixed" / "s.usda", tiny_base).read_text()
    assert "targetPsnr" not in fixed and "timeLimit" not in fixed
    aimed = write_scene_layer(replace(spec, render=replace(spec.render, target_psnr=40.0)),
                              tmp_path / "aimed" / "s.usda", tiny_base).read_text()
    assert "float allo:render:targetPsnr = 40" in aimed and "timeLimit" not in aimed
    capped = write_scene_layer(replace(spec, render=replace(spec.render, target_psnr=38.5, time_limit=90.0)),
                               tmp_path / "capped" / "s.usda", tiny_base)
    stage = Usd.Stage.Open(str(capped))
    settings = stage.GetPrimAtPath("/Render/Settings")
    assert settings.GetAttribute("allo:render:targetPsnr").Get() == 38.5
    assert settings.GetAttribute("allo:render:timeLimit").Get() == 90.0


@pytest.mark.parametrize("target,limit,needle", [
    (float("nan"), 0.0, "target_psnr nan"), (-3.0, 0.0, "target_psnr -3"), (1e9, 0.0, "target_psnr 1e+09"),
    (40.0, -1.0, "time_limit -1"), (40.0, float("inf"), "time_limit inf"), (0.0, 60.0, "without target_psnr"),
])
def test_a_bad_target_writes_no_layer(tiny_base, tmp_path, target, limit, needle):
    from dataclasses import replace

    spec = make_spec()
    with pytest.raises(LayerError, match=re.escape(needle)):
        write_scene_layer(replace(spec, render=replace(spec.render, target_psnr=target, time_limit=limit)),
                          tmp_path / "s.usda", tiny_base)
    assert not (tmp_path / "s.usda").exists()


def test_a_target_with_lens_glare_writes_no_layer(tiny_base, tmp_path):
    from dataclasses import replace

    spec = make_spec()
    aimed = replace(spec, render=replace(spec.render, target_psnr=40.0), effects=replace(spec.effects, glare=True))
    with pytest.raises(LayerError, match="not rendered with lens glare"):
        write_scene_layer(aimed, tmp_path / "s.usda", tiny_base)
    assert not (tmp_path / "s.usda").exists()
