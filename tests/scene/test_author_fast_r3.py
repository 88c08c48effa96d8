"""The shortcuts of issue 26 (round 3) give exactly the bits of the code they stand in for:
RayScene.hits_from is first_hit_fan's hits, fixedmath's small-matrix product on Python floats is
the broadcast form, and matrix_to_quat on Python floats is its former array form (checks
included). The part-box cull that replaced the sphere, corner and triangle footprints is tested
with the placement (tests/scene/test_rig_placement.py: it keeps every covered pixel and the count)."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core import geometry
from allo_usd.core.errors import AlloError
from allo_usd.scene.raycast import RayFan, RayScene


def _bits(a) -> bytes:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes()


def _blob_scene(seed: int, owners=(2,)) -> RayScene:
    """Random triangles around the origin (some nearly edge-on to any ray), one part per owner id."""
    rng = np.random.default_rng(seed)
    parts = []
    for oid in owners:
        centres = rng.normal(size=(300, 1, 3))
        pts = (centres + rng.normal(scale=0.3, size=(300, 3, 3))).reshape(-1, 3)
        parts.append((pts, np.arange(len(pts)).reshape(-1, 3), oid))
    return RayScene(parts)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hits_from_is_first_hit_fans_hits(seed):
    rng = np.random.default_rng(seed)
    scene = _blob_scene(seed, owners=(0, 1, 2))                 # owner 0 hits count as none
    for _ in range(20):
        origin = rng.normal(size=3) * 6.0
        dirs = rng.normal(size=(2000, 3)) * rng.uniform(0.1, 3.0)
        fan = RayFan.of_rows(dirs)
        owner, dist = scene.first_hit_fan(origin, fan)
        want = np.flatnonzero(owner > 0)
        rays, got = scene.hits_from(origin, fan)
        assert np.array_equal(rays, want) and _bits(got) == _bits(dist[want])
        rays2, none = scene.hits_from(origin, fan, distances=False)
        assert np.array_equal(rays2, want) and none is None
    rays, dist = scene.hits_from(np.full(3, 100.0), RayFan.of_rows(np.array([[1.0, 0.0, 0.0]])))
    assert rays.size == 0 and dist.size == 0


def _matmul_broadcast(a, b):
    out = a[:, 0, None] * b[0, None, :]
    for i in range(1, a.shape[1]):
        out = out + a[:, i, None] * b[i, None, :]
    return out


def test_small_matmul_is_the_broadcast_form():
    rng = np.random.default_rng(5)
    shapes = [((3, 3), (3, 3)), ((1, 3), (3, 3)), ((2, 4), (4, 1)), ((4, 2), (2, 4)), ((0, 3), (3, 3)),
              ((3, 3), (3, 0)), ((1, 1), (1, 1))]
    specials = np.array([np.inf, -np.inf, np.nan, 1e308, -1e308, 5e-324, -0.0, 0.0])
    with np.errstate(all="ignore"):
        for _ in range(300):
            for sa, sb in shapes:
                a = rng.normal(size=sa) * 10.0 ** rng.uniform(-5, 5)
                b = rng.normal(size=sb) * 10.0 ** rng.uniform(-5, 5)
                if a.size and rng.random() < 0.2:
                    a.flat[rng.integers(a.size)] = rng.choice(specials)
                want = _matmul_broadcast(a, b)
                got = fm.matmul(a, b)
                assert got.shape == want.shape and got.dtype == np.float64
                assert _bits(got) == _bits(want), (a, b)


def _matrix_to_quat_array_form(r):
    """matrix_to_quat as it was, on numpy arrays."""
    r = geometry.check_finite("rotation matrix", r)
    if abs(fm.det3(r) - 1.0) > 1e-6 or not np.allclose(_matmul_broadcast(r, r.T), np.eye(3), atol=1e-6):
        raise AlloError("not a rotation")
    t = r[0, 0] + r[1, 1] + r[2, 2]
    k = int(np.argmax(np.array([t, r[0, 0], r[1, 1], r[2, 2]])))
    if k == 0:
        s = np.sqrt(1.0 + t) * 2
        q = np.array([0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s])
    elif k == 1:
        s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = np.array([(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s])
    elif k == 2:
        s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = np.array([(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s])
    else:
        s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = np.array([(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s])
    q /= fm.norm(q)
    return q if q[0] >= 0 else -q


def test_matrix_to_quat_is_its_array_form():
    rng = np.random.default_rng(9)
    mats = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for _ in range(3000):
        q = rng.normal(size=4)
        if rng.random() < 0.3:          # near 180 degrees about some axis: every branch of Shepperd's method
            q[0] *= 1e-4
        mats.append(geometry.quat_to_matrix(q / np.linalg.norm(q)))
    for m in mats:
        m = m + rng.normal(size=(3, 3)) * 1e-9 * rng.integers(0, 2)
        assert _bits(geometry.matrix_to_quat(m)) == _bits(_matrix_to_quat_array_form(m))
    for bad in (np.diag([1.0, 1.0, -1.0]), np.eye(3) * 1.01, np.array([[1.0, 1e-5, 0], [0, 1, 0], [0, 0, 1]])):
        with pytest.raises(AlloError, match="not orthonormal"):
            geometry.matrix_to_quat(bad)
    with pytest.raises(AlloError, match="3x3"):
        geometry.matrix_to_quat(np.eye(4))
    with pytest.raises(AlloError, match="NaN"):
        geometry.matrix_to_quat(np.full((3, 3), np.nan))
