"""The shortcuts of issue 26 (round 2) give exactly the bits of the code they stand in for: a RayFan
cast with first_hit_fan is first_hit from repeated origins (placement's and the rig's clearance
probes), fixedmath.tan's one-reduction scalar path is sin / cos, _sphere_box on Python floats is
its fm.matmul form, the cached intrinsics are camera_intrinsics, and part_boxes without np.unique
is its former form."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.geometry import box_corners, camera_intrinsics, quat_to_matrix
from allo_usd.scene import placement, rig
from allo_usd.scene.raycast import RayFan, RayScene, intrinsic_rows


def _bits(a) -> bytes:
    return np.ascontiguousarray(a).tobytes()


def _blob(n_tris: int = 400, seed: int = 0) -> RayScene:
    """A random triangle soup with some degenerate triangles."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n_tris * 3, 3)) * rng.uniform(0.5, 3.0)
    pts[:30] = pts[0]
    return RayScene([(pts, np.arange(len(pts)).reshape(-1, 3), 2)])


@pytest.mark.parametrize("seed", range(6))
def test_fan_is_first_hit_from_repeated_origins(seed):
    rng = np.random.default_rng(seed)
    scene = _blob(seed=seed)
    dirs = rng.normal(size=(int(rng.integers(1, 300)), 3))
    if seed % 2:
        dirs[0] = 0.0                                  # a direction without a length
    fan = RayFan.of_rows(dirs)
    for _ in range(5):
        p = rng.normal(size=3) * rng.uniform(0.1, 4.0)
        want = scene.first_hit(np.repeat(p[None], len(dirs), 0), dirs)
        got = scene.first_hit_fan(p, fan)
        assert all(_bits(w) == _bits(g) for w, g in zip(want, got))
        got_cols = scene.first_hit_fan(p, RayFan(*(np.ascontiguousarray(dirs[:, j]) for j in range(3))))
        assert all(_bits(w) == _bits(g) for w, g in zip(want, got_cols))


def test_module_fans_are_their_directions():
    scene = _blob(seed=9)
    p = np.array([0.3, -0.2, 0.1])
    for dirs, fan in ((placement._SPHERE_DIRS, placement._SPHERE_FAN), (rig._CLEARANCE_DIRS, rig._CLEARANCE_FAN)):
        want = scene.first_hit(np.repeat(p[None], len(dirs), 0), dirs)
        assert all(_bits(w) == _bits(g) for w, g in zip(want, scene.first_hit_fan(p, fan)))


def test_tan_scalar_is_sin_over_cos():
    rng = np.random.default_rng(1)
    xs = np.concatenate([rng.uniform(-4, 4, 20000), rng.uniform(-1e5, 1e5, 5000), rng.uniform(-1e-8, 1e-8, 500),
                         [0.0, -0.0, 1e-300, fm.PI / 2, -fm.PI / 2, fm.PI, 2.0 ** -27, -(2.0 ** -27)]])
    for x in xs.tolist():
        want = fm._sincos(np.array([x]), False)[0] / fm._sincos(np.array([x]), True)[0]
        got = fm.tan(x)
        assert _bits(np.float64(want)) == _bits(np.float64(got)), x
        assert fm._s_sin_cos(x) == (fm._s_sincos(x, False), fm._s_sincos(x, True))


def _sphere_box_reference(cam_pos, cam_rot, width, height, centre, radius, lens):
    """_sphere_box as it was: numpy intrinsics and fm.matmul."""
    k = camera_intrinsics(width, height, lens)
    c = fm.matmul(np.asarray(centre, dtype=np.float64) - np.asarray(cam_pos, dtype=np.float64), np.asarray(cam_rot))
    depth = -c[2]
    if depth <= radius * 1.01:
        return None
    bounds = []
    for lateral in (c[0], c[1]):
        h = fm.hypot(lateral, depth)
        theta, beta = fm.arctan2(lateral, depth), fm.arcsin(min(1.0, radius / h))
        bounds.append((fm.tan(theta - beta), fm.tan(theta + beta)))
    (sx0, sx1), (sy0, sy1) = bounds
    return placement._bounds_to_pixels(width, height, sx0 * k[0, 0] + k[0, 2], sx1 * k[0, 0] + k[0, 2],
                                       k[1, 2] - sy1 * k[1, 1], k[1, 2] - sy0 * k[1, 1])


@pytest.mark.parametrize("lens", [DEFAULT_CAMERA, CameraModel(principal_point_offset_px=(13.25, -7.5))])
def test_sphere_box_is_its_matmul_form(lens):
    rng = np.random.default_rng(3)
    for _ in range(2000):
        cam = rng.normal(size=3) * 10
        rot = quat_to_matrix(rng.normal(size=4))
        centre = cam + rng.normal(size=3) * rng.uniform(0.5, 40)
        radius = float(rng.uniform(0.01, 5.0))
        w = int(rng.choice([480, 1920]))
        h = w * 9 // 16
        assert placement._sphere_box(cam, rot, w, h, centre, radius, lens) == \
            _sphere_box_reference(cam, rot, w, h, centre, radius, lens)


def test_intrinsic_rows_are_camera_intrinsics():
    for lens in (DEFAULT_CAMERA, CameraModel(principal_point_offset_px=(3.5, 1.25)).scaled(0.25)):
        for w, h in ((480, 270), (1920, 1080), (641, 479)):
            assert _bits(np.array(intrinsic_rows(w, h, lens))) == _bits(camera_intrinsics(w, h, lens))


def test_part_boxes_without_unique():
    scene = _blob(n_tris=700, seed=4)
    cent = scene.vertices[scene.faces].mean(axis=1)
    groups = [np.arange(len(scene.faces))]
    for _ in range(5):
        split = []
        for g in groups:
            c = cent[g]
            order = np.argsort(c[:, int(np.argmax(np.ptp(c, axis=0)))], kind="stable")
            split += [g[order[:len(g) // 2]], g[order[len(g) // 2:]]]
        groups = split
    want = np.array([box_corners(scene.vertices[np.unique(scene.faces[g])]) for g in groups]).reshape(-1, 8, 3)
    assert _bits(scene.part_boxes(5)) == _bits(want)
