"""allo_usd.core.fixedmath: accurate, and the same bits as plain scalar IEEE arithmetic.

What makes authored files the same on every x86-64 machine is that every value reaching a file is
computed from correctly rounded operations in a fixed order. Three checks guard it here:
- accuracy: each function is within 1 ulp (a few for tan, log2, power) of the C library's on random
  inputs, and exact on the special values that matter (signed zeros, infinities, powers of two);
- independence from numpy's SIMD loops: the vectorised functions give, bit for bit, what a plain
  Python transcription of fdlibm gives on Python floats (CPython does each float operation on its
  own, so no SIMD width, FMA contraction, BLAS kernel or libm variant can enter), and the sums of
  products equal the same sums written out in Python;
- one answer whatever the route: a scalar gets the bits of the vectorised path, tan's scalar path
  is sine over cosine, and matmul (by columns, on Python floats for small matrices) and
  matmul_lists give the broadcast sum in index order (reference_matmul).
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


def test_norms_are_the_written_out_python_sums_and_products_agree_with_numpy():
    """Lengths are the sums of squares written out in Python floats; products, cross products and
    determinants agree with numpy's (test_matmul_is_the_broadcast_sum_in_index_order checks the
    products' bits)."""
    a, b = RNG.normal(size=(50, 3, 3)), RNG.normal(size=(50, 3, 3))
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


# --- the scalar path and the small-matrix products: the same bits as the vectorised forms -----------

SCALAR_RNG = np.random.default_rng(26)
SCALAR_N = 6000


def _bits(a) -> list[int]:
    return np.asarray(a, dtype=np.float64).reshape(-1).view(np.int64).tolist()


def _edges(*values) -> np.ndarray:
    return np.array(values, dtype=np.float64)


ANGLES = np.concatenate([SCALAR_RNG.uniform(-7, 7, SCALAR_N), SCALAR_RNG.uniform(-8e5, 8e5, SCALAR_N),
                         SCALAR_RNG.normal(0, 1e-8, SCALAR_N),
                         np.arange(-400, 401) * (math.pi / 4),   # where the reduction's later stages run
                         _edges(0.0, -0.0, 2.0 ** -27, -(2.0 ** -27), 2.0 ** -28, 5e-324, fm.REDUCTION_LIMIT * 0.999)])
UNIT = np.concatenate([SCALAR_RNG.uniform(-1, 1, SCALAR_N), 1 - SCALAR_RNG.uniform(0, 1e-9, SCALAR_N),
                       -1 + SCALAR_RNG.uniform(0, 1e-9, SCALAR_N),
                       _edges(0.0, -0.0, 0.5, -0.5, 0.975, -0.975, 1.0, -1.0, 2.0 ** -27, 2.0 ** -58, 1e-300)])
POSITIVE = np.concatenate([np.exp(SCALAR_RNG.uniform(-700, 700, SCALAR_N)), SCALAR_RNG.uniform(0.6, 1.5, SCALAR_N),
                           _edges(1.0, 2.0, 0.5, 5e-324, 1e308, math.sqrt(0.5), 1 - 2.0 ** -53)])
REAL = np.concatenate([SCALAR_RNG.uniform(-3, 3, SCALAR_N), SCALAR_RNG.standard_cauchy(SCALAR_N) * 1e3,
                       _edges(0.0, -0.0, 0.4375, 0.6875, 1.1875, 2.4375, -2.4375, 1e300, -5e-324)])
ONE_ARG = {"sin": ANGLES, "cos": ANGLES,
           "tan": np.concatenate([ANGLES[:2 * SCALAR_N], np.arange(-40, 41) * (math.pi / 2)]),
           "arcsin": UNIT, "arccos": UNIT, "arctan": REAL, "log": POSITIVE, "log2": POSITIVE}


@pytest.mark.parametrize("name", sorted(ONE_ARG))
def test_a_scalar_gets_the_bits_of_the_vectorised_path(name):
    f, x = getattr(fm, name), ONE_ARG[name]
    vectorised = f(x)
    assert _bits([f(float(v)) for v in x]) == _bits(vectorised)   # Python floats
    assert _bits([f(v) for v in x]) == _bits(vectorised)          # numpy float64 scalars
    assert all(type(f(float(v))) is float for v in x[:50])


@pytest.mark.parametrize("name", ["arctan2", "hypot"])
@pytest.mark.slow
def test_two_argument_scalars_get_the_bits_of_the_vectorised_path(name):
    f = getattr(fm, name)
    n = SCALAR_N
    y = np.concatenate([SCALAR_RNG.normal(size=n), SCALAR_RNG.normal(size=n) * 1e-300,
                        SCALAR_RNG.normal(size=n) * 1e300,
                        _edges(0.0, -0.0, 1.0, -1.0, 0.0, -0.0, 1e308, -1e308, 3.0)])
    x = np.concatenate([SCALAR_RNG.normal(size=n), SCALAR_RNG.normal(size=n), SCALAR_RNG.normal(size=n) * 1e-300,
                        _edges(1.0, 1.0, -1.0, -1.0, -1.0, -2.0, 1e-308, 1e-308, 4.0)])
    assert _bits([f(float(a), float(b)) for a, b in zip(y, x)]) == _bits(f(y, x))


def test_special_scalars_still_take_the_vectorised_path():
    """inf, nan, a zero divisor and out-of-range arguments are decided as the vectorised path decides them."""
    for name in ("sin", "cos", "tan", "arctan", "arcsin", "arccos", "log", "log2"):
        f = getattr(fm, name)
        for v in (math.inf, -math.inf, math.nan, 1.5, -1.5, 0.0, -0.0, -2.0):
            got, want = f(v), f(np.array([v]))[0]
            assert _bits(got) == _bits(want) or (math.isnan(got) and math.isnan(want)), (name, v)
    for a, b in [(1.0, 0.0), (-1.0, -0.0), (0.0, 0.0), (1e308, 1e-308), (math.inf, 1.0), (1.0, math.nan)]:
        got, want = fm.arctan2(a, b), fm.arctan2(np.array([a]), np.array([b]))[0]
        assert _bits(got) == _bits(want) or (math.isnan(got) and math.isnan(want)), (a, b)
    with pytest.raises(AlloError, match="reduce the angle"):
        fm.cos(1e7)
    with pytest.raises(AlloError, match="reduce the angle"):
        fm.tan(-1e7)


def reference_tan(x: float) -> float:
    """tan as the vectorised sine over the vectorised cosine (one reduction each): the form the
    scalar tan's one-reduction path must equal bit for bit."""
    return fm._sincos(np.array([x]), False)[0] / fm._sincos(np.array([x]), True)[0]


@pytest.mark.slow
def test_tan_scalar_is_sin_over_cos():
    rng = np.random.default_rng(1)
    xs = np.concatenate([rng.uniform(-4, 4, 20000), rng.uniform(-1e5, 1e5, 5000), rng.uniform(-1e-8, 1e-8, 500),
                         [0.0, -0.0, 1e-300, fm.PI / 2, -fm.PI / 2, fm.PI, 2.0 ** -27, -(2.0 ** -27)]])
    for x in xs.tolist():
        want = reference_tan(x)
        got = fm.tan(x)
        assert _bits(np.float64(want)) == _bits(np.float64(got)), x
        assert fm._s_sin_cos(x) == (fm._s_sincos(x, False), fm._s_sincos(x, True))


def reference_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(.., n, k) @ (.., k, m) as the broadcast sum in index order, a[.., :, 0] b[.., 0, :] +
    a[.., :, 1] b[.., 1, :] + ...: the plain numpy form fixedmath.matmul (by columns from
    _ROWS_BY_COLUMN rows, on Python floats below), _matmul_small and matmul_lists must equal bit for bit."""
    out = a[..., :, 0, None] * b[..., 0, None, :]
    for i in range(1, a.shape[-1]):
        out = out + a[..., :, i, None] * b[..., i, None, :]
    return out


_SPECIALS = np.array([np.inf, -np.inf, np.nan, 1e308, -1e308, 5e-324, -0.0, 0.0])


def _matmul_inputs(case: str, arg):
    """(a, b) pairs for one case of the matmul test."""
    if case == "by column":      # around the row count where the products go column by column
        rows, inner, cols = arg
        a, b = SCALAR_RNG.normal(size=(rows, inner)) * 1e3, SCALAR_RNG.normal(size=(inner, cols))
        a[0, 0], a[1, 0], b[0, 0] = -0.0, 1e-320, -0.0
        yield a, b
    elif case == "small":        # few rows and columns, empty ones, every scale, a special value now and then
        rng = np.random.default_rng(5)
        shapes = [((3, 3), (3, 3)), ((1, 3), (3, 3)), ((2, 4), (4, 1)), ((4, 2), (2, 4)), ((0, 3), (3, 3)),
                  ((3, 3), (3, 0)), ((1, 1), (1, 1))]
        for _ in range(300):
            for sa, sb in shapes:
                a = rng.normal(size=sa) * 10.0 ** rng.uniform(-5, 5)
                b = rng.normal(size=sb) * 10.0 ** rng.uniform(-5, 5)
                if a.size and rng.random() < 0.2:
                    a.flat[rng.integers(a.size)] = rng.choice(_SPECIALS)
                yield a, b
    elif case == "lists":        # random shapes up to 4x4, special values
        rng = np.random.default_rng(9)
        special = [np.inf, -np.inf, np.nan, -0.0, 0.0, 1e308, 5e-324]
        for _ in range(500):
            n, k, m = (int(x) for x in rng.integers(1, 5, 3))
            a, b = rng.normal(size=(n, k)) * 10.0 ** rng.integers(-5, 5), rng.normal(size=(k, m))
            if rng.random() < 0.3:
                a.flat[rng.integers(a.size)] = rng.choice(special)
            yield a, b
    else:                        # a batch of 3x3 products
        rng = np.random.default_rng(20300101)
        yield rng.normal(size=(50, 3, 3)), rng.normal(size=(50, 3, 3))


_MATMUL_CASES = ([("by column", (rows, inner, cols)) for rows in (fm._ROWS_BY_COLUMN - 1, fm._ROWS_BY_COLUMN, 5000)
                  for inner, cols in ((3, 3), (3, 1), (1, 4), (4, 2))]
                 + [("small", None), ("lists", None), ("batch", None)])


@pytest.mark.parametrize("case, arg", _MATMUL_CASES)
def test_matmul_is_the_broadcast_sum_in_index_order(case, arg):
    """fixedmath.matmul, by columns or on Python floats, and matmul_lists give the broadcast sum's
    bits, signed zeros, subnormals, infinities and NaN included; a batch of 3x3 products is the sum
    written out one Python float operation at a time."""
    for a, b in _matmul_inputs(case, arg):
        with np.errstate(all="ignore"):
            want = reference_matmul(a, b)
            got = fm.matmul(a, b)
        assert got.shape == want.shape and got.dtype == np.float64 and got.flags.c_contiguous
        assert _bits(got) == _bits(want), (a, b)
        if a.ndim == 2 and a.size and b.size:
            lists = np.array(fm.matmul_lists(a.tolist(), b.tolist()), dtype=np.float64)
            assert _bits(lists) == _bits(want), (a, b)
        if a.ndim == 3:
            for k in range(a.shape[0]):
                for i in range(3):
                    for j in range(3):
                        s = float(a[k, i, 0]) * float(b[k, 0, j])
                        s = s + float(a[k, i, 1]) * float(b[k, 1, j])
                        s = s + float(a[k, i, 2]) * float(b[k, 2, j])
                        assert got[k, i, j] == s


def test_norm_of_a_small_vector_is_the_numpy_sum():
    for v in [SCALAR_RNG.normal(size=n) * s for n in (1, 3, 4, 16) for s in (1.0, 1e-200, 1e200)] + \
             [np.zeros(3), _edges(-0.0), _edges(np.inf, 1.0), SCALAR_RNG.normal(size=(3, 3))]:
        flat = v.reshape(-1)
        with np.errstate(over="ignore"):
            s = flat[0] * flat[0]
            for k in range(1, flat.size):
                s = s + flat[k] * flat[k]
        assert _bits(fm.norm(v)) == _bits(np.sqrt(s)) and type(fm.norm(v)) is float
    assert math.isnan(fm.norm(_edges(np.nan, 1.0)))
    assert fm.norm(np.ones(3), keepdims=True).shape == (1,)


def test_norm_quiet_state_restores_numpy_error_state():
    before = np.geterr()
    with np.errstate(over="raise", invalid="warn", divide="raise"):
        inside = np.geterr()
        big = np.array([[1e200, 1e200, 0.0], [np.inf, 1.0, 1.0]])
        assert np.isinf(fm.norm(big, axis=-1)).all()     # no FloatingPointError from the guarded sum
        assert np.geterr() == inside
    assert np.geterr() == before


# --- exp2 (the film exposure from its EV) ----------------------------------------------------------

def _exp2_ulps(xs) -> np.ndarray:
    """|fm.exp2(x) - 2**x| in ulps of 2**x, 2**x from Python's decimal at 60 digits (its exp and ln are
    correctly rounded: no libm enters the reference)."""
    import decimal
    from fractions import Fraction

    got = fm.exp2(np.asarray(xs, dtype=np.float64))
    out = []
    with decimal.localcontext() as ctx:
        ctx.prec = 60
        ln2 = decimal.Decimal(2).ln()
        for x, g in zip(xs, got):
            exact = Fraction((decimal.Decimal(float(x)) * ln2).exp())
            out.append(float(abs(Fraction(float(g)) - exact) / Fraction(math.ulp(float(exact)))))
    return np.array(out)


def test_exp2_of_an_integer_is_exact():
    ks = np.arange(-1080, 1030)
    got = fm.exp2(ks.astype(np.float64))
    want = [math.ldexp(1.0, int(k)) if k < 1024 else math.inf for k in ks]
    assert _bits(got) == _bits(np.array(want))
    assert fm.exp2(0.0) == 1.0 and fm.exp2(-0.0) == 1.0 and type(fm.exp2(3.0)) is float


def test_exp2_within_an_ulp_of_the_true_value():
    """Random exponents over the whole range, the EV range a plan uses, near integers, near the
    overflow and subnormal ends: within 1 ulp of 2**x to 60 digits (0.83 ulp measured)."""
    rng = np.random.default_rng(20300102)
    xs = np.concatenate([rng.uniform(-1074, 1024, 3000), rng.uniform(-20, 20, 3000),
                         np.arange(-40, 40) + rng.uniform(-1e-9, 1e-9, 80), np.arange(-40, 40) + 0.5,
                         rng.uniform(1023, 1024, 200), rng.uniform(-1074, -1022, 200), rng.uniform(-1e-12, 1e-12, 50)])
    err = _exp2_ulps(xs)
    assert err.max() < 1.0, xs[err.argmax()]


def test_exp2_special_values_are_c99s():
    got = fm.exp2(np.array([np.nan, np.inf, -np.inf, 1024.0, 1e300, -1075.0, -1e300]))
    assert np.isnan(got[0]) and list(got[1:]) == [np.inf, 0.0, np.inf, np.inf, 0.0, 0.0]
    assert math.isnan(fm.exp2(math.nan)) and fm.exp2(math.inf) == math.inf and fm.exp2(-math.inf) == 0.0


def test_exp2_scalar_is_the_vectorised_value():
    xs = np.random.default_rng(20300103).uniform(-30, 30, 2000)
    assert _bits(np.array([fm.exp2(float(x)) for x in xs])) == _bits(fm.exp2(xs))


@pytest.mark.process
def test_exp2_is_the_same_on_glibcs_fma_and_plain_paths():
    """The film exposure's 2**EV: Python's `2.0 ** x` calls glibc's pow, whose FMA and non-FMA variants
    (picked by CPU through ifuncs; GLIBC_TUNABLES turns FMA and AVX2 off) round some exponents
    differently; fixedmath.exp2 uses only correctly rounded operations, so both give its same bits."""
    import hashlib
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = ("import hashlib, numpy as np\nfrom allo_usd.core import fixedmath as fm\n"
              "xs = np.random.default_rng(7).uniform(-20, 20, 200_000)\n"
              "print(hashlib.sha256(fm.exp2(xs).tobytes()).hexdigest(),"
              " hashlib.sha256(np.array([2.0 ** float(x) for x in xs]).tobytes()).hexdigest())\n")
    runs = []
    for tunables in (None, "glibc.cpu.hwcaps=-AVX2,-FMA,-FMA4,-AVX"):
        env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
        if tunables:
            env["GLIBC_TUNABLES"] = tunables
        out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
        runs.append(out.stdout.split())
    assert runs[0][0] == runs[1][0]
    if " fma " in Path("/proc/cpuinfo").read_text():   # the check means something: glibc's pow did change
        assert runs[0][1] != runs[1][1]
    assert runs[0][0] == hashlib.sha256(fm.exp2(np.random.default_rng(7).uniform(-20, 20, 200_000)).tobytes()).hexdigest()


def test_inv4_inverts_affine_and_general_matrices_without_lapack():
    """inv4: an affine matrix's inverse keeps the exact last row 0 0 0 1, a rigid one's rotation is the
    transpose to rounding; any invertible 4x4 agrees with LAPACK's inverse to rounding; a singular one
    gives non-finite entries instead of an exception."""
    rng = np.random.default_rng(20300105)
    for _ in range(300):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        rigid = np.eye(4)
        rigid[:3, :3], rigid[:3, 3] = q, rng.uniform(-500, 500, 3)
        inv = fm.inv4(rigid)
        assert inv[3].tolist() == [0.0, 0.0, 0.0, 1.0]
        assert np.abs(inv[:3, :3] - q.T).max() < 1e-14
        assert np.abs(inv[:3, 3] + q.T @ rigid[:3, 3]).max() < 1e-11
        general = rng.normal(size=(4, 4))
        assert np.allclose(fm.inv4(general), np.linalg.inv(general), rtol=1e-9, atol=1e-9)
    assert not np.isfinite(fm.inv4(np.zeros((4, 4)))).all()
    with pytest.raises(ValueError, match="4x4"):
        fm.inv4(np.eye(3))
