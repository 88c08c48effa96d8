"""The bodies' drawn outlines are the true discs: the committed sphere meshes, seen from any direction at
the distances of a year of layers, have a mean outline angular radius within 1e-4 of asin(R / d).

Independent of allo_usd.assets: the meshes are read from the committed stage (what Blender loads),
triangulated, and the outline is found from the edges themselves. A silhouette edge joins a triangle
that faces the eye and one that faces away; along each azimuth around the body's centre direction the
drawn outline is the farthest crossing of a silhouette edge (exact for any closed mesh, convex or not).
Angles come from the gnomonic projection about the centre direction: a point at radius t is atan(t)
from the centre.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from allo_usd.core.constants import EARTH_RADIUS_M, MOON_RADIUS_M, SUN_RADIUS_M
from allo_usd.core.paths import STAGES
from allo_usd.sky.ephemeris import default_epochs
from allo_usd.sky.model import compute_sky
from allo_usd.sky.orbit import Orbit

BUDGET = 1e-4        # relative, on the mean outline angular radius
AZIMUTHS = 2048      # samples around the outline
RADIUS = {"Sun": SUN_RADIUS_M, "Earth": EARTH_RADIUS_M, "Moon": MOON_RADIUS_M}
PERILUNE_RADII = Orbit().perilune_radius_m / MOON_RADIUS_M  # the nearest any body is seen: 1.87 radii


class Mesh:
    """A committed body mesh: welded vertex positions, real triangles, and each edge's two triangles."""

    def __init__(self, name: str):
        stage = Usd.Stage.Open(str(STAGES / "bodies" / f"{name}.usda"))
        meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
        assert len(meshes) == 1, f"{name}: one mesh expected"
        mesh = meshes[0]
        world = np.array(mesh.ComputeLocalToWorldTransform(Usd.TimeCode.Default()), dtype=np.float64)
        pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
        pts = pts @ world[:3, :3] + world[3, :3]  # Gf matrices act on row vectors
        counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
        indices = np.array(mesh.GetFaceVertexIndicesAttr().Get())
        # Weld coincident vertices (the UV seam and the poles repeat positions), then fan-triangulate.
        _, weld, inverse = np.unique(np.round(pts, 9), axis=0, return_index=True, return_inverse=True)
        self.points = pts[weld]
        assert np.abs(self.points).max() < 1.1, f"{name}: a unit sphere is expected (the layers scale it by R)"
        idx = inverse.ravel()[indices]
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        tris = np.concatenate([np.stack([idx[starts], idx[starts + k], idx[starts + k + 1]], 1)
                               for k in range(1, counts.max() - 1) if np.any(counts > k + 1)])
        tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
        self.tris = tris
        p = self.points
        self.normals = np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])
        edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        owner = np.tile(np.arange(len(tris)), 3)
        key = np.sort(edges, axis=1)
        order = np.lexsort((key[:, 1], key[:, 0]))
        key, owner = key[order], owner[order]
        assert np.all(key[0::2] == key[1::2]), f"{name}: not a closed 2-manifold after welding"
        self.edges, self.faces = key[0::2], np.stack([owner[0::2], owner[1::2]], 1)


def outline_radius(mesh: Mesh, view: np.ndarray, distance: float) -> np.ndarray:
    """Angular radius (rad) of the drawn outline at AZIMUTHS azimuths, seen from `distance` (in the
    mesh's units) along unit `view` from the centre."""
    eye = view * distance
    facing = np.einsum("ij,ij->i", mesh.normals, eye - mesh.points[mesh.tris[:, 0]]) > 0
    sil = mesh.edges[facing[mesh.faces[:, 0]] != facing[mesh.faces[:, 1]]]
    helper = np.array([1.0, 0.0, 0.0]) if abs(view[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(helper, view)
    a /= np.linalg.norm(a)
    b = np.cross(view, a)
    rel = mesh.points - eye
    depth = -(rel @ view)
    xy = np.stack([rel @ a, rel @ b], 1) / depth[:, None]   # gnomonic, about the centre direction
    p, q = xy[sil[:, 0]], xy[sil[:, 1]]
    # Each edge spans a small arc of azimuth: pair it with the azimuth samples inside that arc only.
    step = 2 * np.pi / AZIMUTHS
    ap = np.arctan2(p[:, 1], p[:, 0])
    turn = np.remainder(np.arctan2(q[:, 1], q[:, 0]) - ap + np.pi, 2 * np.pi) - np.pi
    start = np.where(turn > 0, ap, ap + turn)
    first = np.ceil(start / step - 0.5).astype(np.int64)
    count = np.maximum(np.floor((start + np.abs(turn)) / step - 0.5).astype(np.int64) - first + 1, 0)
    edge = np.repeat(np.arange(len(sil)), count)
    k = first[edge] + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    alpha = (k + 0.5) * step
    u = np.stack([np.cos(alpha), np.sin(alpha)], 1)
    pe, de = p[edge], q[edge] - p[edge]
    denom = u[:, 0] * de[:, 1] - u[:, 1] * de[:, 0]
    t = (pe[:, 0] * de[:, 1] - pe[:, 1] * de[:, 0]) / denom   # the ray's crossing of the edge's line
    r = np.full(AZIMUTHS, -np.inf)
    np.maximum.at(r, np.remainder(k, AZIMUTHS), np.where(t > 0, t, -np.inf))
    assert np.all(np.isfinite(r)), "the outline must go all the way round"
    return np.arctan(r)


def view_directions(segments: int, rings: int, count: int = 32) -> list[np.ndarray]:
    """Poles and just off them, the equator on and between meridians, mid-ring latitudes, and a
    Fibonacci spread of `count` more."""
    ring, seg = math.pi / rings, 2 * math.pi / segments
    special = [(0.0, 0.0), (ring / 4, 0.0), (ring / 2, seg / 2)]
    special += [(polar, az) for polar in (math.pi / 2, math.pi / 2 + ring / 2, math.pi / 4 + ring / 2)
                for az in (0.0, seg / 2, seg / 4, math.pi / 4 + seg / 2)]
    special += [(math.pi - polar, az) for polar, az in special[:3]]
    dirs = [np.array([math.sin(t) * math.cos(f), math.sin(t) * math.sin(f), math.cos(t)]) for t, f in special]
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    f = math.pi * (1 + 5 ** 0.5) * i
    dirs += list(np.stack([np.sqrt(1 - z * z) * np.cos(f), np.sqrt(1 - z * z) * np.sin(f), z], 1))
    return dirs


def grid_size(mesh: Mesh) -> tuple[int, int]:
    """(segments, rings) of a UV sphere: rings from the distinct heights, segments from the equator."""
    z = np.unique(np.round(mesh.points[:, 2] / np.abs(mesh.points).max(), 9))
    rings = len(z) - 1
    return (len(mesh.points) - 2) // (rings - 1), rings


@pytest.fixture(scope="module")
def distances():
    """Each body's year of distances from the station, in body radii: min, middle and max."""
    sky = compute_sky(default_epochs(2030, 365))
    out = {}
    for name, radius in RADIUS.items():
        d = np.asarray(sky.distance_m[name.lower()]) / radius
        out[name] = np.linspace(d.min(), d.max(), 3)
    return out


def measure(name: str, distances) -> np.ndarray:
    """(mean, min, max) relative error of the outline angular radius, per view and distance (in radii)."""
    mesh = Mesh(name)
    segments, rings = grid_size(mesh)
    rows = []
    for dist in distances:
        true = math.asin(1.0 / dist)
        for view in view_directions(segments, rings):
            err = outline_radius(mesh, view, dist) / true - 1.0
            rows.append((err.mean(), err.min(), err.max()))
    return np.array(rows)


@pytest.mark.parametrize("name", ["Sun", "Earth", "Moon"])
@pytest.mark.slow
def test_mean_outline_is_the_true_angular_radius(name, distances):
    rows = measure(name, distances[name])
    mean, lo, hi = rows[:, 0], rows[:, 1].min(), rows[:, 2].max()
    print(f"{name}: mean outline error {mean.min():+.2e} .. {mean.max():+.2e}, outline min/max {lo:+.2e} / {hi:+.2e}")
    assert np.all(np.abs(mean) <= BUDGET), (name, mean.min(), mean.max())
    assert lo > -1e-3 and hi < 1e-3  # the polygon's ripple about the circle stays well under a 1e-3


@pytest.mark.slow
def test_pole_views_at_every_distance():
    """Seen over a pole the limb runs parallel to the rings: the worst case, which depends on where the
    limb falls between two rings, so the distance is swept finely, from the Moon's perilune out past
    the Earth's farthest."""
    mesh = Mesh("Moon")
    worst = 0.0
    for dist in np.geomspace(PERILUNE_RADII, 80.0, 60):
        true = math.asin(1.0 / dist)
        for view in (np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])):
            worst = max(worst, abs(outline_radius(mesh, view, dist).mean() / true - 1.0))
    assert worst <= BUDGET, worst


def test_outline_measure_sees_a_known_polygon():
    """The measure itself: a regular N-gon prism's outline seen from far along its axis is the N-gon,
    whose mean radius over azimuth is cos(pi/N) atanh(sin(pi/N)) / (pi/N) of its circumradius."""
    from scipy.spatial import ConvexHull

    n = 16
    f = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(f), np.sin(f)], 1)
    pts = np.concatenate([np.column_stack([ring, np.full(n, h)]) for h in (-0.5, 0.5)])
    mesh = Mesh.__new__(Mesh)
    mesh.points = pts
    hull = ConvexHull(pts)
    tris = hull.simplices.copy()
    centre = pts.mean(axis=0)
    normals = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    flip = np.einsum("ij,ij->i", normals, pts[tris[:, 0]] - centre) < 0
    tris[flip] = tris[flip][:, ::-1]
    mesh.tris = tris
    mesh.normals = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    owner = np.tile(np.arange(len(tris)), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    mesh.edges, mesh.faces = key[order][0::2], np.stack([owner[order][0::2], owner[order][1::2]], 1)
    dist = 1e6
    got = np.tan(outline_radius(mesh, np.array([0.0, 0.0, 1.0]), dist)) * (dist - 0.5)
    x = math.pi / n
    assert got.mean() == pytest.approx(math.cos(x) * math.atanh(math.sin(x)) / x, rel=2e-5)
    assert 1 - 1e-3 < got.max() <= 1.0 and got.min() == pytest.approx(math.cos(x), rel=1e-5)
