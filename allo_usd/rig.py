"""Camera rig: 50 base poses around the station and the paper's seeded perturbation.

Base poses sit at exterior fixture points (plausible arm-camera positions) and look at other
structure 5-40 m away. Poses 1-40 are for training and 41-50 for testing; the test poses use
fixtures no training pose uses, so the two sets share no viewpoint.
"""

from __future__ import annotations

import numpy as np

from .author.base import CameraPose
from .errors import PlacementError
from .geometry import check_finite, look_at
from .raycast import Scene

N_TRAIN, N_TEST = 40, 10
POSITION_SIGMA_M = 1.0
ANGLE_SIGMA_RAD = 0.2
PERTURBATION = "euler-zyx-local"  # R = R_base @ Rz(yaw) @ Ry(pitch) @ Rx(roll), angles ~ N(0, 0.2)
CLEARANCE_M = 0.3
RIG_SEED = 50


def base_poses(fixtures: np.ndarray, structure_points: np.ndarray) -> list[CameraPose]:
    """50 deterministic poses: fixtures split into train and test groups, each pose looking at a
    structure point 5-40 m away (preferring 8-25 m)."""
    fixtures = check_finite("fixture points", fixtures)
    if len(fixtures) < 10:
        raise PlacementError(f"need at least 10 fixture points for 50 poses, got {len(fixtures)}")
    rng = np.random.default_rng(RIG_SEED)
    order = rng.permutation(len(fixtures))
    n_test_fix = max(2, len(fixtures) // 5)
    test_fix, train_fix = order[:n_test_fix], order[n_test_fix:]
    poses = []
    for i in range(N_TRAIN + N_TEST):
        split = "train" if i < N_TRAIN else "test"
        group = train_fix if split == "train" else test_fix
        j = i if split == "train" else i - N_TRAIN
        p = fixtures[group[j % len(group)]]
        d = np.linalg.norm(structure_points - p, axis=1)
        ok = np.flatnonzero((d >= 8) & (d <= 25))
        if len(ok) == 0:
            ok = np.flatnonzero((d >= 5) & (d <= 40))
        if len(ok) == 0:
            ok = np.array([int(np.argmin(np.abs(d - 15)))])
        target = structure_points[ok[rng.integers(len(ok))]]
        poses.append(CameraPose(i + 1, split, p.copy(), look_at(p, target)))
    return poses


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def perturbation_matrix(angles) -> np.ndarray:
    yaw, pitch, roll = angles
    return _rz(yaw) @ _ry(pitch) @ _rx(roll)


def too_close(scene: Scene, p: np.ndarray, clearance: float = CLEARANCE_M) -> bool:
    """True if p is within `clearance` of the station or enclosed by it (parity vote)."""
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                     [1, 1, 1], [-1, -1, 1], [1, -1, -1], [-1, 1, -1]], dtype=np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    owner, dist = scene.first_hit(np.repeat(p[None], len(dirs), 0), dirs)
    return bool((dist < clearance).any() or scene.inside(p))


def perturb(pose: CameraPose, rng: np.random.Generator, station: Scene | None = None,
            max_attempts: int = 100):
    """Paper perturbation (N(0, 1 m) per axis, N(0, 0.2 rad) per angle), resampled while the camera
    would sit inside or against the station. Returns (position, rotation, dpos, dang, attempts)."""
    for attempt in range(1, max_attempts + 1):
        dpos = rng.normal(0.0, POSITION_SIGMA_M, 3)
        dang = rng.normal(0.0, ANGLE_SIGMA_RAD, 3)
        pos = pose.position + dpos
        if station is None or not too_close(station, pos):
            return pos, pose.rotation @ perturbation_matrix(dang), dpos, dang, attempt
    raise PlacementError(f"pose {pose.index}: no perturbed camera outside the station in {max_attempts} "
                         "attempts; move the base pose further from the structure")


def fixtures_from_mesh(points: np.ndarray, triangles: np.ndarray, count: int = 40,
                       standoff: tuple[float, float] = (1.0, 2.5), seed: int = RIG_SEED) -> np.ndarray:
    """Camera fixture points for any station mesh (e.g. an imported model): area-weighted surface
    samples pushed out along their face normal, kept only if clear of all structure."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    area = np.linalg.norm(n, axis=1)
    keep = area > 0
    rng = np.random.default_rng(seed)
    scene = Scene([(p, t, 1)])
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    out = []
    for _ in range(count * 20):
        i = rng.choice(np.flatnonzero(keep), p=area[keep] / area[keep].sum())
        a, b = rng.random(2)
        if a + b > 1:
            a, b = 1 - a, 1 - b
        q = p[t[i, 0]] + a * (p[t[i, 1]] - p[t[i, 0]]) + b * (p[t[i, 2]] - p[t[i, 0]])
        normal = n[i] / area[i]
        if np.dot(normal, q - centre) < 0:  # meshes of unknown winding: point away from the centre
            normal = -normal
        f = q + normal * rng.uniform(*standoff)
        if not too_close(scene, f, clearance=0.5):
            out.append(f)
        if len(out) == count:
            break
    if len(out) < 10:
        raise PlacementError(f"found only {len(out)} clear camera fixtures on the station mesh; "
                             "is it closed and in metres?")
    return np.array(out)
