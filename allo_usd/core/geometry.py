"""Rotations and camera frames in float64: matrices, unit quaternions (w, x, y, z), look-at.

Quaternions are the interchange form (USD `quatd`, Blender QUATERNION mode), never Euler
angles: at pitch +-pi/2 an Euler round trip changes the triple (docs/physics.md section 4).
"""

from __future__ import annotations

import math

import numpy as np

from allo_usd.core.errors import AlloError
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core import fixedmath as fm


def check_finite(name: str, value) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    # a few numbers (a position, a rotation; validate_spec checks ~18 per scene) on Python floats:
    # the same test as np.isfinite(a).all() at a fraction of the cost
    finite = all(map(math.isfinite, a.ravel().tolist())) if a.size <= 16 else np.isfinite(a).all()
    if not finite:
        raise AlloError(f"{name} contains NaN or infinity ({a.tolist()}); fix the pose or plan that produced it")
    return a


def _unit(name: str, value) -> np.ndarray:
    """`value` scaled to unit length; a zero vector has no direction and is an error."""
    a = check_finite(name, value)
    big = np.abs(a).max()
    if big == 0:
        raise AlloError(f"{name} has zero length; give a non-zero vector")
    a = a / big  # pre-scaled, so tiny and huge vectors neither underflow nor overflow
    return a / fm.norm(a)


def unit(v) -> np.ndarray:
    """One vector as float64 divided by its length, unchecked (asset building, where axes are
    known to be non-zero; `_unit` checks user input)."""
    v = np.asarray(v, dtype=np.float64)
    return v / fm.norm(v)


def unit_rows(v) -> np.ndarray:
    """`v` scaled to unit length along its last axis, unchecked (for vectors known to be non-zero;
    `_unit` checks a single vector)."""
    return v / fm.norm(v, axis=-1, keepdims=True)


def rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products of matching rows of two (n, 3) arrays."""
    return fm.dot(a, b)


def angle_between(a, b) -> np.ndarray:
    """Angle between vectors (..., 3) as atan2(|a x b|, a . b): accurate at 0 and pi too."""
    a = unit_rows(np.asarray(a, dtype=np.float64))
    b = unit_rows(np.asarray(b, dtype=np.float64))
    return fm.arctan2(fm.norm(np.cross(a, b), axis=-1), fm.dot(a, b))


def rot_x(a: float) -> np.ndarray:
    """Rotation by `a` radians about +X (right-handed)."""
    c, s = fm.cos(a), fm.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def rot_y(a: float) -> np.ndarray:
    c, s = fm.cos(a), fm.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def rot_z(a: float) -> np.ndarray:
    c, s = fm.cos(a), fm.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


_DIAGONAL_TOLERANCE = 1e-6 + 1e-5 * 1.0       # np.allclose(m, I, atol=1e-6)'s bound (rtol 1e-5) per entry
_OFF_DIAGONAL_TOLERANCE = 1e-6 + 1e-5 * 0.0


def _near_identity(m: np.ndarray) -> bool:
    """np.allclose(m, np.eye(3), atol=1e-6), entry for entry (|m - I| <= atol + rtol |I|; NaN fails),
    on Python floats, without allclose's generic machinery (~60 us; every authored orientation is
    checked)."""
    rows = m.tolist()
    return all(abs(rows[i][j] - (1.0 if i == j else 0.0)) <= (_DIAGONAL_TOLERANCE if i == j else _OFF_DIAGONAL_TOLERANCE)
               for i in range(3) for j in range(3))


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, from a proper rotation matrix (Shepperd's method).
    Computed on Python floats, the same operations in the same order as the 3x3 array form, so the
    same bits at a fraction of the cost: every pose layer and anomalous scene converts one
    orientation."""
    r = check_finite("rotation matrix", r)
    if r.shape != (3, 3):
        raise AlloError(f"rotation matrix has shape {r.shape}; give a 3x3 matrix")
    if abs(fm.det3(r) - 1.0) > 1e-6 or not _near_identity(fm.matmul(r, r.T)):
        raise AlloError("rotation matrix is not orthonormal with det +1; build it from unit axes")
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r.tolist()
    t = r00 + r11 + r22
    cands = (t, r00, r11, r22)
    k = cands.index(max(cands))          # np.argmax: the first largest

    def root(x: float) -> float:        # np.sqrt: NaN below zero (a matrix at the tolerance's edge)
        return math.sqrt(x) * 2 if x >= 0 else math.nan

    if k == 0:
        s = root(1.0 + t)
        q = [0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s]
    elif k == 1:
        s = root(1.0 + r00 - r11 - r22)
        q = [(r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s]
    elif k == 2:
        s = root(1.0 + r11 - r00 - r22)
        q = [(r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s]
    else:
        s = root(1.0 + r22 - r00 - r11)
        q = [(r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s]
    n = math.sqrt(((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3])   # fm.norm's sum
    q = [x / n for x in q]
    return np.array(q if q[0] >= 0 else [-x for x in q])


def quat_to_matrix(q) -> np.ndarray:
    w, x, y, z = _unit("quaternion", q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def look_at(position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera rotation (columns = camera x, y, z in world) looking down -Z at target, +Y up."""
    p = check_finite("camera position", position)
    fwd = check_finite("look target", target) - p
    n = fm.norm(fwd)
    if n == 0:
        raise AlloError("camera position equals its look target; give a target at a distance")
    fwd /= n
    up = _unit("up vector", up)
    if abs(fm.dot(fwd, up)) > 0.999:  # looking straight up/down: pick another up
        up = np.array([1.0, 0.0, 0.0]) if abs(fwd[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(fwd, up)
    x /= fm.norm(x)
    y = np.cross(x, fwd)
    return np.stack([x, y, -fwd], axis=1)


def rotation_towards(direction) -> np.ndarray:
    """A rotation whose local +Z is unit(direction) (used to aim a DistantLight's -Z away from the Sun)."""
    z = _unit("direction", direction)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= fm.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def camera_intrinsics(width: int, height: int, lens: CameraModel = DEFAULT_CAMERA) -> np.ndarray:
    """3x3 pinhole matrix (pixels, pixel-corner convention: the image spans [0, W] x [0, H]) of `lens`
    (default: the paper's 25 mm / 36 mm-wide camera), sensor fit horizontal, with its principal
    point offset (core.camera_model)."""
    return lens.intrinsics(width, height)


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (Fibonacci lattice), deterministic."""
    i = np.arange(n) + 0.5
    phi = fm.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + np.sqrt(5.0)) * i
    return np.stack([fm.cos(theta) * fm.sin(phi), fm.sin(theta) * fm.sin(phi), fm.cos(phi)], axis=1)


def box_corners(points) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box around `points` (an object in its own frame)."""
    p = np.asarray(points, dtype=np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    return np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                     for i in (0, 1) for j in (0, 1) for k in (0, 1)])
