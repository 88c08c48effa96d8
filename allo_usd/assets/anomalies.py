"""Sixteen procedural anomaly assets: hazards floating near the station (ALLO paper, Fig. 4).

Dislodged station parts (thermal blankets, cables, a handrail fragment), things lost during an
EVA (tools, a glove, fasteners, a tether hook) and loose experiment hardware (a crew bag, an
experiment box, a camera). Everything is built from numpy primitives, in metres, Z up, with
the bounding-box centre at the origin, so placement can rotate an asset about its centre.

    build_anomaly("power_drill")            # default variant (the first listed)
    build_anomaly("mli_blanket", "silver")  # a named variant
    ANOMALY_VARIANTS["hammer"]              # ("claw", "mallet")

Builds are deterministic: any randomness (crumples, cable routes) comes from a numpy Generator
seeded with a fixed constant per asset, so the same (name, variant) gives identical arrays.
Each asset stays under ANOMALY_TRIANGLE_BUDGET triangles.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from allo_usd.core.errors import UnknownAnomalyError
from allo_usd.core.geometry import rot_x, rot_y, rot_z, unit
from allo_usd.assets.catalogue import ANOMALY_IDS, ANOMALY_VARIANTS
from allo_usd.assets.mesh import Asset, Material, MeshPart
from allo_usd.assets.primitives import (box, cylinder, cylinder_between, extrude_polygon, frame_from_z, grid,
                                        lathe, merge, path_frames, ring_prism, smooth_path,
                                        superellipsoid, sweep, transform)
from allo_usd.core import fixedmath as fm

ANOMALY_TRIANGLE_BUDGET = 20_000

Parts = list[MeshPart]
Mats = list[Material]


# ---------------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------------

def _m(name: str, rgb, metallic: float = 0.0, roughness: float = 0.5) -> Material:
    return Material(name, tuple(float(c) for c in rgb), float(metallic), float(roughness))


def _rot(axis, angle: float) -> np.ndarray:
    """Rotation matrix about a unit axis (Rodrigues)."""
    k = unit(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + fm.sin(angle) * kx + (1 - fm.cos(angle)) * fm.matmul(kx, kx)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / fm.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _with(part: MeshPart, points: np.ndarray | None = None, name: str | None = None,
          material: str | None = None, smooth: bool | None = None) -> MeshPart:
    return MeshPart(name or part.name, part.points if points is None else points, part.face_counts,
                    part.face_indices, material or part.material, part.uv,
                    part.smooth if smooth is None else smooth)


def _subset(part: MeshPart, keep: np.ndarray, name: str, material: str, smooth: bool | None = None) -> MeshPart:
    """The faces of `part` where `keep` is true, with unused vertices dropped."""
    counts = part.face_counts
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    sel = np.concatenate([np.arange(s, s + c) for s, c, k in zip(starts, counts, keep) if k])
    idx = part.face_indices[sel]
    used, remap = np.unique(idx, return_inverse=True)
    uv = None if part.uv is None else part.uv[sel]
    return MeshPart(name, part.points[used], counts[keep], remap.reshape(-1), material, uv,
                    part.smooth if smooth is None else smooth)


def _resample(path: np.ndarray, s_values: np.ndarray) -> np.ndarray:
    """Points of a polyline at the given arc lengths."""
    s = np.concatenate([[0.0], np.cumsum(fm.norm(np.diff(path, axis=0), axis=1))])
    return np.stack([np.interp(s_values, s, path[:, k]) for k in range(3)], axis=1)


def _arc_length(path: np.ndarray) -> float:
    return float(fm.norm(np.diff(path, axis=0), axis=1).sum())


def _waves(rng: np.random.Generator, pts: np.ndarray, n: int, lam_min: float, lam_max: float,
           ridged: bool = False) -> np.ndarray:
    """Sum of n plane waves of random direction, phase and wavelength, roughly in [-1, 1].
    `ridged` folds each wave (|sin|), giving the sharp creases of crumpled foil."""
    dim = pts.shape[1]
    dirs = rng.normal(size=(n, dim))
    dirs /= fm.norm(dirs, axis=1, keepdims=True)
    lam = fm.exp(rng.uniform(fm.log(lam_min), fm.log(lam_max), n))
    phase = rng.uniform(0.0, 2 * np.pi, n)
    amp = lam / lam.max()
    arg = fm.matmul(pts, (dirs * (2 * np.pi / lam)[:, None]).T) + phase
    if ridged:
        sign = rng.choice([-1.0, 1.0], n)
        w = (np.abs(fm.sin(arg)) - 2 / np.pi) * 2 * sign
    else:
        w = fm.sin(arg)
    return (w * amp).sum(axis=1) / np.sqrt((amp * amp).sum() * 2)


def _fold(pts: np.ndarray, origin, normal_angle: float, radius: float, angle: float) -> np.ndarray:
    """Fold a sheet lying near z=0 along a line: points beyond the line through `origin` (on the
    side `normal_angle` points to, in XY) wrap up around a cylinder of `radius` by up to `angle`
    radians, then carry on straight. Smooth and orientation-preserving while z < radius."""
    r = rot_z(-normal_angle)
    p = fm.matmul(pts - np.array([origin[0], origin[1], 0.0]), r.T)
    d, h = p[:, 0], p[:, 2]
    m = d > 0
    arc = np.minimum(d, radius * angle)
    th = arc / radius
    rest = d - arc
    rho = radius - h
    if (rho[m] <= 0).any():
        raise ValueError("_fold: sheet rises above the fold radius; use a larger radius")
    x_new = rho * fm.sin(th) + rest * fm.cos(th)
    z_new = radius - rho * fm.cos(th) + rest * fm.sin(th)
    p[m, 0], p[m, 2] = x_new[m], z_new[m]
    return fm.matmul(p, r) + np.array([origin[0], origin[1], 0.0])


def _random_walk(rng: np.random.Generator, n: int, step: float, max_turn: float) -> np.ndarray:
    d = unit(rng.normal(size=3))
    pts = [np.zeros(3)]
    for _ in range(n - 1):
        axis = np.cross(d, rng.normal(size=3))
        d = fm.matmul(_rot(axis, rng.uniform(0.3, 1.0) * max_turn), d)
        pts.append(pts[-1] + d * step * rng.uniform(0.75, 1.25))
    return np.array(pts)


def _self_clear(path: np.ndarray, radius: float) -> bool:
    """True when no two parts of the tube around `path` come closer than its diameter."""
    ds = _arc_length(path) / (len(path) - 1)
    gap = max(1, int(np.ceil(8 * radius / ds)))
    d = fm.norm(path[:, None, :] - path[None, :, :], axis=-1)
    i, j = np.triu_indices(len(path), gap)
    return bool((d[i, j] > 2.4 * radius).all())


def _cable_route(seed: int, n_ctrl: int, step: float, max_turn: float, samples: int, radius: float,
                 max_extent: float = 1.6) -> np.ndarray:
    rng = np.random.default_rng(seed)
    for _ in range(200):
        ctrl = _random_walk(rng, n_ctrl, step, max_turn)
        path = smooth_path(ctrl, samples)
        if np.ptp(path, axis=0).max() <= max_extent and _self_clear(path, radius):
            return path
    raise RuntimeError(f"no self-clear cable route for seed {seed}")  # pragma: no cover


def _hexagon(circumradius: float, points_per_side: int = 1) -> np.ndarray:
    """A regular hexagon (flats on +-Y), optionally with extra points along each side."""
    corners = np.array([[fm.cos(a), fm.sin(a)] for a in np.arange(6) * np.pi / 3]) * circumradius
    out = []
    for i in range(6):
        a, b = corners[i], corners[(i + 1) % 6]
        for t in np.arange(points_per_side) / points_per_side:
            out.append(a + (b - a) * t)
    return np.array(out)


def _circle(radius: float, n: int, phase: float = 0.0) -> np.ndarray:
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False) + phase
    return np.column_stack([fm.cos(t), fm.sin(t)]) * radius


def _gear(r_out: float, r_in: float, teeth: int) -> np.ndarray:
    """A knurled outline: 4 points per tooth alternating between two radii."""
    t = np.linspace(0.0, 2 * np.pi, 4 * teeth, endpoint=False)
    r = np.where((np.arange(4 * teeth) // 2) % 2 == 0, r_out, r_in)
    return np.column_stack([fm.cos(t) * r, fm.sin(t) * r])


def _boundary_loop(nu: int, nv: int) -> np.ndarray:
    """Vertex indices of a grid's border, counter-clockwise seen from +Z."""
    w = nu + 1
    bottom = [s for s in range(nu)]
    right = [r * w + nu for r in range(nv)]
    top = [nv * w + s for s in range(nu, 0, -1)]
    left = [r * w for r in range(nv, 0, -1)]
    return np.array(bottom + right + top + left)


def _axis_matrix(origin, axis, scale=1.0) -> np.ndarray:
    """Matrix taking local +Z to `axis`, placed at `origin`."""
    return transform(origin, frame_from_z(axis), scale)


# ---------------------------------------------------------------------------------------------
# Thermal blankets (multi-layer insulation)
# ---------------------------------------------------------------------------------------------

_MLI = {
    "kapton": ((0.62, 0.33, 0.07), 1.0, 0.32),      # amber Kapton outer layer, gold look
    "aluminized": ((0.80, 0.80, 0.82), 1.0, 0.22),  # aluminised Mylar / Kapton
    "beta_cloth": ((0.78, 0.77, 0.72), 0.0, 0.85),  # white glass-fibre beta cloth
    "mylar_bronze": ((0.70, 0.55, 0.35), 1.0, 0.28),
}


def _mli_mat(name: str, kind: str) -> Material:
    rgb, met, rough = _MLI[kind]
    return _m(name, rgb, met, rough)


def _sheet(name: str, size_u: float, size_v: float, material: str, nu: int, nv: int, height: np.ndarray,
           thickness: float) -> MeshPart:
    """A double-sided crumpled sheet (`grid` keeps front and back quads on the same diagonal)."""
    return grid(name, size_u, size_v, material, nu, nv, height=height, double_sided_thickness=thickness)


def _mli_sheet(variant: str) -> tuple[Parts, Mats]:
    rng = np.random.default_rng(1101)
    su, sv, nu, nv, t = 1.3, 0.85, 64, 42, 0.002
    uu, vv = np.meshgrid(np.linspace(-su / 2, su / 2, nu + 1), np.linspace(-sv / 2, sv / 2, nv + 1))
    xy = np.column_stack([uu.ravel(), vv.ravel()])
    h = (0.08 * _waves(rng, xy, 4, 0.9, 2.2) + 0.022 * _waves(rng, xy, 10, 0.25, 0.7, ridged=True)
         + 0.004 * _waves(rng, xy, 12, 0.08, 0.18, ridged=True))
    sheet = _sheet("sheet", su, sv, "outer", nu, nv, h.reshape(nv + 1, nu + 1), t)

    def deform(p):
        p = _fold(p, (0.42, 0.18), fm.radians(35), 0.05, fm.radians(150))
        return _fold(p, (-0.5, -0.3), fm.radians(200), 0.06, fm.radians(70))

    pts = deform(sheet.points)
    sheet = _with(sheet, pts)
    n_top = nu * nv
    top = _subset(sheet, np.arange(2 * n_top) < n_top, "blanket_outer", "outer")
    back = _subset(sheet, np.arange(2 * n_top) >= n_top, "blanket_inner", "inner")
    ring = _boundary_loop(nu, nv)
    edge = np.column_stack([xy[ring], h[ring] - t / 2])
    binding = sweep("edge_binding", deform(edge), 0.0045, "binding", segments=8, closed=True, aspect=0.7,
                    up=(0.0, 0.0, 1.0))
    # Quilting tack ties through the layers, on a regular grid.
    w = nu + 1
    ties = []
    for r_ in range(4, nv - 2, 8):
        for c_ in range(4, nu - 2, 8):
            i = r_ * w + c_
            nrm = np.cross(pts[i + 1] - pts[i - 1], pts[i + w] - pts[i - w])
            ties.append(cylinder(f"tie_{len(ties)}", 0.0065, 0.0025, "binding", 10,
                                 _axis_matrix(pts[i] - 0.0005 * unit(nrm), nrm)))
    outer, inner = {"gold": ("kapton", "aluminized"), "silver": ("aluminized", "mylar_bronze"),
                    "white": ("beta_cloth", "aluminized")}[variant]
    mats = [_mli_mat("outer", outer), _mli_mat("inner", inner), _m("binding", (0.55, 0.55, 0.53), 0.0, 0.75)]
    return [top, back, binding, merge("tack_ties", ties)], mats


def _mli_torn(variant: str) -> tuple[Parts, Mats]:
    rng = np.random.default_rng(1202)
    su, sv, nu, nv, t = 0.64, 0.52, 56, 46, 0.0015
    uu, vv = np.meshgrid(np.linspace(-su / 2, su / 2, nu + 1), np.linspace(-sv / 2, sv / 2, nv + 1))
    xy = np.column_stack([uu.ravel(), vv.ravel()])
    h = (0.035 * _waves(rng, xy, 5, 0.35, 0.9) + 0.014 * _waves(rng, xy, 10, 0.12, 0.3, ridged=True)
         + 0.003 * _waves(rng, xy, 12, 0.04, 0.08, ridged=True))
    h_in = h - 0.004 - 0.002 * (1 + _waves(rng, xy, 6, 0.05, 0.2))

    def outline(n_harm_seed: int, base: float) -> Callable[[np.ndarray], np.ndarray]:
        g = np.random.default_rng(n_harm_seed)
        ks = np.arange(2, 40)
        amp = np.where(ks < 6, 0.07, 0.05 / np.sqrt(ks)) * g.uniform(0.3, 1.0, len(ks))
        ph = g.uniform(0, 2 * np.pi, len(ks))
        return lambda th: base + (amp[None, :] * fm.cos(ks[None, :] * th[:, None] + ph[None, :])).sum(1)

    def face_mask(r_of_theta):  # faces (front and back) whose centre lies inside the torn outline
        cx = (uu[:-1, :-1] + uu[1:, 1:]).ravel() / 2
        cy = (vv[:-1, :-1] + vv[1:, 1:]).ravel() / 2
        ex, ey = cx / (su / 2), cy / (sv / 2)
        keep = fm.hypot(ex, ey) < r_of_theta(fm.arctan2(ey, ex))
        return np.concatenate([keep, keep])

    def deform(p):
        return _fold(p, (0.13, 0.02), fm.radians(-20), 0.05, fm.radians(160))

    outer = _sheet("outer", su, sv, "face", nu, nv, h.reshape(nv + 1, nu + 1), t)
    inner = _sheet("inner", su, sv, "layer", nu, nv, h_in.reshape(nv + 1, nu + 1), t)
    keep_o = face_mask(outline(7, 0.86))
    keep_i = face_mask(outline(8, 0.84))
    n = nu * nv
    outer = _with(outer, deform(outer.points))
    inner = _with(inner, deform(inner.points))
    first = np.arange(2 * n) < n
    parts = [_subset(outer, keep_o & first, "blanket_face", "face"),
             _subset(outer, keep_o & ~first, "blanket_back", "back"),
             _subset(inner, keep_i, "inner_layer", "layer")]
    face, back, layer = {"silver": ("aluminized", "kapton", "mylar_bronze"),
                         "gold": ("kapton", "aluminized", "aluminized")}[variant]
    return parts, [_mli_mat("face", face), _mli_mat("back", back), _mli_mat("layer", layer)]


def _mli_strip(variant: str) -> tuple[Parts, Mats]:
    rng = np.random.default_rng(1303)
    su, sv, nu, nv, t = 1.25, 0.2, 110, 12, 0.002
    uu, vv = np.meshgrid(np.linspace(-su / 2, su / 2, nu + 1), np.linspace(-sv / 2, sv / 2, nv + 1))
    xy = np.column_stack([uu.ravel(), vv.ravel()])
    h = 0.012 * _waves(rng, xy, 10, 0.1, 0.35, ridged=True) + 0.0025 * _waves(rng, xy, 10, 0.04, 0.08, ridged=True)
    strip = _sheet("strip", su, sv, "face", nu, nv, h.reshape(nv + 1, nu + 1), t)

    def deform(p):
        p = _fold(p, (0.33, 0.0), 0.0, 0.07, fm.radians(215))          # curled free end
        x = p[:, 0]
        a = 1.4 * (x + su / 2) / su                                    # twist along the strip
        y, z = p[:, 1], p[:, 2]
        y2, z2 = y * fm.cos(a) - z * fm.sin(a), y * fm.sin(a) + z * fm.cos(a)
        bow = 0.18 * fm.sin(np.pi * (x + su / 2) / su)                 # gentle bow
        return np.column_stack([x, y2 + bow, z2])

    strip = _with(strip, deform(strip.points))
    n = nu * nv
    first = np.arange(2 * n) < n
    parts = [_subset(strip, first, "strip_face", "face"), _subset(strip, ~first, "strip_back", "back")]
    edges = []
    for row in (0, nv):
        idx = row * (nu + 1) + np.arange(nu + 1)
        edge = np.column_stack([xy[idx], h[idx] - t / 2])
        edges.append(sweep(f"edge_{'a' if row == 0 else 'b'}", deform(edge), 0.004, "binding", segments=8,
                           aspect=0.7, up=(0.0, 0.0, 1.0)))
    parts.append(merge("edge_binding", edges))
    face, back = {"silver": ("aluminized", "kapton"), "gold": ("kapton", "aluminized"),
                  "white": ("beta_cloth", "aluminized")}[variant]
    mats = [_mli_mat("face", face), _mli_mat("back", back), _m("binding", (0.6, 0.6, 0.58), 0.0, 0.7)]
    return parts, mats


# ---------------------------------------------------------------------------------------------
# Cables
# ---------------------------------------------------------------------------------------------

def _connector(tag: str, end: np.ndarray, direction: np.ndarray, cable_r: float) -> dict[str, MeshPart]:
    """A circular mil-spec style plug at a cable end: rubber boot, metal shell, knurled coupling
    nut and a dark insert face, pointing along `direction`."""
    m = _axis_matrix(end, direction)
    boot = lathe(f"boot_{tag}", [(0.0, -0.045), (cable_r * 1.12, -0.045), (cable_r * 1.3, -0.02),
                                 (0.0165, 0.0), (0.0165, 0.004), (0.0, 0.004)], "boot", 20, matrix=m)
    shell = lathe(f"shell_{tag}", [(0.0, 0.0), (0.0185, 0.0), (0.0185, 0.036), (0.0155, 0.036),
                                   (0.0155, 0.063), (0.0, 0.063)], "shell", 24, matrix=m)
    nut = extrude_polygon(f"nut_{tag}", _gear(0.0225, 0.0212, 20), 0.022, "shell",
                          matrix=fm.matmul(m, transform((0.0, 0.0, 0.048))))
    face = cylinder(f"face_{tag}", 0.0125, 0.004, "insert", 20, matrix=fm.matmul(m, transform((0.0, 0.0, 0.061))))
    return {"boot": boot, "shell": shell, "nut": nut, "face": face}


def _power_cable(variant: str) -> tuple[Parts, Mats]:
    r = 0.011
    path = _cable_route(2101, 7, 0.32, 1.1, 220, r, max_extent=1.3)
    cable = sweep("cable", path, r, "jacket", segments=14)
    ends = [_connector("a", path[0], path[0] - path[1], r), _connector("b", path[-1], path[-1] - path[-2], r)]
    parts = [cable]
    for key, mat in (("boot", "boot"), ("shell", "shell"), ("nut", "shell"), ("face", "insert")):
        parts.append(merge(f"connector_{key}", [e[key] for e in ends], mat))
    jacket = {"black": (0.02, 0.02, 0.022), "orange": (0.75, 0.18, 0.02)}[variant]
    mats = [_m("jacket", jacket, 0.0, 0.55), _m("boot", (0.03, 0.03, 0.03), 0.0, 0.8),
            _m("shell", (0.55, 0.56, 0.52), 1.0, 0.35), _m("insert", (0.08, 0.12, 0.2), 0.0, 0.6)]
    return parts, mats


def _data_cable(variant: str) -> tuple[Parts, Mats]:
    r = 0.005
    path = _cable_route(2202, 10, 0.14, 1.9, 280, r, max_extent=0.8)
    length = _arc_length(path)
    parts = [sweep("cable", path, r, "jacket", segments=10)]
    sleeves = []
    for i, (s0, s1) in enumerate(((0.0, 0.025), (length - 0.025, length))):
        seg = _resample(path, np.linspace(s0, s1, 6))
        sleeves.append(sweep(f"end_{i}", seg, r * 1.35, "sleeve", segments=10))
    parts.append(merge("end_sleeves", sleeves))
    labels = []
    for i, s0 in enumerate((0.09, length - 0.13)):
        seg = _resample(path, np.linspace(s0, s0 + 0.04, 8))
        labels.append(sweep(f"label_{i}", seg, r * 1.4, "label", segments=10))
    parts.append(merge("id_labels", labels))
    tips = [cylinder_between(f"tip_{i}", p, p + 0.012 * unit(p - q), r * 0.5, "conductor", 8)
            for i, (p, q) in enumerate(((path[0], path[1]), (path[-1], path[-2])))]
    parts.append(merge("conductors", tips))
    jacket = {"white": (0.78, 0.78, 0.76), "blue": (0.04, 0.12, 0.5)}[variant]
    mats = [_m("jacket", jacket, 0.0, 0.45), _m("sleeve", (0.02, 0.02, 0.02), 0.0, 0.6),
            _m("label", (0.85, 0.7, 0.05), 0.0, 0.5), _m("conductor", (0.75, 0.4, 0.2), 1.0, 0.3)]
    return parts, mats


def _cable_harness(variant: str) -> tuple[Parts, Mats]:
    r = 0.0045
    centre = _cable_route(2303, 6, 0.26, 0.9, 240, 4 * r, max_extent=1.1)
    length = _arc_length(centre)
    tang, nrm, bin_ = path_frames(centre)
    s = np.linspace(0.0, length, len(centre))
    fan = 1.0 + 2.5 * np.square(np.clip(1 - s / 0.08, 0, 1)) + 2.5 * np.square(np.clip(1 - (length - s) / 0.08, 0, 1))
    rho = 1.2 * r * fan
    twist = 2 * np.pi * s / 0.09
    wires, tips = [], []
    for i in range(3):
        a = twist + 2 * np.pi * i / 3
        path = centre + rho[:, None] * (fm.cos(a)[:, None] * nrm + fm.sin(a)[:, None] * bin_)
        trim = [0.004 * i, 0.004 * (2 - i)]
        path = _resample(path, np.linspace(trim[0], _arc_length(path) - trim[1], 220))
        wires.append(sweep(f"wire_{i}", path, r, f"wire_{i}", segments=8))
        for p, q in ((path[0], path[1]), (path[-1], path[-2])):
            tips.append(cylinder_between(f"tip_{i}_{len(tips)}", p, p + 0.01 * unit(p - q), r * 0.55,
                                         "conductor", 8))
    ties = []
    for k, st in enumerate(np.arange(0.16, length - 0.1, 0.2)):
        j = int(np.searchsorted(s, st))
        c, tz, nz = centre[j], tang[j], nrm[j]
        bz = np.cross(tz, nz)
        a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        rad = 2.2 * r + 0.001
        loop = c + rad * (fm.cos(a)[:, None] * nz + fm.sin(a)[:, None] * bz)
        ties.append(sweep(f"tie_{k}", loop, 0.0008, "tie", segments=6, closed=True, aspect=3.0,
                          exponent=0.5, up=loop - c))
        head_c = c + (rad + 0.003) * nz
        ties.append(box(f"tie_head_{k}", (0.006, 0.007, 0.005), "tie",
                        transform(head_c, np.column_stack([bz, tz, nz]))))
    parts = wires + [merge("conductors", tips), merge("cable_ties", ties)]
    colours = {"default": [(0.6, 0.03, 0.02), (0.8, 0.8, 0.78), (0.02, 0.02, 0.02)],
               "grey": [(0.3, 0.3, 0.32), (0.45, 0.45, 0.47), (0.2, 0.2, 0.22)]}[variant]
    mats = [_m(f"wire_{i}", c, 0.0, 0.45) for i, c in enumerate(colours)]
    mats += [_m("conductor", (0.75, 0.4, 0.2), 1.0, 0.3), _m("tie", (0.03, 0.03, 0.03), 0.0, 0.5)]
    return parts, mats


# ---------------------------------------------------------------------------------------------
# Tools
# ---------------------------------------------------------------------------------------------

def _power_drill(variant: str) -> tuple[Parts, Mats]:
    ry = rot_y(np.pi / 2)  # local +Z -> world +X
    parts = [
        superellipsoid("body", (0.19, 0.066, 0.085), "shell", 0.55, 40, 20, transform((0.0, 0.0, 0.0))),
        superellipsoid("rear_cap", (0.045, 0.07, 0.088), "dark", 0.5, 32, 16, transform((-0.083, 0.0, 0.0))),
        lathe("nose", [(0.0, 0.0), (0.031, 0.0), (0.031, 0.012), (0.027, 0.03), (0.0, 0.03)], "dark", 28,
              matrix=transform((0.085, 0.0, 0.0), ry)),
        extrude_polygon("chuck_sleeve", _gear(0.0215, 0.0200, 18), 0.036, "dark",
                        matrix=transform((0.133, 0.0, 0.0), ry)),
        lathe("chuck_jaws", [(0.0, 0.0), (0.019, 0.0), (0.0175, 0.006), (0.009, 0.022), (0.0, 0.022)], "metal",
              24, matrix=transform((0.150, 0.0, 0.0), ry)),
    ]
    bit = lathe("bit", [(0.0, 0.0), (0.004, 0.0), (0.004, 0.06), (0.0, 0.072)], "metal", 12,
                matrix=transform((0.165, 0.0, 0.0), ry))
    parts.append(bit)
    handle_path = np.linspace([0.0, 0.0, -0.005], [-0.032, 0.0, -0.17], 12)
    parts.append(sweep("handle", handle_path, 0.0165, "shell", segments=20, aspect=1.42, exponent=0.8,
                       up=(0.0, 1.0, 0.0)))
    grip_path = np.linspace([-0.014, 0.0, -0.03], [-0.042, 0.0, -0.15], 10)
    parts.append(sweep("grip", grip_path, 0.0172, "dark", segments=20, aspect=0.9, exponent=0.8,
                       up=(0.0, 1.0, 0.0)))
    parts.append(box("trigger", (0.014, 0.016, 0.032), "dark", transform((0.018, 0.0, -0.05), rot_y(-0.2))))
    parts.append(cylinder("direction_switch", 0.0055, 0.074, "dark", 16,
                          transform((0.0, -0.037, -0.032), rot_x(-np.pi / 2))))
    parts.append(superellipsoid("battery", (0.118, 0.082, 0.066), "dark", 0.28, 32, 16,
                                transform((-0.035, 0.0, -0.195))))
    parts.append(superellipsoid("foot", (0.122, 0.086, 0.022), "shell", 0.3, 32, 16,
                                transform((-0.035, 0.0, -0.158))))
    vents = [box(f"vent_{side + 1}_{k}", (0.004, 0.004, 0.032), "vent",
                 transform((-0.07 + 0.011 * k, side * 0.0335, 0.0)))
             for side in (-1, 1) for k in range(4)]
    parts.append(merge("vents", vents))
    shell = {"yellow": (0.85, 0.5, 0.01), "red": (0.55, 0.02, 0.015)}[variant]
    mats = [_m("shell", shell, 0.0, 0.4), _m("dark", (0.025, 0.025, 0.027), 0.0, 0.6),
            _m("metal", (0.62, 0.62, 0.6), 1.0, 0.3), _m("vent", (0.005, 0.005, 0.005), 0.0, 0.9)]
    return parts, mats


def _finger_path(base, direction, bend_axis, length: float, bend: float, samples_body: int = 14,
                 tip_r: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Centre line of a finger (3 phalanges bending about `bend_axis`) and arc lengths of the
    samples, dense near the rounded tip."""
    d = unit(direction)
    pts = [np.asarray(base, dtype=np.float64)]
    for frac in (0.45, 0.3, 0.25):
        d = fm.matmul(_rot(bend_axis, bend), d)
        pts.append(pts[-1] + d * frac * length)
    dense = smooth_path(pts, 200)
    total = _arc_length(dense)
    s = np.concatenate([np.linspace(0.0, total - tip_r, samples_body, endpoint=False),
                        total - tip_r + tip_r * fm.sin(np.linspace(0.0, np.pi / 2, 7))])
    return _resample(dense, s), s


def _finger_radius(s: np.ndarray, r0: float, r1: float) -> np.ndarray:
    total = s[-1]
    r = r0 + (r1 - r0) * s / total
    tip = s > total - r1
    r[tip] = np.sqrt(np.clip(r1 * r1 - np.square(s[tip] - (total - r1)), 0.0, None))
    return r


def _eva_glove(variant: str) -> tuple[Parts, Mats]:
    curl = fm.radians(48 if variant == "curled" else 14)
    parts = [superellipsoid("palm", (0.10, 0.115, 0.044), "fabric", 0.6, 40, 20),
             superellipsoid("palm_pad", (0.086, 0.09, 0.012), "rubber", 0.3, 32, 12,
                            transform((0.0, 0.006, -0.018)))]
    fingers, tips = [], []
    spec = [(-0.034, 0.088, 0.0118), (-0.0115, 0.098, 0.0122), (0.0115, 0.093, 0.0118), (0.034, 0.074, 0.0108)]
    for i, (x, length, r0) in enumerate(spec):
        path, s = _finger_path((x, 0.035, 0.0), (0.04 * x / 0.034, 1.0, 0.0), (1.0, 0.0, 0.0), length, -curl,
                               tip_r=r0 * 0.92)
        rad = _finger_radius(s, r0, r0 * 0.92)
        fingers.append(sweep(f"finger_{i}", path, rad, "fabric", segments=14))
        k = int(np.searchsorted(s, s[-1] - 0.024))
        tips.append(sweep(f"tip_{i}", path[k:], rad[k:] + 0.0009, "rubber", segments=14))
    thumb_axis = unit((0.3, 0.35, -1.0))
    path, s = _finger_path((-0.04, -0.005, -0.004), (-0.75, 0.62, -0.25), thumb_axis, 0.075, -curl * 0.8,
                           tip_r=0.0115)
    rad = _finger_radius(s, 0.0135, 0.0115)
    fingers.append(sweep("thumb", path, rad, "fabric", segments=14))
    k = int(np.searchsorted(s, s[-1] - 0.024))
    tips.append(sweep("tip_thumb", path[k:], rad[k:] + 0.0009, "rubber", segments=14))
    parts += [merge("fingers", fingers), merge("fingertips", tips)]
    # Back-of-hand restraint strap wrapping over the palm.
    t = np.linspace(-0.05, np.pi + 0.05, 30)
    strap = np.column_stack([0.0535 * np.sign(fm.cos(t)) * fm.power(np.abs(fm.cos(t)), 0.6),
                             np.full(len(t), -0.018),
                             0.0235 * np.sign(fm.sin(t)) * fm.power(np.abs(fm.sin(t)), 0.6)])
    out = strap * np.array([1.0 / (0.0535 * 0.0535), 0.0, 1.0 / (0.0235 * 0.0235)])
    parts.append(sweep("strap", strap, 0.0015, "strap", segments=8, aspect=8.0, exponent=0.4, up=out))
    # Wrist: fabric neck, blue disconnect ring, flared gauntlet with a dark lining.
    to_wrist = rot_x(np.pi / 2)          # local +Z -> world -Y
    flat = transform((0.0, -0.035, 0.0), to_wrist, (1.0, 0.72, 1.0))
    parts.append(lathe("wrist", [(0.0, 0.0), (0.036, 0.0), (0.034, 0.02), (0.036, 0.04), (0.0, 0.04)],
                       "fabric", 28, matrix=flat))
    parts.append(lathe("wrist_ring", [(0.026, 0.036), (0.047, 0.036), (0.049, 0.042), (0.049, 0.056),
                                      (0.047, 0.062), (0.026, 0.062)], "ring", 36, closed=True,
                       matrix=transform((0.0, -0.035, 0.0), to_wrist)))
    parts.append(lathe("gauntlet", [(0.0, 0.058), (0.043, 0.058), (0.045, 0.075), (0.054, 0.135), (0.057, 0.14),
                                    (0.051, 0.14), (0.047, 0.133)], "fabric", 32,
                       matrix=transform((0.0, -0.035, 0.0), to_wrist, (1.0, 0.8, 1.0))))
    parts.append(lathe("lining", [(0.0475, 0.1325), (0.0, 0.1325)], "lining", 32,
                       matrix=transform((0.0, -0.035, 0.0), to_wrist, (1.0, 0.8, 1.0))))
    fabric = {"default": (0.8, 0.8, 0.77), "worn": (0.5, 0.47, 0.4), "curled": (0.8, 0.8, 0.77)}[variant]
    rubber = (0.12, 0.12, 0.13) if variant != "worn" else (0.07, 0.065, 0.06)
    mats = [_m("fabric", fabric, 0.0, 0.9), _m("rubber", rubber, 0.0, 0.7),
            _m("strap", (0.25, 0.27, 0.3), 0.0, 0.8), _m("ring", (0.05, 0.12, 0.45), 0.8, 0.35),
            _m("lining", (0.03, 0.03, 0.035), 0.0, 0.9)]
    return parts, mats


def _wrench(variant: str) -> tuple[Parts, Mats]:
    shaft = extrude_polygon("shaft", [(-0.09, -0.0075), (0.085, -0.0095), (0.085, 0.0095), (-0.09, 0.0075)],
                            0.0062, "steel")
    # Open-end jaw head: a disc with a 13 mm slot angled 15 degrees.
    R, w, xb = 0.0205, 0.0068, -0.0015
    a0 = fm.arcsin(w / R)
    arc = np.linspace(a0, 2 * np.pi - a0, 40)
    outline = [np.column_stack([R * fm.cos(arc), R * fm.sin(arc)])]
    x_edge = R * fm.cos(a0)
    outline.append([[x_edge * 0.5 + xb * 0.5, -w]])
    bottom = np.linspace(-np.pi / 2, -3 * np.pi / 2, 12)
    outline.append(np.column_stack([xb + w * fm.cos(bottom), w * fm.sin(bottom)]))
    outline.append([[x_edge * 0.5 + xb * 0.5, w]])
    jaw = fm.matmul(np.concatenate(outline), rot_z(fm.radians(15))[:2, :2].T)
    open_head = extrude_polygon("open_end", jaw, 0.0075, "steel", transform((0.108, 0.0, 0.0)))
    star = _circle(1.0, 24, 0.0) * np.where(np.arange(24) % 2 == 0, 0.0079, 0.0069)[:, None]
    ring_head = ring_prism("box_end", _circle(0.0172, 24), star, 0.009, "steel",
                           transform((-0.106, 0.0, 0.002), rot_y(0.26)))
    grip = extrude_polygon("grip", [(-0.062, -0.0088), (0.05, -0.0102), (0.05, 0.0102), (-0.062, 0.0088)],
                           0.0078, "grip")
    steel, grip_c = {"chrome": ((0.78, 0.78, 0.8), (0.6, 0.03, 0.02)),
                     "black_oxide": ((0.06, 0.06, 0.065), (0.8, 0.5, 0.02))}[variant]
    mats = [_m("steel", steel, 1.0, 0.2 if variant == "chrome" else 0.45), _m("grip", grip_c, 0.0, 0.6)]
    return [shaft, open_head, ring_head, grip], mats


def _hammer(variant: str) -> tuple[Parts, Mats]:
    z = np.linspace(-0.17, 0.135, 16)
    radius = 0.0125 + 0.003 * np.clip((-0.05 - z) / 0.12, 0.0, 1.0)
    handle = sweep("handle", np.column_stack([np.zeros_like(z), np.zeros_like(z), z]), radius, "handle",
                   segments=20, aspect=0.72, up=(1.0, 0.0, 0.0))
    zg = np.linspace(-0.172, -0.05, 10)
    rg = 0.0145 + 0.003 * np.clip((-0.05 - zg) / 0.12, 0.0, 1.0)
    rg[0] = rg[1]
    grip = sweep("grip", np.column_stack([np.zeros_like(zg), np.zeros_like(zg), zg]), rg, "grip",
                 segments=20, aspect=0.78, up=(1.0, 0.0, 0.0))
    parts = [handle, grip]
    hz = 0.14
    if variant == "claw":
        parts.append(box("head_eye", (0.034, 0.026, 0.036), "head", transform((0.0, 0.0, hz))))
        parts.append(lathe("face", [(0.0, 0.0), (0.012, 0.0), (0.011, 0.015), (0.014, 0.032), (0.0158, 0.046),
                                    (0.0158, 0.052), (0.0138, 0.055), (0.0, 0.055)], "head", 28,
                           matrix=transform((0.012, 0.0, hz), rot_y(np.pi / 2))))
        prongs = []
        for side in (-1, 1):
            ctrl = np.array([[-0.012, side * 0.0046, hz + 0.006], [-0.035, side * 0.005, hz + 0.006],
                             [-0.062, side * 0.0056, hz - 0.006], [-0.088, side * 0.0068, hz - 0.03]])
            path = smooth_path(ctrl, 20)
            rad = np.linspace(0.0048, 0.0022, 20)
            prongs.append(sweep(f"claw_{'l' if side < 0 else 'r'}", path, rad, "head", segments=16, aspect=2.2,
                                exponent=0.7, up=(0.0, 1.0, 0.0)))
        parts.append(merge("claw", prongs))
        mats = [_m("head", (0.55, 0.56, 0.58), 1.0, 0.3), _m("handle", (0.8, 0.48, 0.02), 0.0, 0.45),
                _m("grip", (0.02, 0.02, 0.02), 0.0, 0.8)]
    else:
        parts.append(lathe("head", [(0.0, -0.058), (0.027, -0.058), (0.031, -0.054), (0.031, 0.054),
                                    (0.027, 0.058), (0.0, 0.058)], "head", 32,
                           matrix=transform((0.0, 0.0, hz), rot_y(np.pi / 2))))
        parts.append(lathe("band", [(0.0, -0.016), (0.0325, -0.016), (0.0325, 0.016), (0.0, 0.016)], "band",
                           32, matrix=transform((0.0, 0.0, hz), rot_y(np.pi / 2))))
        mats = [_m("head", (0.75, 0.75, 0.72), 0.0, 0.6), _m("handle", (0.42, 0.22, 0.08), 0.0, 0.55),
                _m("grip", (0.1, 0.1, 0.35), 0.0, 0.7), _m("band", (0.6, 0.6, 0.6), 1.0, 0.3)]
    return parts, mats


def _bolt_cluster(variant: str) -> tuple[Parts, Mats]:
    rng = np.random.default_rng(3404)
    kinds = ["bolt"] * 6 + ["nut"] * 4 + ["washer"] * 3
    centres: list[np.ndarray] = []
    while len(centres) < len(kinds):
        c = rng.uniform(-0.06, 0.06, 3)
        if fm.norm(c) <= 0.06 and all(fm.norm(c - o) > 0.034 for o in centres):
            centres.append(c)
    bolts, heads, nuts, washers = [], [], [], []
    pitch, r_maj, r_min = 0.002, 0.005, 0.0041
    for i, (kind, c) in enumerate(zip(kinds, centres)):
        m = transform(c, _random_rotation(rng))
        if kind == "bolt":
            length = float(rng.choice([0.025, 0.032, 0.04, 0.05]))
            prof = [(0.0, -length), (r_min - 0.0004, -length), (r_maj, -length + 0.0012)]
            for zt in np.arange(-length + 0.0012 + pitch / 2, -0.007, pitch / 2):
                k = int(round((zt + length - 0.0012) / (pitch / 2)))
                prof.append((r_min if k % 2 else r_maj, zt))
            prof += [(r_maj, -0.007), (r_maj, 0.0005), (0.0, 0.0005)]
            bolts.append(lathe(f"shank_{i}", prof, "bolt", 14, matrix=m))
            heads.append(extrude_polygon(f"head_{i}", _hexagon(0.0092), 0.0065, "bolt",
                                         fm.matmul(m, transform((0.0, 0.0, 0.00325)))))
            heads.append(lathe(f"collar_{i}", [(0.0, 0.0), (0.0085, 0.0), (0.0085, 0.001), (0.0, 0.001)], "bolt",
                               20, matrix=m))
            if i % 3 == 0:  # a nut threaded part way up
                nuts.append(ring_prism(f"nut_on_{i}", _hexagon(0.0092, 2), _circle(0.0045, 12), 0.008, "nut",
                                       fm.matmul(m, transform((0.0, 0.0, -length * 0.55)))))
        elif kind == "nut":
            nuts.append(ring_prism(f"nut_{i}", _hexagon(0.0092, 2), _circle(0.0048, 12), 0.008, "nut", m))
        else:
            washers.append(lathe(f"washer_{i}", [(0.0053, -0.001), (0.0105, -0.001), (0.0105, 0.001),
                                                 (0.0053, 0.001)], "washer", 24, closed=True, matrix=m))
    parts = [merge("bolt_shanks", bolts), merge("bolt_heads", heads), merge("nuts", nuts),
             merge("washers", washers)]
    bolt, nut = {"steel": ((0.62, 0.62, 0.63), (0.72, 0.6, 0.28)),
                 "titanium": ((0.42, 0.4, 0.38), (0.1, 0.22, 0.55))}[variant]
    mats = [_m("bolt", bolt, 1.0, 0.35), _m("nut", nut, 1.0, 0.3), _m("washer", (0.7, 0.7, 0.7), 1.0, 0.4)]
    return parts, mats


def _tether_hook(variant: str) -> tuple[Parts, Mats]:
    ctrl = np.array([[-0.021, -0.040, 0], [-0.023, 0.0, 0], [-0.021, 0.040, 0], [-0.008, 0.057, 0],
                     [0.012, 0.056, 0], [0.026, 0.040, 0], [0.029, 0.0, 0], [0.026, -0.038, 0],
                     [0.011, -0.054, 0], [-0.008, -0.055, 0]], dtype=np.float64)
    loop = smooth_path(ctrl, 120, closed=True)
    gap = (loop[:, 0] > 0.018) & (np.abs(loop[:, 1]) < 0.03)
    first_gap = int(np.argmax(gap))
    n_gap = int(gap.sum())
    order = np.roll(np.arange(len(loop)), -(first_gap + n_gap))
    body_path = loop[order[: len(loop) - n_gap]]
    parts = [sweep("hook_body", body_path, 0.0055, "hook", segments=14)]
    g0, g1 = body_path[-1], body_path[0]
    inward = np.array([-0.0012, 0.0, 0.0])
    parts.append(cylinder_between("gate", g0 + inward, g1 + inward, 0.0038, "gate", 14))
    parts.append(lathe("gate_pin", [(0.0, -0.004), (0.0045, -0.004), (0.0045, 0.004), (0.0, 0.004)], "gate", 14,
                       matrix=transform(g0 + inward, rot_y(np.pi / 2))))
    # Swivel ring around the bottom bar, in the YZ plane.
    ring_c = np.array([0.0, -0.0605, 0.0])
    a = np.linspace(0.0, 2 * np.pi, 36, endpoint=False)
    ring = ring_c + 0.0115 * np.column_stack([np.zeros_like(a), fm.cos(a), fm.sin(a)])
    parts.append(sweep("swivel", ring, 0.0025, "gate", segments=10, closed=True))
    k = 1.45  # the hardware above is drawn at carabiner scale 1; EVA hooks are this much bigger
    parts = [p.transformed(transform(scale=k)) for p in parts]
    # Webbing strap, folded round the swivel at the top and ending in a sewn loop with a D-ring.
    top = k * (ring_c + np.array([0.0, -0.0115, 0.0]))
    ctrl = np.array([top + [0.0, -0.002, 0.0], top + [0.0, -0.04, 0.0], [0.02, -0.17, 0.02], [-0.03, -0.27, 0.05],
                     [0.01, -0.37, 0.02], [0.05, -0.44, -0.02]])
    path = smooth_path(ctrl, 90)
    phi = np.linspace(0.0, 1.3, len(path))
    up = np.column_stack([fm.sin(phi), np.zeros_like(phi), fm.cos(phi)])
    parts.append(sweep("strap", path, 0.0013, "strap", segments=12, aspect=9.5, exponent=0.35, up=up))
    fold = path[:14] + 0.0028 * up[:14]
    parts.append(sweep("strap_fold", fold, 0.0013, "strap", segments=12, aspect=9.5, exponent=0.35, up=up[:14]))
    stitch_pts = _resample(path, np.linspace(0.022, 0.05, 6)) + 0.0015 * up[:6]
    parts.append(sweep("stitching", stitch_pts, 0.0015, "stitch", segments=12, aspect=7.5, exponent=0.3,
                       up=up[:6]))
    end = path[-1]
    t_end = unit(path[-1] - path[-3])
    ring_frame = np.column_stack([unit(np.cross(up[-1], t_end)), up[-1], t_end])
    dring = np.array([[0.0, 0.0], [0.018, 0.0], [0.018, 0.006], [0.009, 0.02], [-0.009, 0.02], [-0.018, 0.006],
                      [-0.018, 0.0]])
    dring3 = end + fm.matmul(np.column_stack([dring[:, 0], np.zeros(len(dring)), dring[:, 1] + 0.004]), np.column_stack(
        [ring_frame[:, 0], ring_frame[:, 1], ring_frame[:, 2]]).T)
    parts.append(sweep("d_ring", smooth_path(dring3, 40, closed=True), 0.0022, "gate", segments=10, closed=True))
    hook, strap = {"default": ((0.55, 0.56, 0.58), (0.8, 0.78, 0.7)),
                   "yellow": ((0.7, 0.25, 0.03), (0.85, 0.6, 0.03))}[variant]
    mats = [_m("hook", hook, 1.0, 0.3), _m("gate", (0.7, 0.7, 0.72), 1.0, 0.25),
            _m("strap", strap, 0.0, 0.9), _m("stitch", (0.2, 0.2, 0.22), 0.0, 0.9)]
    return parts, mats


# ---------------------------------------------------------------------------------------------
# Station hardware and loose gear
# ---------------------------------------------------------------------------------------------

def _handrail(variant: str) -> tuple[Parts, Mats]:
    x = np.linspace(-0.42, 0.42, 70)
    zr = 0.052
    path = np.column_stack([x, np.zeros_like(x), np.full_like(x, zr)])
    rail = sweep("rail", path, 0.0165, "rail", segments=20, aspect=0.64, exponent=0.55, up=(0.0, 0.0, 1.0))
    posts, feet, bolts = [], [], []
    stand_x = (-0.36, -0.02, 0.32)
    for k, sx in enumerate(stand_x):
        trapezoid = [(-0.026, 0.0), (0.026, 0.0), (0.016, zr - 0.005), (-0.016, zr - 0.005)]
        posts.append(extrude_polygon(f"post_{k}", trapezoid, 0.02, "rail", transform((sx, 0.0, 0.0), rot_x(np.pi / 2))))
        if variant == "bent" and k == 2:
            continue  # sheared off at the foot
        feet.append(box(f"foot_{k}", (0.075, 0.044, 0.006), "foot", transform((sx, 0.0, -0.003))))
        for bx in (-0.029, 0.029):
            bolts.append(extrude_polygon(f"bolt_{k}_{bx > 0:d}", _hexagon(0.0055), 0.004, "bolt",
                                         transform((sx + bx, 0.0, 0.002))))
    parts = [rail, merge("standoffs", posts), merge("feet", feet), merge("bolt_heads", bolts)]
    if variant == "bent":
        def deform(p):
            p = _fold(p, (0.12, 0.0), 0.0, 0.16, fm.radians(38))
            return _fold(p, (-0.25, 0.0), np.pi, 0.3, fm.radians(12))
        parts = [_with(p, deform(p.points)) for p in parts]
    mats = [_m("rail", (0.75, 0.48, 0.05), 0.5, 0.4), _m("foot", (0.5, 0.5, 0.52), 1.0, 0.4),
            _m("bolt", (0.65, 0.65, 0.66), 1.0, 0.3)]
    return parts, mats


def _crew_bag(variant: str) -> tuple[Parts, Mats]:
    rng = np.random.default_rng(5505)
    a, b, c, e = 0.46, 0.36, 0.24, 0.2
    body = superellipsoid("bag", (a, b, c), "fabric", e, 64, 32)
    p = body.points
    q = p / (np.array([a, b, c]) / 2)
    g = np.sign(q) * fm.power(np.abs(q), 2 / e - 1) / (np.array([a, b, c]) / 2)
    nrm = g / fm.norm(g, axis=1, keepdims=True)
    wr = 0.006 * _waves(rng, p, 14, 0.05, 0.2, ridged=True) + 0.004 * _waves(rng, p, 6, 0.2, 0.5)
    sag = np.column_stack([np.zeros(len(p)), np.zeros(len(p)), -0.012 * np.square(fm.cos(np.pi * p[:, 0] / a))])
    parts = [_with(body, p + wr[:, None] * nrm + sag * (p[:, 2:3] > 0))]
    # Zipper all round the lid, just below the top edge.
    t = np.linspace(0.0, 2 * np.pi, 120, endpoint=False)
    ex = 0.3
    zip_loop = np.column_stack([(a / 2 + 0.004) * np.sign(fm.cos(t)) * fm.power(np.abs(fm.cos(t)), ex),
                                (b / 2 + 0.004) * np.sign(fm.sin(t)) * fm.power(np.abs(fm.sin(t)), ex),
                                np.full_like(t, c / 2 - 0.03)])
    nx = np.column_stack([np.sign(fm.cos(t)) * fm.power(np.abs(fm.cos(t)), 2 - ex) / a,
                          np.sign(fm.sin(t)) * fm.power(np.abs(fm.sin(t)), 2 - ex) / b, np.zeros_like(t)])
    parts.append(sweep("zipper", zip_loop, 0.0025, "zipper", segments=8, closed=True, aspect=2.0, up=nx))
    parts.append(box("zipper_pull", (0.012, 0.004, 0.03), "metal",
                     transform((a / 2 - 0.06, -b / 2 - 0.008, c / 2 - 0.045))))

    def arch(name, start, end, outward, height, width):
        start, end, outward = (np.asarray(v, dtype=np.float64) for v in (start, end, outward))
        fr = np.array([0.0, 0.12, 0.3, 0.5, 0.7, 0.88, 1.0])
        lift = np.array([0.0, 0.0, 0.65, 1.0, 0.65, 0.0, 0.0]) * height + 0.005
        ctrl = start[None, :] + fr[:, None] * (end - start)[None, :] + lift[:, None] * outward[None, :]
        return sweep(name, smooth_path(ctrl, 40), 0.0016, "webbing", segments=12, aspect=width / 0.0032,
                     exponent=0.35, up=outward)

    straps = [arch("handle_top", (-0.15, 0.0, c / 2), (0.15, 0.0, c / 2), (0, 0, 1), 0.05, 0.035),
              arch("handle_left", (-a / 2, -0.1, 0.0), (-a / 2, 0.1, 0.0), (-1, 0, 0), 0.035, 0.03),
              arch("handle_right", (a / 2, -0.1, 0.0), (a / 2, 0.1, 0.0), (1, 0, 0), 0.035, 0.03)]
    parts.append(merge("handles", straps))
    parts.append(box("label_pocket", (0.15, 0.004, 0.09), "pocket", transform((0.05, -b / 2 - 0.004, -0.02))))
    parts.append(box("label_card", (0.12, 0.002, 0.06), "card", transform((0.05, -b / 2 - 0.0065, -0.02))))
    fabric, webbing = {"white": ((0.72, 0.7, 0.62), (0.45, 0.45, 0.43)),
                       "blue": ((0.04, 0.1, 0.3), (0.03, 0.03, 0.035))}[variant]
    mats = [_m("fabric", fabric, 0.0, 0.92), _m("webbing", webbing, 0.0, 0.85),
            _m("zipper", (0.03, 0.03, 0.03), 0.0, 0.6), _m("metal", (0.6, 0.6, 0.6), 1.0, 0.3),
            _m("pocket", (0.55, 0.55, 0.55), 0.0, 0.3), _m("card", (0.85, 0.85, 0.8), 0.0, 0.6)]
    return parts, mats


def _experiment_box(variant: str) -> tuple[Parts, Mats]:
    sx, sy, sz, f = 0.40, 0.26, 0.22, 0.012
    parts = [box("body", (sx - 0.004, sy - 0.004, sz - 0.004), "body")]
    rails = []
    for ax, length in enumerate((sx, sy, sz)):
        for u in (-1, 1):
            for v in (-1, 1):
                pos = np.zeros(3)
                others = [i for i in range(3) if i != ax]
                pos[others[0]] = u * ((sx, sy, sz)[others[0]] / 2 - f / 2)
                pos[others[1]] = v * ((sx, sy, sz)[others[1]] / 2 - f / 2)
                size = np.full(3, f)
                size[ax] = length
                rails.append(box(f"rail_{len(rails)}", size, "frame", transform(pos)))
    parts.append(merge("frame", rails))
    yf = sy / 2
    parts.append(box("front_panel", (sx - 2 * f, 0.004, sz - 2 * f), "panel", transform((0.0, yf, 0.0))))
    out = rot_x(-np.pi / 2)  # local +Z -> world +Y
    conns, faces, nuts = [], [], []
    for k, cx in enumerate((-0.12, -0.07, -0.02)):
        m = transform((cx, yf, -0.045), out)
        conns.append(box(f"flange_{k}", (0.034, 0.034, 0.004), "metal", fm.matmul(m, transform((0.0, 0.0, 0.003)))))
        conns.append(lathe(f"shell_{k}", [(0.0, 0.0), (0.0125, 0.0), (0.0125, 0.024), (0.0, 0.024)], "metal", 20,
                           matrix=m))
        nuts.append(extrude_polygon(f"coupling_{k}", _gear(0.0145, 0.0137, 14), 0.01, "connector",
                                    fm.matmul(m, transform((0.0, 0.0, 0.014)))))
        faces.append(cylinder(f"insert_{k}", 0.0095, 0.0015, "insert", 16, fm.matmul(m, transform((0.0, 0.0, 0.024)))))
    parts += [merge("connector_shells", conns), merge("connector_nuts", nuts), merge("connector_inserts", faces)]
    switches = []
    for k, cx in enumerate((0.06, 0.095)):
        m = transform((cx, yf, -0.05), out)
        switches.append(cylinder(f"bushing_{k}", 0.0055, 0.01, "metal", 12, m))
        tip = np.array([cx + 0.004, yf + 0.028, -0.043])
        switches.append(cylinder_between(f"lever_{k}", (cx, yf + 0.008, -0.05), tip, 0.0018, "metal", 8))
    parts.append(merge("toggles", switches))
    leds = [cylinder(f"led_{k}", 0.0042, 0.005, f"led_{k}", 12, transform((cx, yf, 0.055), out))
            for k, cx in enumerate((0.06, 0.085, 0.11))]
    parts += leds
    parts.append(box("label", (0.13, 0.003, 0.04), "label", transform((-0.07, yf + 0.002, 0.05))))
    screws = [cylinder(f"screw_{i + 1}_{j + 1}", 0.0045, 0.004, "metal", 12, transform((i * 0.165, yf, j * 0.08), out))
              for i in (-1, 1) for j in (-1, 1)]
    parts.append(merge("panel_screws", screws))
    handles = []
    for i in (-1, 1):
        hx = i * 0.17
        ctrl = np.array([[hx, yf, -0.07], [hx, yf + 0.03, -0.066], [hx, yf + 0.035, 0.0], [hx, yf + 0.03, 0.066],
                         [hx, yf, 0.07]])
        handles.append(sweep(f"handle_{i + 1}", smooth_path(ctrl, 30), 0.0055, "metal", segments=10))
    parts.append(merge("handles", handles))
    vents = [box(f"vent_{k}", (0.004, 0.12, 0.008), "vent", transform((sx / 2, 0.0, -0.06 + 0.022 * k)))
             for k in range(6)]
    parts.append(merge("vents", vents))
    parts.append(box("top_label", (0.16, 0.1, 0.002), "label", transform((0.05, 0.0, sz / 2))))
    body, frame, panel = {"default": ((0.72, 0.72, 0.7), (0.5, 0.5, 0.52), (0.04, 0.04, 0.045)),
                          "black": ((0.03, 0.03, 0.032), (0.2, 0.2, 0.21), (0.35, 0.35, 0.33))}[variant]
    mats = [_m("body", body, 0.0, 0.5), _m("frame", frame, 1.0, 0.4), _m("panel", panel, 0.3, 0.5),
            _m("metal", (0.7, 0.7, 0.7), 1.0, 0.3), _m("connector", (0.25, 0.28, 0.18), 0.6, 0.5),
            _m("insert", (0.02, 0.02, 0.02), 0.0, 0.7), _m("label", (0.85, 0.82, 0.3), 0.0, 0.6),
            _m("vent", (0.01, 0.01, 0.01), 0.0, 0.9),
            _m("led_0", (0.05, 0.8, 0.1), 0.0, 0.2), _m("led_1", (0.9, 0.5, 0.02), 0.0, 0.2),
            _m("led_2", (0.9, 0.05, 0.03), 0.0, 0.2)]
    return parts, mats


def _camera_unit(variant: str) -> tuple[Parts, Mats]:
    ry = rot_y(np.pi / 2)  # local +Z -> world +X
    parts = [superellipsoid("housing", (0.2, 0.13, 0.12), "housing", 0.25, 40, 20)]
    if variant == "camera":
        parts.append(lathe("lens_barrel", [(0.0, 0.0), (0.045, 0.0), (0.045, 0.03), (0.042, 0.034), (0.042, 0.07),
                                           (0.038, 0.072), (0.0, 0.072)], "dark", 32,
                           matrix=transform((0.095, 0.0, 0.0), ry)))
        parts.append(extrude_polygon("focus_ring", _gear(0.0455, 0.0440, 24), 0.016, "dark",
                                     transform((0.145, 0.0, 0.0), ry)))
        parts.append(lathe("hood", [(0.046, 0.06), (0.065, 0.125), (0.063, 0.127), (0.044, 0.066)], "dark", 32,
                           closed=True, matrix=transform((0.095, 0.0, 0.0), ry)))
        parts.append(lathe("lens_glass", [(0.0, 0.0), (0.034, 0.0), (0.0, 0.008)], "glass", 32,
                           matrix=transform((0.165, 0.0, 0.0), ry)))
    else:
        parts.append(lathe("bezel", [(0.0, 0.0), (0.062, 0.0), (0.062, 0.022), (0.055, 0.022), (0.05, 0.01),
                                     (0.0, 0.01)], "dark", 40, matrix=transform((0.095, 0.0, 0.0), ry)))
        leds = [cylinder(f"emitter_{i}", 0.0085, 0.008, "led", 16,
                         transform((0.105, 0.021 * fm.cos(a), 0.021 * fm.sin(a)), ry))
                for i, a in enumerate(np.arange(6) * np.pi / 3)]
        leds.append(cylinder("emitter_c", 0.0085, 0.008, "led", 16, transform((0.105, 0.0, 0.0), ry)))
        parts.append(merge("emitters", leds))
        fins = [box(f"fin_{k}", (0.12, 0.004, 0.03), "bracket", transform((-0.02, -0.04 + 0.016 * k, 0.07)))
                for k in range(6)]
        parts.append(merge("cooling_fins", fins))
    # Pan-tilt yoke and base.
    arms = [box(f"arm_{s + 1}", (0.04, 0.008, 0.11), "bracket", transform((0.0, s * 0.073, -0.045)))
            for s in (-1, 1)]
    pivots = [cylinder(f"pivot_{s + 1}", 0.018, 0.012, "bracket", 20,
                       transform((0.0, s * 0.066, 0.0), rot_x(-s * np.pi / 2))) for s in (-1, 1)]
    parts.append(merge("yoke", arms + pivots + [box("yoke_base", (0.05, 0.154, 0.01), "bracket",
                                                    transform((0.0, 0.0, -0.1)))]))
    parts.append(lathe("pan_unit", [(0.0, -0.16), (0.04, -0.16), (0.04, -0.135), (0.03, -0.125), (0.03, -0.105),
                                    (0.0, -0.105)], "housing", 28))
    parts.append(lathe("connector", [(0.0, 0.0), (0.014, 0.0), (0.014, 0.025), (0.0, 0.025)], "connector", 16,
                       matrix=transform((-0.098, 0.0, -0.02), rot_y(-np.pi / 2))))
    mats = [_m("housing", (0.75, 0.75, 0.73), 0.0, 0.45), _m("dark", (0.02, 0.02, 0.022), 0.2, 0.5),
            _m("bracket", (0.5, 0.5, 0.52), 1.0, 0.4), _m("connector", (0.25, 0.28, 0.18), 0.6, 0.5)]
    if variant == "camera":
        mats.append(_m("glass", (0.01, 0.015, 0.03), 0.0, 0.04))
    else:
        mats.append(_m("led", (0.9, 0.88, 0.7), 0.0, 0.15))
    return parts, mats


# ---------------------------------------------------------------------------------------------
# Registry and public API
# ---------------------------------------------------------------------------------------------

_BUILDERS: dict[str, Callable[[str], tuple[Parts, Mats]]] = {
    "mli_blanket": _mli_sheet,
    "mli_torn_sheet": _mli_torn,
    "mli_strip": _mli_strip,
    "power_cable": _power_cable,
    "data_cable": _data_cable,
    "cable_harness": _cable_harness,
    "power_drill": _power_drill,
    "eva_glove": _eva_glove,
    "wrench": _wrench,
    "hammer": _hammer,
    "bolt_cluster": _bolt_cluster,
    "tether_hook": _tether_hook,
    "handrail": _handrail,
    "crew_bag": _crew_bag,
    "experiment_box": _experiment_box,
    "camera_unit": _camera_unit,
}


def build_anomaly(name: str, variant: str | None = None) -> Asset:
    """The anomaly asset `name` (an id of ANOMALY_VARIANTS) in `variant` (default: the first).

    Metres, Z up, bounding-box centre at the origin. Raises UnknownAnomalyError (a ValueError)
    naming the valid choices for an unknown id or variant.
    """
    if name not in _BUILDERS:
        raise UnknownAnomalyError(
            f"unknown anomaly {name!r}; valid anomaly ids are: {', '.join(ANOMALY_IDS)}")
    variants, builder = ANOMALY_VARIANTS[name], _BUILDERS[name]
    variant = variants[0] if variant is None else variant
    if variant not in variants:
        raise UnknownAnomalyError(
            f"anomaly {name!r} has no variant {variant!r}; valid variants are: {', '.join(variants)}")
    parts, materials = builder(variant)
    lo = np.min([p.points.min(axis=0) for p in parts], axis=0)
    hi = np.max([p.points.max(axis=0) for p in parts], axis=0)
    centre = transform(-(lo + hi) / 2.0)
    parts = [p.transformed(centre) for p in parts]
    used = {p.material for p in parts}
    return Asset(name, tuple(parts), tuple(m for m in materials if m.name in used))
