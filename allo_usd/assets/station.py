"""A procedural ISS-like space station, built from numpy primitives (no bpy, no pxr).

Frame: metres, Z up (zenith, away from the Moon), +X the flight direction, Y along the truss
(+Y starboard). The integrated truss runs along Y through the origin's neighbourhood at
z = TRUSS_Z; the pressurised modules run along X below it at z = MODULE_Z, with the US lab
under the centre truss segment and the Russian segment aft (-X).

Layout, loosely after the real station:

* Integrated truss, 109 m: S0 in the middle, S1/P1 (big thermal radiators), S3/P3 (logistics
  carriers), the solar alpha rotary joints (SARJ), then the outboard S4-S6/P4-P6 segments, which
  hang under their side's alpha joint (turned about the truss axis, SARJ_ANGLE at rest); each of
  S4, S6, P4, P6 carries two solar-array wings (35 m x 12 m, two blankets either side of a lattice
  mast), each under its own beta joint (turned about its mast), and a photovoltaic radiator.
* US segment along X: PMA-2 (+ a docked capsule) - Harmony (Columbus starboard, Kibo port with
  its logistics module and exposed facility) - Destiny - Unity (Quest airlock starboard,
  Tranquility port with the Cupola and PMM, Z1 truss with the Ku dish on top) - PMA-1.
* Russian segment: Zarya (Rassvet + a docked Soyuz below), Zvezda (Poisk above, Nauka below,
  its own solar arrays, a docked Progress aft).

Everything is deterministic: the few random details (equipment boxes, payloads) come from a
local numpy Generator with a fixed seed. Parts of one material are merged by region (and joint)
so the asset stays under ~100 parts and ~150k triangles. Joints (station_joints, Asset.joints): a
part under a joint is in the joint's frame; Asset.triangle_soup(angles) poses it, and
build_station(articulated=False) merges everything flat at rest (bit-identical to the static
station the camera rig was chosen on).

Thin sheets render from both sides: each solar blanket (part solar_wing_<seg><a|b>, material
solar_cells, cells facing +X of the turned outboard frame) has a Kapton back sheet 2 cm behind
it (part solar_wing_backs); radiator panels are thin boxes. Textured materials keep a white
base_color because the author multiplies the texture by it; the colour lives in the texture.
Texture UVs are in tiles (metres / *_TILE), so the tiling textures keep a physical scale.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from allo_usd.assets.mesh import Asset, Joint, Material, MeshPart
from allo_usd.assets.primitives import (box, box_between, cylinder, cylinder_between, dish, frame_from_z, grid,
                                        merge, scale_uv, transform, uv_sphere)
from allo_usd.core.geometry import rot_x, rot_y, rot_z, unit
from allo_usd.core import fixedmath as fm

# ----------------------------------------------------------------------------- layout constants
TRUSS_Z = 2.0             # height of the truss axis
MODULE_Z = -2.0           # height of the module axis (US lab, nodes, Russian segment)
TRUSS_HALF_LENGTH = 54.5  # the truss spans y in [-54.5, 54.5] (109 m)
HX, HZ = 2.25, 1.5        # half width (X) and half height (Z) of the inboard truss
HXO, HZO = 2.0, 1.4       # the same for the outboard (S4/S6, P4/P6) truss
SARJ_Y = (31.5, 33.0)     # |y| range of the solar alpha rotary joints
SARJ_ANGLE = fm.radians(25.0)   # outboard truss rotation about the truss axis: the alpha joints' rest angle
WING_Y = (39.0, 52.0)           # |y| of the solar wing pairs on S4/P4 and S6/P6
WING_LENGTH = 32.6              # blanket length; a wing reaches ~36.7 m from the truss axis
BLANKET_WIDTH = 4.6
BLANKET_GAP = 2.8               # between the two blankets of a wing (the mast runs there)
ARM_BASE = np.array([HX + 1.45, 3.0, TRUSS_Z])  # robotic-arm base on the mobile base system

# texture tile sizes in metres
SOLAR_TILE = 0.64     # 8 x 8 cells of 8 cm per tile
MLI_TILE = 1.0
SKIN_TILE = 2.0
RADIATOR_TILE = 2.0

# ----------------------------------------------------------------------------- materials
MLI_GOLD = "mli_gold"
MLI_SILVER = "mli_silver"
SOLAR = "solar_cells"
SOLAR_BACK = "solar_back"
RADIATOR = "radiator"
METAL = "bare_metal"
SKIN = "module_skin"
TRUSS = "truss_paint"
DARK = "dark_grey"
HANDRAIL = "handrail_yellow"
WINDOW = "window_glass"


def _materials() -> tuple[Material, ...]:
    # Textured materials keep base_color white: the author multiplies the texture by base_color
    # (UsdUVTexture `scale`), so the colour lives in the texture (see _textures).
    white = (1.0, 1.0, 1.0)
    return (
        Material(MLI_GOLD, white, metallic=1.0, roughness=0.45, base_color_texture="mli_gold"),
        Material(MLI_SILVER, white, metallic=1.0, roughness=0.5, base_color_texture="mli_silver"),
        Material(SOLAR, white, metallic=0.1, roughness=0.15, base_color_texture="solar_cells"),
        Material(SOLAR_BACK, (0.55, 0.32, 0.10), metallic=0.0, roughness=0.6),
        Material(RADIATOR, white, metallic=0.0, roughness=0.75, base_color_texture="radiator"),
        Material(METAL, (0.91, 0.92, 0.92), metallic=1.0, roughness=0.35),
        Material(SKIN, white, metallic=0.0, roughness=0.8, base_color_texture="module_skin"),
        Material(TRUSS, (0.55, 0.55, 0.54), metallic=0.0, roughness=0.55),
        Material(DARK, (0.035, 0.035, 0.04), metallic=0.0, roughness=0.6),
        Material(HANDRAIL, (0.70, 0.45, 0.06), metallic=0.0, roughness=0.5),
        Material(WINDOW, (0.01, 0.01, 0.012), metallic=0.0, roughness=0.05),
    )


# ----------------------------------------------------------------------------- textures
def _periodic_noise(rng: np.random.Generator, n: int, fmin: float, fmax: float,
                    aniso: float = 1.0) -> np.ndarray:
    """Band-limited noise on an n x n torus (tiles seamlessly), zero mean, unit std."""
    fy = np.fft.fftfreq(n)[:, None] * n
    fx = np.fft.rfftfreq(n)[None, :] * n
    f = np.sqrt(np.square(fx * aniso) + np.square(fy))
    band = ((f >= fmin) & (f <= fmax)).astype(np.float64) / np.maximum(f, 1.0)
    spec = (rng.normal(size=band.shape) + 1j * rng.normal(size=band.shape)) * band
    field = np.fft.irfft2(spec, s=(n, n))
    field -= field.mean()
    return field / (field.std() + 1e-12)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _solar_texture(rng: np.random.Generator, n: int = 512, cells: int = 8) -> np.ndarray:
    """Dark blue cells with silver gaps, busbars, clipped corners and a copper panel seam."""
    cp = n // cells
    tone = 1.0 + 0.07 * rng.normal(size=(cells, cells))
    img = np.repeat(np.repeat(tone, cp, 0), cp, 1)[..., None] * np.array([22.0, 34.0, 84.0])
    i = np.arange(n)
    li = i % cp
    # faint fingers across each cell and two busbars
    fingers = (li % 8 == 4)
    img[:, fingers] += np.array([6.0, 8.0, 14.0])
    bus = (li == cp // 3) | (li == 2 * cp // 3)
    img[bus, :] = np.array([70.0, 78.0, 104.0])
    # pseudo-square cells: clipped corners show the light substrate
    dy, dx = np.meshgrid(np.abs(li - (cp - 1) / 2), np.abs(li - (cp - 1) / 2), indexing="ij")
    corner = (dx + dy) > 0.86 * cp
    img[corner] = np.array([150.0, 150.0, 158.0])
    gap = (li <= 0) | (li >= cp - 2)
    img[gap, :] = np.array([138.0, 140.0, 150.0])
    img[:, gap] = np.array([138.0, 140.0, 150.0])
    seam = (i < 2) | (i >= n - 2)
    img[seam, :] = np.array([170.0, 120.0, 62.0])
    return _to_u8(img)


def _periodic_voronoi(rng: np.random.Generator, n: int, gu: int, gv: int):
    """Voronoi cells of a jittered gu x gv seed grid on an n x n torus (tiles seamlessly).

    Distances are in cell units (so gu < gv gives cells elongated along u). Returns the nearest
    and second-nearest seed distances, the nearest seed's index and the offset to it.
    """
    jitter = rng.random((gv, gu, 2))
    v, u = np.meshgrid((np.arange(n) + 0.5) / n * gv, (np.arange(n) + 0.5) / n * gu, indexing="ij")
    cu, cv = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    best = np.full((2, n, n), np.inf)
    idx = np.zeros((n, n), dtype=np.int64)
    rel = np.zeros((n, n, 2))
    for dv in range(-2, 3):
        for du in range(-2, 3):
            ku, kv = cu + du, cv + dv
            iu, iv = ku % gu, kv % gv
            su = ku + jitter[iv, iu, 0]
            sv = kv + jitter[iv, iu, 1]
            du_, dv_ = u - su, v - sv
            d = fm.hypot(du_, dv_)
            closer = d < best[0]
            best[1] = np.where(closer, best[0], np.minimum(best[1], d))
            best[0] = np.where(closer, d, best[0])
            idx = np.where(closer, iv * gu + iu, idx)
            rel[closer] = np.stack([du_, dv_], -1)[closer]
    return best[0], best[1], idx, rel


def _mli_texture(rng: np.random.Generator, color, n: int = 512) -> np.ndarray:
    """Crumpled foil: faceted cells of varying brightness, creases, and soft waviness."""
    gu, gv = 11, 20
    f1, f2, idx, rel = _periodic_voronoi(rng, n, gu, gv)
    seeds = gu * gv
    level = rng.uniform(0.55, 1.1, seeds)                 # each facet catches the light differently
    tilt = rng.normal(size=(seeds, 2)) * 0.22             # and shades across itself
    shade = level[idx] + fm.dot(rel, tilt[idx])
    crease = fm.exp(-np.square((f2 - f1) * (n / gv) / 1.6))   # thin lines where facets meet
    shade = shade * (1.0 - 0.35 * crease) + 0.12 * crease * (level[idx] > 0.9)
    wave = _periodic_noise(rng, n, 2, 8)
    fine = _periodic_noise(rng, n, 40, 120)
    shade = shade * (1.0 + 0.08 * wave) + 0.04 * fine
    img = np.clip(shade, 0.25, 1.2)[..., None] * np.asarray(color, dtype=np.float64)
    i = np.arange(n)
    seam = (i < 3) | (i >= n - 3)                          # blanket stitching at the tile border
    img[seam, :] *= 0.7
    img[:, seam] *= 0.7
    return _to_u8(img)


def _skin_texture(rng: np.random.Generator, n: int = 512) -> np.ndarray:
    """Beta-cloth covered debris shields: 4 x 2 panels a tile, seams, stitching, faint dirt."""
    pu, pv = 2, 2
    tone = 1.0 + 0.025 * rng.normal(size=(pv, pu))
    img = np.repeat(np.repeat(tone, n // pv, 0), n // pu, 1)[..., None] * np.array([226.0, 224.0, 214.0])
    img *= (1.0 + 0.025 * _periodic_noise(rng, n, 2, 10))[..., None]
    i = np.arange(n)
    su, sv = i % (n // pu), i % (n // pv)
    stitch_u = (su % 16 == 8) & (np.arange(n)[:, None] % 4 < 2)
    img[stitch_u] *= 0.94
    seam_u, seam_v = (su < 2), (sv < 2)
    img[:, seam_u] = np.array([172.0, 170.0, 162.0])
    img[seam_v, :] = np.array([172.0, 170.0, 162.0])
    bolts = ((su % 64) == 5)[None, :] & ((sv % 64) == 5)[:, None]   # fasteners along the panels
    img[bolts] *= 0.8
    return _to_u8(img)


def _radiator_texture(rng: np.random.Generator, n: int = 512) -> np.ndarray:
    """White panels with fine flow-tube lines along v and faint mottling."""
    img = np.full((n, n, 3), 236.0) * np.array([1.0, 1.0, 0.985])
    img *= (1.0 + 0.02 * _periodic_noise(rng, n, 2, 12))[..., None]
    i = np.arange(n)
    tubes = (i % 32) < 2
    img[:, tubes] *= 0.86
    return _to_u8(img)


def _textures() -> dict[str, np.ndarray]:
    return {k: v.copy() for k, v in _cached_textures().items()}


@lru_cache(maxsize=1)
def _cached_textures() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(4242)
    return {
        "solar_cells": _solar_texture(rng),
        "mli_gold": _mli_texture(rng, (246.0, 192.0, 92.0)),
        "mli_silver": _mli_texture(rng, (236.0, 236.0, 230.0)),
        "module_skin": _skin_texture(rng),
        "radiator": _radiator_texture(rng),
    }


# ----------------------------------------------------------------------------- helpers
def _basis(u, v) -> np.ndarray:
    """Rotation with columns u, v (orthogonalised), u x v."""
    u = unit(u)
    v = np.asarray(v, dtype=np.float64)
    v = unit(v - fm.dot(v, u) * u)
    return np.stack([u, v, np.cross(u, v)], axis=1)


def _obox(center, u, v, size, material: str, uv_scale: float = 1.0) -> MeshPart:
    """A box whose local x, y run along u, v (z = u x v), sizes along those."""
    return box("p", size, material, transform(center, _basis(u, v)), uv_scale)


def _tiled(part: MeshPart, tile: float, circumference: float | None = None) -> MeshPart:
    """Scale metre UVs to `tile`-metre texture tiles; around a cylinder use a whole number."""
    su = 1.0 / tile
    if circumference:
        su = max(1, round(circumference / tile)) / circumference
    return scale_uv(part, su, 1.0 / tile)


def _sphere_tiled(part: MeshPart, radius: float, tile: float) -> MeshPart:
    """uv_sphere UVs ([0, 1]^2) scaled to `tile`-metre tiles (a whole number around)."""
    return scale_uv(part, max(1, round(2 * np.pi * radius / tile)), np.pi * radius / tile)


def _perp(axis) -> tuple[np.ndarray, np.ndarray]:
    f = frame_from_z(axis)
    return f[:, 0], f[:, 1]


class _Parts:
    """Collects primitives into named groups of one material (per joint); merged at the end.

    `matrix` is a 4x4 matrix into the station frame, or a (joint, 4x4 matrix into that joint's
    frame) pair for parts that hang under a joint (the outboard truss, the solar wings)."""

    def __init__(self, articulated: bool = True) -> None:
        self.groups: dict[tuple, tuple[str, list[MeshPart]]] = {}
        self.rest = None if articulated else _rest_frames()

    def add(self, group: str, material: str, *parts: MeshPart, matrix=None) -> None:
        joint = None
        if isinstance(matrix, tuple):
            joint, matrix = matrix
            if self.rest is not None:   # flat: straight into the station frame at rest, as one group
                joint, matrix = None, fm.matmul(self.rest[joint], matrix)
        if (joint, group) in self.groups and self.groups[joint, group][0] != material:
            group = f"{group}_{material}"   # a second material in one region gets its own part
        mat, plist = self.groups.setdefault((joint, group), (material, []))
        for p in parts:
            plist.append(p if matrix is None else p.transformed(matrix))

    def build(self) -> tuple[MeshPart, ...]:
        return tuple(replace(merge(name, plist, mat), joint=joint)
                     for (joint, name), (mat, plist) in self.groups.items() if plist)


def _inboard() -> np.ndarray:
    return transform((0.0, 0.0, TRUSS_Z))


def _outboard_rest() -> np.ndarray:
    """The outboard truss frame (its alpha joint's) in the station frame, at rest."""
    return transform((0.0, 0.0, TRUSS_Z), rot_y(SARJ_ANGLE))


def _outboard(sign: int) -> tuple[str, np.ndarray]:
    """Parts built in the outboard truss frame of one side hang under that side's alpha joint."""
    return ALPHA_JOINTS[sign], np.eye(4)


# ----------------------------------------------------------------------------- truss
def _lattice(y0: float, y1: float, hx: float, hz: float, bay: float = 2.4,
             longeron: float = 0.16, member: float = 0.09, joint: float = 0.26) -> list[MeshPart]:
    """A rectangular Warren truss along Y (local frame, axis at the origin)."""
    parts = []
    corners = [(-hx, -hz), (hx, -hz), (hx, hz), (-hx, hz)]
    n = max(1, int(round((y1 - y0) / bay)))
    ys = np.linspace(y0, y1, n + 1)
    up = [(0, 0, 1), (0, 0, 1), (0, 0, 1), (0, 0, 1)]
    for (cx, cz) in corners:
        parts.append(box("p", (longeron, y1 - y0, longeron), TRUSS, transform((cx, (y0 + y1) / 2, cz))))
    for k, y in enumerate(ys):
        end = k in (0, n)
        w = joint if end else member
        if end:  # interface frames sit just inside the segment, so neighbours make a double ring
            y = y + (joint / 2 if k == 0 else -joint / 2)
        for f in range(4):
            (ax, az), (bx, bz) = corners[f], corners[(f + 1) % 4]
            parts.append(box_between("p", (ax, y, az), (bx, y, bz), w, TRUSS, up=(0, 1, 0)))
        if end:  # joint blocks at the segment interface
            for (cx, cz) in corners:
                parts.append(box("p", (0.42, joint, 0.42), TRUSS, transform((cx, y, cz))))
    for k in range(n):
        for f in range(4):
            (ax, az), (bx, bz) = corners[f], corners[(f + 1) % 4]
            if (k + f) % 2:
                (ax, az), (bx, bz) = (bx, bz), (ax, az)
            parts.append(box_between("p", (ax, ys[k], az), (bx, ys[k + 1], bz), member, TRUSS, up=up[f]))
    return parts


def _equipment(rng, b: _Parts, y0, y1, hx, hz, matrix, density=0.8, top=True) -> None:
    """Boxes inside the truss bays and a few ORUs on its top face."""
    n = max(1, int(round((y1 - y0) / 2.4)))
    ys = np.linspace(y0, y1, n + 1)
    groups = [("truss_equipment", SKIN), ("truss_equipment_dark", DARK), ("truss_equipment_mli", MLI_GOLD)]
    for k in range(n):
        lo, hi = ys[k] + 0.15, ys[k + 1] - 0.15
        if rng.random() < density:
            for _ in range(rng.integers(1, 3)):
                sx = rng.uniform(0.8, 2 * hx - 0.8)
                sy = rng.uniform(0.6, hi - lo)
                sz = rng.uniform(0.5, 2 * hz - 0.8)
                cx = rng.uniform(-hx + 0.25 + sx / 2, hx - 0.25 - sx / 2)
                cy = rng.uniform(lo + sy / 2, hi - sy / 2)
                cz = rng.uniform(-hz + 0.25 + sz / 2, hz - 0.25 - sz / 2)
                g, mat = groups[rng.choice(3, p=[0.5, 0.25, 0.25])]
                tile = MLI_TILE if mat == MLI_GOLD else SKIN_TILE
                b.add(g, mat, box("p", (sx, sy, sz), mat, transform((cx, cy, cz)), 1.0 / tile), matrix=matrix)
        if top and rng.random() < 0.55:  # an ORU sitting on the top face
            sx, sy, sz = rng.uniform(0.7, 1.6), rng.uniform(0.6, min(1.8, hi - lo)), rng.uniform(0.35, 0.8)
            cx = rng.uniform(-hx + 0.2 + sx / 2, hx - 0.2 - sx / 2)
            cy = rng.uniform(lo + sy / 2, hi - sy / 2)
            g, mat = groups[rng.choice(3, p=[0.45, 0.15, 0.4])]
            tile = MLI_TILE if mat == MLI_GOLD else SKIN_TILE
            b.add(g, mat, box("p", (sx, sy, sz), mat, transform((cx, cy, hz + 0.08 + sz / 2)), 1.0 / tile),
                  matrix=matrix)


def _elc(rng, b: _Parts, yc: float, side: int, matrix) -> None:
    """An ExPRESS logistics carrier: a deck on struts off the top (side=+1) or bottom face."""
    z0 = side * (HZ + 0.15)
    zd = side * (HZ + 0.75)
    for dx in (-1.5, 1.5):
        for dy in (-1.6, 1.6):
            b.add("truss_hardware", METAL, box_between("p", (dx * 0.8, yc + dy * 0.8, z0),
                                                        (dx, yc + dy, zd), 0.1, METAL), matrix=matrix)
    b.add("truss_equipment", SKIN, box("p", (4.0, 4.2, 0.22), SKIN, transform((0, yc, zd)), 1 / SKIN_TILE),
          matrix=matrix)
    groups = [("truss_equipment", SKIN, SKIN_TILE), ("truss_equipment_dark", DARK, 1.0),
              ("truss_equipment_mli", MLI_GOLD, MLI_TILE)]
    for cx in (-1.1, 1.1):
        for cy in (-1.3, 0.0, 1.3):
            if rng.random() < 0.8:
                sx, sy, sz = rng.uniform(0.9, 1.5), rng.uniform(0.8, 1.15), rng.uniform(0.4, 1.1)
                g, mat, tile = groups[rng.choice(3, p=[0.35, 0.15, 0.5])]
                zc = zd + side * (0.11 + sz / 2)
                b.add(g, mat, box("p", (sx, sy, sz), mat, transform((cx, yc + cy, zc)), 1 / tile), matrix=matrix)


def _sarj(b: _Parts, sign: int) -> None:
    y0, y1 = (SARJ_Y[0] * sign, SARJ_Y[1] * sign)
    m = _inboard()
    lo, hi = min(y0, y1), max(y0, y1)
    b.add("truss_equipment_dark", DARK, cylinder("p", 1.75, hi - lo, DARK, 40,
                                                 transform((0, lo, 0), rot_x(-np.pi / 2))), matrix=m)
    for y in (lo, hi - 0.3):
        b.add("truss_hardware", METAL, cylinder("p", 2.15, 0.3, METAL, 40,
                                                transform((0, y, 0), rot_x(-np.pi / 2))), matrix=m)
    for k in range(6):  # drive / lock boxes around the ring
        a = k * np.pi / 3 + np.pi / 6
        c = np.array([2.25 * fm.cos(a), (lo + hi) / 2, 2.25 * fm.sin(a)])
        b.add("truss_equipment", SKIN, _obox(c, (0, 1, 0), (fm.cos(a), 0, fm.sin(a)), (0.7, 0.4, 0.45), SKIN,
                                             1 / SKIN_TILE), matrix=m)


def _truss(rng, b: _Parts) -> None:
    m_in = _inboard()
    segments = [  # name, y0, y1, outboard, hx, hz
        ("S0", -6.7, 6.7, False, HX, HZ),
        ("S1", 6.7, 20.5, False, HX, HZ), ("S3", 20.5, SARJ_Y[0], False, HX, HZ),
        ("S4", SARJ_Y[1], 45.0, True, HXO, HZO), ("S5", 45.0, 47.5, True, 1.5, 1.15),
        ("S6", 47.5, TRUSS_HALF_LENGTH, True, HXO, HZO),
    ]
    for name, y0, y1, outboard, hx, hz in segments:
        sides = [(name, y0, y1)]
        if name != "S0":
            sides.append(("P" + name[1:], -y1, -y0))
        for nm, a, c in sides:
            mat = _outboard(1 if nm[0] == "S" else -1) if outboard else m_in
            b.add(f"truss_{nm}", TRUSS, *_lattice(a, c, hx, hz), matrix=mat)
            _equipment(rng, b, a, c, hx, hz, mat, density=0.45 if outboard else 0.75, top=not outboard)
    # segment end caps where the truss meets the SARJ: solid bulkhead plates
    for s in (1, -1):
        for y, mat, hx, hz in ((s * (SARJ_Y[0] - 0.1), m_in, HX, HZ), (s * (SARJ_Y[1] + 0.1), _outboard(s), HXO, HZO)):
            b.add("truss_equipment", SKIN, box("p", (2 * hx - 0.3, 0.12, 2 * hz - 0.3), SKIN,
                                               transform((0, y, 0)), 1 / SKIN_TILE), matrix=mat)
        _sarj(b, s)
    # mobile transporter rails on the +X face, and the mobile base system with the arm base
    for z in (-0.9, 0.9):
        b.add("truss_hardware", METAL, box("p", (0.14, 2 * SARJ_Y[0] - 1.0, 0.22), METAL,
                                           transform((HX + 0.12, 0, z))), matrix=m_in)
    y_mbs = ARM_BASE[1]
    b.add("truss_equipment", SKIN, box("p", (0.5, 2.8, 2.6), SKIN, transform((HX + 0.45, y_mbs, 0)),
                                       1 / SKIN_TILE), matrix=m_in)
    b.add("truss_equipment_dark", DARK, box("p", (0.35, 1.2, 1.2), DARK, transform((HX + 0.85, y_mbs - 0.6, 0.5))),
          matrix=m_in)
    b.add("truss_hardware", METAL,
          cylinder("p", 0.32, 0.6, METAL, 20, transform((HX + 0.7, y_mbs, 0), rot_y(np.pi / 2))),
          cylinder("p", 0.45, 0.12, METAL, 20, transform((HX + 1.3, y_mbs, 0), rot_y(np.pi / 2))),
          matrix=m_in)
    # ELCs and the AMS-like payload on S3/P3
    _elc(rng, b, 24.0, +1, m_in)
    _elc(rng, b, 28.0, -1, m_in)
    _elc(rng, b, -24.5, +1, m_in)
    _elc(rng, b, -28.0, -1, m_in)
    _ams(b, 27.8, m_in)
    # S0 - Destiny attachment struts
    for x in (-1.6, 1.6):
        for y in (-2.5, 2.5):
            b.add("truss_hardware", METAL, box_between("p", (x * 0.7, y * 0.5, MODULE_Z + 1.8),
                                                        (x, y, TRUSS_Z - HZ), 0.14, METAL))
    # S-band antennas on S1 / P1 and a few upright booms
    for y in (14.5, -14.5):
        base = np.array([HX - 0.6, y, HZ + 0.1])
        b.add("truss_hardware", METAL, box_between("p", base, base + (0, 0, 1.3), 0.12, METAL), matrix=m_in)
        b.add("antennas", SKIN, dish("p", 0.45, 0.14, SKIN, 20, 3,
                                     transform(base + (0.15, 0, 1.35), frame_from_z((1, 0, 0.6)))), matrix=m_in)


def _ams(b: _Parts, y: float, matrix) -> None:
    """A large payload on the S3 top face: an octagonal drum with side radiators."""
    zc = HZ + 0.6
    b.add("truss_hardware", METAL, *[box_between("p", (sx * 1.3, y + sy * 1.0, HZ), (sx * 1.1, y + sy * 0.8, zc),
                                                 0.12, METAL) for sx in (-1, 1) for sy in (-1, 1)], matrix=matrix)
    b.add("truss_equipment", SKIN, cylinder("p", 1.35, 1.6, SKIN, 8,
                                            transform((0, y, zc), frame_from_z((0, 0, 1)))), matrix=matrix)
    b.add("truss_equipment_mli", MLI_GOLD, _tiled(cylinder("p", 1.0, 0.6, MLI_GOLD, 16,
                                                            transform((0, y, zc + 1.6))), MLI_TILE, 2 * np.pi),
          matrix=matrix)
    for s in (-1, 1):
        b.add("radiator_S1", RADIATOR, box("p", (0.06, 2.6, 1.9), RADIATOR,
                                           transform((s * 1.5, y, zc + 0.95)), 1 / RADIATOR_TILE), matrix=matrix)


# ----------------------------------------------------------------------------- radiators
def _panel_stack(b: _Parts, group: str, start, length_dir, width_dir, width: float, n: int,
                 panel: float, gap: float, offset: float, matrix) -> None:
    """n thin radiator panels in a row from `start`, with two edge rails behind them."""
    start = np.asarray(start, dtype=np.float64)
    r, w = unit(length_dir), unit(width_dir)
    normal = np.cross(w, r)
    for i in range(n):
        c = start + r * (offset + i * (panel + gap) + panel / 2)
        b.add(group, RADIATOR, _obox(c, w, r, (width, panel, 0.05), RADIATOR, 1 / RADIATOR_TILE), matrix=matrix)
    end = start + r * (offset + n * (panel + gap) - gap)
    for s in (-1, 1):
        e = w * s * (width / 2 - 0.1) - normal * 0.08
        b.add("truss_hardware", METAL, box_between("p", start + e, end + e, 0.08, METAL), matrix=matrix)
    for i in range(n + 1):  # cross members at the hinges
        c = start + r * (offset + i * (panel + gap) - gap / 2) - normal * 0.08
        b.add("truss_hardware", METAL, box_between("p", c - w * (width / 2 - 0.1), c + w * (width / 2 - 0.1),
                                                    0.06, METAL), matrix=matrix)


RADIATOR_BEAM = np.array([-HX - 0.25, 0.0, -HZ - 0.2])   # the S1/P1 radiator beam's axis (inboard frame, along Y)
RADIATOR_PHI = fm.radians(35.0)                          # rest: the panels hang down and aft, 35 degrees aft of nadir


def _radiators(b: _Parts) -> None:
    r = np.array([-fm.sin(RADIATOR_PHI), 0.0, -fm.cos(RADIATOR_PHI)])   # down and aft
    m = _inboard()
    for s, name in ((1, "radiator_S1"), (-1, "radiator_P1")):
        y0, y1 = 10.0 * s, 20.2 * s
        beam = RADIATOR_BEAM
        b.add("truss_hardware", METAL, box_between("p", beam + (0, y0, 0), beam + (0, y1, 0), 0.35, METAL),
              cylinder("p", 0.55, 0.6, METAL, 24, transform(beam + (0, y0 - 0.6 if s > 0 else y0, 0),
                                                             rot_x(-np.pi / 2))), matrix=m)
        for k in range(3):
            yc = s * (11.6 + 3.5 * k)
            if b.rest is None:   # articulated: the panels turn about the beam on its TRRJ (joint frame at the beam)
                _panel_stack(b, name + "_panels", (0.0, yc, 0.0), r, (0, 1, 0), 3.2, 8, 2.7, 0.1, 0.45,
                             (RADIATOR_JOINTS[s], np.eye(4)))
            else:                # flat: exactly as the static station was built
                _panel_stack(b, name, beam + (0, yc, 0), r, (0, 1, 0), 3.2, 8, 2.7, 0.1, 0.45, m)
    # photovoltaic radiators: one per solar module, sticking out aft in the outboard frame
    for s in (1, -1):
        mo = _outboard(s)
        for yc in (41.0, 50.5):
            start = np.array([-HXO - 0.1, s * yc, 0.0])
            b.add("truss_hardware", METAL, box("p", (0.5, 1.2, 1.0), METAL, transform(start + (-0.1, 0, 0))),
                  matrix=mo)
            _panel_stack(b, "radiator_PV", start, (-1, 0, 0), (0, 1, 0), 3.4, 7, 1.85, 0.1, 0.4, mo)


# ----------------------------------------------------------------------------- solar arrays
def _mast(length0: float, length1: float, radius: float = 0.42, bay: float = 1.5) -> list[MeshPart]:
    """A triangular lattice mast along +Z (wing frame)."""
    parts = []
    ang = fm.radians([90.0, 210.0, 330.0])
    c = np.stack([radius * fm.cos(ang), radius * fm.sin(ang)], 1)
    n = int(round((length1 - length0) / bay))
    zs = np.linspace(length0, length1, n + 1)
    for (x, y) in c:
        parts.append(box("p", (0.05, 0.05, length1 - length0), TRUSS, transform((x, y, (length0 + length1) / 2))))
    for k, z in enumerate(zs):
        for i in range(3):
            a, bb = c[i], c[(i + 1) % 3]
            parts.append(box_between("p", (a[0], a[1], z), (bb[0], bb[1], z), 0.04, TRUSS))
            if k < n:
                parts.append(box_between("p", (a[0], a[1], z), (bb[0], bb[1], zs[k + 1]), 0.025, TRUSS))
    return parts


def _wing(b: _Parts, name: str) -> None:
    """One solar wing: BGA + canister + two blankets either side of a mast, in its beta joint's frame
    (the mast along +Z, the cells facing +X)."""
    m = (beta_joint_name(name), np.eye(4))
    z0 = HZO
    b.add("truss_hardware", METAL, cylinder("p", 0.55, 0.7, METAL, 24, transform((0, 0, z0))), matrix=m)
    b.add("solar_blanket_boxes", SKIN, _tiled(cylinder("p", 0.62, 1.2, SKIN, 24, transform((0, 0, z0 + 0.7))),
                                              SKIN_TILE, 2 * np.pi * 0.62), matrix=m)
    zb = z0 + 1.9
    zs, ze = zb + 0.5, zb + 0.5 + WING_LENGTH
    b.add("solar_masts", TRUSS, *_mast(zb, ze + 0.3), matrix=m)
    front = np.stack([[0, 1, 0], [0, 0, 1], [1, 0, 0]], 1).astype(float)    # u->Y, v->Z, n->+X
    back = np.stack([[0, -1, 0], [0, 0, 1], [-1, 0, 0]], 1).astype(float)   # u->-Y, v->Z, n->-X
    for s in (-1, 1):
        yb = s * (BLANKET_GAP / 2 + BLANKET_WIDTH / 2)
        cz = (zs + ze) / 2
        f = grid("p", BLANKET_WIDTH, WING_LENGTH, SOLAR, 1, 6, transform((0.01, yb, cz), front))
        bk = grid("p", BLANKET_WIDTH, WING_LENGTH, SOLAR_BACK, 1, 1, transform((-0.01, yb, cz), back))
        b.add(f"solar_wing_{name}", SOLAR,
              scale_uv(f, BLANKET_WIDTH / SOLAR_TILE, WING_LENGTH / SOLAR_TILE), matrix=m)
        b.add("solar_wing_backs", SOLAR_BACK, bk, matrix=m)
        for zc, h in ((zb + 0.25, 0.5), (ze + 0.15, 0.3)):   # blanket box and tip bar
            b.add("solar_blanket_boxes", SKIN,
                  box("p", (0.45, BLANKET_WIDTH + 0.15, h), SKIN, transform((0, yb, zc)), 1 / SKIN_TILE),
                  matrix=m)
        # guide wires along the outer edges
        yw = s * (BLANKET_GAP / 2 + BLANKET_WIDTH + 0.06)
        b.add("truss_hardware", METAL, box("p", (0.02, 0.02, WING_LENGTH), METAL, transform((0, yw, cz))),
              matrix=m)
    b.add("truss_hardware", METAL,
          box("p", (0.5, BLANKET_GAP + 2 * BLANKET_WIDTH, 0.12), METAL, transform((0, 0, ze + 0.38))),
          box("p", (0.5, BLANKET_GAP + 2 * BLANKET_WIDTH, 0.12), METAL, transform((0, 0, zb + 0.56))), matrix=m)


def _solar(b: _Parts) -> None:
    for side, s in (("S", 1), ("P", -1)):
        for seg, yc in (("4", WING_Y[0]), ("6", WING_Y[1])):
            name = side + seg
            _wing(b, name + "a")
            _wing(b, name + "b")
            # the integrated equipment assembly: a white box frame carrying the BGAs
            b.add("truss_equipment", SKIN, box("p", (2 * HXO - 0.5, 3.0, 2 * HZO - 0.4), SKIN,
                                               transform((0, s * yc, 0)), 1 / SKIN_TILE), matrix=_outboard(s))


# ----------------------------------------------------------------------------- joints
# The outboard truss of each side turns about the truss axis (Y through (0, 0, TRUSS_Z)) on its solar
# alpha rotary joint; each wing turns about its mast (its frame's Z) on its beta gimbal, under its
# side's alpha joint. Rest angles are the pose the static station was built in. Limits (degrees,
# docs/physics.md "Sun-tracking arrays"): the SARJ turns continuously (-180..180, angles wrap), as on
# the ISS; the beta gimbals are held to +-BETA_LIMIT (the +-75 degree solar beta range the ISS's orbit
# needs; a choice); at a limit a wing stops there and misses the Sun by the excess.
ALPHA_JOINTS = {1: "AlphaS", -1: "AlphaP"}
# The S1/P1 thermal radiators turn about their beam (station Y) on the thermal radiator rotary joints
# (TRRJ), edge-on to the Sun so it heats them least. Rest 0 is the pose the static station was built in
# (panels 35 degrees aft of nadir). The limits keep the 22 m panels clear of the modules forward of the
# truss and of the truss itself (tests/scene/test_tracking.py sweeps them: docs/physics.md section 14).
RADIATOR_JOINTS = {1: "RadiatorS", -1: "RadiatorP"}
RADIATOR_LIMITS = (-85.0, 85.0)
ALPHA_REST = float(fm.degrees(SARJ_ANGLE))
BETA_LIMIT = 75.0
BETA_REST = {"S4a": 8.0, "S4b": -5.0, "S6a": -3.0, "S6b": 10.0, "P4a": 5.0, "P4b": -9.0, "P6a": -7.0, "P6b": 4.0}
WINGS = tuple(BETA_REST)   # "b" wings hang below the truss: their frame is turned 180 degrees about X


def beta_joint_name(wing: str) -> str:
    return f"Beta{wing}"


def _rest_frames() -> dict[str, np.ndarray]:
    """{joint: its frame in the station frame at rest}, composed as the static station always was (so
    the flat build, from which the camera rig was chosen, stays bit-identical)."""
    frames = {}
    for s in (1, -1):
        frames[ALPHA_JOINTS[s]] = _outboard_rest()
    for wing in WINGS:
        s = 1 if wing[0] == "S" else -1
        yc = s * (WING_Y[0] if wing[1] == "4" else WING_Y[1])
        flip = np.eye(4) if wing.endswith("a") else transform(rotate=rot_x(np.pi))
        frames[beta_joint_name(wing)] = fm.matmul(fm.matmul(fm.matmul(_outboard_rest(), transform((0.0, yc, 0.0))), flip),
                                                   transform(rotate=rot_z(fm.radians(BETA_REST[wing]))))
    for s in (1, -1):
        frames[RADIATOR_JOINTS[s]] = transform(_radiator_hinge())
    return frames


def _radiator_hinge() -> tuple[float, float, float]:
    """The radiator joints' origin in the station frame: on the beam's axis (rounded: 0.3, not 0.30000000000000004)."""
    x, y, z = RADIATOR_BEAM + (0.0, 0.0, TRUSS_Z)
    return (round(float(x), 9), round(float(y), 9), round(float(z), 9))


def station_joints() -> tuple[Joint, ...]:
    """The 2 alpha joints, the 8 beta joints (parents first), then the 2 radiator joints."""
    joints = [Joint(ALPHA_JOINTS[s], None, "Y", ALPHA_REST, -180.0, 180.0, (0.0, 0.0, TRUSS_Z),
                    tracks="Sun", op="alpha") for s in (1, -1)]
    for wing in WINGS:
        s = 1 if wing[0] == "S" else -1
        yc = s * (WING_Y[0] if wing[1] == "4" else WING_Y[1])
        joints.append(Joint(beta_joint_name(wing), ALPHA_JOINTS[s], "Z", BETA_REST[wing], -BETA_LIMIT, BETA_LIMIT,
                            (0.0, yc, 0.0), (180.0 if wing.endswith("b") else 0.0, 0.0, 0.0), tracks="Sun",
                            op="beta"))
    joints += [Joint(RADIATOR_JOINTS[s], None, "Y", 0.0, *RADIATOR_LIMITS, _radiator_hinge(),
                     tracks="SunEdgeOn", op="trrj") for s in (1, -1)]
    return tuple(joints)


def _small_array(b: _Parts, root, direction, length: float, width: float, tilt: float, group: str) -> None:
    """A single-blanket array on a boom (Russian modules, vehicles): direction is the span."""
    root = np.asarray(root, dtype=np.float64)
    d = unit(direction)
    n = fm.matmul(rot_y(tilt), np.array([0.0, 0.0, 1.0]))
    n = unit(n - fm.dot(n, d) * d)
    w = np.cross(d, n)                       # across the blanket
    c = root + d * (0.6 + length / 2)
    rot_f = np.stack([w, d, n], 1)           # grid u->w, v->d, normal n
    rot_b = np.stack([-w, d, -n], 1)
    f = grid("p", width, length, SOLAR, 1, 2, transform(c + n * 0.01, rot_f))
    bk = grid("p", width, length, SOLAR_BACK, 1, 1, transform(c - n * 0.01, rot_b))
    b.add(group, SOLAR, scale_uv(f, width / SOLAR_TILE, length / SOLAR_TILE))
    b.add("solar_wing_backs", SOLAR_BACK, bk)
    b.add("truss_hardware", METAL, box_between("p", root, root + d * 0.65, 0.1, METAL))
    for k in range(1, 4):  # panel frames across the blanket
        p = root + d * (0.6 + length * k / 4)
        b.add("truss_hardware", METAL, box_between("p", p - w * width / 2, p + w * width / 2, 0.04, METAL))


# ----------------------------------------------------------------------------- modules
def _sections(b: _Parts, start, axis, sections, segments: int = 48) -> float:
    """Stack of cylinders / frusta along `axis` from `start`: (length, r0, r1, group, material)."""
    start = np.asarray(start, dtype=np.float64)
    axis = unit(axis)
    rot = frame_from_z(axis)
    t = 0.0
    for length, r0, r1, group, mat in sections:
        part = cylinder("p", r0, length, mat, segments, transform(start + axis * t, rot), radius_top=r1)
        if mat in (SKIN, MLI_GOLD, MLI_SILVER):
            part = _tiled(part, SKIN_TILE if mat == SKIN else MLI_TILE, 2 * np.pi * max(r0, r1))
        b.add(group, mat, part)
        t += length
    return t


def _skin(length: float, r0: float, r1: float, group: str) -> tuple:
    return (length, r0, r1, group, SKIN)


def _port(length: float, r: float) -> tuple:
    return (length, r, r, "module_ports", METAL)


def _foil(length: float, r0: float, r1: float) -> tuple:
    return (length, r0, r1, "russian_mli", MLI_SILVER)


def _handrails(b: _Parts, start, axis, radius: float, t0: float, t1: float, angles, spacing: float = 1.6) -> None:
    start = np.asarray(start, dtype=np.float64)
    axis = unit(axis)
    e1, e2 = _perp(axis)
    n = max(1, int((t1 - t0) // spacing))
    ts = np.linspace(t0, t1, n + 2)[1:-1]
    for a in angles:
        rd = fm.cos(a) * e1 + fm.sin(a) * e2
        for t in ts:
            p0 = start + axis * (t - 0.3)
            p1 = start + axis * (t + 0.3)
            for p in (p0, p1):
                b.add("module_handrails", HANDRAIL, box_between("p", p + rd * (radius - 0.02), p + rd * (radius + 0.14),
                                                                0.035, HANDRAIL))
            b.add("module_handrails", HANDRAIL, box_between("p", p0 + rd * (radius + 0.14), p1 + rd * (radius + 0.14),
                                                            0.035, HANDRAIL, up=rd))


def _clutter(rng, b: _Parts, start, axis, radius: float, t0: float, t1: float, count: int) -> None:
    """Small external boxes (avionics, MLI-covered payloads, grapple fixtures) on a barrel."""
    start = np.asarray(start, dtype=np.float64)
    axis = unit(axis)
    e1, e2 = _perp(axis)
    for k in range(count):
        a = rng.uniform(0, 2 * np.pi)
        t = rng.uniform(t0 + 0.5, t1 - 0.5)
        rd = fm.cos(a) * e1 + fm.sin(a) * e2
        tang = np.cross(axis, rd)
        kind = k % 3
        if kind == 2:   # grapple fixture: a base plate and a pin
            c = start + axis * t + rd * (radius + 0.05)
            b.add("module_details_dark", DARK, _obox(c, axis, tang, (0.45, 0.45, 0.14), DARK))
            b.add("module_ports", METAL, cylinder("p", 0.06, 0.35, METAL, 10,
                                                  transform(c, frame_from_z(rd))))
            continue
        h = rng.uniform(0.15, 0.45)
        size = (rng.uniform(0.4, 1.2), rng.uniform(0.3, 0.8), h)
        c = start + axis * t + rd * (radius + h / 2 - 0.04)
        if kind == 0:
            b.add("module_details_mli", MLI_GOLD, _obox(c, axis, tang, size, MLI_GOLD, 1 / MLI_TILE))
        else:
            b.add("module_details_dark", DARK, _obox(c, axis, tang, size, DARK))


def _cbm(b: _Parts, center, axis, r: float = 1.0, length: float = 0.35) -> None:
    """A berthing / docking ring from `center` along `axis`."""
    axis = unit(axis)
    b.add("module_ports", METAL, cylinder("p", r, length, METAL, 32, transform(center, frame_from_z(axis))))


def _us_module(b: _Parts, name: str, start, axis, length: float, radius: float, cone: float = 0.6,
               rails=True, rng=None, clutter: int = 0) -> None:
    """A US-style module: CBM rings at both ends, end cones and a skin-covered barrel."""
    main = length - 2 * (0.3 + cone)
    _sections(b, start, axis, [
        (0.3, 1.0, 1.0, "module_ports", METAL),
        (cone, 1.3, radius, name, SKIN),
        (main, radius, radius, name, SKIN),
        (cone, radius, 1.3, name, SKIN),
        (0.3, 1.0, 1.0, "module_ports", METAL),
    ])
    if rails:
        _handrails(b, start, axis, radius, 0.3 + cone, length - 0.3 - cone,
                   fm.radians([20, 110, 200, 290]))
    if clutter:
        _clutter(rng, b, start, axis, radius, 0.3 + cone, length - 0.3 - cone, clutter)


def _node_ports(b: _Parts, center, radius: float, dirs, reach: float = 2.7) -> None:
    """Berthing rings on a node's sides, each reaching `reach` from the node axis."""
    center = np.asarray(center, dtype=np.float64)
    for d in dirs:
        d = unit(d)
        _cbm(b, center + d * (radius - 0.2), d, 1.05, reach - radius + 0.2)


def _cupola(b: _Parts, top) -> None:
    top = np.asarray(top, dtype=np.float64)
    down = np.array([0.0, 0.0, -1.0])
    rot = frame_from_z(down)
    b.add("module_cupola", SKIN, _tiled(cylinder("p", 1.5, 0.45, SKIN, 6, transform(top, rot)), SKIN_TILE, 9.0))
    fr = cylinder("p", 1.5, 0.75, SKIN, 6, transform(top + down * 0.45, rot), radius_top=0.8)
    b.add("module_cupola", SKIN, _tiled(fr, SKIN_TILE, 9.0))
    # windows: one on each frustum face, and the round top one
    pts = fr.points
    for k in range(6):
        i, j = k, (k + 1) % 6
        quad = pts[[i, j, j + 6, i + 6]]
        c = quad.mean(axis=0)
        nrm = unit(np.cross(quad[1] - quad[0], quad[2] - quad[1]))
        along = unit(quad[1] - quad[0])
        up = unit(np.cross(nrm, along))
        b.add("module_windows", WINDOW, _obox(c + nrm * 0.01, along, up, (0.75, 0.5, 0.03), WINDOW))
    b.add("module_windows", WINDOW, cylinder("p", 0.5, 0.05, WINDOW, 24, transform(top + down * 1.2, rot)))


def _modules(rng, b: _Parts) -> None:
    X, Y, Z = np.eye(3)
    zc = MODULE_Z
    # --- US segment -----------------------------------------------------------------------
    _us_module(b, "module_destiny", (-4.25, 0, zc), X, 8.5, 2.15, rng=rng, clutter=6)
    b.add("module_windows", WINDOW, cylinder("p", 0.3, 0.05, WINDOW, 20,
                                             transform((1.0, 0, zc - 2.17), rot_x(np.pi))))
    _us_module(b, "module_harmony", (4.25, 0, zc), X, 7.2, 2.2, cone=0.5, rng=rng, clutter=3)
    hc = np.array([7.85, 0, zc])
    _node_ports(b, hc, 2.2, [Y, -Y, Z, -Z])
    _us_module(b, "module_unity", (-4.25, 0, zc), -X, 5.5, 2.25, cone=0.4, rails=False)
    uc = np.array([-7.0, 0, zc])
    _node_ports(b, uc, 2.25, [Y, -Y, Z, -Z])
    # PMA-2 + docking adapter + a docked capsule, forward
    _sections(b, (11.45, 0, zc), X, [
        (1.9, 1.0, 0.85, "module_pma", SKIN), (0.45, 0.95, 0.95, "module_ports", METAL),
        (0.3, 0.75, 0.75, "module_ports", METAL),
        (2.3, 0.8, 1.85, "vehicles", SKIN), (0.25, 1.9, 1.9, "module_details_dark", DARK),
        (2.8, 1.85, 1.85, "vehicles", SKIN)])
    # PMA-3 on Harmony zenith
    _sections(b, hc + Z * 2.7, Z, [(1.6, 1.0, 0.85, "module_pma", SKIN), (0.4, 0.95, 0.95, "module_ports", METAL)])
    # Columbus (starboard) and Kibo (port) on Harmony
    col = "module_columbus"
    _sections(b, hc + Y * 2.7, Y, [_skin(0.6, 1.3, 2.25, col), _skin(5.4, 2.25, 2.25, col), _skin(0.9, 2.25, 1.2, col)])
    _handrails(b, hc + Y * 2.7, Y, 2.25, 0.6, 6.0, fm.radians([30, 150, 270]))
    _clutter(rng, b, hc + Y * 2.7, Y, 2.25, 0.6, 6.0, 4)
    for k, (dx, dz) in enumerate(((-1.3, 0.9), (1.3, 0.9), (0.0, -1.2))):   # external payloads on the end cone
        mat, g = (MLI_GOLD, "module_details_mli") if k != 1 else (DARK, "module_details_dark")
        b.add(g, mat, box("p", (1.0, 0.9, 0.8), mat, transform(hc + (dx, 9.9, dz)), 1 / MLI_TILE))
    kibo_len = 11.2
    kibo = "module_kibo"
    _sections(b, hc - Y * 2.7, -Y, [_skin(0.6, 1.3, 2.2, kibo), _skin(kibo_len - 1.2, 2.2, 2.2, kibo),
                                    _skin(0.6, 2.2, 1.3, kibo)])
    _handrails(b, hc - Y * 2.7, -Y, 2.2, 0.6, kibo_len - 0.6, fm.radians([0, 135, 225]))
    _clutter(rng, b, hc - Y * 2.7, -Y, 2.2, 0.6, kibo_len - 0.6, 6)
    # Kibo logistics module (zenith) and exposed facility (end)
    elm = "module_kibo_elm"
    _sections(b, hc + (0, -7.5, 2.3), Z, [_port(0.3, 1.0), _skin(0.5, 1.3, 2.2, elm), _skin(3.0, 2.2, 2.2, elm),
                                          _skin(0.5, 2.2, 1.3, elm)])
    ef_y = -(2.7 + kibo_len + 0.3)
    _cbm(b, hc + (0, ef_y + 0.3, 0), -Y, 0.9, 0.3)
    ef = hc + (0, ef_y - 2.8, 0)
    b.add("module_kibo_ef", TRUSS, box("p", (5.0, 5.6, 0.9), TRUSS, transform(ef)))
    for cx in (-1.6, 0.0, 1.6):
        for cy in (-1.8, 0.6):
            sz = rng.uniform(0.6, 1.3)
            mat, g = (MLI_GOLD, "module_details_mli") if rng.random() < 0.6 else (SKIN, "module_kibo_ef_payloads")
            tile = MLI_TILE if mat == MLI_GOLD else SKIN_TILE
            b.add(g, mat, box("p", (1.3, rng.uniform(1.5, 2.2), sz), mat, transform(ef + (cx, cy, 0.45 + sz / 2)),
                              1 / tile))
    # Quest airlock (starboard of Unity) with gas tanks
    _sections(b, uc + Y * 2.7, Y, [(0.4, 1.3, 2.0, "module_quest", SKIN), (2.6, 2.0, 2.0, "module_quest", SKIN),
                                   (0.3, 2.0, 1.1, "module_quest", SKIN), (2.2, 1.1, 1.1, "module_quest", SKIN),
                                   (0.2, 0.9, 0.9, "module_ports", METAL)])
    for ax, az in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        b.add("module_details_mli", MLI_GOLD, _sphere_tiled(uv_sphere("p", 0.55, MLI_GOLD, 20, 10,
                                       transform(uc + (ax * 1.55, 4.6, az * 1.55))), 0.55, MLI_TILE))
    # Tranquility (port of Unity) with the Cupola below, PMM forward
    _us_module(b, "module_tranquility", uc - Y * 2.7, -Y, 6.7, 2.2, cone=0.4, rng=rng, clutter=4)
    n3 = uc - Y * 6.05
    _cupola(b, n3 - Z * 2.15)
    _sections(b, n3 + X * 2.4, X, [(0.3, 1.0, 1.0, "module_ports", METAL), (0.5, 1.3, 2.2, "module_pmm", SKIN),
                                   (4.0, 2.2, 2.2, "module_pmm", SKIN), (0.5, 2.2, 1.3, "module_pmm", SKIN)])
    # Z1 truss on Unity with control-moment-gyro domes and the Ku-band dish
    z1 = uc + Z * 2.25
    m_z1 = transform((z1[0], 0.0, z1[2] + 1.55))
    b.add("truss_Z1", TRUSS, *[p.transformed(transform(rotate=rot_z(np.pi / 2)))
                               for p in _lattice(-1.9, 1.9, 1.9, 1.5, bay=1.9)], matrix=m_z1)
    for dx in (-0.9, 0.9):
        for dy in (-0.9, 0.9):
            cmg = uv_sphere("p", 0.6, SKIN, 20, 10, transform((dx, dy, -0.3)))
            b.add("truss_equipment", SKIN, _sphere_tiled(cmg, 0.6, SKIN_TILE), matrix=m_z1)
    ku_base = z1 + (0, -1.2, 3.0)
    b.add("truss_hardware", METAL, box_between("p", ku_base, ku_base + (0, -0.5, 2.6), 0.15, METAL))
    b.add("antennas", SKIN, dish("p", 0.95, 0.3, SKIN, 28, 4,
                                 transform(ku_base + (0.3, -0.5, 2.75), frame_from_z((1.0, -0.4, 0.8)))))
    b.add("truss_hardware", METAL, cylinder_between("p", ku_base + (0.3, -0.5, 2.75),
                                                    ku_base + (0.3, -0.5, 2.75) + unit((1.0, -0.4, 0.8)) * 0.9,
                                                    0.05, METAL, 8))
    # PMA-1 between Unity and Zarya
    _sections(b, (-9.75, 0, zc), -X, [(2.0, 1.0, 1.3, "module_pma", SKIN)])
    # --- Russian segment --------------------------------------------------------------------
    zarya = [(0.3, 0.6, 0.6, "module_ports", METAL), (1.2, 1.1, 1.45, "russian_mli", MLI_SILVER),
             (2.3, 1.45, 1.45, "russian_mli", MLI_SILVER), (0.8, 1.45, 2.05, "module_zarya", SKIN),
             (7.2, 2.05, 2.05, "module_zarya", SKIN), (0.8, 2.05, 1.0, "russian_mli", MLI_SILVER)]
    _sections(b, (-11.75, 0, zc), -X, zarya)
    _handrails(b, (-16.05, 0, zc), -X, 2.05, 0.3, 7.0, fm.radians([45, 135, 315]))
    _clutter(rng, b, (-16.05, 0, zc), -X, 2.05, 0.3, 7.0, 5)
    for s in (1, -1):   # Zarya's retracted array stubs
        b.add("module_details_dark", DARK, box("p", (1.2, 1.6, 0.1), DARK, transform((-19.0, s * 2.8, zc))))
    # Rassvet on Zarya nadir with a Soyuz below it
    rz = np.array([-13.6, 0.0, zc - 1.45])
    t = _sections(b, rz, -Z, [(0.3, 0.7, 0.7, "module_ports", METAL), (5.4, 1.17, 1.17, "module_rassvet", SKIN),
                              (0.3, 0.6, 0.6, "module_ports", METAL)])
    _soyuz(b, rz - Z * t, -Z, "vehicles")
    # Zvezda
    zv = np.array([-25.5, 0.0, zc])
    b.add("russian_mli", MLI_SILVER, _sphere_tiled(uv_sphere("p", 1.15, MLI_SILVER, 32, 16, transform(zv)), 1.15,
                                                   MLI_TILE))
    zvz = "module_zvezda"
    _sections(b, zv - X * 0.9, -X, [_skin(3.6, 1.45, 1.45, zvz), _foil(1.0, 1.45, 2.07), _skin(5.3, 2.07, 2.07, zvz),
                                    _foil(0.7, 2.07, 1.0), _port(0.5, 0.6)])
    _handrails(b, zv - X * 0.9, -X, 1.45, 0.2, 3.4, fm.radians([45, 135, 225, 315]), spacing=1.2)
    _handrails(b, zv - X * 5.5, -X, 2.07, 0.0, 5.3, fm.radians([90, 270]))
    _clutter(rng, b, zv - X * 5.5, -X, 2.07, 0.0, 5.3, 4)
    for s in (1, -1):
        _small_array(b, zv + (-8.0, s * 2.0, 0), (0, s, 0), 10.7, 3.3, fm.radians(30), "solar_small_arrays")
    # Zvezda antennas: a few small dishes and whips
    for (dx, a) in ((-7.0, 50), (-10.0, 130), (-10.0, 230)):
        ang = fm.radians(a)
        rd = np.array([0.0, fm.cos(ang), fm.sin(ang)])
        p = zv + X * dx + rd * 2.07
        b.add("truss_hardware", METAL, box_between("p", p, p + rd * 0.7, 0.06, METAL))
        b.add("antennas", SKIN, dish("p", 0.3, 0.08, SKIN, 16, 2, transform(p + rd * 0.7, frame_from_z(rd + X * 0.5))))
    for dx in (-9.0, -9.5, -10.0):
        b.add("truss_hardware", METAL, cylinder_between("p", zv + (dx, 0.3, 2.0), zv + (dx, 0.9, 3.3), 0.02, METAL, 6))
    # Poisk (zenith), Nauka + Prichal (nadir)
    _sections(b, zv + Z * 1.0, Z, [(0.3, 0.7, 0.7, "module_ports", METAL), (3.6, 1.3, 1.3, "module_poisk", SKIN),
                                   (0.3, 0.6, 0.6, "module_ports", METAL)])
    nk = "module_nauka"
    t = _sections(b, zv - Z * 1.0, -Z, [_port(0.3, 0.7), _skin(3.0, 1.45, 1.45, nk), _foil(1.0, 1.45, 2.05),
                                        _skin(7.7, 2.05, 2.05, nk), _foil(0.7, 2.05, 1.1), _port(0.3, 0.7)])
    _handrails(b, zv - Z * 5.3, -Z, 2.05, 0.0, 7.7, fm.radians([0, 180]))
    b.add("russian_mli", MLI_SILVER, _sphere_tiled(uv_sphere("p", 1.3, MLI_SILVER, 32, 16,
                                                               transform(zv - Z * (1.0 + t + 1.2))), 1.3, MLI_TILE))
    b.add("radiator_PV", RADIATOR, _obox(zv + (-1.0, 2.4, -9.0), (0, 0, 1), (1, 0, 0), (5.0, 1.8, 0.05), RADIATOR,
                                         1 / RADIATOR_TILE))
    # Progress at Zvezda aft
    _progress(b, zv - X * 12.0, -X)


def _soyuz(b: _Parts, start, axis, group: str) -> None:
    """Orbital module sphere, descent-module bell, service module with two small arrays."""
    start = np.asarray(start, dtype=np.float64)
    axis = unit(axis)
    orbital = uv_sphere("p", 1.13, MLI_SILVER, 28, 14, transform(start + axis * 1.13))
    b.add("russian_mli", MLI_SILVER, _sphere_tiled(orbital, 1.13, MLI_TILE))
    dark = "module_details_dark"
    _sections(b, start + axis * 2.2, axis, [_foil(2.1, 0.85, 1.1), (0.3, 1.1, 1.1, dark, DARK),
                                            _skin(2.4, 1.36, 1.36, group), (0.3, 1.36, 1.1, dark, DARK)], 28)
    e1 = np.array([0.0, 1.0, 0.0])
    for s in (1, -1):
        _small_array(b, start + axis * 5.8 + e1 * s * 1.3, e1 * s, 4.0, 1.15, fm.radians(-20), "solar_small_arrays")
    b.add("module_ports", METAL, cylinder("p", 0.25, 0.4, METAL, 12, transform(start - axis * 0.2, frame_from_z(axis))))


def _progress(b: _Parts, start, axis) -> None:
    start = np.asarray(start, dtype=np.float64)
    axis = unit(axis)
    b.add("russian_mli", MLI_SILVER, _sphere_tiled(uv_sphere("p", 1.12, MLI_SILVER, 28, 14,
                                                                  transform(start + axis * 1.25)), 1.12, MLI_TILE))
    _sections(b, start + axis * 2.2, axis, [(1.7, 1.1, 1.1, "vehicles", SKIN),
                                            (0.3, 1.1, 1.36, "module_details_dark", DARK),
                                            (2.5, 1.36, 1.36, "vehicles", SKIN)], 28)
    for s in (1, -1):
        _small_array(b, start + axis * 5.4 + np.array([0, s * 1.3, 0]), (0, s, 0), 4.0, 1.15, fm.radians(15),
                     "solar_small_arrays")


# ----------------------------------------------------------------------------- public API
def build_station(articulated: bool = True) -> Asset:
    """The whole station as one Asset named "Station" (deterministic): the outboard trusses and the
    wings hang under their joints (at rest), or, with articulated=False, everything is merged flat
    in the station frame at rest (the static station as built before it had joints)."""
    rng = np.random.default_rng(20240611)
    b = _Parts(articulated)
    _truss(rng, b)
    _radiators(b)
    _solar(b)
    _modules(rng, b)
    return Asset("Station", b.build(), _materials(), _textures(), station_joints() if articulated else ())


def station_triangles(angles: dict[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """All of the station merged: (V, 3) float64 points and (T, 3) int triangles, for ray casting;
    the joints at rest, or at `angles` ({joint name: degrees}, rest where not given)."""
    if angles:
        pts, tris = _station_asset().triangle_soup(angles)
        return pts, tris
    pts, tris = _station_soup()
    return pts.copy(), tris.copy()


@lru_cache(maxsize=1)
def _station_asset() -> Asset:
    return build_station()


@lru_cache(maxsize=1)
def _station_soup() -> tuple[np.ndarray, np.ndarray]:
    return build_station(articulated=False).triangle_soup()


def station_fixture_points() -> np.ndarray:
    """(K, 3) plausible robotic-arm camera positions, 0.5-3 m off the station's exterior.

    Spread over the truss faces (inboard and, turned with the SARJ, outboard), the modules of
    both segments, and around the arm base on the mobile base system (ARM_BASE).
    """
    pts: list[np.ndarray] = []
    tz = TRUSS_Z
    for y in (-28.0, -16.0, -10.0, 10.0, 16.0, 27.0):          # forward (+X) face of the truss
        pts.append(np.array([HX + 1.6, y, tz + 0.4]))
    for y in (-22.0, -12.0, 5.5, 12.0, 19.0):                  # above the truss
        pts.append(np.array([0.3, y, tz + HZ + 1.9]))
    for y in (-15.0, 15.0):                                    # below the truss, forward of the radiators
        pts.append(np.array([1.2, y, tz - HZ - 1.5]))
    mo = _outboard_rest()
    for y in (-48.5, -36.0, 36.0, 48.5):                       # forward face of the turned outboard truss
        p = fm.matmul(mo, np.array([HXO + 1.5, y, 0.3, 1.0]))
        pts.append(p[:3])
    zc = MODULE_Z
    pts += [
        np.array([9.8, 0.0, zc + 2.2 + 1.3]),      # above Harmony, forward of PMA-3
        np.array([2.5, 3.7, zc - 0.3]),            # starboard of Destiny
        np.array([0.0, 0.0, zc - 2.15 - 1.5]),     # below Destiny
        np.array([7.85, 10.9, zc + 0.5]),          # off the end of Columbus
        np.array([7.85, -16.6, zc + 2.9]),         # above the Kibo exposed facility
        np.array([-7.0, 9.2, zc]),                 # off the Quest hatch
        np.array([-8.5, -5.0, zc - 4.9]),          # beside the Cupola
        np.array([-17.5, 0.0, zc + 2.05 + 1.4]),   # above Zarya
        np.array([-18.0, 3.6, zc - 0.8]),          # starboard of Zarya
        np.array([-33.0, 0.0, zc + 2.07 + 1.5]),   # above Zvezda
        np.array([-7.0, 2.2, tz + 3.2]),           # above Z1, by the Ku dish
    ]
    base = ARM_BASE
    pts += [base + np.array([1.5, 0.0, 0.0]), base + np.array([1.1, 1.4, 0.9]),
            base + np.array([1.0, -1.5, -0.8])]
    return np.array(pts, dtype=np.float64)
