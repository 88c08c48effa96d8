"""Moon, Earth and Sun as unit spheres with procedural equirectangular textures.

The sky module places them at true scale (scale = body radius, translate = true position),
so one unit sphere per body serves every day. Albedos follow PHYSICS.md section 5: the
textures average to the Moon's geometric albedo 0.12 and the Earth's Bond albedo about 0.31.
The Sun's disc is an emitter of constant radiance (radiance does not fall with distance; its
solid angle does), so its value lives in the asset, not in each scene.
"""

from __future__ import annotations

import numpy as np

from ..mesh import Asset, Material
from .primitives import uv_sphere

SOLAR_CONSTANT_W_M2 = 1361.0
AU_M = 1.495978707e11
SUN_RADIUS_M = 696_340e3
# Radiance of the solar disc: irradiance / solid angle = E / (pi sin^2 theta) at 1 AU.
SUN_RADIANCE = SOLAR_CONSTANT_W_M2 / (np.pi * (SUN_RADIUS_M / AU_M) ** 2)

MOON_ALBEDO = 0.12
EARTH_ALBEDO = 0.306


def _fbm(h: int, w: int, seed: int, octaves: int = 6, base: int = 4) -> np.ndarray:
    """Fractal value noise on an equirectangular grid, wrapping in longitude, in [0, 1]."""
    rng = np.random.default_rng(seed)
    out = np.zeros((h, w))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        gh, gw = base * 2 ** o // 2 + 1, base * 2 ** o
        grid = rng.random((gh + 1, gw))
        y = np.linspace(0, gh, h, endpoint=False)
        x = np.linspace(0, gw, w, endpoint=False)
        y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
        fy, fx = (y - y0)[:, None], (x - x0)[None, :]
        fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
        x1 = (x0 + 1) % gw
        a = grid[y0][:, x0]
        b = grid[y0][:, x1]
        c = grid[y0 + 1][:, x0]
        d = grid[y0 + 1][:, x1]
        out += amp * ((a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy)
        total += amp
        amp *= 0.5
    return out / total


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    c = np.clip(linear, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return np.round(s * 255).astype(np.uint8)


def moon_texture(h: int = 512, w: int = 1024) -> np.ndarray:
    n = _fbm(h, w, seed=1737)
    maria = _fbm(h, w, seed=42, octaves=3, base=3) > 0.56
    rng = np.random.default_rng(7)
    lat = np.linspace(np.pi / 2, -np.pi / 2, h)[:, None]
    lon = np.linspace(-np.pi, np.pi, w, endpoint=False)[None, :]
    craters = np.zeros((h, w))
    for _ in range(160):  # bright-rimmed craters with dark floors
        clat, clon = np.arcsin(rng.uniform(-1, 1)), rng.uniform(-np.pi, np.pi)
        r = rng.uniform(0.01, 0.08)
        d = np.arccos(np.clip(np.sin(lat) * np.sin(clat) + np.cos(lat) * np.cos(clat) * np.cos(lon - clon), -1, 1))
        craters += np.exp(-((d - r) / (0.15 * r)) ** 2) * 0.35 - (d < r) * 0.08
    albedo = 1.0 + 0.5 * (n - 0.5) - 0.35 * maria + craters
    albedo *= MOON_ALBEDO / albedo.mean()
    return _to_srgb8(np.repeat(albedo[..., None], 3, axis=2))


def earth_texture(h: int = 512, w: int = 1024) -> np.ndarray:
    land = _fbm(h, w, seed=6371, octaves=6, base=3)
    clouds = _fbm(h, w, seed=2030, octaves=6, base=6)
    lat = np.linspace(90, -90, h)[:, None] * np.ones((1, w))
    ocean = np.array([0.02, 0.05, 0.14])
    green = np.array([0.08, 0.12, 0.05])
    desert = np.array([0.35, 0.27, 0.16])
    ice = np.array([0.85, 0.87, 0.9])
    is_land = land > 0.53
    dry = _fbm(h, w, seed=11, octaves=3, base=4)[..., None]
    col = np.where(is_land[..., None], green * (1 - dry) + desert * dry, ocean)
    col = np.where((np.abs(lat) > 72)[..., None], ice, col)
    cover = np.clip((clouds - 0.45) * 3.0, 0, 1)[..., None]
    col = col * (1 - cover) + 0.8 * cover
    col *= EARTH_ALBEDO / col.mean()
    return _to_srgb8(col)


def build_bodies() -> dict[str, Asset]:
    """Unit spheres named Moon, Earth and Sun with their materials and textures."""
    moon = Asset("Moon", (uv_sphere("Surface", 1.0, "Regolith", segments=128, rings=64),),
                 (Material("Regolith", (1.0, 1.0, 1.0), 0.0, 0.95, base_color_texture="moon_albedo"),),
                 {"moon_albedo": moon_texture()})
    earth = Asset("Earth", (uv_sphere("Surface", 1.0, "EarthSurface", segments=128, rings=64),),
                  (Material("EarthSurface", (1.0, 1.0, 1.0), 0.0, 0.8, base_color_texture="earth_albedo"),),
                  {"earth_albedo": earth_texture()})
    sun_color = np.array([1.0, 0.97, 0.92])
    sun = Asset("Sun", (uv_sphere("Surface", 1.0, "Photosphere", segments=48, rings=24),),
                (Material("Photosphere", (0.0, 0.0, 0.0), 0.0, 1.0,
                          emissive_color=tuple(float(c) for c in sun_color * SUN_RADIANCE)),))
    return {"Moon": moon, "Earth": earth, "Sun": sun}
