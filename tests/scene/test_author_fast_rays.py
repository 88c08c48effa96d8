"""The shortcuts of issue 26 in ray casting and placement give exactly the bits of the code they
stand in for: first_hit_fan of a per-call RayFan is first_hit on broadcast origins and stacked directions, the
component-wise pixel rays are pixel_rays, _unitize's all-nonzero path is its masked path,
visible_fraction's per-component posed count is the (n, 3) count, fixedmath.norm's cheap error
state restores numpy's, and geometry's identity check is np.allclose's decision."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core import geometry
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.geometry import quat_to_matrix
from allo_usd.scene import placement, raycast
from allo_usd.scene.raycast import RayFan, RayScene, pixel_ray_columns, pixel_rays

RNG = np.random.default_rng(2626)


def _bits(a) -> bytes:
    return np.ascontiguousarray(a).tobytes()


def _blob(n_tris: int = 400, seed: int = 0, centre=(0.0, 0.0, 0.0)) -> RayScene:
    """A random triangle soup around `centre`, with some degenerate triangles."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n_tris * 3, 3)) * rng.uniform(0.2, 2.0) + np.asarray(centre)
    pts[:30] = pts[0]                               # zero-area triangles (no normal)
    tris = np.arange(len(pts)).reshape(-1, 3)
    return RayScene([(pts, tris, 2)])


@pytest.mark.parametrize("seed", range(6))
def test_first_hit_fan_of_component_arrays_is_first_hit(seed):
    rng = np.random.default_rng(seed)
    scene = _blob(seed=seed)
    origin = rng.normal(size=3) * 5
    n = int(rng.integers(1, 3000))
    dirs = -origin + rng.normal(size=(n, 3)) * 1.5
    dirs[: n // 20] = 0.0                           # zero directions take the masked path
    owner, dist = scene.first_hit(np.broadcast_to(origin, (n, 3)), dirs)
    owner2, dist2 = scene.first_hit_fan(origin, RayFan(dirs[:, 0].copy(), dirs[:, 1].copy(), dirs[:, 2].copy()))
    assert _bits(owner) == _bits(owner2) and _bits(dist) == _bits(dist2)
    assert (owner > 0).any()


def test_first_hit_fan_no_rays():
    owner, dist = _blob().first_hit_fan(np.zeros(3), RayFan(np.zeros(0), np.zeros(0), np.zeros(0)))
    assert owner.shape == dist.shape == (0,)


def test_unitize_fast_path_is_the_masked_path():
    v = RNG.normal(size=(5000, 3)) * 10.0 ** RNG.uniform(-6, 6, (5000, 1))
    fast, ok = raycast._unitize(v)
    assert ok.all()
    length = fm.norm(v, axis=-1)
    inv = np.where(ok, 1.0 / np.where(ok, length, 1.0), 1.0)
    assert _bits(fast) == _bits(v * inv[:, None])


@pytest.mark.parametrize("lens", [DEFAULT_CAMERA, CameraModel(principal_point_offset_px=(12.5, -7.0))])
def test_pixel_ray_columns_are_pixel_rays(lens):
    rot = quat_to_matrix(RNG.normal(size=4))
    idx = RNG.choice(480 * 270, 3000, replace=False)
    for index in (None, np.sort(idx)):
        o, d = pixel_rays([1.0, 2.0, 3.0], rot, 480, 270, index, lens)
        cols = pixel_ray_columns(rot, 480, 270, index, lens)
        assert all(_bits(d[:, j]) == _bits(cols[j]) for j in range(3))


def _posed_reference(station, anomaly, cam_pos, cam_rot, width, height, idx, lens, pose, sphere, stride):
    """visible_fraction's (n, 3) path before issue 26, for rays=None and a posed object."""
    o, d = pixel_rays(cam_pos, cam_rot, width, height, idx, lens)
    if not len(o):
        return 0.0
    if sphere is not None:
        c, r = sphere
        v = c - o[0]
        t = fm.dot(d, v)
        miss = (fm.dot(v, v) - t * t > r * r) | (t < -r)
        keep = np.flatnonzero(~miss)
        if keep.size == 0:
            return 0.0
        o, d = o[keep], d[keep]
    position, rotation = np.asarray(pose[0], dtype=np.float64), np.asarray(pose[1], dtype=np.float64)
    origin = fm.matmul(np.asarray(cam_pos, dtype=np.float64)[None] - position, rotation)
    a_owner, a_dist = anomaly.first_hit(np.broadcast_to(origin, d.shape), fm.matmul(d, rotation))
    hit = a_owner > 0
    if not hit.any():
        return 0.0
    if station is None:
        return float(hit.sum() * stride * stride / (width * height))
    hidden = station.occluded(o[hit], d[hit], a_dist[hit])
    return float((~hidden).sum() * stride * stride / (width * height))


@pytest.mark.parametrize("seed", range(8))
def test_posed_fraction_is_the_n_by_3_count(seed):
    rng = np.random.default_rng(100 + seed)
    cam_pos = np.array([0.0, 0.0, 0.0])
    cam_rot = quat_to_matrix(rng.normal(size=4))
    position = -cam_rot[:, 2] * rng.uniform(3, 12) + rng.normal(size=3) * 0.5
    # the station partly between the camera and the object (some rays hidden, some not)
    anomaly, station = _blob(200, seed), _blob(60, seed + 50, 0.6 * position + cam_rot[:, 0] * 1.5)
    pose = (position, quat_to_matrix(rng.normal(size=4)))
    width, height, stride = 160, 90, int(rng.integers(1, 3))
    idx = placement._box_indices((0, width - 1, 0, height - 1), width, stride)
    for sphere in (None, (position, 3.0)):
        for st in (None, station):
            want = _posed_reference(st, anomaly, cam_pos, cam_rot, width, height, idx, DEFAULT_CAMERA, pose,
                                    sphere, stride)
            got = placement._posed_fraction(st, anomaly, cam_pos, width, height, pose, stride, sphere,
                                            pixel_ray_columns(cam_rot, width, height, idx, DEFAULT_CAMERA))
            assert got.hex() == want.hex()
            seen.add((st is None, got > 0.0))


seen: set = set()   # (without a station, fraction > 0) of each case above


def test_posed_fraction_cases_were_all_seen():
    """Both counts (silhouette alone, and behind the station) were exercised with something visible."""
    assert {(True, True), (False, True)} <= seen, seen

def test_norm_quiet_state_restores_numpy_error_state():
    before = np.geterr()
    with np.errstate(over="raise", invalid="warn", divide="raise"):
        inside = np.geterr()
        big = np.array([[1e200, 1e200, 0.0], [np.inf, 1.0, 1.0]])
        assert np.isinf(fm.norm(big, axis=-1)).all()     # no FloatingPointError from the guarded sum
        assert np.geterr() == inside
    assert np.geterr() == before


def test_identity_check_is_allcloses_decision():
    rng = np.random.default_rng(7)
    for _ in range(20000):
        m = np.eye(3) + rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-8, -4)
        if rng.random() < 0.02:
            m[rng.integers(3), rng.integers(3)] = rng.choice([np.nan, np.inf, -np.inf])
        assert geometry._near_identity(m) == np.allclose(m, np.eye(3), atol=1e-6)


@pytest.mark.parametrize("value", [(1.0, 2.0, 3.0), (1.0, float("nan")), [[1, 2], [3, float("inf")]], np.zeros((5, 5)),
                                   np.full(20, np.inf), np.full(16, -np.inf), 5.0, float("-inf"), [], 5e-324, 1e308])
def test_check_finite_decides_as_isfinite(value):
    from allo_usd.core.errors import AlloError

    finite = bool(np.isfinite(np.asarray(value, dtype=np.float64)).all())
    if finite:
        assert _bits(geometry.check_finite("v", value)) == _bits(np.asarray(value, dtype=np.float64))
    else:
        with pytest.raises(AlloError):
            geometry.check_finite("v", value)
