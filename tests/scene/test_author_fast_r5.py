"""The shortcuts of issue 26 (round 5) give exactly the bits of the code they stand in for: a few rays'
hits on Python floats (`RayScene._few_hits`, behind `first_hit` and `first_hit_fan` up to `_FEW`
rays) are the numpy path's; the part-box union with both axes stacked is its former form, written
out here as the oracle; `fixedmath.matmul_lists` is `fm.matmul`; the object's extent kept on its BVH
is what each group computed."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core.geometry import box_corners
from allo_usd.scene import placement, raycast, rig
from allo_usd.scene.raycast import RayFan, RayScene
from tests.support.helpers import tiny_station


def _bits(a) -> bytes:
    a = np.asarray(a)
    return a.dtype.str.encode() + np.ascontiguousarray(a).tobytes()


def _station() -> RayScene:
    pts, tris = tiny_station().triangle_soup()
    return RayScene([(pts, tris, 1)])


def _soup(seed: int) -> RayScene:
    """Random triangles with degenerate ones, and faces in the planes x = k that axis rays graze."""
    rng = np.random.default_rng(seed)
    pts = (rng.normal(size=(300, 1, 3)) * 2.0 + rng.normal(scale=0.5, size=(300, 3, 3))).reshape(-1, 3)
    pts[:60, 0] = np.round(pts[:60, 0])
    pts[60:90] = pts[60]
    owner_a, owner_b = np.arange(450).reshape(-1, 3), np.arange(450, 900).reshape(-1, 3)
    return RayScene([(pts[:450], owner_a, 1), (pts[450:], owner_b - 450, 2)])


def _numpy_path(monkeypatch, fn):
    """`fn()` with the few-ray path switched off (fans made inside `fn` carry no rows)."""
    with monkeypatch.context() as m:
        m.setattr(raycast, "_FEW", 0)
        return fn()


@pytest.mark.parametrize("make", [_station, lambda: _soup(1), lambda: _soup(2)])
def test_few_rays_are_the_numpy_hits(make, monkeypatch):
    scene = make()
    rng = np.random.default_rng(11)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    dropped = hits = 0
    for k in range(400):
        n = int(rng.integers(1, raycast._FEW + 1))
        o = lo + (hi - lo) * rng.random((n, 3))
        d = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 1e3])
        if k % 5 == 0:                                     # towards a face's centre along its plane: grazing hits
            tri = scene.vertices[scene.faces[rng.integers(len(scene.faces), size=n)]]
            normal = fm.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            centre = tri.mean(axis=1)
            o = centre + 2.0 * (centre - tri[:, 0]) + normal * 1e-9
            d = (centre - o) - normal * rng.choice([0.0, 1e-7, 1e-6])
        if k % 7 == 0:
            d[-1] = 0.0                                    # a direction without a length
        got = scene.first_hit(o, d)
        want = _numpy_path(monkeypatch, lambda: scene.first_hit(o, d))
        assert [_bits(a) for a in got] == [_bits(a) for a in want]
        fan = RayFan.of_rows(d)
        assert fan.rows is not None
        got_fan = scene.first_hit_fan(o[0], fan)
        want_fan = _numpy_path(monkeypatch, lambda: scene.first_hit_fan(o[0], RayFan.of_rows(d)))
        assert [_bits(a) for a in got_fan] == [_bits(a) for a in want_fan]
        embree = scene._run(o, raycast._unitize(d)[0])
        hits += int((want[0] > 0).sum())
        dropped += int(((embree != -1) & (want[0] == 0)).sum())
    assert hits > 500 and dropped > 0                     # both kinds of hit were exercised


def test_a_fan_past_few_rays_takes_the_numpy_path():
    assert RayFan.of_rows(np.eye(3)[np.arange(raycast._FEW + 1) % 3]).rows is None
    assert rig._CLEARANCE_FAN.rows is not None and placement._SPHERE_FAN.rows is None


def test_the_rig_clearance_and_the_line_of_sight_are_unchanged(monkeypatch):
    """too_close and the one-ray look along a candidate's line of sight, on the station."""
    scene = _station()
    rng = np.random.default_rng(5)
    lo, hi = scene.vertices.min(axis=0) - 2.0, scene.vertices.max(axis=0) + 2.0
    points = lo + (hi - lo) * rng.random((300, 3))
    got = [rig.too_close(scene, p) for p in points]
    assert got == _numpy_path(monkeypatch, lambda: [rig.too_close(scene, p) for p in points])
    assert 0 < sum(got) < len(got)
    rays = scene.vertices[rng.integers(len(scene.vertices), size=300)] - points + rng.normal(scale=0.5, size=(300, 3))
    rays /= fm.norm(rays, axis=1, keepdims=True)
    got = [scene.first_hit(p[None], r[None])[1][0] for p, r in zip(points, rays)]
    want = _numpy_path(monkeypatch, lambda: [scene.first_hit(p[None], r[None])[1][0] for p, r in zip(points, rays)])
    assert _bits(got) == _bits(want) and np.isfinite(got).sum() > 50


def _old_rects_union(width, height, stride, u0, u1, v0, v1):
    """placement._rects_union before round 5: each axis on its own, every part in the loop."""
    phase, m = stride // 2, placement.CULL_MARGIN_PX
    none = np.zeros(0, dtype=np.int64)
    if phase >= width or phase >= height:
        return none, none, none, none
    t0 = np.maximum(-((phase - np.ceil(u0 - (0.5 + m)).astype(np.int64)) // stride), 0)
    t1 = np.minimum((np.floor(u1 - (0.5 - m)).astype(np.int64) - phase) // stride, (width - 1 - phase) // stride)
    r0 = np.maximum(-((phase - np.ceil(v0 - (0.5 + m)).astype(np.int64)) // stride), 0)
    r1 = np.minimum((np.floor(v1 - (0.5 - m)).astype(np.int64) - phase) // stride, (height - 1 - phase) // stride)
    some = (t0 <= t1) & (r0 <= r1)
    if not some.any():
        return none, none, none, none
    c0, c1, w0, w1 = int(t0[some].min()), int(t1[some].max()), int(r0[some].min()), int(r1[some].max())
    covered = np.zeros((w1 - w0 + 1, c1 - c0 + 1), dtype=bool)
    for a, b, c, d in zip((r0 - w0).tolist(), (r1 - w0 + 1).tolist(), (t0 - c0).tolist(), (t1 - c0 + 1).tolist()):
        if a < b and c < d:
            covered[a:b, c:d] = True
    jj, ii = np.nonzero(covered)
    return phase + stride * np.arange(c0, c1 + 1), phase + stride * np.arange(w0, w1 + 1), ii, jj


def test_the_union_is_its_former_form():
    rng = np.random.default_rng(4)
    cases = 0
    for k in range(3000):
        w, h, stride, parts = (int(rng.integers(1, 240)), int(rng.integers(1, 140)), int(rng.integers(1, 5)),
                               int(rng.integers(1, 70)))
        u0, v0 = rng.uniform(-40, w + 40, parts), rng.uniform(-40, h + 40, parts)
        u1, v1 = u0 + rng.uniform(-4, 50, parts), v0 + rng.uniform(-4, 50, parts)
        if k % 3 == 0:                                     # edges on and near pixel centres
            u0, v0 = np.round(u0) + 0.5 + rng.choice([0.0, 0.05, -0.05, 0.0500001], parts), np.round(v0) + 0.45
        got = placement._rects_union(w, h, stride, np.stack([u0, v0]), np.stack([u1, v1]))
        want = _old_rects_union(w, h, stride, u0, u1, v0, v1)
        assert all(g.dtype == np.int64 and _bits(g) == _bits(x) for g, x in zip(got, want)), (w, h, stride)
        cases += bool(len(want[2]))
    assert cases > 1500


def test_matmul_lists_is_fixedmath_matmul():
    rng = np.random.default_rng(9)
    special = [np.inf, -np.inf, np.nan, -0.0, 0.0, 1e308, 5e-324]
    for _ in range(500):
        n, k, m = (int(x) for x in rng.integers(1, 5, 3))
        a, b = rng.normal(size=(n, k)) * 10.0 ** rng.integers(-5, 5), rng.normal(size=(k, m))
        if rng.random() < 0.3:
            a.flat[rng.integers(a.size)] = rng.choice(special)
        with np.errstate(all="ignore"):
            want = a[:, :, None] * b[None, :, :]          # the broadcast form, summed in index order
            acc = want[:, 0]
            for i in range(1, k):
                acc = acc + want[:, i]
        got = np.array(fm.matmul_lists(a.tolist(), b.tolist()), dtype=np.float64)
        assert _bits(got) == _bits(acc) and _bits(fm.matmul(a, b)) == _bits(acc)


def test_the_extent_kept_on_the_bvh_follows_the_points():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(200, 3))
    tris = rng.integers(0, 200, size=(100, 3))
    scene = placement.anomaly_scene(pts, tris)
    radius, corners = placement._extent(scene, pts)
    assert radius == float(fm.norm(pts, axis=1).max()) and _bits(corners) == _bits(box_corners(pts))
    assert placement._extent(scene, pts)[1] is corners             # kept
    other = pts * 2.0
    radius2, corners2 = placement._extent(scene, other)           # other points: computed afresh
    assert radius2 == float(fm.norm(other, axis=1).max()) and _bits(corners2) == _bits(box_corners(other))


def test_a_placement_is_the_same_with_the_extent_kept():
    """Two groups of one asset on one BVH place as a fresh BVH each would."""
    station = _station()
    obj = (np.array([[-0.3, -0.2, -0.15], [0.3, -0.2, -0.15], [0.3, 0.2, -0.15], [-0.3, 0.2, -0.15],
                     [-0.3, -0.2, 0.15], [0.3, -0.2, 0.15], [0.3, 0.2, 0.15], [-0.3, 0.2, 0.15]]))
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6], [0, 4, 5], [0, 5, 1], [1, 5, 6], [1, 6, 2],
                      [2, 6, 7], [2, 7, 3], [3, 7, 4], [3, 4, 0]])
    cam_pos = np.array([15.0, 8.0, 5.0])
    look = -cam_pos / fm.norm(cam_pos)
    right = fm.cross(look, np.array([0.0, 0.0, 1.0]))
    right /= fm.norm(right)
    cam_rot = np.stack([right, fm.cross(right, look), -look], axis=1)
    shared = placement.anomaly_scene(obj, faces)
    for seed in (1, 2):
        got = placement.place(station, obj, faces, cam_pos, cam_rot, np.random.default_rng(seed), 160, 90,
                              check_width=None, anomaly=shared)
        want = placement.place(station, obj, faces, cam_pos, cam_rot, np.random.default_rng(seed), 160, 90,
                               check_width=None)
        assert [(p.depth_index, None if p.position is None else _bits(p.position), p.area_fraction) for p in got] == \
            [(p.depth_index, None if p.position is None else _bits(p.position), p.area_fraction) for p in want]
    assert shared.memo["extent"][0] is obj
