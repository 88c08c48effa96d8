"""allo_usd.core.fixedmath: accurate, and the same bits as plain scalar IEEE arithmetic.

What makes authored files the same on every x86-64 machine is that every value reaching a file is
computed from correctly rounded operations in a fixed order. Two checks guard it here:
- accuracy: each function is within 1 ulp (a few for tan, log2, power) of the C library's on random
  inputs, and exact on the special values that matter (signed zeros, infinities, powers of two);
- independence from numpy's SIMD loops: the vectorised functions give, bit for bit, what a plain
  Python transcription of fdlibm gives on Python floats (CPython does each float operation on its
  own, so no SIMD width, FMA contraction, BLAS kernel or libm variant can enter), and the sums of
  products equal the same sums written out in Python.
tests/system/test_determinism.py authors real trees under other numpy feature sets; this file checks the
parts in isolation and on many more inputs.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core.errors import AlloError


def _ulps(a, b) -> np.ndarray:
    """Distance in units in the last place between float64 arrays (same sign assumed)."""
    ai = np.asarray(a, dtype=np.float64).view(np.int64)
    bi = np.asarray(b, dtype=np.float64).view(np.int64)
    return np.abs(ai - bi)


RNG = np.random.default_rng(20300101)
N = 20_000
CASES = {
    "sin": (fm.sin, math.sin, np.concatenate([RNG.uniform(-7, 7, N), RNG.uniform(-2e5, 2e5, N), RNG.uniform(-1e-4, 1e-4, N)]), 1),
    "cos": (fm.cos, math.cos, np.concatenate([RNG.uniform(-7, 7, N), RNG.uniform(-2e5, 2e5, N), RNG.uniform(-1e-4, 1e-4, N)]), 1),
    "tan": (fm.tan, math.tan, RNG.uniform(-1.5, 1.5, N), 3),
    "arctan": (fm.arctan, math.atan, np.concatenate([RNG.uniform(-3, 3, N), RNG.standard_cauchy(N) * 1e3]), 1),
    "arcsin": (fm.arcsin, math.asin, np.concatenate([RNG.uniform(-1, 1, N), 1 - RNG.uniform(0, 1e-9, N)]), 1),
    "arccos": (fm.arccos, math.acos, np.concatenate([RNG.uniform(-1, 1, N), -1 + RNG.uniform(0, 1e-9, N)]), 1),
    "exp": (fm.exp, math.exp, np.concatenate([RNG.uniform(-740, 705, N), RNG.uniform(-1, 1, N)]), 1),
    "log": (fm.log, math.log, np.concatenate([np.exp(RNG.uniform(-700, 700, N)), RNG.uniform(0.6, 1.5, N)]), 1),
    "log2": (fm.log2, math.log2, np.concatenate([np.exp(RNG.uniform(-700, 700, N)), RNG.uniform(0.6, 1.5, N)]), 2),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_within_an_ulp_of_the_c_library(name):
    ours, libm, x, bound = CASES[name]
    got = ours(x)
    want = np.array([libm(v) for v in x])
    assert got.dtype == np.float64 and got.shape == x.shape
    assert _ulps(got, want).max() <= bound, name
    assert isinstance(ours(float(x[0])), float)   # a scalar in, a Python float out


def test_arctan2_quadrants_and_special_values():
    y, x = RNG.normal(size=N), RNG.normal(size=N)
    assert _ulps(fm.arctan2(y, x), [math.atan2(a, b) for a, b in zip(y, x)]).max() <= 1
    special = [0.0, -0.0, 1.0, -1.0, math.inf, -math.inf]
    for a in special:
        for b in special:
            got, want = fm.arctan2(a, b), math.atan2(a, b)
            assert got == want and math.copysign(1, got) == math.copysign(1, want), (a, b)
    assert math.isnan(fm.arctan2(math.nan, 1.0))


def test_special_values():
    assert fm.sin(0.0) == 0.0 and math.copysign(1, fm.sin(-0.0)) == -1 and fm.cos(0.0) == 1.0
    assert fm.exp(0.0) == 1.0 and fm.exp(-math.inf) == 0.0 and fm.exp(math.inf) == math.inf and fm.exp(1000.0) == math.inf
    assert fm.log(1.0) == 0.0 and fm.log(0.0) == -math.inf and math.isnan(fm.log(-1.0))
    assert [fm.log2(2.0 ** k) for k in (-1074, -3, 0, 1, 10, 1023)] == [-1074.0, -3.0, 0.0, 1.0, 10.0, 1023.0]
    assert fm.arccos(1.0) == 0.0 and fm.arccos(-1.0) == math.pi and fm.arcsin(1.0) == math.pi / 2
    assert math.isnan(fm.arcsin(1.5)) and math.isnan(fm.sin(math.inf)) and math.isnan(fm.cos(math.nan))
    assert fm.power(0.0, 2.4) == 0.0 and fm.power(1.0, 0.3) == 1.0 and abs(fm.power(2.0, 0.5) - math.sqrt(2)) < 1e-15
    assert fm.hypot(3.0, 4.0) == 5.0 and fm.hypot(1e300, 1e300) == pytest.approx(math.hypot(1e300, 1e300), rel=1e-15)


def test_huge_angles_are_refused_not_rounded():
    with pytest.raises(AlloError, match="reduce the angle"):
        fm.sin(1e7)
    assert fm.sin(8e5) == pytest.approx(math.sin(8e5), abs=1e-15)


# --- the reference: fdlibm in plain Python floats (one IEEE operation at a time, no numpy) ---------

def _exponent(x: float) -> int:
    return (struct.unpack("<Q", struct.pack("<d", x))[0] >> 52) & 0x7FF


def _ref_rem_pio2(x: float) -> tuple[int, float, float]:
    fn = float(round(x * 6.36619772367581382433e-01))
    if fn == 0.0:
        return 0, x, 0.0
    r = x - fn * 1.57079632673412561417e+00
    w = fn * 6.07710050650619224932e-11
    j = _exponent(x)
    if j - _exponent(r - w) > 16:
        t = r
        w = fn * 6.07710050630396597660e-11
        r = t - w
        w = fn * 2.02226624879595063154e-21 - ((t - r) - w)
        if j - _exponent(r - w) > 49:
            t = r
            w = fn * 2.02226624871116645580e-21
            r = t - w
            w = fn * 8.47842766036889956997e-32 - ((t - r) - w)
    y0 = r - w
    return int(fn) & 3, y0, (r - y0) - w


def _ref_ksin(x: float, y: float) -> float:
    z = x * x
    v = z * x
    r = 8.33333333332248946124e-03 + z * (-1.98412698298579493134e-04 + z * (2.75573137070700676789e-06
                                          + z * (-2.50507602534068634195e-08 + z * 1.58969099521155010221e-10)))
    return x - ((z * (0.5 * y - v * r) - y) - v * -1.66666666666666324348e-01)


def _ref_kcos(x: float, y: float) -> float:
    z = x * x
    w = z * z
    r = (z * (4.16666666666666019037e-02 + z * (-1.38888888888741095749e-03 + z * 2.48015872894767294178e-05))
         + w * w * (-2.75573143513906633035e-07 + z * (2.08757232129817482790e-09 + z * -1.13596475577881948265e-11)))
    hz = 0.5 * z
    w = 1.0 - hz
    return w + (((1.0 - w) - hz) + (z * r - x * y))


def _ref_sin(x: float) -> float:
    if abs(x) < 2.0 ** -27:
        return x
    n, a, b = _ref_rem_pio2(x)
    return (_ref_ksin(a, b), _ref_kcos(a, b), -_ref_ksin(a, b), -_ref_kcos(a, b))[n]


def _ref_cos(x: float) -> float:
    if abs(x) < 2.0 ** -27:
        return 1.0
    n, a, b = _ref_rem_pio2(x)
    return (_ref_kcos(a, b), -_ref_ksin(a, b), -_ref_kcos(a, b), _ref_ksin(a, b))[n]


def test_sin_cos_equal_a_scalar_python_transcription_bit_for_bit():
    """The vectorised numpy code gives exactly what one-operation-at-a-time Python floats give."""
    x = np.concatenate([RNG.uniform(-10, 10, 4000), RNG.uniform(-5e5, 5e5, 4000), RNG.normal(0, 0.2, 4000),
                        np.arange(-40, 41) * (math.pi / 4)])   # near multiples of pi/4: the reduction's worst
    assert fm.sin(x).tolist() == [_ref_sin(float(v)) for v in x]
    assert fm.cos(x).tolist() == [_ref_cos(float(v)) for v in x]


def test_sums_of_products_are_the_written_out_python_sums():
    a, b = RNG.normal(size=(50, 3, 3)), RNG.normal(size=(50, 3, 3))
    got = fm.matmul(a, b)
    for k in range(50):
        for i in range(3):
            for j in range(3):
                s = float(a[k, i, 0]) * float(b[k, 0, j])
                s = s + float(a[k, i, 1]) * float(b[k, 1, j])
                s = s + float(a[k, i, 2]) * float(b[k, 2, j])
                assert got[k, i, j] == s
    v = RNG.normal(size=(200, 3))
    lengths = fm.norm(v, axis=1)
    assert lengths.tolist() == [math.sqrt((float(x) * float(x) + float(y) * float(y)) + float(z) * float(z)) for x, y, z in v]
    assert fm.norm(v[0]) == lengths[0]
    np.testing.assert_allclose(fm.matmul(a, b), a @ b, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(fm.apply(a[0], v), v @ a[0].T, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(fm.matmul(a[0], v[0]), a[0] @ v[0], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(fm.matmul(v[0], a[0]), v[0] @ a[0], rtol=1e-13, atol=1e-15)
    assert fm.det3(a[0]) == pytest.approx(np.linalg.det(a[0]), rel=1e-12)
    np.testing.assert_array_equal(fm.cross(v[:10], v[10:20]), np.cross(v[:10], v[10:20]))


@pytest.mark.slow
def test_camera_quaternions_are_the_scalar_reference(tmp_path):
    """A sample of written values: each demo camera's orientation in its pose layer equals the same
    computation done in plain Python floats (the base pose's matrix, Rz(yaw) Ry(pitch) Rx(roll) from
    the recorded offsets with the scalar sine above, Shepperd's quaternion, normalised), bit for bit."""
    from pxr import Sdf

    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.plan.model import demo_plan
    from allo_usd.run.author import author
    from allo_usd.usd.stage_geometry import read_rig

    author(demo_plan(), tmp_path / "tree", limit=7, progress=False, workers=1)
    rig = {p.index: p for p in read_rig(BASE_STAGE)}
    layers = sorted((tmp_path / "tree" / "poses").rglob("*.usda"))
    assert len(layers) >= 4
    for path in layers:
        layer = Sdf.Layer.FindOrOpen(str(path))
        world = layer.GetPrimAtPath("/World")
        yaw, pitch, roll = (float(v) for v in world.attributes["allo:cameraOffsetRotation"].default)
        base = rig[int(world.attributes["allo:pose"].default)].rotation.tolist()
        cz, sz, cy, sy, cx, sx = _ref_cos(yaw), _ref_sin(yaw), _ref_cos(pitch), _ref_sin(pitch), _ref_cos(roll), _ref_sin(roll)
        rz = [[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]]
        ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]]
        rx = [[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]]
        r = _mul(base, _mul(_mul(rz, ry), rx))
        want = _quat(r)
        q = layer.GetPrimAtPath("/World/Camera").attributes["xformOp:orient"].default
        got = [float(q.real), *(float(c) for c in q.imaginary)]
        assert got == want, path.name


def _mul(a, b):
    return [[(a[i][0] * b[0][j] + a[i][1] * b[1][j]) + a[i][2] * b[2][j] for j in range(3)] for i in range(3)]


def _quat(r):
    t = (r[0][0] + r[1][1]) + r[2][2]
    k = max(range(4), key=lambda i: (t, r[0][0], r[1][1], r[2][2])[i])
    if k == 0:
        s = math.sqrt(1.0 + t) * 2
        q = [0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s]
    elif k == 1:
        s = math.sqrt(((1.0 + r[0][0]) - r[1][1]) - r[2][2]) * 2
        q = [(r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s]
    elif k == 2:
        s = math.sqrt(((1.0 + r[1][1]) - r[0][0]) - r[2][2]) * 2
        q = [(r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s]
    else:
        s = math.sqrt(((1.0 + r[2][2]) - r[0][0]) - r[1][1]) * 2
        q = [(r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s]
    n = math.sqrt(((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3])
    q = [c / n for c in q]
    return q if q[0] >= 0 else [-c for c in q]


def test_srgb8_codes_are_the_transfer_rounded_and_decided_by_comparisons():
    """The PNG's 8-bit codes: the IEC 61966-2-1 curve rounded to the nearest level, decided by
    comparing each value with the 255 level thresholds (no CPU-dependent `power` per pixel)."""
    from allo_usd.output.writers import _SRGB8_THRESHOLDS, linear_to_srgb8

    c = np.concatenate([RNG.random(50_000) ** 3, RNG.random(1000) * 1e-3, [0.0, 1.0, 0.0031308]])
    s = np.array([12.92 * v if v <= 0.0031308 else 1.055 * math.pow(v, 1 / 2.4) - 0.055 for v in c])
    want = np.rint(s * 255.0)
    got = linear_to_srgb8(c).astype(np.float64)
    near = np.abs(s * 255.0 - np.floor(s * 255.0) - 0.5) < 1e-9     # within rounding of a half level
    assert np.array_equal(got[~near], want[~near]) and np.abs(got - want).max() <= 1
    assert np.all(np.diff(_SRGB8_THRESHOLDS) > 0) and len(_SRGB8_THRESHOLDS) == 255
    assert linear_to_srgb8(np.array([np.nan, -1.0, np.inf, 2.0, _SRGB8_THRESHOLDS[99]])).tolist() == [0, 0, 255, 255, 100]
    assert linear_to_srgb8(np.zeros((2, 3, 3), dtype=np.float32)).shape == (2, 3, 3)
