"""Property tests of the float64 rotation helpers (quaternions, look-at frames, aiming a light), and
the shorter routes in allo_usd.core.geometry (the identity check, check_finite, matrix_to_quat on
Python floats) giving the decisions and bits of their plain forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from allo_usd.core import geometry
from allo_usd.core.errors import AlloError
from allo_usd.core.geometry import look_at, matrix_to_quat, quat_to_matrix, rotation_towards

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
quat = st.tuples(finite, finite, finite, finite).map(np.array).filter(lambda q: np.linalg.norm(q) > 1e-3)


def unit(v) -> np.ndarray:
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


def assert_rotation(r: np.ndarray, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=atol)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=atol)


# Directions close to and exactly on the vertical, where a look-at frame is most fragile.
near_vertical = st.builds(lambda s, e, a: np.array([e * math.cos(a), e * math.sin(a), s]),
                          st.sampled_from([1.0, -1.0]), st.floats(0.0, 1e-2), st.floats(0.0, 2 * math.pi))
direction = st.one_of(vec3.filter(lambda v: np.linalg.norm(v) > 1e-6), near_vertical,
                      st.sampled_from([np.array(v, float) for v in
                                       [(0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]]))


@settings(max_examples=400, deadline=None)
@given(quat)
@pytest.mark.slow
def test_quaternion_matrix_round_trip(q):
    r = quat_to_matrix(q)
    assert_rotation(r)
    back = matrix_to_quat(r)
    assert np.linalg.norm(back) == pytest.approx(1.0, abs=1e-14)
    assert back[0] >= 0.0
    expected = unit(q) * (1.0 if q[0] >= 0 else -1.0)  # q and -q are the same rotation
    if abs(expected[0]) < 1e-9:  # w = 0: both signs have w >= 0; compare the rotations instead
        np.testing.assert_allclose(quat_to_matrix(back), r, atol=1e-12)
    else:
        np.testing.assert_allclose(back, expected, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(back), r, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.sampled_from([(1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1),
                        (math.sqrt(0.5), 0, math.sqrt(0.5), 0), (0, math.sqrt(0.5), math.sqrt(0.5), 0)]))
def test_half_turns_and_identity_round_trip(q):  # every branch of Shepperd's method
    r = quat_to_matrix(np.array(q, float))
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-15)


@settings(max_examples=400, deadline=None)
@given(vec3, direction, st.floats(0.1, 1e6))
@pytest.mark.slow
def test_look_at_is_orthonormal_and_points_at_the_target(position, view, distance):
    target = position + unit(view) * distance
    assume(np.linalg.norm(target - position) > 1e-3 * distance)  # not lost to float64 cancellation
    r = look_at(position, target)
    assert_rotation(r, atol=1e-12)
    forward = -r[:, 2]  # cameras look down local -Z
    true = unit(target - position)
    assert math.acos(min(1.0, float(forward @ true))) < 1e-7
    if abs(true[2]) < 0.999:  # +Y up: the camera's up lies in the plane of the view and world +Z
        assert r[2, 1] > 0.0
        assert abs(r[2, 0]) < 1e-9  # no roll: camera x stays horizontal


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_look_at_exactly_vertical(sign):
    p = np.array([12.0, 3.0, 4.0])
    r = look_at(p, p + [0.0, 0.0, sign * 10.0])
    assert_rotation(r)
    np.testing.assert_allclose(-r[:, 2], [0.0, 0.0, sign], atol=1e-15)


@settings(max_examples=400, deadline=None)
@given(direction)
@pytest.mark.slow
def test_rotation_towards_maps_z_to_the_direction(d):
    r = rotation_towards(d)
    assert_rotation(r)
    np.testing.assert_allclose(r @ [0.0, 0.0, 1.0], unit(d), atol=1e-14)
    q = matrix_to_quat(r)  # what the author writes as xformOp:orient
    np.testing.assert_allclose(quat_to_matrix(q) @ [0.0, 0.0, 1.0], unit(d), atol=1e-14)


@pytest.mark.parametrize("call", [
    lambda: matrix_to_quat(np.full((3, 3), np.nan)),
    lambda: quat_to_matrix([np.nan, 0, 0, 1]),
    lambda: look_at([0, 0, np.nan], [1, 0, 0]),
    lambda: look_at([0, 0, 0], [np.inf, 0, 0]),
    lambda: rotation_towards([np.nan, 0, 1]),
])
def test_nan_input_raises_the_package_error(call):
    with pytest.raises(AlloError, match="NaN or infinity"):
        call()


@pytest.mark.parametrize("call, match", [
    (lambda: matrix_to_quat(np.diag([1.0, 1.0, -1.0])), "det"),
    (lambda: matrix_to_quat(2 * np.eye(3)), "orthonormal"),
    (lambda: look_at([1, 2, 3], [1, 2, 3]), "target"),
])
def test_degenerate_input_raises_the_package_error(call, match):
    with pytest.raises(AlloError, match=match):
        call()


@pytest.mark.parametrize("call", [
    lambda: quat_to_matrix([0.0, 0.0, 0.0, 0.0]),
    lambda: rotation_towards([0.0, 0.0, 0.0]),
    lambda: look_at([0, 0, 0], [1, 0, 0], up=(0.0, 0.0, 0.0)),
])
def test_zero_vectors_raise_instead_of_returning_nan(call):
    with pytest.raises(AlloError, match="zero length"):
        call()


@pytest.mark.parametrize("scale", [1e-200, 1e200])
def test_tiny_and_huge_directions_keep_their_direction(scale):
    d = np.array([0.3, -0.5, 0.8]) * scale
    np.testing.assert_allclose(rotation_towards(d)[:, 2], unit([0.3, -0.5, 0.8]), atol=1e-15)
    np.testing.assert_allclose(quat_to_matrix(np.array([1.0, 0, 0, 0]) * scale), np.eye(3), atol=1e-15)


# --- the shorter routes give the decisions and bits of their plain forms --------------------------

def _bits(a) -> bytes:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes()


@pytest.mark.slow
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
    finite = bool(np.isfinite(np.asarray(value, dtype=np.float64)).all())
    if finite:
        got = geometry.check_finite("v", value)
        want = np.asarray(value, dtype=np.float64)
        assert np.ascontiguousarray(got).tobytes() == np.ascontiguousarray(want).tobytes()
    else:
        with pytest.raises(AlloError):
            geometry.check_finite("v", value)


def reference_matrix_to_quat(r):
    """matrix_to_quat on numpy arrays (the checks included, the orthonormality product as the
    broadcast sum in index order): the form its Python-float route must equal bit for bit."""
    from allo_usd.core import fixedmath as fm

    r = geometry.check_finite("rotation matrix", r)
    rrt = r[:, 0, None] * r.T[0, None, :]
    for i in range(1, 3):
        rrt = rrt + r[:, i, None] * r.T[i, None, :]
    if abs(fm.det3(r) - 1.0) > 1e-6 or not np.allclose(rrt, np.eye(3), atol=1e-6):
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
        assert _bits(geometry.matrix_to_quat(m)) == _bits(reference_matrix_to_quat(m))
    for bad in (np.diag([1.0, 1.0, -1.0]), np.eye(3) * 1.01, np.array([[1.0, 1e-5, 0], [0, 1, 0], [0, 0, 1]])):
        with pytest.raises(AlloError, match="not orthonormal"):
            geometry.matrix_to_quat(bad)
    with pytest.raises(AlloError, match="3x3"):
        geometry.matrix_to_quat(np.eye(4))
    with pytest.raises(AlloError, match="NaN"):
        geometry.matrix_to_quat(np.full((3, 3), np.nan))
