"""Eclipse geometry, pure numpy and vectorised: disc overlaps, eclipse states, lit fractions.

Eclipses (docs/physics.md section 7)
    Two-cone test per shadowing body (Moon, Earth) with angles from ``atan2(|a x b|, a . b)``.
    The lit fraction is 1 - (exact area of overlap of the Sun's and the body's discs, taken as
    flat circles with the angular radii) / (area of the Sun's disc); umbra gives exactly 0, lit
    exactly 1. Flat-disc vs spherical-cap geometry changes the lit fraction by < 1e-4 even at
    perilune (Moon 32 deg in radius). If Moon and Earth both cover part of the Sun at once (rare:
    a lunar eclipse while the station is behind the Moon), the uncovered area of the Sun's disc
    is computed exactly (Green's theorem over the boundary arcs); ``eclipse_body`` and ``eclipse_state``
    then follow the body that alone would leave less light.

"""

from __future__ import annotations

import functools
import math

import numpy as np

from allo_usd.core.constants import MOON_RADIUS_M, SUN_RADIUS_M
from allo_usd.core.errors import SkyInputError
from allo_usd.core.geometry import angle_between, rowdot, unit_rows
from allo_usd.sky.ephemeris import finite_number
from allo_usd.core import fixedmath as fm

SHADOW_BODIES: tuple[str, ...] = ("moon", "earth")
ECLIPSE_STATES: tuple[str, ...] = ("lit", "penumbra", "annular", "umbra")  # index = state code
LIT, PENUMBRA, ANNULAR, UMBRA = 0, 1, 2, 3


# ---------------------------------------------------------------------------------------------
# Eclipse geometry (pure numpy, vectorised)


def _x_minus_sin_x(x: np.ndarray) -> np.ndarray:
    """x - sin(x) without cancellation for small x (Taylor series below 0.5)."""
    x = np.asarray(x, dtype=np.float64)
    x2 = x * x
    series = x * x2 * (1 / 6 - x2 * (1 / 120 - x2 * (1 / 5040 - x2 * (1 / 362880 - x2 * (
        1 / 39916800 - x2 * (1 / 6227020800))))))
    return np.where(np.abs(x) < 0.5, series, x - fm.sin(x))


def _check_finite_nonneg(name: str, v: np.ndarray) -> None:
    if not np.all(np.isfinite(v)):
        raise SkyInputError(f"{name} contains NaN or inf")
    if np.any(v < 0.0):
        raise SkyInputError(f"{name} must be >= 0")


def disc_overlap_area(r1, r2, d) -> np.ndarray:
    """Exact area shared by two flat discs of radii r1, r2 whose centres are d apart.

    Vectorised and broadcasting. Handles disjoint (0), containment (pi min(r)^2) and the lens
    in between, which is computed from chord half-angles atan2(4K, ...) (K: triangle area by
    the cancellation-free Heron formula) and segments r^2/2 (phi - sin phi), so it stays
    accurate when one disc is 100x the other.
    """
    r1, r2, d = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (r1, r2, d)))
    for name, v in (("r1", r1), ("r2", r2), ("d", d)):
        _check_finite_nonneg(name, v)
    rs, rl = np.minimum(r1, r2), np.maximum(r1, r2)
    contain = d <= rl - rs
    apart = d >= r1 + r2
    lens = ~(contain | apart)
    out = np.where(contain, np.pi * rs * rs, 0.0)
    if np.any(lens):
        a1, a2, dd = r1[lens], r2[lens], d[lens]
        sides = np.sort(np.stack([dd, a1, a2]), axis=0)  # ascending: c <= b <= a
        c, b, a = sides[0], sides[1], sides[2]
        # 4 * triangle area; a product of square roots cannot underflow like sqrt(product)
        four_k = (np.sqrt(a + (b + c)) * np.sqrt(np.maximum(c - (a - b), 0.0))
                  * np.sqrt(c + (a - b)) * np.sqrt(np.maximum(a + (b - c), 0.0)))
        half1 = fm.arctan2(four_k, (dd - a2) * (dd + a2) + a1 * a1)  # chord half-angle at centre 1
        half2 = fm.arctan2(four_k, (dd - a1) * (dd + a1) + a2 * a2)
        area = 0.5 * a1 * a1 * _x_minus_sin_x(2.0 * half1) + 0.5 * a2 * a2 * _x_minus_sin_x(2.0 * half2)
        out[lens] = np.minimum(area, np.pi * np.square(rs[lens]))
    return out


def classify_eclipse(theta_sun, theta_body, separation, body_nearer=True) -> tuple[np.ndarray, np.ndarray]:
    """docs/physics.md section 7 cone test on angular radii and centre separation (radians).

    Returns (state code array: 0 lit, 1 penumbra, 2 annular, 3 umbra; lit fraction in [0, 1]).
    Only a body nearer than the Sun (``body_nearer``) can shadow. Umbra gives exactly 0 and lit
    exactly 1; in between the lit fraction is 1 - overlap / (pi theta_sun^2).
    """
    ts_, tb, sep = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (theta_sun, theta_body, separation)))
    for name, v in (("theta_sun", ts_), ("theta_body", tb), ("separation", sep)):
        _check_finite_nonneg(name, v)
    if np.any(ts_ <= 0.0):
        raise SkyInputError("theta_sun must be > 0")
    nearer = np.broadcast_to(np.asarray(body_nearer, dtype=bool), ts_.shape)
    code = np.where(sep < ts_ + tb, PENUMBRA, LIT)
    code = np.where(sep < ts_ - tb, ANNULAR, code)
    code = np.where(sep < tb - ts_, UMBRA, code)
    code = np.where(nearer, code, LIT).astype(np.int8)
    lit = 1.0 - disc_overlap_area(ts_, tb, sep) / (np.pi * ts_ * ts_)
    lit = np.clip(lit, 0.0, 1.0)
    lit = np.where(code == LIT, 1.0, np.where(code == UMBRA, 0.0, lit))
    return code, lit


def eclipse_from_vectors(u_sun, u_body, sun_radius_m: float = SUN_RADIUS_M, body_radius_m: float = MOON_RADIUS_M):
    """Cone test from vectors station->Sun and station->body (..., 3), any common frame.

    Returns (state code, lit fraction, theta_sun, theta_body, separation).
    """
    u_sun = np.asarray(u_sun, dtype=np.float64)
    u_body = np.asarray(u_body, dtype=np.float64)
    if not (np.all(np.isfinite(u_sun)) and np.all(np.isfinite(u_body))):
        raise SkyInputError("eclipse vectors contain NaN or inf")
    ds = fm.norm(u_sun, axis=-1)
    db = fm.norm(u_body, axis=-1)
    if np.any(ds <= sun_radius_m) or np.any(db <= body_radius_m):
        raise SkyInputError("observer is inside the Sun or the shadowing body (distance <= radius)")
    theta_s = fm.arcsin(sun_radius_m / ds)
    theta_b = fm.arcsin(body_radius_m / db)
    sep = angle_between(u_sun, u_body)
    code, lit = classify_eclipse(theta_s, theta_b, sep, db < ds)
    return code, lit, theta_s, theta_b, sep


QUADRATURE_POINTS = 256


@functools.lru_cache(maxsize=4)
def _sunflower(n: int) -> np.ndarray:
    """n points of equal area over the unit disc (Vogel's spiral), (n, 2): a deterministic quadrature."""
    k = np.arange(n, dtype=np.float64) + 0.5
    r = np.sqrt(k / n)
    phi = k * (np.pi * (3.0 - math.sqrt(5.0)))
    q = np.stack([r * fm.cos(phi), r * fm.sin(phi)], axis=1)
    q.flags.writeable = False
    return q


def body_lit_fraction(sun, body, body_radius_m: float, occluder, occluder_radius_m: float,
                      points: int = QUADRATURE_POINTS) -> np.ndarray:
    """Share of the sunlight a body intercepts that reaches it past an occluding body, per epoch.

    ``sun``, ``body``, ``occluder``: centres (N, 3) or (3,), metres, any common frame. The body's
    cross-section as the Sun sees it is sampled with ``points`` equal-area points, each lifted
    onto the sunlit hemisphere; the result is the mean of the two-disc lit fraction of the Sun
    seen from each point (:func:`eclipse_from_vectors`), in [0, 1]: 1 exactly where no point of
    the body can see the occluder overlap the Sun (tested at the centre with a strict bound, so
    those epochs skip the quadrature), 0 in total eclipse.
    """
    sun, body, occ = (np.atleast_2d(np.asarray(x, dtype=np.float64)) for x in (sun, body, occluder))
    if not (np.isfinite(sun).all() and np.isfinite(body).all() and np.isfinite(occ).all()):
        raise SkyInputError("body_lit_fraction: positions contain NaN or inf")
    r_b, r_o = finite_number("body_radius_m", body_radius_m), finite_number("occluder_radius_m", occluder_radius_m)
    if r_b <= 0.0 or r_o <= 0.0:
        raise SkyInputError("body_lit_fraction: radii must be positive")
    u_s, u_o = sun - body, occ - body
    d_s, d_o = fm.norm(u_s, axis=-1), fm.norm(u_o, axis=-1)
    if np.any(d_s <= SUN_RADIUS_M + r_b) or np.any(d_o <= r_o + r_b):
        raise SkyInputError("body_lit_fraction: the bodies overlap the Sun or each other")
    # From any point within r_b of the centre the Sun and the occluder move by at most asin(r_b/d)
    # and grow to at most asin(R/(d - r_b)); if even that cannot make them overlap, all is lit.
    reach = (fm.arcsin(SUN_RADIUS_M / (d_s - r_b)) + fm.arcsin(r_b / d_s)
             + fm.arcsin(r_o / (d_o - r_b)) + fm.arcsin(r_b / d_o))
    out = np.ones(d_s.shape)
    cand = np.flatnonzero((angle_between(u_s, u_o) < reach) & (d_o < d_s))
    if cand.size:
        s_hat = unit_rows(u_s[cand])
        helper = np.where(np.abs(s_hat[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
        e1 = unit_rows(np.cross(s_hat, helper))
        e2 = np.cross(s_hat, e1)
        if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 1:
            raise SkyInputError(f"points must be a positive integer, got {points!r}")
        q = _sunflower(int(points))
        up = np.sqrt(np.maximum(1.0 - fm.dot(q, q), 0.0))
        offset = (q[None, :, 0, None] * e1[:, None, :] + q[None, :, 1, None] * e2[:, None, :]
                  + up[None, :, None] * s_hat[:, None, :])
        p = body[cand, None, :] + r_b * offset  # (m, points, 3) on the sunlit face
        _, lit, *_ = eclipse_from_vectors(sun[cand, None, :] - p, occ[cand, None, :] - p, SUN_RADIUS_M, r_o)
        out[cand] = lit.mean(axis=1)
    return out


def _arc_term(cx: float, cy: float, r: float, a: float, b: float) -> float:
    """Green's-theorem integral 1/2 (x dy - y dx) along a circle arc, counter-clockwise a -> b."""
    return 0.5 * (r * cx * (fm.sin(b) - fm.sin(a)) - r * cy * (fm.cos(b) - fm.cos(a)) + r * r * (b - a))


def _sun_minus_discs_area(r0: float, discs: list[tuple[float, float, float]]) -> float:
    """Exact area of the disc (0, 0, r0) minus the union of ``discs`` [(cx, cy, r)].

    Boundary of the region = arcs of each circle that lie on it (found from the pairwise
    intersection angles and a midpoint test), summed with Green's theorem; occluder arcs are
    traversed clockwise.
    """
    circles = [(0.0, 0.0, r0)]
    for disc in discs:  # coincident occluders would be counted twice on their shared rim
        if disc not in circles[1:]:
            circles.append(disc)

    def inside(k: int, x: float, y: float) -> bool:
        cx, cy, r = circles[k]
        dx, dy = x - cx, y - cy
        return dx * dx + dy * dy < r * r

    def on_boundary(i: int, x: float, y: float) -> bool:
        if i != 0 and not inside(0, x, y):
            return False
        return not any(inside(k, x, y) for k in range(1, len(circles)) if k != i)

    total = 0.0
    for i, (cx, cy, r) in enumerate(circles):
        angles = []
        for j, (dx_, dy_, rj) in enumerate(circles):
            if j == i:
                continue
            vx, vy = dx_ - cx, dy_ - cy
            d = fm.hypot(vx, vy)
            if d == 0.0 or d >= r + rj or d <= abs(r - rj):
                continue
            base = fm.arctan2(vy, vx)
            half = fm.arccos(max(-1.0, min(1.0, (d * d + r * r - rj * rj) / (2.0 * d * r))))
            angles += [base - half, base + half]
        sign = 1.0 if i == 0 else -1.0
        if not angles:
            if on_boundary(i, cx + r, cy):
                total += sign * math.pi * r * r
            continue
        angles = sorted(a % (2.0 * math.pi) for a in angles)
        angles.append(angles[0] + 2.0 * math.pi)
        for a, b in zip(angles[:-1], angles[1:]):
            if b - a <= 0.0:
                continue
            m = 0.5 * (a + b)
            if on_boundary(i, cx + r * fm.cos(m), cy + r * fm.sin(m)):
                total += sign * _arc_term(cx, cy, r, a, b)
    return max(0.0, min(total, math.pi * r0 * r0))


def lit_two_occluders(u_sun, u_bodies, theta_sun, theta_bodies, seps) -> np.ndarray:
    """Lit fraction of the Sun's disc behind two occulting discs (rare: Moon and Earth at once).

    Disc centres are placed in the azimuthal-equidistant plane about the Sun's centre (the
    separation is preserved exactly) and the uncovered area is computed exactly there.
    """
    s = unit_rows(np.asarray(u_sun, dtype=np.float64))
    helper = np.where(np.abs(s[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = unit_rows(np.cross(s, helper))
    e2 = np.cross(s, e1)
    centres = []
    for u, sep in zip(u_bodies, seps):
        b = unit_rows(np.asarray(u, dtype=np.float64))
        w = b - s * rowdot(b, s)[:, None]
        wn = fm.norm(w, axis=1)
        wn = np.where(wn > 0.0, wn, 1.0)
        centres.append(np.stack([rowdot(w, e1), rowdot(w, e2)], axis=1) * (np.asarray(sep) / wn)[:, None])
    out = np.empty(s.shape[0])
    for m in range(s.shape[0]):
        r0 = float(theta_sun[m])
        discs = [(float(c[m, 0]), float(c[m, 1]), float(tb[m])) for c, tb in zip(centres, theta_bodies)]
        out[m] = _sun_minus_discs_area(r0, discs) / (math.pi * r0 * r0)
    return np.clip(out, 0.0, 1.0)

