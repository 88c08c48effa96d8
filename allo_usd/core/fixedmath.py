"""Maths whose every result is the same double on every x86-64 machine: the values that reach a file.

Why this exists (docs/reliability/determinism.md): numpy's transcendental ufuncs (`np.sin`, `np.arccos`, ...)
switch to Intel's SVML on AVX-512 CPUs, glibc's libm (what `math.sin` and numpy's other paths call)
picks FMA variants of sin, cos, atan, acos, exp, log and pow through ifuncs, and `@`, `np.dot` and
`np.linalg.norm` of a vector go through OpenBLAS, whose kernel depends on the CPU. Each of these
rounds the last bit differently on some inputs (measured here: glibc's FMA and non-FMA sin differ
on random inputs), so a layer authored on one machine differed from the same plan's layer on another.

Everything here is built from IEEE-754 operations that are correctly rounded by definition and
carried out one numpy ufunc at a time (+, -, *, /, sqrt, rint, ldexp, frexp, comparisons and bit
masks), so no SIMD width, FMA contraction or library choice can change a result:
- `sin`, `cos`, `tan`, `arcsin`, `arccos`, `arctan`, `arctan2`, `exp`, `log`, `log2`, `power`: fdlibm's
  algorithms (Sun Microsystems, freely redistributable; the FreeBSD msun versions: e_log2.c for log2,
  e_pow.c for power), vectorised, and `hypot` scaled by the larger magnitude. Their errors against the
  true value, in ulp of the true value: the largest measured (mpmath at 160 bits, 50,000 random inputs
  per range plus the hard ones: near multiples of pi/2, near 1, the ends of each polynomial's interval,
  subnormals, huge and tiny exponents, power's 2.4 and 1/2.4 over [0, 1]) and the bound
  tests/core/test_fixedmath.py::test_within_the_stated_ulps_of_the_true_value checks on each run:

      function   measured  bound       function   measured  bound
      sin        0.75      1           exp        0.83      1
      cos        0.75      1           log        0.79      1
      tan        1.99      2           log2       0.75      1
      arcsin     0.80      1           power      0.84      1
      arccos     0.85      1           hypot      1.87      2
      arctan     0.74      1           radians    0.65      1
      arctan2    1.34      1.5         degrees    0.81      1

  tan is sin / cos (two roundings meet near the poles) and arctan2 rounds y / x before arctan, as
  fdlibm's e_atan2.c does. Exact: log2 of a power of two, power of an integer to an integer power
  whenever the result fits 53 bits, power(2, k) for every k, power(x, 0.5) = sqrt(x)
  (test_power_is_exact_where_the_result_is_a_double). Zeros, infinities, NaN, poles and domain errors
  give C99's Annex F results for every function here (test_special_values_are_c99s,
  test_power_special_values_are_c99s: power(x, +-0) = 1 and power(1, y) = 1 even for NaN, a negative x
  to an integer power, (-1) ** +-inf = 1, power(+-0, y < 0) = inf with the sign of an odd y);
- `exp2` (the film exposure from its EV): exact for an integral x (ldexp), else fdlibm's exp kernel on
  x ln 2 carried as a double-double; within 0.83 ulp measured against 60-digit decimal values (the
  exp2 tests in tests/core/test_fixedmath.py), C99's special values;
- `norm`, `dot`, `matmul`, `det3`, `cross`: sums of products written out in a fixed order; `inv4`: a 4x4
  inverse by cofactors in a fixed order (no LAPACK), an affine matrix's last row kept exactly 0, 0, 0, 1;
- `radians`, `degrees`: one multiplication, as numpy and math do it.
Scalars in give Python floats out; arrays give float64 arrays. Range reduction for sin and cos is
fdlibm's Cody-Waite with pi/2 in 33-bit pieces (to 85, 118 or 151 bits as cancellation needs), valid for |x| < 2**19 * pi/2 (823,550
rad); a larger argument is an error rather than a silently inaccurate value.

Scalars take a path of their own (`_s_*`): the same fdlibm operations, in the same order, on Python
floats. CPython carries out each float operation on its own, correctly rounded, so the bits are those
of the vectorised code (tests/core/test_fixedmath.py checks both against each other on many inputs), at
a few microseconds a call instead of the ~100 us that a dozen one-element numpy ufuncs cost; the
scene resolution of a plan calls these per scalar hundreds of thousands of times. Anything but a
finite float in range (inf, nan, a zero divisor, an angle past the reduction limit) goes the
vectorised way, so special values and errors are exactly as before. `power` is the exception: two
floats take fdlibm's e_pow.c as written, early returns for special values and all, and an array takes
the same steps with each early return as a mask (test_power_scalar_gets_the_bits_of_the_vectorised_path).
"""

from __future__ import annotations

import math
import struct

import numpy as np

from allo_usd.core.errors import AlloError

PI = 3.14159265358979311600e+00
_PIO2_HI, _PIO2_LO, _PIO4_HI = 1.57079632679489655800e+00, 6.12323399573676603587e-17, 7.85398163397448278999e-01
_PI_LO = 1.2246467991473531772e-16
_DEG = PI / 180.0

# rem_pio2 (fdlibm e_rem_pio2.c, the medium-size branch done to its third stage)
_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1, _PIO2_1T = 1.57079632673412561417e+00, 6.07710050650619224932e-11
_PIO2_2, _PIO2_2T = 6.07710050630396597660e-11, 2.02226624879595063154e-21
_PIO2_3, _PIO2_3T = 2.02226624871116645580e-21, 8.47842766036889956997e-32
REDUCTION_LIMIT = 2.0 ** 19 * _PIO2_HI

# k_sin.c, k_cos.c
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11

# s_atan.c
_ATANHI = np.array([4.63647609000806093515e-01, 7.85398163397448278999e-01,
                    9.82793723247329054082e-01, 1.57079632679489655800e+00, 0.0])
_ATANLO = np.array([2.26987774529616870924e-17, 3.06161699786838301793e-17,
                    1.39033110312309984516e-17, 6.12323399573676603587e-17, 0.0])
_AT = (3.33333333333329318027e-01, -1.99999999998764832476e-01, 1.42857142725034663711e-01,
       -1.11111104054623557880e-01, 9.09088713343650656196e-02, -7.69187620504482999495e-02,
       6.66107313738753120669e-02, -5.83357013379057348645e-02, 4.97687799461593236017e-02,
       -3.65315727442169155270e-02, 1.62858201153657823623e-02)

# e_asin.c, e_acos.c
_PS = (1.66666666666666657415e-01, -3.25565818622400915405e-01, 2.01212532134862925881e-01,
       -4.00555345006794114027e-02, 7.91534994289814532176e-04, 3.47933107596021167570e-05)
_QS = (-2.40339491173441421878e+00, 2.02094576023350569471e+00, -6.88283971605453293030e-01,
       7.70381505559019352791e-02)

# e_exp.c, e_log.c
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_INVLN2 = 1.44269504088896338700e+00
_P = (1.66666666666666019037e-01, -2.77777777770155933842e-03, 6.61375632143793436117e-05,
      -1.65339022054652515390e-06, 4.13813679705723846039e-08)
_EXP_HI, _EXP_LO = 7.09782712893383973096e+02, -7.45133219101941108420e+02
_LG = (6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01,
       2.222219843214978396e-01, 1.818357216161805012e-01, 1.531383769920937332e-01,
       1.479819860511658591e-01)
_SQRT_HALF = 7.07106781186547524401e-01
_LN2 = 6.93147180559945286227e-01


def _arr(x) -> tuple[np.ndarray, bool]:
    a = np.asarray(x, dtype=np.float64)
    return a, a.ndim == 0


def _out(a: np.ndarray, scalar: bool):
    return float(a) if scalar else a


def _rem_pio2(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n mod 4, y0, y1) with x = n * pi/2 + (y0 + y1), |y0 + y1| <= ~pi/4 (fdlibm's medium branch)."""
    finite = np.isfinite(x)
    if np.any(np.abs(x[finite]) >= REDUCTION_LIMIT):
        raise AlloError(f"an angle of magnitude >= {REDUCTION_LIMIT:.0f} rad reached sin/cos "
                        "(allo_usd.core.fixedmath reduces |x| < 2**19 * pi/2 exactly); reduce the angle first")
    fn = np.rint(x * _INVPIO2)
    r = x - fn * _PIO2_1          # exact: fn has at most 20 bits and pio2_1 33
    w = fn * _PIO2_1T             # good to about 85 bits
    ex = np.frexp(x)[1]
    # a second and third stage only where the first cancelled (fdlibm's i > 16 and i > 49): a later
    # stage starts over from the previous r, which is exact only after such a cancellation
    for need, hi, lo in ((16, _PIO2_2, _PIO2_2T), (49, _PIO2_3, _PIO2_3T)):
        more = (ex - np.frexp(r - w)[1]) > need
        t = r
        w2 = fn * hi
        r2 = t - w2
        w2 = fn * lo - ((t - r2) - w2)
        r, w = np.where(more, r2, r), np.where(more, w2, w)
    y0 = r - w
    y1 = (r - y0) - w
    n = np.where(finite, fn, 0.0).astype(np.int64) & 3
    return n, y0, y1


def _ksin(x, y):
    z = x * x
    v = z * x
    r = _S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))
    return x - ((z * (0.5 * y - v * r) - y) - v * _S1)


def _kcos(x, y):
    z = x * x
    w = z * z
    r = z * (_C1 + z * (_C2 + z * _C3)) + w * w * (_C4 + z * (_C5 + z * _C6))
    hz = 0.5 * z
    w = 1.0 - hz
    return w + (((1.0 - w) - hz) + (z * r - x * y))


def _sincos(x: np.ndarray, want_cos: bool) -> np.ndarray:
    with np.errstate(all="ignore"):
        n, y0, y1 = _rem_pio2(x)
        s, c = _ksin(y0, y1), _kcos(y0, y1)
        if want_cos:
            out = np.choose(n, [c, -s, -c, s])
        else:
            out = np.choose(n, [s, c, -s, -c])
        tiny = np.abs(x) < 2.0 ** -27     # fdlibm returns x (sin) and 1 (cos) here
        out = np.where(tiny, 1.0 if want_cos else x, out)
        return np.where(np.isfinite(x), out, np.nan)


# --- the scalar path: the same operations on Python floats ------------------------------------------

_INF = math.inf


def _finite(x) -> bool:
    """A float (Python's or numpy's float64, a float subclass) that the scalar path may take."""
    return isinstance(x, float) and -_INF < x < _INF


def _s_rem_pio2(x: float) -> tuple[int, float, float]:
    """`_rem_pio2` of one finite float below REDUCTION_LIMIT."""
    fn = math.copysign(float(round(x * _INVPIO2)), x * _INVPIO2)   # np.rint: half to even, zero's sign kept
    r = x - fn * _PIO2_1
    w = fn * _PIO2_1T
    ex = math.frexp(x)[1]
    for need, hi, lo in ((16, _PIO2_2, _PIO2_2T), (49, _PIO2_3, _PIO2_3T)):
        if ex - math.frexp(r - w)[1] > need:
            t = r
            w2 = fn * hi
            r2 = t - w2
            w = fn * lo - ((t - r2) - w2)
            r = r2
    y0 = r - w
    y1 = (r - y0) - w
    return int(fn) & 3, y0, y1


def _s_sincos(x: float, want_cos: bool) -> float | None:
    """sin or cos of a finite float by `_sincos`'s steps; None when the vectorised path must decide."""
    if abs(x) < 2.0 ** -27:
        return 1.0 if want_cos else x
    if not abs(x) < REDUCTION_LIMIT:
        return None
    n, y0, y1 = _s_rem_pio2(x)
    s, c = _ksin(y0, y1), _kcos(y0, y1)
    return (c, -s, -c, s)[n] if want_cos else (s, c, -s, -c)[n]


def _s_sin_cos(x: float) -> tuple[float, float] | None:
    """(sin, cos) of a finite float, each exactly `_s_sincos`'s, from one range reduction (tan needs both)."""
    if abs(x) < 2.0 ** -27:
        return x, 1.0
    if not abs(x) < REDUCTION_LIMIT:
        return None
    n, y0, y1 = _s_rem_pio2(x)
    s, c = _ksin(y0, y1), _kcos(y0, y1)
    return (s, c, -s, -c)[n], (c, -s, -c, s)[n]


def sin(x):
    if _finite(x) and (r := _s_sincos(float(x), False)) is not None:
        return r
    a, scalar = _arr(x)
    return _out(_sincos(np.atleast_1d(a), False).reshape(a.shape), scalar)


def cos(x):
    if _finite(x) and (r := _s_sincos(float(x), True)) is not None:
        return r
    a, scalar = _arr(x)
    return _out(_sincos(np.atleast_1d(a), True).reshape(a.shape), scalar)


def tan(x):
    """sin(x) / cos(x): within 2 ulp, and the same on every machine (the camera's half-angles)."""
    if _finite(x) and (sc := _s_sin_cos(float(x))) is not None and sc[1]:
        return sc[0] / sc[1]
    a, scalar = _arr(x)
    a1 = np.atleast_1d(a)
    with np.errstate(all="ignore"):
        return _out((_sincos(a1, False) / _sincos(a1, True)).reshape(a.shape), scalar)


def _atan(x: np.ndarray) -> np.ndarray:
    ax = np.abs(x)
    with np.errstate(all="ignore"):
        idx = np.select([ax < 0.4375, ax < 0.6875, ax < 1.1875, ax < 2.4375], [4, 0, 1, 2], 3)
        t = np.select([idx == 4, idx == 0, idx == 1, idx == 2],
                      [ax, (2.0 * ax - 1.0) / (2.0 + ax), (ax - 1.0) / (ax + 1.0), (ax - 1.5) / (1.0 + 1.5 * ax)],
                      -1.0 / ax)
        z = t * t
        w = z * z
        s1 = z * (_AT[0] + w * (_AT[2] + w * (_AT[4] + w * (_AT[6] + w * (_AT[8] + w * _AT[10])))))
        s2 = w * (_AT[1] + w * (_AT[3] + w * (_AT[5] + w * (_AT[7] + w * _AT[9]))))
        small = t - t * (s1 + s2)
        big = _ATANHI[idx] - ((t * (s1 + s2) - _ATANLO[idx]) - t)
        r = np.where(idx == 4, small, big)
        return np.where(np.signbit(x), -r, r)


_ATANHI_S, _ATANLO_S = tuple(map(float, _ATANHI)), tuple(map(float, _ATANLO))


def _s_atan(x: float) -> float:
    """`_atan` of one finite float."""
    ax = abs(x)
    if ax < 0.4375:
        idx, t = 4, ax
    elif ax < 0.6875:
        idx, t = 0, (2.0 * ax - 1.0) / (2.0 + ax)
    elif ax < 1.1875:
        idx, t = 1, (ax - 1.0) / (ax + 1.0)
    elif ax < 2.4375:
        idx, t = 2, (ax - 1.5) / (1.0 + 1.5 * ax)
    else:
        idx, t = 3, -1.0 / ax
    z = t * t
    w = z * z
    s1 = z * (_AT[0] + w * (_AT[2] + w * (_AT[4] + w * (_AT[6] + w * (_AT[8] + w * _AT[10])))))
    s2 = w * (_AT[1] + w * (_AT[3] + w * (_AT[5] + w * (_AT[7] + w * _AT[9]))))
    if idx == 4:
        r = t - t * (s1 + s2)
    else:
        r = _ATANHI_S[idx] - ((t * (s1 + s2) - _ATANLO_S[idx]) - t)
    return -r if math.copysign(1.0, x) < 0.0 else r


def arctan(x):
    if _finite(x):
        return _s_atan(float(x))
    a, scalar = _arr(x)
    return _out(_atan(np.atleast_1d(a)).reshape(a.shape), scalar)


def arctan2(y, x):
    """Angle of (x, y) in [-pi, pi], fdlibm's e_atan2.c case by case (signed zeros and infinities too)."""
    if _finite(y) and _finite(x) and x != 0.0:
        y, x = float(y), float(x)
        q = abs(y / x)
        if q < _INF:
            neg_x = math.copysign(1.0, x) < 0.0
            if y == 0.0:
                r = PI + _PI_LO if neg_x else 0.0
            else:
                z = _s_atan(q)
                r = PI - (z - _PI_LO) if neg_x else z
            return -r if math.copysign(1.0, y) < 0.0 else r
    yy, sy = _arr(y)
    xx, sx = _arr(x)
    yy, xx = np.broadcast_arrays(np.atleast_1d(yy), np.atleast_1d(xx))
    shape = np.broadcast_shapes(np.shape(y), np.shape(x))
    with np.errstate(all="ignore"):
        z = _atan(np.abs(yy / xx))
        neg_x, neg_y = np.signbit(xx), np.signbit(yy)
        r = np.where(neg_x, PI - (z - _PI_LO), z)
        # both infinite: pi/4 or 3pi/4; y = 0: 0 or pi; x = 0 or y infinite: pi/2; x infinite: 0 or pi
        both_inf = np.isinf(xx) & np.isinf(yy)
        r = np.where(both_inf, np.where(neg_x, 3.0 * _PIO4_HI + 3.0 * _PIO2_LO / 2.0, _PIO4_HI + _PIO2_LO / 2.0), r)
        r = np.where(~both_inf & np.isinf(xx), np.where(neg_x, PI + _PI_LO, 0.0), r)
        r = np.where(~both_inf & (np.isinf(yy) | ((xx == 0.0) & (yy != 0.0))), _PIO2_HI + _PIO2_LO, r)
        r = np.where(yy == 0.0, np.where(neg_x, PI + _PI_LO, 0.0), r)
        r = np.where(neg_y, -r, r)
        r = np.where(np.isnan(xx) | np.isnan(yy), np.nan, r)
    return _out(r.reshape(shape), sx and sy)


def _pq(t):
    p = t * (_PS[0] + t * (_PS[1] + t * (_PS[2] + t * (_PS[3] + t * (_PS[4] + t * _PS[5])))))
    q = 1.0 + t * (_QS[0] + t * (_QS[1] + t * (_QS[2] + t * _QS[3])))
    return p, q


def _high_word(x: np.ndarray) -> np.ndarray:
    """x with its low 32 bits cleared (fdlibm's SET_LOW_WORD(x, 0))."""
    return (np.ascontiguousarray(x, dtype=np.float64).view(np.uint64) & np.uint64(0xFFFFFFFF00000000)).view(np.float64)


def _asin(x: np.ndarray) -> np.ndarray:
    ax = np.abs(x)
    with np.errstate(all="ignore"):
        p, q = _pq(x * x)
        small = x + x * (p / q)
        w = 1.0 - ax
        t = w * 0.5
        p, q = _pq(t)
        s = np.sqrt(t)
        near_one = _PIO2_HI - (2.0 * (s + s * (p / q)) - _PIO2_LO)
        hw = _high_word(s)
        c = (t - hw * hw) / (s + hw)
        pp = 2.0 * s * (p / q) - (_PIO2_LO - 2.0 * c)
        qq = _PIO4_HI - 2.0 * hw
        mid = _PIO4_HI - (pp - qq)
        big = np.where(ax >= 0.975, near_one, mid)
        big = np.where(np.signbit(x), -big, big)
        r = np.where(ax < 0.5, np.where(ax < 2.0 ** -27, x, small), big)
        r = np.where(ax == 1.0, x * _PIO2_HI + x * _PIO2_LO, r)
        return np.where(ax > 1.0, np.nan, r)


def _acos(x: np.ndarray) -> np.ndarray:
    ax = np.abs(x)
    with np.errstate(all="ignore"):
        p, q = _pq(x * x)
        small = _PIO2_HI - (x - (_PIO2_LO - x * (p / q)))
        small = np.where(ax <= 2.0 ** -57, _PIO2_HI + _PIO2_LO, small)
        zn = (1.0 + x) * 0.5
        p, q = _pq(zn)
        s = np.sqrt(zn)
        neg = PI - 2.0 * (s + ((p / q) * s - _PIO2_LO))
        zp = (1.0 - x) * 0.5
        p, q = _pq(zp)
        s = np.sqrt(zp)
        df = _high_word(s)
        c = (zp - df * df) / (s + df)
        pos = 2.0 * (df + ((p / q) * s + c))
        r = np.where(ax < 0.5, small, np.where(x < 0.0, neg, pos))
        r = np.where(x == 1.0, 0.0, np.where(x == -1.0, PI + 2.0 * _PIO2_LO, r))
        return np.where(ax > 1.0, np.nan, r)


def _s_high_word(x: float) -> float:
    return struct.unpack("<d", struct.pack("<Q", struct.unpack("<Q", struct.pack("<d", x))[0]
                                           & 0xFFFFFFFF00000000))[0]


def _s_asin(x: float) -> float:
    """`_asin` of one float with |x| <= 1."""
    ax = abs(x)
    if ax == 1.0:
        return x * _PIO2_HI + x * _PIO2_LO
    if ax < 0.5:
        if ax < 2.0 ** -27:
            return x
        p, q = _pq(x * x)
        return x + x * (p / q)
    w = 1.0 - ax
    t = w * 0.5
    p, q = _pq(t)
    s = math.sqrt(t)
    if ax >= 0.975:
        big = _PIO2_HI - (2.0 * (s + s * (p / q)) - _PIO2_LO)
    else:
        hw = _s_high_word(s)
        c = (t - hw * hw) / (s + hw)
        pp = 2.0 * s * (p / q) - (_PIO2_LO - 2.0 * c)
        qq = _PIO4_HI - 2.0 * hw
        big = _PIO4_HI - (pp - qq)
    return -big if math.copysign(1.0, x) < 0.0 else big


def _s_acos(x: float) -> float:
    """`_acos` of one float with |x| <= 1."""
    if x == 1.0:
        return 0.0
    if x == -1.0:
        return PI + 2.0 * _PIO2_LO
    ax = abs(x)
    if ax < 0.5:
        if ax <= 2.0 ** -57:
            return _PIO2_HI + _PIO2_LO
        p, q = _pq(x * x)
        return _PIO2_HI - (x - (_PIO2_LO - x * (p / q)))
    if x < 0.0:
        zn = (1.0 + x) * 0.5
        p, q = _pq(zn)
        s = math.sqrt(zn)
        return PI - 2.0 * (s + ((p / q) * s - _PIO2_LO))
    zp = (1.0 - x) * 0.5
    p, q = _pq(zp)
    s = math.sqrt(zp)
    df = _s_high_word(s)
    c = (zp - df * df) / (s + df)
    return 2.0 * (df + ((p / q) * s + c))


def arcsin(x):
    if _finite(x) and abs(x) <= 1.0:
        return _s_asin(float(x))
    a, scalar = _arr(x)
    return _out(_asin(np.atleast_1d(a)).reshape(a.shape), scalar)


def arccos(x):
    if _finite(x) and abs(x) <= 1.0:
        return _s_acos(float(x))
    a, scalar = _arr(x)
    return _out(_acos(np.atleast_1d(a)).reshape(a.shape), scalar)


def exp(x):
    a, scalar = _arr(x)
    x1 = np.atleast_1d(a)
    with np.errstate(all="ignore"):
        k = np.rint(x1 * _INVLN2)
        k = np.where(np.isfinite(k), k, 0.0)
        hi = x1 - k * _LN2_HI
        lo = k * _LN2_LO
        r = hi - lo
        t = r * r
        c = r - t * (_P[0] + t * (_P[1] + t * (_P[2] + t * (_P[3] + t * _P[4]))))
        y0 = 1.0 - ((r * c) / (c - 2.0) - r)
        y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
        ki = k.astype(np.int64)
        # 2**k in two steps, so that k down to -1074 (a subnormal result) scales without overflow
        half = ki // 2
        y = np.ldexp(np.ldexp(y, half), ki - half)
        out = np.where(k == 0.0, y0, y)
        out = np.where(x1 > _EXP_HI, np.inf, np.where(x1 < _EXP_LO, 0.0, out))
        out = np.where(np.isnan(x1), np.nan, out)
    return _out(out.reshape(a.shape), scalar)


def _log(x: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):
        m, e = np.frexp(x)           # x = m * 2**e, m in [0.5, 1): exact
        low = m < _SQRT_HALF
        m = np.where(low, m * 2.0, m)
        k = (e - low).astype(np.float64)
        f = m - 1.0
        s = f / (2.0 + f)
        z = s * s
        w = z * z
        t1 = w * (_LG[1] + w * (_LG[3] + w * _LG[5]))
        t2 = z * (_LG[0] + w * (_LG[2] + w * (_LG[4] + w * _LG[6])))
        r = t2 + t1
        hfsq = 0.5 * f * f
        k0 = f - (hfsq - s * (hfsq + r))
        kn = k * _LN2_HI - ((hfsq - (s * (hfsq + r) + k * _LN2_LO)) - f)
        out = np.where(k == 0.0, k0, kn)
        out = np.where(x == 0.0, -np.inf, np.where(x < 0.0, np.nan, out))
        return np.where(np.isposinf(x), np.inf, np.where(np.isnan(x), np.nan, out))


def _s_log(x: float) -> float:
    """`_log` of one finite float > 0."""
    m, e = math.frexp(x)
    low = m < _SQRT_HALF
    if low:
        m = m * 2.0
    k = float(e - low)
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    t1 = w * (_LG[1] + w * (_LG[3] + w * _LG[5]))
    t2 = z * (_LG[0] + w * (_LG[2] + w * (_LG[4] + w * _LG[6])))
    r = t2 + t1
    hfsq = 0.5 * f * f
    if k == 0.0:
        return f - (hfsq - s * (hfsq + r))
    return k * _LN2_HI - ((hfsq - (s * (hfsq + r) + k * _LN2_LO)) - f)


def log(x):
    if _finite(x) and x > 0.0:
        return _s_log(float(x))
    a, scalar = _arr(x)
    return _out(_log(np.atleast_1d(a)).reshape(a.shape), scalar)


_IVLN2HI, _IVLN2LO = 1.44269504072144627571e+00, 1.67517131648865118353e-10   # 1/ln 2 in 33 + 53 bits


def _log2_parts(f, k, high_word):
    """FreeBSD msun's e_log2.c on the reduced argument: log2(1 + f) + k, f = m - 1 with m in [sqrt(1/2),
    sqrt(2)), with log(1 + f) split into hi (its high word) + lo before either is multiplied by 1/ln 2 in
    two pieces; floats or arrays alike (`high_word` is the matching SET_LOW_WORD(x, 0))."""
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    t1 = w * (_LG[1] + w * (_LG[3] + w * _LG[5]))
    t2 = z * (_LG[0] + w * (_LG[2] + w * (_LG[4] + w * _LG[6])))
    hfsq = 0.5 * f * f
    r = s * (hfsq + (t2 + t1))
    hi = high_word(f - hfsq)
    lo = ((f - hi) - hfsq) + r
    val_hi = hi * _IVLN2HI
    val_lo = (lo + hi) * _IVLN2LO + lo * _IVLN2HI
    w = k + val_hi
    val_lo = val_lo + ((k - w) + val_hi)
    return val_lo + w


def log2(x):
    """Base-2 logarithm as FreeBSD's e_log2.c computes it: the exponent k plus log2 of the mantissa in
    [sqrt(1/2), sqrt(2)), carried in two pieces so that adding k loses nothing; exact for powers of two."""
    if _finite(x) and x > 0.0:
        m, e = math.frexp(float(x))
        low = m < _SQRT_HALF
        return _log2_parts((m * 2.0 if low else m) - 1.0, float(e - low), _s_high_word)
    a, scalar = _arr(x)
    x1 = np.atleast_1d(a)
    with np.errstate(all="ignore"):
        m, e = np.frexp(x1)
        low = m < _SQRT_HALF
        out = _log2_parts(np.where(low, m * 2.0, m) - 1.0, (e - low).astype(np.float64), _high_word)
        out = np.where(x1 > 0.0, out, _log(x1))
        out = np.where(np.isposinf(x1), np.inf, out)
    return _out(out.reshape(a.shape), scalar)


def radians(x):
    a, scalar = _arr(x)
    return _out(a * _DEG, scalar)


def degrees(x):
    a, scalar = _arr(x)
    return _out(a * (180.0 / PI), scalar)


# --- sums of products in a fixed order (no BLAS) ---------------------------------------------------

class _QuietOverflow:
    """`np.errstate(over="ignore", invalid="ignore")` for `norm`, at a tenth of its cost: numpy 1.x keeps
    the error state as [buffer size, error mask, callback] (geterrobj), and errstate's Python layer
    (seterr, geterr) cost more than the small sums norm guards (ray casting calls it ~20,000 times a
    plan day). The state only decides warnings, never a value. Without geterrobj (numpy 2): errstate."""

    _MASK = (7 << 3) | (7 << 9)   # the over and invalid fields (3 bits each): 0 = ignore

    def __enter__(self):
        self._old = np.geterrobj()
        np.seterrobj([self._old[0], self._old[1] & ~self._MASK, self._old[2]])

    def __exit__(self, *exc):
        np.seterrobj(self._old)
        return False


def _quiet_overflow():
    return _QuietOverflow() if hasattr(np, "geterrobj") else np.errstate(over="ignore", invalid="ignore")


def dot(a, b):
    """Sum of products over the last axis, left to right (broadcasting); a scalar for two vectors."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    n = a.shape[-1]
    if b.shape[-1] != n:
        raise ValueError(f"dot: last axes differ ({a.shape} and {b.shape})")
    s = a[..., 0] * b[..., 0]
    for k in range(1, n):
        s = s + a[..., k] * b[..., k]
    return float(s) if np.ndim(s) == 0 else s


def norm(v, axis=None, keepdims: bool = False):
    """Euclidean length: of the whole array (axis None, numpy's default) or along `axis`, as the
    square root of the squares summed in index order (no BLAS)."""
    v = np.asarray(v, dtype=np.float64)
    if axis is None and v.size <= 16:   # a vector or a quaternion: the same sum on Python floats, which
        flat = v.reshape(-1).tolist()   # overflow to inf without numpy's error state (its cost here)
        s = flat[0] * flat[0] if flat else 0.0
        for x in flat[1:]:
            s = s + x * x
        out = math.sqrt(s)
        return np.full((1,) * v.ndim, out) if keepdims else out
    with _quiet_overflow():   # a huge vector's length is inf, as BLAS gives it
        if axis is None:
            flat = v.reshape(-1)
            s = flat[0] * flat[0] if flat.size else 0.0
            for k in range(1, flat.size):
                s = s + flat[k] * flat[k]
            out = np.sqrt(np.float64(s))
            return np.full((1,) * v.ndim, out) if keepdims else float(out)
        if axis not in (-1, v.ndim - 1):   # the last axis (rows of vectors) needs no move
            v = np.moveaxis(v, axis, -1)
        s = dot(v, v)
        out = np.sqrt(s)
    if keepdims:
        out = np.expand_dims(out, axis)
    return float(out) if np.ndim(out) == 0 else out


def matmul(a, b):
    """`a @ b` with each entry summed in index order (no BLAS): (.., n, k) @ (.., k, m), a (k,) vector
    on either side as numpy treats it."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim == 1 and b.ndim == 1:
        return dot(a, b)
    if b.ndim == 1:        # (.., n, k) @ (k,) -> (.., n)
        return dot(a, b)
    if a.ndim == 1:        # (k,) @ (.., k, m) -> (.., m)
        return matmul(a[None, :], b)[..., 0, :]
    k = a.shape[-1]
    if b.shape[-2] != k:
        raise ValueError(f"matmul: inner sizes differ ({a.shape} @ {b.shape})")
    if a.ndim == 2 and b.ndim == 2 and k and a.shape[0] >= _ROWS_BY_COLUMN:
        return _matmul_rows(a, b)
    if a.ndim == 2 and b.ndim == 2 and 0 < k <= 4 and a.shape[0] <= 4 and b.shape[1] <= 4:
        return _matmul_small(a, b)
    out = a[..., :, 0, None] * b[..., 0, None, :]
    for i in range(1, k):
        out = out + a[..., :, i, None] * b[..., i, None, :]
    return out


_ROWS_BY_COLUMN = 64   # from this many rows, (n, k) @ (k, m) is summed one output column at a time


def _matmul_small(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, k) @ (k, m) for a few rows and columns (rotations, a point): the broadcast form's sums on
    Python floats, each product rounded and added left to right as there, so the same bits (IEEE
    doubles either way; inf and NaN propagate alike) without a dozen numpy calls on 3x3 arrays."""
    return np.array(matmul_lists(a.tolist(), b.tolist()), dtype=np.float64).reshape(a.shape[0], b.shape[1])


def matmul_lists(a: list, b: list) -> list:
    """`_matmul_small` on nested lists of Python floats ((n, k) rows times (k, m) rows), returning rows:
    for callers that go on in Python floats (placement's camera-frame map), so the same bits without
    the arrays around them."""
    cols = list(zip(*b))
    out = []
    for r in a:
        line = []
        for c in cols:
            acc = r[0] * c[0]
            for i in range(1, len(r)):
                acc = acc + r[i] * c[i]
            line.append(acc)
        out.append(line)
    return out


def _matmul_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, k) @ (k, m) for many rows (ray directions, mesh points): the same products summed in the
    same order as `matmul`'s broadcast form, computed one output column at a time into a C-ordered
    result, which is about 5x faster for thousands of rows (no (n, 1) x (1, m) broadcasting)."""
    out = np.empty((a.shape[0], b.shape[1]))
    cols = [a[:, i] for i in range(a.shape[1])]
    for j in range(b.shape[1]):
        o = out[:, j]
        np.multiply(cols[0], b[0, j], out=o)
        for i in range(1, len(cols)):
            np.add(o, cols[i] * b[i, j], out=o)
    return out


def apply(rotation, points):
    """Rows of `points` (n, 3) transformed by the 3x3 `rotation`: points @ rotation.T, in fixed order."""
    return matmul(np.asarray(points, dtype=np.float64), np.asarray(rotation, dtype=np.float64).T)


def cross(a, b):
    """Cross product over the last axis (written out; numpy's is the same products)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def det3(m) -> float:
    """Determinant of a 3x3 matrix by cofactors of its first row (no LAPACK), on Python floats (the
    same operations as on numpy's float64 scalars, so the same bits)."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(m, dtype=np.float64)[:3, :3].tolist()
    return m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20) + m02 * (m10 * m21 - m11 * m20)


def hypot(x, y):
    """sqrt(x*x + y*y), scaled by the larger magnitude so that neither overflows nor underflows."""
    if _finite(x) and _finite(y):
        ax, ay = abs(float(x)), abs(float(y))
        big = ax if ax >= ay else ay
        if not big > 0.0:
            return 0.0
        small = (ay if ax >= ay else ax) / big
        return big * math.sqrt(1.0 + small * small)
    xa, sx = _arr(x)
    ya, sy = _arr(y)
    ax, ay = np.abs(xa), np.abs(ya)
    big = np.maximum(ax, ay)
    with np.errstate(all="ignore"):
        small = np.minimum(ax, ay) / np.where(big > 0.0, big, 1.0)
        out = np.where(big > 0.0, big * np.sqrt(1.0 + small * small), 0.0)
        out = np.where(np.isnan(ax) | np.isnan(ay), np.nan, out)
        out = np.where(np.isinf(ax) | np.isinf(ay), np.inf, out)     # C99: even with the other NaN
    return _out(out, sx and sy)


# --- power: fdlibm's e_pow.c (FreeBSD msun), word for word ------------------------------------------
# log2|x| in two pieces t1 + t2 (t1 with 29 trailing zero bits), y * log2|x| = n + y' carried to about
# 64 bits, then 2**n * exp(y' ln 2); "nearly rounded", exact for integer powers of integers that fit.
# One change: for |y| > 2**31 and x within 2**-20 of 1, fdlibm multiplies t = |x| - 1 (up to 33
# significant bits) by the 24-bit ivln2_h as if the product were exact, which it is not, and y * log2|x|
# then lost up to 460 ulp of the result; here t is split into its high word (21 bits, so the product is
# exact) and the rest, which joins v.
# The steps work on the 32-bit halves of a double (fdlibm's GET_HIGH_WORD, SET_LOW_WORD ...): here
# int64 arrays holding the signed high word and the unsigned low word, and Python ints on the scalar path.

_BP, _DP_H, _DP_L = (1.0, 1.5), (0.0, 5.84962487220764160156e-01), (0.0, 1.35003920212974897128e-08)
_L = (5.99999999999994648725e-01, 4.28571428578550184252e-01, 3.33333329818377432918e-01,
      2.72728123808534006489e-01, 2.30660745775561754067e-01, 2.06975017800338417784e-01)
_LG2_H, _LG2_L = 6.93147182464599609375e-01, -1.90465429995776804525e-09
_OVT = 8.0085662595372944372e-17
_CP, _CP_H, _CP_L = 9.61796693925975554329e-01, 9.61796700954437255859e-01, -7.02846165095275826516e-09
_IVLN2, _IVLN2_H, _IVLN2_L = 1.44269504088896338700e+00, 1.44269502162933349609e+00, 1.92596299112661746887e-08
_TWO53 = 9007199254740992.0


def _words(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(signed high word, unsigned low word) of each double, as int64."""
    bits = np.ascontiguousarray(x, dtype=np.float64).view(np.uint64)
    return (bits >> np.uint64(32)).astype(np.uint32).view(np.int32).astype(np.int64), \
        (bits & np.uint64(0xFFFFFFFF)).astype(np.int64)


def _from_words(hi: np.ndarray, lo=0) -> np.ndarray:
    """The double with high word `hi` (its low 32 bits) and low word `lo`."""
    high = (np.asarray(hi, dtype=np.int64) & 0xFFFFFFFF).astype(np.uint64) << np.uint64(32)
    return np.ascontiguousarray(high | np.asarray(lo, dtype=np.int64).astype(np.uint64)).view(np.float64)


def _pow_log2(ax: np.ndarray, ix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """log2(ax) = t1 + t2 for finite ax > 0 (ix: its high word), fdlibm's main branch."""
    sub = ix < 0x00100000                     # subnormal: scale by 2**53 first
    ax = np.where(sub, ax * _TWO53, ax)
    ix = np.where(sub, _words(ax)[0], ix)
    n = np.where(sub, -53, 0) + (ix >> 20) - 0x3FF
    j = ix & 0x000FFFFF
    ix = j | 0x3FF00000
    k = np.where(j <= 0x3988E, 0, np.where(j < 0xBB67A, 1, 0))     # |x| < sqrt(3/2), < sqrt(3)
    top = j >= 0xBB67A
    n = np.where(top, n + 1, n)
    ix = np.where(top, ix - 0x00100000, ix)
    ax = _from_words(ix, _words(ax)[1])
    bp = np.where(k == 1, _BP[1], _BP[0])
    u = ax - bp
    v = 1.0 / (ax + bp)
    ss = u * v
    s_h = _high_word(ss)
    t_h = _from_words(((ix >> 1) | 0x20000000) + 0x00080000 + (k << 18))
    t_l = ax - (t_h - bp)
    s_l = v * ((u - s_h * t_h) - s_h * t_l)
    s2 = ss * ss
    r = s2 * s2 * (_L[0] + s2 * (_L[1] + s2 * (_L[2] + s2 * (_L[3] + s2 * (_L[4] + s2 * _L[5])))))
    r = r + s_l * (s_h + ss)
    s2 = s_h * s_h
    t_h = _high_word(3.0 + s2 + r)
    t_l = r - ((t_h - 3.0) - s2)
    u = s_h * t_h
    v = s_l * t_h + t_l * ss
    p_h = _high_word(u + v)
    p_l = v - (p_h - u)
    z_h = _CP_H * p_h
    z_l = _CP_L * p_h + p_l * _CP + np.where(k == 1, _DP_L[1], _DP_L[0])
    t = n.astype(np.float64)
    dp_h = np.where(k == 1, _DP_H[1], _DP_H[0])
    t1 = _high_word(((z_h + z_l) + dp_h) + t)
    t2 = z_l - (((t1 - t) - dp_h) - z_h)
    return t1, t2


def _pow_log2_near_one(t, high_word):
    """log2(1 + t) = t1 + t2 for |t| < 2**-20 by the series to t**4, floats or arrays alike (`high_word`:
    the matching SET_LOW_WORD(x, 0)); t is split so that ivln2_h * t_hi is exact (the change above)."""
    w = (t * t) * (0.5 - t * (0.3333333333333333333333 - t * 0.25))
    t_h = high_word(t)
    u = _IVLN2_H * t_h
    v = ((t - t_h) * _IVLN2_H + t * _IVLN2_L) - w * _IVLN2
    t1 = high_word(u + v)
    return t1, v - (t1 - u)


def _pow_exp2(p_h: np.ndarray, p_l: np.ndarray, z: np.ndarray) -> np.ndarray:
    """2**(p_h + p_l) for z = p_h + p_l in (-1075, 1024] (fdlibm's tail)."""
    j = _words(z)[0]
    i = j & 0x7FFFFFFF
    big = i > 0x3FE00000                       # |z| > 0.5: n = [z + 0.5]
    k = np.where(big, (i >> 20) - 0x3FF, 0)
    nn = j + (0x00100000 >> (k + 1))
    k = np.where(big, ((nn & 0x7FFFFFFF) >> 20) - 0x3FF, 0)
    t = _from_words(nn & ~(0x000FFFFF >> k))
    n = ((nn & 0x000FFFFF) | 0x00100000) >> (20 - k)
    n = np.where(big, np.where(j < 0, -n, n), 0)
    p_h = np.where(big, p_h - t, p_h)
    t = _high_word(p_l + p_h)
    u = t * _LG2_H
    v = (p_l - (t - p_h)) * _LN2 + t * _LG2_L
    z = u + v
    w = v - (z - u)
    t = z * z
    t1 = z - t * (_P[0] + t * (_P[1] + t * (_P[2] + t * (_P[3] + t * _P[4]))))
    r = (z * t1) / (t1 - 2.0) - (w + z * w)
    z = 1.0 - (r - z)
    return np.ldexp(z, n)                      # fdlibm adds n to the exponent, or scalbn when subnormal


def _pow(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x ** y, fdlibm's __ieee754_pow on arrays: every lane takes the general path, then fdlibm's early
    returns replace it, applied from the last to the first so that the first that applies wins (each
    only where some lane needs it: a colour curve's lanes need none)."""
    hx, lx = _words(x)
    hy, _ = _words(y)
    ix, iy = hx & 0x7FFFFFFF, hy & 0x7FFFFFFF
    ax, ay = np.abs(x), np.abs(y)
    neg_x, big_y = hx < 0, iy > 0x41E00000
    if neg_x.any():
        integral = (ay >= _TWO53) | (np.rint(y) == y)
        odd = integral & (ay < _TWO53) & ((np.where(ay < _TWO53, np.rint(y), 0.0).astype(np.int64) & 1) == 1)
        s = np.where(neg_x & odd, -1.0, 1.0)   # the sign of (negative) ** (odd integer)
    else:
        integral = odd = np.zeros(x.shape, dtype=bool)    # only read where x < 0
        s = 1.0
    # log2|x| = t1 + t2: the main branch, or the series in |x| - 1 when |y| > 2**31 (x within 2**-20 of 1)
    finite_x = np.isfinite(x) & (x != 0.0)
    t1, t2 = _pow_log2(np.where(finite_x, ax, 1.0), np.where(finite_x, ix, 0x3FF00000))
    if big_y.any():
        n1, n2 = _pow_log2_near_one(ax - 1.0, _high_word)
        t1, t2 = np.where(big_y, n1, t1), np.where(big_y, n2, t2)
    # (y1 + y2) * (t1 + t2) = p_h + p_l
    y1 = _high_word(y)
    p_l = (y - y1) * t1 + y * t2
    p_h = y1 * t1
    z = p_l + p_h
    over = (z > 1024.0) | ((z == 1024.0) & (p_l + _OVT > z - p_h))
    under = (z < -1075.0) | ((z == -1075.0) & (p_l <= z - p_h))
    ok = np.isfinite(z) & ~over & ~under
    out = s * _pow_exp2(np.where(ok, p_h, 0.0), np.where(ok, p_l, 0.0), np.where(ok, z, 0.0))

    def put(mask, value):
        nonlocal out
        if mask.any():
            out = np.where(mask, value() if callable(value) else value, out)

    put(over, lambda: s * np.inf)
    put(under, lambda: s * 0.0)
    if big_y.any():   # |y| > 2**31 and x not within 2**-20 of 1, and |y| > 2**64: overflow or underflow outright
        put(big_y & (ix < 0x3FEFFFFF), lambda: np.where(y < 0.0, s * np.inf, s * 0.0))
        put(big_y & (ix > 0x3FF00000), lambda: np.where(y > 0.0, s * np.inf, s * 0.0))
        huge_y = iy > 0x43F00000
        put(huge_y & (ix <= 0x3FEFFFFF), lambda: np.where(y < 0.0, np.inf, 0.0))
        put(huge_y & (ix >= 0x3FF00000), lambda: np.where(y > 0.0, np.inf, 0.0))
    put(neg_x & ~integral, np.nan)                               # (x < 0) ** (not an integer)

    def special_x():                                             # x = +-0, +-inf, +-1
        zx = np.where(hy < 0, 1.0 / ax, ax)
        return np.where(neg_x, np.where((ix == 0x3FF00000) & ~integral, np.nan, np.where(odd, -zx, zx)), zx)

    put((lx == 0) & ((ix == 0x7FF00000) | (ix == 0) | (ix == 0x3FF00000)), special_x)
    # y = +-inf, +-1, 2, 0.5
    put(np.isinf(y), lambda: np.where(ax == 1.0, 1.0, np.where(ax > 1.0, np.where(y > 0.0, np.inf, 0.0),
                                                                np.where(y < 0.0, np.inf, 0.0))))
    put(y == 2.0, lambda: x * x)
    put(y == -1.0, lambda: 1.0 / x)
    put(y == 1.0, x)
    put((y == 0.5) & ~neg_x, lambda: np.sqrt(ax))
    put(np.isnan(x) | np.isnan(y), np.nan)
    put((x == 1.0) | (y == 0.0), 1.0)
    return out


def _s_words(x: float) -> tuple[int, int]:
    lo, hi = struct.unpack("<Ii", struct.pack("<d", x))
    return hi, lo


def _s_from_words(hi: int, lo: int = 0) -> float:
    return struct.unpack("<d", struct.pack("<II", lo, hi & 0xFFFFFFFF))[0]


def _s_pow(x: float, y: float) -> float:
    """`_pow` of two floats: fdlibm's __ieee754_pow as it is written, early returns and all."""
    if y == 0.0 or x == 1.0:
        return 1.0
    if x != x or y != y:
        return math.nan
    ay = abs(y)
    integral = ay >= _TWO53 or float(round(y)) == y if ay != _INF else True
    odd = integral and ay < _TWO53 and int(y) & 1 == 1
    if ay == _INF:
        ax = abs(x)
        if ax == 1.0:
            return 1.0
        if ax > 1.0:
            return _INF if y > 0.0 else 0.0
        return _INF if y < 0.0 else 0.0
    if y == 1.0:
        return x
    if y == -1.0:
        return 1.0 / x if x != 0.0 else math.copysign(_INF, x)
    if y == 2.0:
        return x * x
    hx, lx = _s_words(x)
    if y == 0.5 and hx >= 0:
        return math.sqrt(x)
    ax = abs(x)
    ix = hx & 0x7FFFFFFF
    if ax == _INF or ax == 0.0 or ax == 1.0:
        z = (1.0 / ax if ax != 0.0 else _INF) if y < 0.0 else ax
        if hx < 0:
            if ax == 1.0 and not integral:
                return math.nan
            if odd:
                z = -z
        return z
    if hx < 0 and not integral:
        return math.nan
    s = -1.0 if hx < 0 and odd else 1.0
    iy = _s_words(y)[0] & 0x7FFFFFFF
    if iy > 0x41E00000:
        if iy > 0x43F00000:
            if ix <= 0x3FEFFFFF:
                return _INF if y < 0.0 else 0.0
            return _INF if y > 0.0 else 0.0
        if ix < 0x3FEFFFFF:
            return s * _INF if y < 0.0 else s * 0.0
        if ix > 0x3FF00000:
            return s * _INF if y > 0.0 else s * 0.0
        t1, t2 = _pow_log2_near_one(ax - 1.0, _s_high_word)
    else:
        n = 0
        if ix < 0x00100000:
            ax = ax * _TWO53
            n = -53
            ix = _s_words(ax)[0]
        n = n + (ix >> 20) - 0x3FF
        j = ix & 0x000FFFFF
        ix = j | 0x3FF00000
        if j <= 0x3988E:
            k = 0
        elif j < 0xBB67A:
            k = 1
        else:
            k = 0
            n = n + 1
            ix = ix - 0x00100000
        ax = _s_from_words(ix, _s_words(ax)[1])
        bp = _BP[k]
        u = ax - bp
        v = 1.0 / (ax + bp)
        ss = u * v
        s_h = _s_high_word(ss)
        t_h = _s_from_words(((ix >> 1) | 0x20000000) + 0x00080000 + (k << 18))
        t_l = ax - (t_h - bp)
        s_l = v * ((u - s_h * t_h) - s_h * t_l)
        s2 = ss * ss
        r = s2 * s2 * (_L[0] + s2 * (_L[1] + s2 * (_L[2] + s2 * (_L[3] + s2 * (_L[4] + s2 * _L[5])))))
        r = r + s_l * (s_h + ss)
        s2 = s_h * s_h
        t_h = _s_high_word(3.0 + s2 + r)
        t_l = r - ((t_h - 3.0) - s2)
        u = s_h * t_h
        v = s_l * t_h + t_l * ss
        p_h = _s_high_word(u + v)
        p_l = v - (p_h - u)
        z_h = _CP_H * p_h
        z_l = _CP_L * p_h + p_l * _CP + _DP_L[k]
        t = float(n)
        t1 = _s_high_word(((z_h + z_l) + _DP_H[k]) + t)
        t2 = z_l - (((t1 - t) - _DP_H[k]) - z_h)
    y1 = _s_high_word(y)
    p_l = (y - y1) * t1 + y * t2
    p_h = y1 * t1
    z = p_l + p_h
    if z > 1024.0 or (z == 1024.0 and p_l + _OVT > z - p_h):
        return s * _INF
    if z < -1075.0 or (z == -1075.0 and p_l <= z - p_h):
        return s * 0.0
    j = _s_words(z)[0]
    i = j & 0x7FFFFFFF
    n = 0
    if i > 0x3FE00000:
        k = (i >> 20) - 0x3FF
        nn = j + (0x00100000 >> (k + 1))
        k = ((nn & 0x7FFFFFFF) >> 20) - 0x3FF
        t = _s_from_words(nn & ~(0x000FFFFF >> k))
        n = ((nn & 0x000FFFFF) | 0x00100000) >> (20 - k)
        if j < 0:
            n = -n
        p_h = p_h - t
    t = _s_high_word(p_l + p_h)
    u = t * _LG2_H
    v = (p_l - (t - p_h)) * _LN2 + t * _LG2_L
    z = u + v
    w = v - (z - u)
    t = z * z
    t1 = z - t * (_P[0] + t * (_P[1] + t * (_P[2] + t * (_P[3] + t * _P[4]))))
    r = (z * t1) / (t1 - 2.0) - (w + z * w)
    z = 1.0 - (r - z)
    return s * math.ldexp(z, n)


def power(x, y):
    """x ** y as C99's pow (Annex F.10.4.4 for zeros, infinities, NaN and negative x), by fdlibm's e_pow.c:
    within 1 ulp (see the module docstring), exact for integer powers of integers that fit a double."""
    if isinstance(x, float) and isinstance(y, float):
        return _s_pow(float(x), float(y))
    xa, sx = _arr(x)
    ya, sy = _arr(y)
    xb, yb = np.broadcast_arrays(np.atleast_1d(xa), np.atleast_1d(ya))
    shape = np.broadcast_shapes(xa.shape, ya.shape)
    with np.errstate(all="ignore"):
        out = _pow(xb.reshape(-1), yb.reshape(-1))
    return _out(out.reshape(shape), sx and sy)


# --- 2**x (the film exposure from its EV) -----------------------------------------------------------

_SPLIT = 134217729.0                                  # 2**27 + 1: Veltkamp's split of a double into two halves
_LN2_LO2 = 2.3190468138462996e-17                    # ln 2 - _LN2 (the double's own error)
_LN2_H, _LN2_L = 6.931471824645996094e-01, -1.904654323148236e-09   # _LN2 = _LN2_H + _LN2_L, 26 bits each


def exp2(x):
    """2 ** x. An integral x is exact (ldexp: 2**-1074 .. 2**1023, 0 below, inf above); otherwise
    x = k + f with k = rint(x) and |f| <= 1/2 (exact), and 2**f = exp(f ln 2) by fdlibm's exp kernel
    on f ln 2 carried as a double-double (Dekker's product of f and ln 2's two doubles, no FMA), so
    the one rounding error is the kernel's: within 1 ulp (tests/core/test_fixedmath.py checks against
    2**x to 60 digits). C99's special values: exp2(nan) = nan, exp2(inf) = inf, exp2(-inf) = 0."""
    a, scalar = _arr(x)
    x1 = np.atleast_1d(a)
    with np.errstate(all="ignore"):
        finite = np.abs(x1) <= 1100.0                  # beyond, 2**x is 0 or inf (and nan stays nan)
        k = np.where(finite, np.rint(x1), 0.0)
        f = np.where(finite, x1 - k, 0.0)              # exact (Sterbenz), |f| <= 1/2
        # f ln 2 = hi + e exactly up to ln 2's own error: hi = f * _LN2 rounded, e its remainder (Dekker)
        hi = f * _LN2
        c = _SPLIT * f
        f_h = c - (c - f)
        f_l = f - f_h
        e = ((f_h * _LN2_H - hi) + f_h * _LN2_L + f_l * _LN2_H) + f_l * _LN2_L
        lo = -(e + f * _LN2_LO2)                       # fdlibm's convention: the argument is hi - lo
        r = hi - lo
        t = r * r
        cc = r - t * (_P[0] + t * (_P[1] + t * (_P[2] + t * (_P[3] + t * _P[4]))))
        y = 1.0 - ((lo - (r * cc) / (2.0 - cc)) - hi)
        y = np.where(f == 0.0, 1.0, y)
        out = np.ldexp(y, k.astype(np.int64))         # one rounding, only for a subnormal result
        out = np.where(finite, out, np.where(np.isnan(x1), np.nan, np.where(x1 > 0.0, np.inf, 0.0)))
    return _out(out.reshape(a.shape), scalar)


# --- the inverse of a 4x4 transform (no LAPACK) ----------------------------------------------------

def inv4(m) -> np.ndarray:
    """Inverse of a 4x4 matrix by cofactors, each entry a fixed sum of products divided by the
    determinant (no LAPACK, whose LU kernels round by CPU). An affine matrix (last row exactly
    0, 0, 0, 1: every transform USD composes) inverts as [[A^-1, -A^-1 t], [0, 0, 0, 1]], its last row
    exact; a singular one gives inf or nan entries (numpy's inv raises instead)."""
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (4, 4):
        raise ValueError(f"inv4: a 4x4 matrix, got shape {a.shape}")
    (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23), (a30, a31, a32, a33) = a.tolist()
    with np.errstate(all="ignore"):
        if (a30, a31, a32, a33) == (0.0, 0.0, 0.0, 1.0):
            c00, c01, c02 = a11 * a22 - a12 * a21, a12 * a20 - a10 * a22, a10 * a21 - a11 * a20
            c10, c11, c12 = a02 * a21 - a01 * a22, a00 * a22 - a02 * a20, a01 * a20 - a00 * a21
            c20, c21, c22 = a01 * a12 - a02 * a11, a02 * a10 - a00 * a12, a00 * a11 - a01 * a10
            det = np.float64(a00 * c00 + a01 * c01 + a02 * c02)
            r = [[c00 / det, c10 / det, c20 / det], [c01 / det, c11 / det, c21 / det],
                 [c02 / det, c12 / det, c22 / det]]
            t = [-(r[i][0] * a03 + r[i][1] * a13 + r[i][2] * a23) for i in range(3)]
            return np.array([r[0] + [t[0]], r[1] + [t[1]], r[2] + [t[2]], [0.0, 0.0, 0.0, 1.0]])
        s0, s1, s2 = a00 * a11 - a10 * a01, a00 * a12 - a10 * a02, a00 * a13 - a10 * a03
        s3, s4, s5 = a01 * a12 - a11 * a02, a01 * a13 - a11 * a03, a02 * a13 - a12 * a03
        c5, c4, c3 = a22 * a33 - a32 * a23, a21 * a33 - a31 * a23, a21 * a32 - a31 * a22
        c2, c1, c0 = a20 * a33 - a30 * a23, a20 * a32 - a30 * a22, a20 * a31 - a30 * a21
        det = np.float64(s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0)
        adj = [[a11 * c5 - a12 * c4 + a13 * c3, -a01 * c5 + a02 * c4 - a03 * c3,
                a31 * s5 - a32 * s4 + a33 * s3, -a21 * s5 + a22 * s4 - a23 * s3],
               [-a10 * c5 + a12 * c2 - a13 * c1, a00 * c5 - a02 * c2 + a03 * c1,
                -a30 * s5 + a32 * s2 - a33 * s1, a20 * s5 - a22 * s2 + a23 * s1],
               [a10 * c4 - a11 * c2 + a13 * c0, -a00 * c4 + a01 * c2 - a03 * c0,
                a30 * s4 - a31 * s2 + a33 * s0, -a20 * s4 + a21 * s2 - a23 * s0],
               [-a10 * c3 + a11 * c1 - a12 * c0, a00 * c3 - a01 * c1 + a02 * c0,
                -a30 * s3 + a31 * s1 - a32 * s0, a20 * s3 - a21 * s1 + a22 * s0]]
        return np.array(adj, dtype=np.float64) / det
