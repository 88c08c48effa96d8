"""UsdGeom's implicit shapes (Cube, Sphere, Cylinder, Cone, Capsule, Plane) as polygon meshes, at a
stated accuracy. Pure numpy: no pxr, no bpy; angles through allo_usd.core.fixedmath, so the vertices
(which reach the annotations' model boxes) are the same on every machine.

Accuracy: every vertex lies on the true surface, and every point of the tessellated surface lies
within CHORD_TOLERANCE x the shape's radius of it (0.1 %). A circle of radius r cut into n equal
chords departs from the arc by at most r (1 - cos(pi / n)), so a revolved profile takes
n = ceil(pi / acos(1 - eps)) segments around (`circle_segments`, 72 at 0.1 %). A sphere's quad spans
a step in longitude and one in latitude, and its plane departs from the sphere by r (1 - cos a),
a the angular radius of the circle through its corners (at most half its diagonal, step / sqrt 2 in
each direction): `sphere_segments` takes sqrt(2) times as many (100 around, 50 rings). The
capsule's hemispheres are the sphere's; cylinders, cones and the capsule's side are exact along
their axis and off by the circle's chord error around it. Cube and Plane are exact.

Faces wind counter-clockwise seen from outside (outward normals, USD's rightHanded orientation);
closed shapes are closed (every edge between two faces, once in each direction). Smooth shapes
(sphere, cylinder, cone, capsule: `Shape.smooth`) keep their flat caps on vertices of their own, so
smooth shading averages the normals of the curved faces only; the cone's apex is one vertex.

`axis` (USD's X, Y or Z) is the spine of the revolved shapes and the normal of the plane: a shape is
made along Z and its coordinates turned cyclically (a rotation, so the winding stays outward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from allo_usd.core import fixedmath as fm

CHORD_TOLERANCE = 1e-3   # distance of the tessellated surface from the true one, relative to the radius


@dataclass(frozen=True, eq=False)
class Shape:
    points: np.ndarray        # (N, 3) float32
    face_counts: np.ndarray   # (F,) int32
    face_indices: np.ndarray  # (sum,) int32
    smooth: bool


def _even(x: float) -> int:
    n = math.ceil(x - 1e-9)
    return n + n % 2


def circle_segments(eps: float = CHORD_TOLERANCE) -> int:
    """Segments around a circle so that every chord stays within eps x the radius of the arc (even)."""
    return _even(math.pi / fm.arccos(1.0 - eps))


def sphere_segments(eps: float = CHORD_TOLERANCE) -> int:
    """Segments around a sphere (and half as many rings from pole to pole) so that every face stays
    within eps x the radius of the sphere: sqrt(2) x circle_segments' count (even, a multiple of 4
    so that the capsule's hemispheres have whole rings)."""
    n = math.ceil(math.sqrt(2.0) * math.pi / fm.arccos(1.0 - eps) - 1e-9)
    return n + (-n) % 4


def _orient(points: np.ndarray, axis: str) -> np.ndarray:
    """A shape made along Z, turned so that its Z lies along `axis` (a cyclic turn of the coordinates)."""
    if axis == "Z":
        return points
    if axis == "X":
        return points[:, [2, 0, 1]]
    if axis == "Y":
        return points[:, [1, 2, 0]]
    raise ValueError(f"axis must be X, Y or Z, not {axis!r}")


class _Builder:
    def __init__(self):
        self.points: list[np.ndarray] = []
        self.faces: list[list[int]] = []
        self.n = 0

    def add_points(self, pts: np.ndarray) -> int:
        start = self.n
        self.points.append(np.asarray(pts, dtype=np.float64).reshape(-1, 3))
        self.n += len(self.points[-1])
        return start

    def revolve(self, profile: list[tuple[float, float]], n: int) -> None:
        """A surface of revolution about Z through the (radius, z) profile, bottom to top; a radius of 0
        (first or last only) is a pole, one vertex."""
        phi = 2.0 * math.pi * np.arange(n) / n
        cos, sin = fm.cos(phi), fm.sin(phi)
        rings = []
        for r, z in profile:
            if r == 0.0:
                rings.append(self.add_points([0.0, 0.0, z]))
            else:
                rings.append(self.add_points(np.column_stack([r * cos, r * sin, np.full(n, z)])))
        poles = [r == 0.0 for r, _ in profile]
        for k in range(len(profile) - 1):
            lo, hi = rings[k], rings[k + 1]
            for j in range(n):
                j1 = (j + 1) % n
                if poles[k]:
                    self.faces.append([lo, hi + j1, hi + j])
                elif poles[k + 1]:
                    self.faces.append([lo + j, lo + j1, hi])
                else:
                    self.faces.append([lo + j, lo + j1, hi + j1, hi + j])

    def disc(self, r: float, z: float, n: int, up: bool) -> None:
        """A flat n-gon of radius r at height z, facing +Z (up) or -Z, on vertices of its own."""
        phi = 2.0 * math.pi * np.arange(n) / n
        start = self.add_points(np.column_stack([r * fm.cos(phi), r * fm.sin(phi), np.full(n, z)]))
        order = list(range(start, start + n))
        self.faces.append(order if up else order[::-1])

    def shape(self, smooth: bool, axis: str = "Z") -> Shape:
        points = _orient(np.concatenate(self.points), axis).astype(np.float32)
        counts = np.array([len(f) for f in self.faces], dtype=np.int32)
        indices = np.array([i for f in self.faces for i in f], dtype=np.int32)
        return Shape(points, counts, indices, smooth)


def cube(size: float) -> Shape:
    """UsdGeom.Cube: edges of length `size`, centred on the origin."""
    h = size / 2.0
    b = _Builder()
    b.add_points([[x, y, z] for z in (-h, h) for y in (-h, h) for x in (-h, h)])
    # corners: index = x + 2y + 4z (each 0 for -h, 1 for +h)
    b.faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    return b.shape(smooth=False)


def sphere(radius: float, eps: float = CHORD_TOLERANCE) -> Shape:
    """UsdGeom.Sphere, centred on the origin, poles on Z."""
    n = sphere_segments(eps)
    m = n // 2
    theta = math.pi * np.arange(m + 1) / m
    profile = [(0.0, -radius)] + [(radius * fm.sin(t), -radius * fm.cos(t)) for t in theta[1:-1]] + [(0.0, radius)]
    b = _Builder()
    b.revolve(profile, n)
    return b.shape(smooth=True)


def cylinder(radius_bottom: float, radius_top: float, height: float, axis: str = "Z",
             eps: float = CHORD_TOLERANCE) -> Shape:
    """UsdGeom.Cylinder (radius_bottom == radius_top) and Cylinder_1 (a frustum; one radius may be 0,
    a cone): spine along `axis`, from -height/2 (radiusBottom) to +height/2 (radiusTop), capped."""
    n = circle_segments(eps)
    h = height / 2.0
    b = _Builder()
    b.revolve([(radius_bottom, -h), (radius_top, h)], n)
    if radius_bottom > 0:
        b.disc(radius_bottom, -h, n, up=False)
    if radius_top > 0:
        b.disc(radius_top, h, n, up=True)
    return b.shape(smooth=True, axis=axis)


def cone(radius: float, height: float, axis: str = "Z", eps: float = CHORD_TOLERANCE) -> Shape:
    """UsdGeom.Cone: base of `radius` at -height/2, apex at +height/2 along `axis`."""
    return cylinder(radius, 0.0, height, axis, eps)


def capsule(radius: float, height: float, axis: str = "Z", eps: float = CHORD_TOLERANCE) -> Shape:
    """UsdGeom.Capsule: a cylinder of `radius` and `height` (the spine without the caps) along `axis`,
    closed by two hemispheres of `radius`."""
    n = sphere_segments(eps)
    q = n // 4                     # rings from a pole to the equator, as on the sphere
    h = height / 2.0
    theta = (math.pi / 2.0) * np.arange(q + 1) / q          # 0 at the pole .. pi/2 at the equator
    bottom = [(radius * fm.sin(t), -h - radius * fm.cos(t)) for t in theta]
    top = [(radius * fm.sin(t), h + radius * fm.cos(t)) for t in theta[::-1]]
    bottom[0], top[-1] = (0.0, bottom[0][1]), (0.0, top[-1][1])
    b = _Builder()
    b.revolve(bottom + top, n)
    return b.shape(smooth=True, axis=axis)


# UsdGeom.Plane: the axes width and length lie along, by its axis (the plane's normal)
PLANE_AXES = {"Z": (0, 1), "Y": (0, 2), "X": (2, 1)}


def plane(width: float, length: float, axis: str = "Z") -> Shape:
    """UsdGeom.Plane: a width x length rectangle centred on the origin, facing +axis (one quad; USD's
    doubleSided only permits a renderer to cull its back, and Cycles draws both sides)."""
    if axis not in PLANE_AXES:
        raise ValueError(f"axis must be X, Y or Z, not {axis!r}")
    wi, li = PLANE_AXES[axis]
    corners = np.zeros((4, 3))
    for k, (sw, sl) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
        corners[k, wi], corners[k, li] = sw * width / 2.0, sl * length / 2.0
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[1])
    if normal["XYZ".index(axis)] < 0:
        corners = corners[::-1]
    b = _Builder()
    b.add_points(corners)
    b.faces = [[0, 1, 2, 3]]
    return b.shape(smooth=False)
