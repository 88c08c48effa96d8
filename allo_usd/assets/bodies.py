"""Moon, Earth and Sun as unit spheres with procedural equirectangular textures.

The sky module places them at true scale (scale = body radius, translate = true position),
so one unit sphere per body serves every day. "Unit" means the drawn outline: the mesh is a 192 x 96
UV sphere whose vertices lie slightly outside radius 1 (by 1.3e-4, `body_sphere`), so that the polygon's
outline has, on average around it, the true radius from any view (tests/sky/test_silhouettes.py); vertices
on the unit sphere would draw every body a little small. The Sun's sphere emits nothing and is cut out
everywhere (UsdPreviewSurface opacity 0 under opacityThreshold 0.5: no renderer draws it, and it is
not refractive glass, which opacity 0 with threshold 0 may be): the Sun is the station's UsdLux
DistantLight, whose angular diameter, irradiance and colour (SUN_COLOR) draw the disc (radiance
SUN_RADIANCE at 1 AU) and light the scene once, in any renderer. The sphere is there so that the
disc's pixels carry class 1 in the mask.

Albedo convention: BOND albedo, area-weighted, for both bodies (docs/physics.md section 5: Moon
0.11, Earth 0.306). Both bodies are Lambertian (UsdPreviewSurface `ior = 1`: no specular layer),
and for a Lambertian sphere the fraction of the incident sunlight it reflects back into space, its Bond albedo, equals
the diffuse reflectance. So a texture whose *area-weighted* mean reflectance equals the Bond albedo
reflects the right total energy, which is what moonshine and earthshine on the station depend on.
(A geometric albedo is a different quantity, the full-phase brightness against a Lambertian disc;
using it for one body and the Bond albedo for the other mixed conventions.) The mean is taken:
- over area: each texel row weighted by cos(latitude) of its centre, proportional to the area the
  row covers on the sphere (an equirectangular map over-counts the poles);
- over the decoded texture: the 8-bit sRGB PNG as Blender reads it, back to linear reflectance;
- over the three channels with equal weights (a white sun; Bond albedo is a bolometric figure).
`area_weighted_reflectance` computes it, and the textures are normalised to it after quantisation.
The Earth's surfaces keep plausible reflectances (ocean about 0.06, vegetation and desert 0.1-0.3,
ice and cloud tops about 0.8, land about 29% of the area) and its cloud cover is solved for so that
the planet reaches 0.306: most of the Earth's Bond albedo is cloud.

Why `ior = 1`, measured in Cycles (bpy 5.0.1): with the default ior 1.5, the Principled BSDF adds a
dielectric specular layer over the diffuse base. A plane of base colour 0.11 (roughness 0.95) lit
at normal incidence then reflects 0.123 of the light instead of 0.110, and the Moon seen at
quarter phase renders 1.40x the Lambertian prediction (the Earth 1.02x). With ior 1 the
reflectance is the base colour (0.1099, 0.3057 measured) and the rendered bodies match the
Lambertian prediction (tests/assets/test_bodies.py).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from allo_usd.core.constants import AU_M, SOLAR_CONSTANT, SUN_RADIUS_M
from allo_usd.assets.mesh import Asset, Material, MeshPart
from allo_usd.assets.primitives import sphere_outline_scale, uv_sphere
from allo_usd.core import fixedmath as fm

# Radiance of the solar disc: irradiance / solid angle = E / (pi sin^2 theta) at 1 AU (what the
# DistantLight's disc has: UsdLux's size factor of a normalised DistantLight, read_lights.distant_size_factor).
SUN_RADIANCE = SOLAR_CONSTANT / (np.pi * (SUN_RADIUS_M / AU_M) * (SUN_RADIUS_M / AU_M))

MOON_ALBEDO = 0.11    # Bond albedo (geometric: 0.12)
EARTH_ALBEDO = 0.306  # Bond albedo (geometric: 0.434)
MOON_MARIA_FRACTION = 0.17   # of the surface area (about 31% of the near side, 2% of the far side)
EARTH_LAND_FRACTION = 0.29   # of the surface area
EARTH_ICE_LATITUDE_DEG = 72.0
EARTH_CLOUD_TOP = 0.8        # linear reflectance of thick cloud tops
# The bodies' sphere: 192 x 96 keeps the mean outline within 9e-5 of the true disc from every view
# (128 x 64 would leave 2e-4: seen over a pole the limb runs between two rings; sphere_outline_scale).
BODY_SEGMENTS, BODY_RINGS = 192, 96


def _fbm(h: int, w: int, seed: int, octaves: int = 6, base: int = 4) -> np.ndarray:
    """Fractal value noise on an equirectangular grid, wrapping in longitude, in [0, 1]."""
    rng = np.random.default_rng(seed)
    out = np.zeros((h, w))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        gh, gw = base * (1 << o) // 2 + 1, base * (1 << o)
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
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * fm.power(c, 1 / 2.4) - 0.055)
    return np.round(s * 255).astype(np.uint8)


def srgb8_to_linear(texture: np.ndarray) -> np.ndarray:
    """Linear reflectance of an 8-bit sRGB texture, decoded as Blender reads an sRGB image."""
    c = np.asarray(texture, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, fm.power((c + 0.055) / 1.055, 2.4))   # not ** 2.4: SVML on AVX-512


def row_latitudes(h: int) -> np.ndarray:
    """Latitude (radians) of each texel row's centre; row 0 is the north pole's row (uv_sphere's v)."""
    return np.pi / 2 - (np.arange(h) + 0.5) * np.pi / h


def area_weights(h: int) -> np.ndarray:
    """(h, 1) weights proportional to the sphere area each equirectangular row covers."""
    return fm.cos(row_latitudes(h))[:, None]


def area_weighted_reflectance(texture: np.ndarray) -> float:
    """Mean linear reflectance of an (H, W, 3) 8-bit sRGB equirectangular texture over the sphere's area."""
    linear = srgb8_to_linear(texture).mean(axis=2)
    w = area_weights(linear.shape[0]) * np.ones((1, linear.shape[1]))
    return float((linear * w).sum() / w.sum())


def _weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    order = np.argsort(values, axis=None)
    cum = np.cumsum(weights.ravel()[order])
    return float(values.ravel()[order][np.searchsorted(cum, q * cum[-1])])


def _normalised_srgb8(linear: np.ndarray, albedo: float) -> np.ndarray:
    """`linear` scaled so the 8-bit sRGB texture it becomes has area-weighted reflectance `albedo`.

    Iterated, because quantisation (and clipping, if any texel reaches 1) shifts the mean a little.
    """
    h = linear.shape[0]
    w = area_weights(h)[..., None] * np.ones((1, linear.shape[1], 1))
    scale = albedo / float((linear * w).sum() / (w.sum() * linear.shape[2]))
    for _ in range(8):
        tex = _to_srgb8(linear * scale)
        got = area_weighted_reflectance(tex)
        if abs(got - albedo) < 1e-4 * albedo:
            break
        scale *= albedo / got
    return tex


def moon_texture(h: int = 512, w: int = 1024) -> np.ndarray:
    """Grey regolith: dark maria, brighter highlands, bright-rimmed craters; Bond albedo 0.11."""
    weights = area_weights(h) * np.ones((1, w))
    n = _fbm(h, w, seed=1737)
    mare = _fbm(h, w, seed=42, octaves=3, base=3)
    maria = mare > _weighted_quantile(mare, weights, 1.0 - MOON_MARIA_FRACTION)
    rng = np.random.default_rng(7)
    lat = row_latitudes(h)[:, None]
    lon = np.linspace(-np.pi, np.pi, w, endpoint=False)[None, :]
    craters = np.zeros((h, w))
    for _ in range(160):  # bright-rimmed craters with dark floors
        clat, clon = fm.arcsin(rng.uniform(-1, 1)), rng.uniform(-np.pi, np.pi)
        r = rng.uniform(0.01, 0.08)
        d = fm.arccos(np.clip(fm.sin(lat) * fm.sin(clat) + fm.cos(lat) * fm.cos(clat) * fm.cos(lon - clon), -1, 1))
        craters += fm.exp(-np.square((d - r) / (0.15 * r))) * 0.35 - (d < r) * 0.08
    albedo = 1.0 + 0.5 * (n - 0.5) - 0.35 * maria + craters
    return _normalised_srgb8(np.repeat(albedo[..., None], 3, axis=2), MOON_ALBEDO)


def earth_texture(h: int = 512, w: int = 1024) -> np.ndarray:
    """Oceans, continents (vegetation to desert), polar ice and clouds; Bond albedo 0.306.

    The surface reflectances are fixed at plausible values; the cloud cover is solved for (by
    bisection on its threshold) so that the area-weighted reflectance reaches EARTH_ALBEDO.
    """
    weights = area_weights(h) * np.ones((1, w))
    land = _fbm(h, w, seed=6371, octaves=6, base=3)
    clouds = _fbm(h, w, seed=2030, octaves=6, base=6)
    lat = fm.degrees(row_latitudes(h))[:, None] * np.ones((1, w))
    ocean = np.array([0.03, 0.05, 0.10])
    green = np.array([0.08, 0.12, 0.05])
    desert = np.array([0.35, 0.27, 0.16])
    ice = np.array([0.80, 0.82, 0.85])
    is_land = land > _weighted_quantile(land, weights, 1.0 - EARTH_LAND_FRACTION)
    dry = _fbm(h, w, seed=11, octaves=3, base=4)[..., None]
    surface = np.where(is_land[..., None], green * (1 - dry) + desert * dry, ocean)
    surface = np.where((np.abs(lat) > EARTH_ICE_LATITUDE_DEG)[..., None], ice, surface)

    def with_clouds(threshold: float) -> np.ndarray:
        cover = np.clip((clouds - threshold) * 3.0, 0, 1)[..., None]
        return surface * (1 - cover) + EARTH_CLOUD_TOP * cover

    def mean(col: np.ndarray) -> float:
        return float((col.mean(axis=2) * weights).sum() / weights.sum())

    lo, hi = 0.0, 1.0  # higher threshold, fewer clouds, darker planet
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mean(with_clouds(mid)) > EARTH_ALBEDO else (lo, mid)
    return _normalised_srgb8(with_clouds(0.5 * (lo + hi)), EARTH_ALBEDO)


def body_sphere(material: str, textured: bool = True) -> MeshPart:
    """The unit sphere every body is drawn with: its outline, seen from any direction at any distance, has
    the true mean radius to within 9e-5 (primitives.sphere_outline_scale; tests/sky/test_silhouettes.py).
    Untextured (the Sun's), it carries no UVs: they are most of the file's size."""
    part = uv_sphere("Surface", sphere_outline_scale(BODY_SEGMENTS, BODY_RINGS), material,
                     segments=BODY_SEGMENTS, rings=BODY_RINGS)
    return part if textured else replace(part, uv=None)


def build_bodies() -> dict[str, Asset]:
    """Unit spheres named Moon, Earth and Sun with their materials and textures."""
    moon = Asset("Moon", (body_sphere("Regolith"),),
                 (Material("Regolith", (1.0, 1.0, 1.0), 0.0, 1.0, base_color_texture="moon_albedo", ior=1.0),),
                 {"moon_albedo": moon_texture()})
    earth = Asset("Earth", (body_sphere("EarthSurface"),),
                  (Material("EarthSurface", (1.0, 1.0, 1.0), 0.0, 1.0, base_color_texture="earth_albedo", ior=1.0),),
                  {"earth_albedo": earth_texture()})
    sun = Asset("Sun", (body_sphere("Photosphere", textured=False),),
                (Material("Photosphere", (0.0, 0.0, 0.0), 0.0, 1.0, opacity=0.0, opacity_threshold=0.5),))
    return {"Moon": moon, "Earth": earth, "Sun": sun}
