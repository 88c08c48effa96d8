"""The implicit shapes' tessellation: on the surface, within the stated chord error, wound outward,
closed, along each axis, at each size."""

from __future__ import annotations

import math

import numpy as np
import pytest

from allo_usd.usd import implicit_shapes as S
from allo_usd.usd.implicit_shapes import CHORD_TOLERANCE

AXES = ("X", "Y", "Z")
SPINE = {"X": 0, "Y": 1, "Z": 2}


def faces(shape):
    starts = np.concatenate([[0], np.cumsum(shape.face_counts)[:-1]])
    return [shape.face_indices[s:s + c] for s, c in zip(starts, shape.face_counts)]


def newell(pts: np.ndarray) -> np.ndarray:
    """A polygon's area-weighted normal (right-handed: counter-clockwise seen from the front)."""
    return np.cross(pts, np.roll(pts, -1, axis=0)).sum(axis=0) / 2.0


def plane_distance(pts: np.ndarray) -> float:
    """Distance of a face's plane from the origin."""
    n = newell(pts)
    return float(abs(n @ pts[0]) / np.linalg.norm(n))


def welded_edges(shape) -> dict:
    """Directed edges between welded vertices (the caps sit on vertices of their own) -> count."""
    keys = [tuple(k) for k in np.round(shape.points.astype(np.float64), 5)]
    ids = {}
    weld = np.array([ids.setdefault(k, len(ids)) for k in keys])
    edges: dict = {}
    for f in faces(shape):
        w = weld[f]
        for a, b in zip(w, np.roll(w, -1)):
            if a != b:
                edges[(a, b)] = edges.get((a, b), 0) + 1
    return edges


def assert_closed(shape):
    edges = welded_edges(shape)
    assert set(edges.values()) == {1}, "an edge used twice in one direction: inconsistent winding"
    assert all((b, a) in edges for a, b in edges), "an edge with one face only: a hole"


def assert_outward(shape, centre=(0.0, 0.0, 0.0)):
    for f in faces(shape):
        pts = shape.points[f].astype(np.float64)
        assert newell(pts) @ (pts.mean(axis=0) - centre) > 0


def test_segment_counts_meet_the_bound():
    n = S.circle_segments()
    assert n == 72 and 1 - math.cos(math.pi / n) <= CHORD_TOLERANCE < 1 - math.cos(math.pi / (n - 2))
    assert S.sphere_segments() == 100 and S.sphere_segments(1e-2) < 100
    assert S.circle_segments(1e-4) > 200


@pytest.mark.parametrize("radius", [0.01, 1.0, 250.0])
def test_sphere(radius):
    s = S.sphere(radius)
    assert s.smooth
    d = np.linalg.norm(s.points.astype(np.float64), axis=1)
    np.testing.assert_allclose(d, radius, rtol=1e-6)
    worst = max(radius - plane_distance(s.points[f].astype(np.float64)) for f in faces(s))
    assert 0 < worst <= CHORD_TOLERANCE * radius * (1 + 1e-3)
    assert_closed(s)
    assert_outward(s)


@pytest.mark.parametrize("axis", AXES)
@pytest.mark.parametrize("radius,height", [(0.5, 2.0), (3.0, 0.1)])
def test_cylinder(axis, radius, height):
    s = S.cylinder(radius, radius, height, axis)
    pts = s.points.astype(np.float64)
    spine = pts[:, SPINE[axis]]
    across = np.delete(pts, SPINE[axis], axis=1)
    rho = np.linalg.norm(across, axis=1)
    np.testing.assert_allclose(rho, radius, rtol=1e-6)          # every vertex on the rim
    np.testing.assert_allclose(np.abs(spine), height / 2, rtol=1e-6)
    # the side's faces are as far from the spine as their chords: within the bound
    side = [f for f in faces(s) if len(f) == 4]
    mid = np.array([across[f[:2]].mean(axis=0) for f in side])
    chord = radius - np.linalg.norm(mid, axis=1)
    assert chord.max() <= CHORD_TOLERANCE * radius
    assert_closed(s)
    assert_outward(s)
    assert s.smooth


@pytest.mark.parametrize("axis", AXES)
def test_cone(axis):
    s = S.cone(1.5, 2.0, axis)
    pts = s.points.astype(np.float64)
    apex = np.zeros(3)
    apex[SPINE[axis]] = 1.0
    assert np.isclose(pts, apex, atol=1e-6).all(axis=1).sum() == 1      # one apex, on +axis
    rim = pts[np.isclose(pts[:, SPINE[axis]], -1.0)]
    np.testing.assert_allclose(np.linalg.norm(np.delete(rim, SPINE[axis], axis=1), axis=1), 1.5, rtol=1e-6)
    assert_closed(s)
    assert_outward(s)


def test_frustum_and_inverted_cone():
    assert_closed(S.cylinder(1.0, 0.5, 2.0))
    assert_outward(S.cylinder(1.0, 0.5, 2.0))
    s = S.cylinder(0.0, 1.0, 2.0, "X")      # apex at -X
    assert_closed(s)
    assert_outward(s)
    assert s.points[:, 0].min() == pytest.approx(-1.0)


@pytest.mark.parametrize("axis", AXES)
def test_capsule(axis):
    r, h = 0.4, 1.2
    s = S.capsule(r, h, axis)
    pts = s.points.astype(np.float64)
    k = SPINE[axis]
    # distance from the spine segment (-h/2..h/2 on the axis) is the radius everywhere
    t = np.clip(pts[:, k], -h / 2, h / 2)
    nearest = np.zeros_like(pts)
    nearest[:, k] = t
    np.testing.assert_allclose(np.linalg.norm(pts - nearest, axis=1), r, rtol=1e-6)
    assert pts[:, k].max() == pytest.approx(h / 2 + r)
    assert_closed(s)
    assert_outward(s)
    for f in faces(s):                       # every face within the bound of the capsule's surface
        p = pts[f]
        c = p.mean(axis=0)
        if abs(c[k]) > h / 2:                # a hemisphere's face: its plane from the hemisphere's centre
            centre = np.zeros(3)
            centre[k] = math.copysign(h / 2, c[k])
            assert r - plane_distance(p - centre) <= CHORD_TOLERANCE * r * (1 + 1e-3)


def test_cube():
    s = S.cube(2.0)
    assert not s.smooth and len(s.points) == 8 and list(s.face_counts) == [4] * 6
    np.testing.assert_allclose(np.abs(s.points), 1.0)
    assert_closed(s)
    assert_outward(s)
    assert_outward(S.cube(0.05))


@pytest.mark.parametrize("axis", AXES)
def test_plane(axis):
    s = S.plane(2.0, 4.0, axis)
    n = newell(s.points.astype(np.float64))
    assert n["XYZ".index(axis)] == pytest.approx(8.0)      # area 8, facing +axis
    wi, li = S.PLANE_AXES[axis]
    assert np.abs(s.points[:, wi]).max() == 1.0 and np.abs(s.points[:, li]).max() == 2.0
    assert not s.smooth


def test_bad_axis():
    with pytest.raises(ValueError):
        S.cylinder(1, 1, 1, "W")
