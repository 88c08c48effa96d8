"""The Moon's and Earth's textures: Bond albedo over the sphere's area, and plausible detail.

The shipped PNGs (stages/bodies/textures) are read back here and decoded from sRGB independently
of allo_usd.assets.bodies, so the tests check what Blender will actually load.
"""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from allo_usd.core.paths import STAGES

TEXTURES = STAGES / "bodies" / "textures"


def _linear(name: str) -> np.ndarray:
    c = np.asarray(Image.open(TEXTURES / name).convert("RGB"), dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _area_weights(h: int, w: int) -> np.ndarray:
    """Exact sphere area of each texel row: sin(upper edge latitude) - sin(lower edge latitude)."""
    edges = np.linspace(np.pi / 2, -np.pi / 2, h + 1)
    return (np.sin(edges[:-1]) - np.sin(edges[1:]))[:, None] * np.ones((1, w))


def _area_mean(values: np.ndarray) -> float:
    w = _area_weights(*values.shape[:2])
    return float((values * w).sum() / w.sum())


def _area_fraction(selected: np.ndarray) -> float:
    return _area_mean(selected.astype(np.float64))


@pytest.mark.parametrize("name, bond", [("moon_albedo.png", 0.11), ("earth_albedo.png", 0.306)])
def test_area_weighted_reflectance_is_the_bond_albedo(name, bond):
    lin = _linear(name)
    assert _area_mean(lin.mean(axis=2)) == pytest.approx(bond, rel=2e-3)
    assert lin.max() < 1.0  # nothing clipped: the mean was reached by physical values, not saturation


def test_earth_plain_pixel_mean_is_not_what_is_normalised():
    """An equirectangular map over-counts the poles: the per-pixel mean overstates the ice."""
    lin = _linear("earth_albedo.png").mean(axis=2)
    assert lin.mean() > _area_mean(lin) + 0.005


@pytest.mark.slow
def test_module_measure_matches_the_independent_one():
    from allo_usd.assets.bodies import EARTH_ALBEDO, MOON_ALBEDO, area_weighted_reflectance

    for name, bond in (("moon_albedo.png", MOON_ALBEDO), ("earth_albedo.png", EARTH_ALBEDO)):
        tex = np.asarray(Image.open(TEXTURES / name).convert("RGB"))
        assert area_weighted_reflectance(tex) == pytest.approx(_area_mean(_linear(name).mean(axis=2)), rel=1e-6)
        assert area_weighted_reflectance(tex) == pytest.approx(bond, rel=2e-3)


def test_earth_shows_oceans_continents_ice_and_clouds():
    lin = _linear("earth_albedo.png")
    r, g, b = lin[..., 0], lin[..., 1], lin[..., 2]
    ocean = (b > 1.5 * r) & (lin.max(axis=2) < 0.15)             # dark and blue
    land = (r >= b) & (lin.max(axis=2) < 0.5)                     # green to desert, under no thick cloud
    bright = lin.min(axis=2) > 0.4                                # cloud tops and ice
    assert 0.15 < _area_fraction(ocean) < 0.6
    assert 0.05 < _area_fraction(land) < 0.35
    assert 0.15 < _area_fraction(bright) < 0.5
    h = lin.shape[0]
    polar = np.r_[0:h // 20, h - h // 20:h]                       # |latitude| > 81 deg: ice caps
    assert bright[polar].mean() > 0.9
    assert _linear("earth_albedo.png")[ocean].mean(axis=0)[2] < 0.12  # the ocean stays dark (about 0.06)


def test_moon_shows_maria_and_highlands():
    lin = _linear("moon_albedo.png")
    assert np.allclose(lin[..., 0], lin[..., 1]) and np.allclose(lin[..., 1], lin[..., 2])  # grey
    grey = lin[..., 0]
    w = _area_weights(*grey.shape)
    order = np.argsort(grey, axis=None)
    cum = np.cumsum(w.ravel()[order]) / w.sum()
    p10, p50, p90 = (grey.ravel()[order][np.searchsorted(cum, q)] for q in (0.1, 0.5, 0.9))
    assert p10 < 0.85 * p50 < p90 * 0.85  # dark maria and bright highlands, not a flat grey
    assert 0.03 < grey.min() and grey.max() < 0.3  # regolith: no black or white texels
    assert 0.08 < _area_fraction(grey < 0.85 * p50) < 0.35  # the maria cover a minority of the area


def _expected_radiance(desc, body_pos, body_radius, sun_dir, irradiance, texture: np.ndarray):
    """Per-pixel Lambertian radiance (times exposure) of a textured sphere, by analytic ray casting
    through each pixel centre; NaN where the ray misses. Texel lookup follows uv_sphere's mapping."""
    w, h = desc.render.resolution
    cam = desc.camera
    sx = ((np.arange(w) + 0.5) / w - 0.5) * cam.sensor_width_mm
    sy = (0.5 - (np.arange(h) + 0.5) / h) * cam.sensor_width_mm * h / w
    d = np.stack(np.broadcast_arrays(sx[None, :], sy[:, None], -cam.focal_length_mm), -1)
    d = d @ cam.matrix[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = cam.matrix[:3, 3] - np.asarray(body_pos)
    b = d @ oc
    disc = b * b - (oc @ oc - body_radius ** 2)
    t = -b - np.sqrt(np.where(disc > 0, disc, np.nan))
    n = (oc + t[..., None] * d) / body_radius
    u = (np.arctan2(n[..., 1], n[..., 0]) % (2 * np.pi)) / (2 * np.pi)
    theta = np.arccos(np.clip(n[..., 2], -1, 1))
    th, tw = texture.shape[:2]
    row = np.clip(np.nan_to_num(theta / np.pi * th), 0, th - 1).astype(int)
    col = np.clip(np.nan_to_num(u * tw), 0, tw - 1).astype(int)
    albedo = texture[row, col].mean(axis=-1)
    cos_i = n @ np.asarray(sun_dir)  # negative on the night side
    return albedo * irradiance * np.clip(cos_i, 0, None) / np.pi * desc.render.exposure, cos_i


@pytest.mark.render
@pytest.mark.parametrize("body, day", [("Moon", 0), ("Earth", 10)])  # both near half phase
def test_rendered_body_has_its_albedo_and_a_terminator(tiny_base, tmp_path, body, day):
    from dataclasses import replace

    from pxr import Sdf

    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.blender.render import render_scene
    from allo_usd.core.geometry import look_at
    from allo_usd.usd.read import read_scene
    from allo_usd.scene.resolve import sun_and_bodies
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.scene.spec import CameraSpec
    from allo_usd.plan.settings import EffectsSpec

    from tests.support.helpers import make_spec

    sun, bodies = sun_and_bodies(compute_sky(default_epochs()[day:day + 1]), 0)
    target = np.array(bodies[body].position)
    pos = target / np.linalg.norm(target) * 80.0  # outside the station, looking away from it
    spec = replace(make_spec(resolution=(96, 54), samples=16), sun=sun, bodies=bodies,
                   camera=CameraSpec(tuple(pos), look_at(pos, target)),
                   effects=EffectsSpec(inspection_light=False, body_shine=False))
    layer = write_scene_layer(spec, tmp_path / "s.usda", tiny_base)
    # A long lens, so the body spans about 80% of the frame's height (the layer is the record).
    half_angle = np.arcsin(bodies[body].radius / np.linalg.norm(target - pos))
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    attr = Sdf.AttributeSpec(sdf.GetPrimAtPath("/World/Camera"), "focalLength", Sdf.ValueTypeNames.Float)
    attr.default = float(0.2025 / 2 / np.tan(half_angle / 0.8))
    sdf.Save()
    desc = read_scene(layer)
    result = render_scene(desc)
    texture = _linear(f"{body.lower()}_albedo.png")
    expected, cos_i = _expected_radiance(desc, target, bodies[body].radius, sun.direction, sun.irradiance, texture)
    got = result.rgb.mean(axis=-1)
    hit = np.isfinite(expected)
    assert 0.2 < hit.mean() < 0.4 and (result.mask[hit] == 1).mean() > 0.97
    # Pixels whose 3x3 neighbourhood is all on the disc: no anti-aliased silhouette in their filter.
    pad = np.pad(hit, 1)
    interior = np.logical_and.reduce([pad[1 + dy:pad.shape[0] - 1 + dy, 1 + dx:pad.shape[1] - 1 + dx]
                                      for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    lit = interior & (cos_i > 0.3)
    dark = interior & (cos_i < -0.2)
    assert lit.sum() > 100 and dark.sum() > 100  # both sides of the terminator are in view
    ratio = got[lit] / expected[lit]
    # Lambertian (ior 1) with the Bond-albedo texture: measured median 0.998-1.003, sum 0.99-1.0.
    assert np.median(ratio) == pytest.approx(1.0, abs=0.03)
    assert got[lit].sum() / expected[lit].sum() == pytest.approx(1.0, abs=0.04)
    assert got[dark].max() < 0.02 * got[lit].mean()  # the night side is dark: a visible terminator
    assert got[lit].max() < 1.0  # not blown out


def test_bodies_are_lambertian_in_the_layer_and_the_description():
    """ior = 1 (no specular layer) is authored on both bodies and reaches the description."""
    from pxr import Usd, UsdShade

    from allo_usd.usd import schema
    from allo_usd.usd.read_material import read_material

    schema.register()
    for body, look in (("Moon", "Regolith"), ("Earth", "EarthSurface")):
        stage = Usd.Stage.Open(str(STAGES / "bodies" / f"{body}.usda"))
        material = UsdShade.Material(stage.GetPrimAtPath(f"/{body}/Looks/{look}"))
        desc = read_material(material)
        assert desc.ior == 1.0 and desc.metallic == 0.0 and desc.base_color == (1.0, 1.0, 1.0)
        assert desc.base_color_texture.endswith(f"{body.lower()}_albedo.png")
    station = Usd.Stage.Open(str(STAGES / "station" / "Station.usda"))
    mats = [UsdShade.Material(p) for p in station.Traverse() if p.IsA(UsdShade.Material)]
    assert mats and all(read_material(m).ior == 1.5 for m in mats)  # the UsdPreviewSurface default
