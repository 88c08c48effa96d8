"""allo_usd.core.fixedmath: accurate, and the same bits as plain scalar IEEE arithmetic.

What makes authored files the same on every x86-64 machine is that every value reaching a file is
computed from correctly rounded operations in a fixed order. Three checks guard it here:
- accuracy: each function is within 1 ulp (a few for tan) of the C library's on random inputs, within
  the module docstring's bound of the true value (mpmath) on random and hard inputs, exact where the
  result is a double (powers of two, integer powers), and C99's on zeros, infinities, NaN and poles;
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


# --- against the true value: mpmath at 160 bits, on random and hard inputs ---------------------------

mpmath = pytest.importorskip("mpmath")
_MP_PREC = 160

# the bound each function must meet, in ulp of the true value (the module docstring's table)
ULP_BOUNDS = {"sin": 1.0, "cos": 1.0, "tan": 2.0, "arcsin": 1.0, "arccos": 1.0, "arctan": 1.0, "arctan2": 1.5,
              "exp": 1.0, "log": 1.0, "log2": 1.0, "power": 1.0, "hypot": 2.0, "radians": 1.0, "degrees": 1.0}


def _true(name: str):
    mp = mpmath.mpf
    return {"sin": lambda x: mpmath.sin(mp(x)), "cos": lambda x: mpmath.cos(mp(x)), "tan": lambda x: mpmath.tan(mp(x)),
            "arcsin": lambda x: mpmath.asin(mp(x)), "arccos": lambda x: mpmath.acos(mp(x)),
            "arctan": lambda x: mpmath.atan(mp(x)), "exp": lambda x: mpmath.exp(mp(x)),
            "log": lambda x: mpmath.log(mp(x)), "log2": lambda x: mpmath.log(mp(x), 2),
            "radians": lambda x: mp(x) * mpmath.pi / 180, "degrees": lambda x: mp(x) * 180 / mpmath.pi,
            "arctan2": lambda y, x: mpmath.atan2(mp(y), mp(x)), "hypot": lambda x, y: mpmath.hypot(mp(x), mp(y)),
            "power": lambda x, y: mpmath.power(mp(x), mp(y))}[name]


def ulp_errors(got, truths) -> np.ndarray:
    """|got - true| in units of the last place of the true value (2**-1074 below the normal range); a
    result of inf counts as exact where the true value rounds to inf."""
    one_ulp_max = mpmath.mpf(2) ** 1024 * (1 - mpmath.mpf(2) ** -54)
    out = []
    for g, t in zip(np.asarray(got, dtype=np.float64).reshape(-1).tolist(), truths):
        if math.isinf(g) and abs(t) >= one_ulp_max and (g > 0) == (t > 0):
            out.append(0.0)
        elif not math.isfinite(g):
            out.append(math.inf)
        else:
            e = mpmath.frexp(t)[1] if t != 0 else -1074
            out.append(float(abs(mpmath.mpf(g) - t) / mpmath.mpf(2) ** max(e - 53, -1074)))
    return np.array(out)


def _around(values, k: int = 4) -> np.ndarray:
    """Each value and its k neighbours on either side."""
    v = np.asarray(values, dtype=np.float64)
    return np.concatenate([v + i * np.spacing(np.abs(v)) for i in range(-k, k + 1)])


def hard_inputs(name: str, rng: np.random.Generator, n: int) -> list:
    """Random inputs over the domain and the hard ones: near multiples of pi/2 for sin, cos and tan, near
    1 for the logarithms and power, the ends of each polynomial's interval, subnormals, huge and tiny
    exponents, the colour curve's 2.4 and 1/2.4 over [0, 1]. Tuples for the two-argument functions."""
    u = rng.uniform
    pio2 = np.arange(-2000, 2001) * (fm.PI / 2)
    if name in ("sin", "cos"):
        return [u(-7, 7, n), u(-8e5, 8e5, n), u(-1e-4, 1e-4, n), _around(pio2[::7])]
    if name == "tan":
        return [u(-1.5, 1.5, n), u(-1e5, 1e5, n), _around(pio2[::7]), _around(np.arange(1, 400) * (fm.PI / 4))]
    if name in ("arcsin", "arccos"):
        edges = _around([0.5, -0.5, 0.975, -0.975, 1e-9, 1.0, -1.0])
        return [u(-1, 1, n), 1 - u(0, 1e-9, n), -1 + u(0, 1e-9, n), edges[np.abs(edges) <= 1.0]]
    if name == "arctan":
        return [u(-3, 3, n), rng.standard_cauchy(n) * 1e3, _around([0.4375, 0.6875, 1.1875, 2.4375, 1e16])]
    if name == "exp":
        return [u(-745, 709.7, n), u(-1, 1, n), u(-745.1, -708, n), _around([709.78, -708.39, 0.5 * math.log(2)])]
    if name in ("log", "log2"):
        return [np.exp(u(-744, 709, n)), u(0.6, 1.5, n), 1 + u(-1e-6, 1e-6, n), u(0, 1, n) * 2.0 ** -1022,
                _around([1.0, math.sqrt(0.5), math.sqrt(2), 2.0, 0.5, 2.0 ** -1022], 8), np.arange(1, 40) * 5e-324]
    if name in ("radians", "degrees"):
        return [u(-400, 400, n), rng.standard_cauchy(n) * 1e6]
    g = rng.normal
    if name == "arctan2":
        return [(g(size=n), g(size=n)), (g(size=n) * 1e-300, g(size=n)), (g(size=n), g(size=n) * 1e-10),
                (g(size=n) * 1e300, g(size=n) * 1e-300)]
    if name == "hypot":
        return [(g(size=n), g(size=n)), (g(size=n) * 1e300, g(size=n) * 1e300), (g(size=n) * 1e-300, g(size=n))]
    c = u(0, 1, n)
    return [(np.exp(u(-20, 20, n)), u(-30, 30, n)),                         # power: general
            (np.exp(u(-700, 700, n)), u(-1.5, 1.5, n)),                     # any magnitude of x
            (c, np.full(n, 2.4)), (c, np.full(n, 1 / 2.4)),                 # the colour curve
            (1 + u(-1e-8, 1e-8, n), u(-1e10, 1e10, n)),                     # near 1, huge y
            (1 + u(-9.5e-7, 9.5e-7, n), rng.choice([-1.0, 1.0], n) * 2.0 ** u(31, 40, n)),   # the |y| > 2**31 series
            (1 + u(-2e-6, 2e-6, n), u(-3e8, 3e8, n)),
            (u(0.5, 2, n), u(-1e-10, 1e-10, n)),                            # tiny y
            (np.exp(u(-3, 3, n)), u(-1070, -700, n) / u(0.9, 1.1, n)),      # results near underflow, subnormal
            (u(0, 1, n) * 2.0 ** -1022, u(0.5, 1.0, n)),                    # subnormal x
            (-np.exp(u(-5, 5, n)), np.rint(u(-60, 60, n))),                 # negative x, integer y
            (u(1.0, 2.0, n), np.full(n, 1023.5))]                           # results near overflow


@pytest.mark.parametrize("name", sorted(ULP_BOUNDS))
def test_within_the_stated_ulps_of_the_true_value(name):
    """Each function's error against the true value (mpmath at 160 bits) stays within the bound the
    module docstring states, on random and hard inputs."""
    f, true, rng = getattr(fm, name), _true(name), np.random.default_rng(sorted(ULP_BOUNDS).index(name))
    with mpmath.workprec(_MP_PREC):
        for case in hard_inputs(name, rng, 800):
            if isinstance(case, tuple):
                a, b = case
                err = ulp_errors(f(a, b), [true(p, q) for p, q in zip(a.tolist(), b.tolist())])
                where = (a[int(np.argmax(err))], b[int(np.argmax(err))])
            else:
                err = ulp_errors(f(case), [true(p) for p in case.tolist()])
                where = case[int(np.argmax(err))]
            assert err.max() <= ULP_BOUNDS[name], (name, err.max(), where)


def test_power_is_exact_where_the_result_is_a_double():
    """Integer powers of integers that fit, every power of two, the square root and the reciprocal."""
    assert [fm.power(2.0, float(k)) for k in range(-1074, 1024)] == [2.0 ** k for k in range(-1074, 1024)]
    k = np.arange(-1074, 1024, dtype=np.float64)
    assert fm.power(np.full(k.shape, 2.0), k).tolist() == [2.0 ** int(v) for v in k]
    assert fm.power(np.full(k.shape, 0.5), -k).tolist() == [2.0 ** int(v) for v in k]
    for base in (3, 5, 7, 10, -3, -10, 12345):
        for e in range(0, 80):
            if abs(base) ** e < 2 ** 53:
                assert fm.power(float(base), float(e)) == float(base ** e), (base, e)
    assert fm.power(2.0, 0.5) == math.sqrt(2.0) and fm.power(10.0, -1.0) == 0.1 and fm.power(-3.0, 3.0) == -27.0


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1.0, a) == math.copysign(1.0, b))


INF, NAN = math.inf, math.nan
# C99 Annex F.10.4.4 (pow), case by case: (x, y, result)
C99_POW = [
    (0.0, -3.0, INF), (-0.0, -3.0, -INF), (0.0, -1.0, INF), (-0.0, -1.0, -INF),     # pole, y an odd integer < 0
    (0.0, -INF, INF), (-0.0, -INF, INF),
    (0.0, -2.0, INF), (-0.0, -2.0, INF), (0.0, -0.5, INF), (-0.0, -0.5, INF), (-0.0, -2.4, INF),   # y < 0 not odd
    (0.0, 3.0, 0.0), (-0.0, 3.0, -0.0), (-0.0, 1.0, -0.0),                          # y an odd integer > 0
    (0.0, 2.0, 0.0), (-0.0, 2.0, 0.0), (-0.0, 0.5, 0.0), (0.0, 2.4, 0.0), (-0.0, INF, 0.0),    # y > 0 not odd
    (-1.0, INF, 1.0), (-1.0, -INF, 1.0),
    (1.0, NAN, 1.0), (1.0, INF, 1.0), (1.0, -INF, 1.0), (1.0, 2.4, 1.0), (1.0, -1e300, 1.0),
    (NAN, 0.0, 1.0), (NAN, -0.0, 1.0), (INF, 0.0, 1.0), (-INF, -0.0, 1.0), (0.0, 0.0, 1.0), (-2.0, 0.0, 1.0),
    (-2.0, 0.5, NAN), (-2.0, 2.4, NAN), (-0.5, -1.5, NAN), (-1.0, 0.5, NAN),        # finite x < 0, non-integer y
    (0.5, -INF, INF), (-0.5, -INF, INF), (2.0, -INF, 0.0), (-2.0, -INF, 0.0),
    (0.5, INF, 0.0), (-0.5, INF, 0.0), (2.0, INF, INF), (-2.0, INF, INF),
    (-INF, -3.0, -0.0), (-INF, -1.0, -0.0), (-INF, -2.0, 0.0), (-INF, -0.5, 0.0),
    (-INF, 3.0, -INF), (-INF, 1.0, -INF), (-INF, 2.0, INF), (-INF, 0.5, INF), (-INF, 2.4, INF),
    (INF, -0.5, 0.0), (INF, -3.0, 0.0), (INF, 0.5, INF), (INF, 3.0, INF),
    (NAN, 2.0, NAN), (NAN, 1.0, NAN), (NAN, -1.0, NAN), (NAN, 0.5, NAN), (NAN, INF, NAN),   # NaN stays NaN
    (0.0, NAN, NAN), (2.0, NAN, NAN), (-1.0, NAN, NAN), (INF, NAN, NAN),
    (-2.0, 3.0, -8.0), (-2.0, -3.0, -0.125), (-2.0, 2.0, 4.0), (-0.5, 2.0 ** 60, 0.0),     # x < 0, integer y
    (-1.0, 2.0 ** 53 + 2, 1.0), (-1.0, 2.0 ** 52 + 1, -1.0),
    (10.0, 400.0, INF), (-10.0, 401.0, -INF), (10.0, -400.0, 0.0), (-10.0, -401.0, -0.0),  # overflow, underflow
    (1e-300, 1e300, 0.0), (1e300, 1e300, INF), (1 + 2.0 ** -52, 2.0 ** 70, INF), (1 - 2.0 ** -53, -(2.0 ** 70), INF),
    (5e-324, 1.0, 5e-324), (5e-324, 2.0, 0.0), (2.0, -1074.0, 5e-324), (2.0, 1023.0, 2.0 ** 1023), (2.0, 1024.0, INF),
]


@pytest.mark.parametrize("x, y, want", C99_POW)
def test_power_special_values_are_c99s(x, y, want):
    assert _same(fm.power(x, y), want), (x, y, fm.power(x, y))
    assert _same(float(fm.power(np.array([x]), np.array([y]))[0]), want)
    got = fm.power(np.array([[x, x]]), y)
    assert got.shape == (1, 2) and _same(float(got[0, 1]), want)


# C99 Annex F for the other functions: (function, arguments, result); the scalar and the array path alike
C99_OTHERS = [
    ("sin", (0.0,), 0.0), ("sin", (-0.0,), -0.0), ("sin", (INF,), NAN), ("sin", (-INF,), NAN), ("sin", (NAN,), NAN),
    ("cos", (0.0,), 1.0), ("cos", (-0.0,), 1.0), ("cos", (INF,), NAN), ("cos", (-INF,), NAN), ("cos", (NAN,), NAN),
    ("tan", (0.0,), 0.0), ("tan", (-0.0,), -0.0), ("tan", (INF,), NAN), ("tan", (-INF,), NAN), ("tan", (NAN,), NAN),
    ("arcsin", (0.0,), 0.0), ("arcsin", (-0.0,), -0.0), ("arcsin", (1.5,), NAN), ("arcsin", (-INF,), NAN),
    ("arcsin", (NAN,), NAN), ("arcsin", (1.0,), math.pi / 2), ("arcsin", (-1.0,), -math.pi / 2),
    ("arccos", (1.0,), 0.0), ("arccos", (-1.0,), math.pi), ("arccos", (1.0000000000000002,), NAN),
    ("arccos", (INF,), NAN), ("arccos", (NAN,), NAN), ("arccos", (0.0,), math.pi / 2), ("arccos", (-0.0,), math.pi / 2),
    ("arctan", (0.0,), 0.0), ("arctan", (-0.0,), -0.0), ("arctan", (INF,), math.pi / 2), ("arctan", (-INF,), -math.pi / 2),
    ("arctan", (NAN,), NAN),
    ("exp", (0.0,), 1.0), ("exp", (-0.0,), 1.0), ("exp", (INF,), INF), ("exp", (-INF,), 0.0), ("exp", (NAN,), NAN),
    ("exp", (710.0,), INF), ("exp", (-746.0,), 0.0), ("exp", (-745.0,), 5e-324),
    ("log", (0.0,), -INF), ("log", (-0.0,), -INF), ("log", (1.0,), 0.0), ("log", (-1.0,), NAN), ("log", (-INF,), NAN),
    ("log", (INF,), INF), ("log", (NAN,), NAN), ("log", (-5e-324,), NAN),
    ("log2", (0.0,), -INF), ("log2", (-0.0,), -INF), ("log2", (1.0,), 0.0), ("log2", (-1.0,), NAN),
    ("log2", (-INF,), NAN), ("log2", (INF,), INF), ("log2", (NAN,), NAN), ("log2", (5e-324,), -1074.0),
    ("hypot", (INF, NAN), INF), ("hypot", (NAN, -INF), INF), ("hypot", (-INF, 1.0), INF), ("hypot", (NAN, 1.0), NAN),
    ("hypot", (1.0, NAN), NAN), ("hypot", (NAN, 0.0), NAN), ("hypot", (-3.0, 0.0), 3.0), ("hypot", (-0.0, -0.0), 0.0),
    ("hypot", (1e308, 1e308), math.hypot(1e308, 1e308)), ("hypot", (5e-324, 5e-324), 5e-324),
    ("radians", (-0.0,), -0.0), ("radians", (INF,), INF), ("radians", (NAN,), NAN),
    ("degrees", (-0.0,), -0.0), ("degrees", (-INF,), -INF), ("degrees", (NAN,), NAN),
] + [("arctan2", (a, b), math.atan2(a, b)) for a in (0.0, -0.0, 1.0, -1.0, INF, -INF, NAN)
     for b in (0.0, -0.0, 1.0, -1.0, INF, -INF, NAN)]


@pytest.mark.parametrize("name, args, want", C99_OTHERS)
def test_special_values_are_c99s(name, args, want):
    f = getattr(fm, name)
    assert _same(f(*args), want), (name, args, f(*args))
    assert _same(float(f(*(np.array([a]) for a in args))[0]), want)


def test_power_scalar_gets_the_bits_of_the_vectorised_path():
    """Python floats take fdlibm's code as written; arrays its masked form: the same bits everywhere,
    special values included, and the array path broadcasts."""
    rng = np.random.default_rng(39)
    n = 1000
    special = np.array([0.0, -0.0, 1.0, -1.0, INF, -INF, NAN, 0.5, -0.5, 2.0, -2.0, 3.0, -3.0, 2.4, 1 / 2.4, 5e-324,
                        -5e-324, 1e308, -1e308, 2.0 ** 31, 2.0 ** 31 + 1, 2.0 ** 53, 2.0 ** 53 + 2, 2.0 ** 64, 1e20,
                        1 - 2.0 ** -53, 1 + 2.0 ** -52, 1 - 2.0 ** -21, 1 + 2.0 ** -20, 1023.0, -1075.0, 1024.0])
    x = np.concatenate([np.exp(rng.uniform(-745, 709, n)) * rng.choice([-1.0, 1.0], n), rng.uniform(0, 1, n),
                        1 + rng.uniform(-1e-6, 1e-6, n), np.repeat(special, len(special))])
    y = np.concatenate([rng.uniform(-40, 40, n), np.full(n, 2.4), rng.uniform(-3e9, 3e9, n), np.tile(special, len(special))])
    y[:n // 3] = np.rint(y[:n // 3])
    vectorised = fm.power(x, y)
    assert _bits([fm.power(float(a), float(b)) for a, b in zip(x, y)]) == _bits(vectorised)
    assert _bits([fm.power(a, b) for a, b in zip(x, y)]) == _bits(vectorised)      # numpy float64 scalars
    assert _bits(fm.power(x[:, None], y[:50])) == _bits(fm.power(np.repeat(x, 50), np.tile(y[:50], len(x))))
    assert type(fm.power(2.0, 3.0)) is float and type(fm.power(2, 3)) is float and fm.power(2, 3) == 8.0


def test_power_of_srgb_codes_matches_the_correctly_rounded_curve():
    """The importer's and the writers' sRGB decode, ((c + 0.055) / 1.055) ** 2.4, on every 8-bit and
    16-bit code: within 1 ulp of the true value (the old exp(y log x) was up to 20 ulp off)."""
    c = np.arange(0, 65536) / 65535.0
    c = c[c > 0.04045]
    base = (c + 0.055) / 1.055
    got = fm.power(base, 2.4)
    with mpmath.workprec(_MP_PREC):
        err = ulp_errors(got[::16], [mpmath.power(mpmath.mpf(float(b)), mpmath.mpf(2.4)) for b in base[::16]])
    assert err.max() <= 1.0


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
