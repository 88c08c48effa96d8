"""Sky geometry for every scene: station orbit (NRHO approximation), Sun/Earth/Moon, eclipses.

numpy + skyfield only (no pxr, no bpy), so it can be tested and benchmarked on its own.
Numbers and conventions follow ``shared/design/PHYSICS.md`` sections 1-6.

Ephemeris
    JPL DE421 from the ``skyfield-data`` package, opened offline
    (``Loader(skyfield_data.get_skyfield_data_path())``, ``load.timescale(builtin=True)``).
    Positions are **geometric** (``body.at(t)``: no light time, no aberration; the apparent
    direction differs by at most ~20 arcsec = 1e-4 rad, about 0.13 px at the centre of a
    1920-wide 25 mm / 36 mm frame). All epochs are computed in ONE vectorised skyfield call per
    body (Sun, Earth, Moon; barycentric, ICRF axes). Valid range: DE421's 1899-07-29 .. 2053-10-09
    (TDB); epochs outside raise :class:`~allo_usd.core.errors.EphemerisRangeError` before skyfield is
    asked for a position.

Station orbit (PHYSICS.md section 1)
    Ellipse (perilune/apolune radii of :class:`Orbit`) fixed in the Earth-Moon *rotating* frame
    rebuilt at each epoch: x = unit(Moon - Earth), z = unit(r x v) of the Moon about the Earth,
    y = z x x. The ellipse lies in the x-z plane with perilune along +z (over the lunar north
    pole) and apolune along -z. Timing by Kepler's equation with the mean motion forced to
    2 pi / period; after perilune the station moves toward +x (away from the Earth). The
    station is Moon + [x y z] . r_rot in ICRF axes. (The approximation puts apolune straight
    below the south pole; the real NRHO's apolune lies ~12,900 km beyond the Moon.)

Station frame (fixed convention; "LVLH-like", relative to the Moon)
    +Z = unit(station - Moon) (zenith, away from the Moon), +X = the station's velocity
    relative to the Moon in ICRF, orthogonalised against Z, +Y = Z x X. The Moon is therefore
    always toward -Z. The velocity is the analytic derivative of station - Moon: Kepler rate
    plus the rotation of the Earth-Moon frame (x from the ephemeris position and velocity; z
    from h_dot = r x a with a = the Sun's tidal acceleration, which is what turns the Moon's
    orbit normal; tests compare it with a central finite difference). Near apolune the speed
    is only ~90 m/s, so ignoring z_dot would tilt X by up to 3e-3 rad.
    ``Sky.icrf_to_station[i] @ v_icrf`` gives a vector in the station frame; its rows are the
    station X, Y, Z axes in ICRF.

Rendering placement (PHYSICS.md section 3, scheme C)
    True scale, station at the origin of the station frame: body centre = direction * distance.
    Casting the centres to float32 (Blender) moves the direction seen from a camera within 100 m
    of the origin by at most ~4e-8 rad (Sun, Earth) and the angular radius by ~1e-7 relative;
    tests hold it to 1e-5 rad and 1e-4.

Eclipses (PHYSICS.md section 6)
    Two-cone test per shadowing body (Moon, Earth) with angles from ``atan2(|a x b|, a . b)``.
    The lit fraction is 1 - (exact area of overlap of the Sun's and the body's discs, taken as
    flat circles with the angular radii) / (area of the Sun's disc); umbra gives exactly 0, lit
    exactly 1. Flat-disc vs spherical-cap geometry changes the lit fraction by < 1e-4 even at
    perilune (Moon 32 deg in radius). If Moon and Earth both cover part of the Sun at once (rare:
    a lunar eclipse while the station is behind the Moon), the uncovered area of the Sun's disc
    is computed exactly (Green's theorem over the boundary arcs); ``eclipse_body`` and ``eclipse_state``
    then follow the body that alone would leave less light.

Sunlight on the bodies (PHYSICS.md sections 5 and 6)
    The station's sun lamp carries the STATION's eclipse, so it must not light the Earth and the
    Moon (a station in the Moon's shadow still sees a sunlit Earth). Each body in
    :data:`LIT_BODIES` gets the Sun as seen from its own centre: direction body -> Sun (station
    frame), irradiance 1361 (1 AU / d_body_sun)^2, the Sun's angular radius there, and the body's
    own lit fraction with the other body as the occluder (the Moon in the Earth's shadow: a lunar
    eclipse; the Earth under the Moon's penumbra: a solar eclipse). That lit fraction is the mean
    over the body's sunlit face, as the Sun sees it, of the two-disc lit fraction at each point
    (a fixed 256-point sunflower quadrature over the cross-section, lifted onto the sphere), so a
    shadow smaller than the body dims it by the share of sunlight it takes: the total solar eclipse
    of 2030-11-25 dims the Earth by 7.5 per cent, not to black. Epochs where no point of the body can see the
    occluder near the Sun (a strict angular bound at the centre) are exactly 1 and skip the
    quadrature. One lamp lights the whole body, so a partial lunar eclipse dims the Moon evenly
    instead of drawing the umbra's edge across it.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import math
import os
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from typing import Iterable, Sequence

import numpy as np

from allo_usd.core.constants import (AU_M, EARTH_RADIUS_M, GM_SUN_M3_S2, MOON_RADIUS_M, SECONDS_PER_DAY, SOLAR_CONSTANT,
                                     SUN_RADIUS_M)
from allo_usd.core.errors import EphemerisRangeError, EpochError, SkyInputError
from allo_usd.core.geometry import angle_between, rowdot, unit_rows
from allo_usd.sky.ephemeris_range import DE421_END_UTC, DE421_START_UTC

__all__ = [
    "BODIES",
    "BODY_RADIUS_M",
    "ECLIPSE_STATES",
    "EclipseEvent",
    "LIT_BODIES",
    "Orbit",
    "Sky",
    "SkyAt",
    "body_lit_fraction",
    "body_placement",
    "body_sun_light",
    "classify_eclipse",
    "compute_sky",
    "de421_range",
    "default_epochs",
    "disc_overlap_area",
    "eclipse_events",
    "eclipse_from_vectors",
    "solve_kepler",
    "sun_light",
]

# ---------------------------------------------------------------------------------------------
# Constants (PHYSICS.md sections 2 and 5)

BODIES: tuple[str, ...] = ("sun", "earth", "moon")
BODY_RADIUS_M: dict[str, float] = {"sun": SUN_RADIUS_M, "earth": EARTH_RADIUS_M, "moon": MOON_RADIUS_M}
SHADOW_BODIES: tuple[str, ...] = ("moon", "earth")
LIT_BODIES: tuple[str, ...] = ("earth", "moon")  # bodies with a sun lamp of their own
OCCLUDER: dict[str, str] = {"earth": "moon", "moon": "earth"}  # what can shadow each lit body
ECLIPSE_STATES: tuple[str, ...] = ("lit", "penumbra", "annular", "umbra")  # index = state code
_STATE_NAMES = np.array(ECLIPSE_STATES)
_BODY_NAMES = np.array(("",) + SHADOW_BODIES)  # 0 -> '', 1 -> moon, 2 -> earth
LIT, PENUMBRA, ANNULAR, UMBRA = 0, 1, 2, 3

_EXPIRED_WARNING = r".*finals2000A\.all has expired.*"
_ISO_FMT = "%Y-%m-%dT%H:%M:%SZ"


# ---------------------------------------------------------------------------------------------
# Ephemeris (offline, cached)


@contextlib.contextmanager
def _quiet_expiry():
    """Silence skyfield-data's "finals2000A.all has expired" RuntimeWarning, here only."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_EXPIRED_WARNING, category=RuntimeWarning)
        yield


@dataclass(frozen=True)
class _Ephemeris:
    ts: object  # skyfield Timescale
    eph: object  # skyfield SpiceKernel
    sun: object
    earth: object
    moon: object
    start_tdb_jd: float
    end_tdb_jd: float
    path: str


@functools.lru_cache(maxsize=1)
def _ephemeris() -> _Ephemeris:
    """Open DE421 and the builtin timescale from skyfield-data; never touches the network."""
    with _quiet_expiry():
        import skyfield_data
        from skyfield.api import Loader

        directory = skyfield_data.get_skyfield_data_path()
        path = os.path.join(directory, "de421.bsp")
        if not os.path.isfile(path):
            raise EphemerisRangeError(
                f"DE421 is missing: expected {path} from the skyfield-data package; "
                "reinstall skyfield-data (no network download is attempted)"
            )
        load = Loader(directory, verbose=False)
        ts = load.timescale(builtin=True)
        eph = load("de421.bsp")
    atexit.register(eph.close)
    starts = [s.start_jd for s in eph.spk.segments]
    ends = [s.end_jd for s in eph.spk.segments]
    return _Ephemeris(
        ts=ts, eph=eph, sun=eph["sun"], earth=eph["earth"], moon=eph["moon"],
        start_tdb_jd=float(max(starts)), end_tdb_jd=float(min(ends)), path=path,
    )


def de421_range() -> tuple[str, str]:
    """The range DE421 covers, as ISO UTC strings (the file's limits are 00:00 TDB)."""
    return DE421_START_UTC, DE421_END_UTC


def _range_text() -> str:
    lo, hi = de421_range()
    return f"DE421 covers 1899-07-29T00:00 TDB to 2053-10-09T00:00 TDB ({lo} to {hi} UTC)"


# ---------------------------------------------------------------------------------------------
# Epochs


def _as_utc(value: object, what: str = "epoch") -> datetime:
    """One epoch as an aware UTC datetime. Naive datetimes are refused, never guessed."""
    if isinstance(value, str):
        try:
            parsed = datetime.fromisoformat(value)
        except ValueError as exc:
            raise EpochError(
                f"{what} {value!r} is not an ISO 8601 date-time; write e.g. '2030-01-01T00:00:00Z'"
            ) from exc
        value = parsed
    if not isinstance(value, datetime):
        raise EpochError(
            f"{what} must be a timezone-aware datetime in UTC, got {type(value).__name__} {value!r}; "
            "use datetime(2030, 1, 1, tzinfo=timezone.utc)"
        )
    if value.tzinfo is None or value.tzinfo.utcoffset(value) is None:
        raise EpochError(
            f"{what} {value.isoformat()} is naive (no timezone); pass a timezone-aware UTC datetime, "
            "e.g. datetime(2030, 1, 1, tzinfo=timezone.utc) or '2030-01-01T00:00:00Z'"
        )
    return value.astimezone(timezone.utc)


def _iso(dt: datetime) -> str:
    return dt.strftime(_ISO_FMT)


def default_epochs(year: int = 2030, days: int = 365) -> list[datetime]:
    """``days`` consecutive days at 00:00 UTC from 1 January of ``year`` (aware datetimes)."""
    if isinstance(year, bool) or not isinstance(year, (int, np.integer)):
        raise EpochError(f"year must be an integer, got {year!r}")
    if isinstance(days, bool) or not isinstance(days, (int, np.integer)) or days < 1:
        raise EpochError(f"days must be a positive integer, got {days!r}")
    start = datetime(int(year), 1, 1, tzinfo=timezone.utc)
    return [start + timedelta(days=k) for k in range(int(days))]


def _time_from_utc(dts: Sequence[datetime], offsets_s: np.ndarray | None = None):
    """Vectorised skyfield Time from aware UTC datetimes (plus optional second offsets)."""
    e = _ephemeris()
    n = len(dts)
    y = np.fromiter((d.year for d in dts), dtype=np.int64, count=n)
    mo = np.fromiter((d.month for d in dts), dtype=np.int64, count=n)
    da = np.fromiter((d.day for d in dts), dtype=np.int64, count=n)
    h = np.fromiter((d.hour for d in dts), dtype=np.int64, count=n)
    mi = np.fromiter((d.minute for d in dts), dtype=np.int64, count=n)
    s = np.fromiter((d.second + d.microsecond * 1e-6 for d in dts), dtype=np.float64, count=n)
    if offsets_s is not None:
        s = s + offsets_s
    with _quiet_expiry():
        return e.ts.utc(y, mo, da, h, mi, s)


def _time_from_start(start: datetime, offsets_s: np.ndarray):
    """Vectorised skyfield Time at ``start`` + offsets (seconds, UTC; skyfield normalises)."""
    e = _ephemeris()
    sec = start.second + start.microsecond * 1e-6 + np.asarray(offsets_s, dtype=np.float64)
    with _quiet_expiry():
        return e.ts.utc(start.year, start.month, start.day, start.hour, start.minute, sec)


def _check_range(t, labels: Sequence[str] | None) -> None:
    """Raise EphemerisRangeError (with the valid range) before skyfield touches DE421."""
    e = _ephemeris()
    whole = np.atleast_1d(t.whole)
    frac = np.atleast_1d(t.tdb_fraction)
    bad = ((whole - e.start_tdb_jd) + frac < 0.0) | ((whole - e.end_tdb_jd) + frac > 0.0)
    if bad.any():
        idx = np.flatnonzero(bad)
        if labels is None:
            with _quiet_expiry():
                shown = [t[int(i)].utc_strftime(_ISO_FMT) for i in idx[:3]]
        else:
            shown = [labels[int(i)] for i in idx[:3]]
        more = f" and {idx.size - 3} more" if idx.size > 3 else ""
        raise EphemerisRangeError(
            f"epoch {', '.join(shown)}{more} is outside the ephemeris: {_range_text()}; "
            "choose epochs inside that range"
        )


@contextlib.contextmanager
def _translate_range_error():
    from skyfield.errors import EphemerisRangeError as SkyfieldRangeError

    try:
        yield
    except SkyfieldRangeError as exc:  # pre-check should make this unreachable
        raise EphemerisRangeError(f"{exc}; {_range_text()}") from exc


# ---------------------------------------------------------------------------------------------
# Orbit


def _finite(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise SkyInputError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(v):
        raise SkyInputError(f"{name} must be finite, got {value!r}")
    return v


def solve_kepler(mean_anomaly, eccentricity: float, tol: float = 1e-12, max_iter: int = 60) -> np.ndarray:
    """Eccentric anomaly E with E - e sin E = M, vectorised Newton to |dE| < ``tol``.

    M is wrapped to [-pi, pi) first, so E is returned in [-pi, pi]. Starts from Danby's
    E0 = M + 0.85 e sign(M), which converges for every 0 <= e < 1.
    """
    e = _finite("eccentricity", eccentricity)
    if not 0.0 <= e < 1.0:
        raise SkyInputError(f"eccentricity must be in [0, 1), got {e}")
    m = np.asarray(mean_anomaly, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise SkyInputError("mean anomaly contains NaN or inf")
    m = np.remainder(m + np.pi, 2.0 * np.pi) - np.pi
    big_e = m + 0.85 * e * np.where(m >= 0.0, 1.0, -1.0)
    for _ in range(max_iter):
        d = (big_e - e * np.sin(big_e) - m) / (1.0 - e * np.cos(big_e))
        big_e = big_e - d
        if not np.any(np.abs(d) >= tol):
            return big_e
    raise SkyInputError(f"Kepler's equation did not converge to {tol} in {max_iter} iterations (e={e})")


@dataclass(frozen=True)
class Orbit:
    """NRHO approximation (PHYSICS.md section 1): ellipse in the Earth-Moon rotating x-z plane.

    ``perilune_epoch`` is the UTC instant of perilune passage; record it in every layer.
    """

    perilune_radius_m: float = 3_249e3
    apolune_radius_m: float = 70_975e3
    period_days: float = 2 * 29.530589 / 9
    perilune_epoch: datetime = datetime(2030, 1, 1, tzinfo=timezone.utc)

    def __post_init__(self) -> None:
        rp = _finite("perilune_radius_m", self.perilune_radius_m)
        ra = _finite("apolune_radius_m", self.apolune_radius_m)
        p = _finite("period_days", self.period_days)
        if rp <= MOON_RADIUS_M:
            raise SkyInputError(f"perilune_radius_m {rp} must exceed the Moon's radius {MOON_RADIUS_M} m")
        if ra < rp:
            raise SkyInputError(f"apolune_radius_m {ra} must be >= perilune_radius_m {rp}")
        if p <= 0.0:
            raise SkyInputError(f"period_days must be positive, got {p}")
        object.__setattr__(self, "perilune_radius_m", rp)
        object.__setattr__(self, "apolune_radius_m", ra)
        object.__setattr__(self, "period_days", p)
        object.__setattr__(self, "perilune_epoch", _as_utc(self.perilune_epoch, "perilune_epoch"))

    @property
    def semi_major_axis_m(self) -> float:
        return 0.5 * (self.perilune_radius_m + self.apolune_radius_m)

    @property
    def eccentricity(self) -> float:
        return (self.apolune_radius_m - self.perilune_radius_m) / (self.apolune_radius_m + self.perilune_radius_m)

    @property
    def period_s(self) -> float:
        return self.period_days * SECONDS_PER_DAY

    @property
    def mean_motion_rad_s(self) -> float:
        """Forced to 2 pi / period (not sqrt(GM/a^3): that would give a 7.43 d period)."""
        return 2.0 * np.pi / self.period_s

    def rotating_state(self, seconds_since_perilune) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) in the rotating frame's (x, y, z) coordinates, m and m/s.

        Velocity is relative to the rotating axes (Kepler rate only). y components are 0.
        """
        dt = np.asarray(seconds_since_perilune, dtype=np.float64)
        a, e = self.semi_major_axis_m, self.eccentricity
        b = a * math.sqrt(1.0 - e * e)
        n = self.mean_motion_rad_s
        big_e = solve_kepler(n * dt, e)
        s, c = np.sin(big_e), np.cos(big_e)
        e_dot = n / (1.0 - e * c)
        zeros = np.zeros_like(s)
        pos = np.stack([b * s, zeros, a * (c - e)], axis=-1)
        vel = np.stack([b * c * e_dot, zeros, -a * s * e_dot], axis=-1)
        return pos, vel

    def as_dict(self) -> dict:
        """Plain values for recording in a layer."""
        return {
            "perilune_radius_m": self.perilune_radius_m,
            "apolune_radius_m": self.apolune_radius_m,
            "period_days": self.period_days,
            "perilune_epoch": _iso(self.perilune_epoch),
            "model": "NRHO approx: Kepler ellipse in Earth-Moon rotating x-z plane, perilune +z",
        }


# ---------------------------------------------------------------------------------------------
# Eclipse geometry (pure numpy, vectorised)


def _x_minus_sin_x(x: np.ndarray) -> np.ndarray:
    """x - sin(x) without cancellation for small x (Taylor series below 0.5)."""
    x = np.asarray(x, dtype=np.float64)
    x2 = x * x
    series = x * x2 * (1 / 6 - x2 * (1 / 120 - x2 * (1 / 5040 - x2 * (1 / 362880 - x2 * (
        1 / 39916800 - x2 * (1 / 6227020800))))))
    return np.where(np.abs(x) < 0.5, series, x - np.sin(x))


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
        half1 = np.arctan2(four_k, (dd - a2) * (dd + a2) + a1 * a1)  # chord half-angle at centre 1
        half2 = np.arctan2(four_k, (dd - a1) * (dd + a1) + a2 * a2)
        area = 0.5 * a1 * a1 * _x_minus_sin_x(2.0 * half1) + 0.5 * a2 * a2 * _x_minus_sin_x(2.0 * half2)
        out[lens] = np.minimum(area, np.pi * rs[lens] ** 2)
    return out


def classify_eclipse(theta_sun, theta_body, separation, body_nearer=True) -> tuple[np.ndarray, np.ndarray]:
    """PHYSICS.md section 6 cone test on angular radii and centre separation (radians).

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
    ds = np.linalg.norm(u_sun, axis=-1)
    db = np.linalg.norm(u_body, axis=-1)
    if np.any(ds <= sun_radius_m) or np.any(db <= body_radius_m):
        raise SkyInputError("observer is inside the Sun or the shadowing body (distance <= radius)")
    theta_s = np.arcsin(sun_radius_m / ds)
    theta_b = np.arcsin(body_radius_m / db)
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
    q = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
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
    r_b, r_o = _finite("body_radius_m", body_radius_m), _finite("occluder_radius_m", occluder_radius_m)
    if r_b <= 0.0 or r_o <= 0.0:
        raise SkyInputError("body_lit_fraction: radii must be positive")
    u_s, u_o = sun - body, occ - body
    d_s, d_o = np.linalg.norm(u_s, axis=-1), np.linalg.norm(u_o, axis=-1)
    if np.any(d_s <= SUN_RADIUS_M + r_b) or np.any(d_o <= r_o + r_b):
        raise SkyInputError("body_lit_fraction: the bodies overlap the Sun or each other")
    # From any point within r_b of the centre the Sun and the occluder move by at most asin(r_b/d)
    # and grow to at most asin(R/(d - r_b)); if even that cannot make them overlap, all is lit.
    reach = (np.arcsin(SUN_RADIUS_M / (d_s - r_b)) + np.arcsin(r_b / d_s)
             + np.arcsin(r_o / (d_o - r_b)) + np.arcsin(r_b / d_o))
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
        up = np.sqrt(np.maximum(1.0 - np.einsum("ij,ij->i", q, q), 0.0))
        offset = (q[None, :, 0, None] * e1[:, None, :] + q[None, :, 1, None] * e2[:, None, :]
                  + up[None, :, None] * s_hat[:, None, :])
        p = body[cand, None, :] + r_b * offset  # (m, points, 3) on the sunlit face
        _, lit, *_ = eclipse_from_vectors(sun[cand, None, :] - p, occ[cand, None, :] - p, SUN_RADIUS_M, r_o)
        out[cand] = lit.mean(axis=1)
    return out


# ---------------------------------------------------------------------------------------------
# Core geometry


def _geometry(t, orbit: Orbit, body_light: bool = True) -> dict[str, np.ndarray]:
    """Everything for the (already range-checked) skyfield Time array ``t`` (the sunlight on the
    Earth and the Moon only with ``body_light``; eclipse scans of the station skip it)."""
    e = _ephemeris()
    with _quiet_expiry(), _translate_range_error():
        sun = e.sun.at(t)
        earth = e.earth.at(t)
        moon = e.moon.at(t)
        tp = e.ts.from_datetime(orbit.perilune_epoch)
    p_sun = sun.position.m.T
    p_earth, v_earth = earth.position.m.T, earth.velocity.m_per_s.T
    p_moon, v_moon = moon.position.m.T, moon.velocity.m_per_s.T

    # Earth-Moon rotating frame, rebuilt per epoch.
    r = p_moon - p_earth
    v = v_moon - v_earth
    r_norm = np.linalg.norm(r, axis=1, keepdims=True)
    x = r / r_norm
    z = unit_rows(np.cross(r, v))
    y = np.cross(z, x)
    x_dot = (v - x * rowdot(x, v)[:, None]) / r_norm
    # z_dot from h_dot = r x a: the Earth-Moon central pull drops out, the Sun's tide remains.
    h = np.cross(r, v)
    h_norm = np.linalg.norm(h, axis=1, keepdims=True)
    to_sun_m, to_sun_e = p_sun - p_moon, p_sun - p_earth
    a_tide = GM_SUN_M3_S2 * (
        to_sun_m / np.linalg.norm(to_sun_m, axis=1, keepdims=True) ** 3
        - to_sun_e / np.linalg.norm(to_sun_e, axis=1, keepdims=True) ** 3
    )
    h_dot = np.cross(r, a_tide)
    z_dot = (h_dot - z * rowdot(z, h_dot)[:, None]) / h_norm

    dt_s = ((np.atleast_1d(t.whole) - tp.whole) + (np.atleast_1d(t.tt_fraction) - tp.tt_fraction)) * SECONDS_PER_DAY
    pos_rot, vel_rot = orbit.rotating_state(dt_s)
    rel = pos_rot[:, :1] * x + pos_rot[:, 2:] * z  # station - Moon, ICRF axes
    vel = vel_rot[:, :1] * x + vel_rot[:, 2:] * z + pos_rot[:, :1] * x_dot + pos_rot[:, 2:] * z_dot

    # Station frame: Z zenith (away from the Moon), X along velocity relative to the Moon.
    zs = unit_rows(rel)
    xs = unit_rows(vel - zs * rowdot(zs, vel)[:, None])
    ys = np.cross(zs, xs)
    icrf_to_station = np.stack([xs, ys, zs], axis=1)  # rows = station axes in ICRF

    vectors = {"sun": (p_sun - p_moon) - rel, "earth": (p_earth - p_moon) - rel, "moon": -rel}
    out: dict[str, np.ndarray] = {
        "station_icrf_m": p_moon + rel,
        "station_rel_moon_icrf_m": rel,
        "station_vel_rel_moon_icrf_m_s": vel,
        "icrf_to_station": icrf_to_station,
        "station_moon_distance_m": np.linalg.norm(rel, axis=1),
        "seconds_since_perilune": dt_s,
    }
    for body, u in vectors.items():
        d = np.linalg.norm(u, axis=1)
        out[f"distance_m.{body}"] = d
        out[f"direction.{body}"] = np.einsum("nij,nj->ni", icrf_to_station, u) / d[:, None]
        out[f"angular_radius_rad.{body}"] = np.arcsin(BODY_RADIUS_M[body] / d)
    out["sun_irradiance_w_m2"] = SOLAR_CONSTANT * (AU_M / out["distance_m.sun"]) ** 2
    if body_light:  # the Sun as each body sees it, for the lamp that lights only that body
        centres = {"earth": p_earth, "moon": p_moon}
        for body in LIT_BODIES:
            to_sun = p_sun - centres[body]
            d = np.linalg.norm(to_sun, axis=1)
            occ = OCCLUDER[body]
            out[f"body_sun_distance_m.{body}"] = d
            out[f"body_sun_direction.{body}"] = np.einsum("nij,nj->ni", icrf_to_station, to_sun) / d[:, None]
            out[f"body_sun_irradiance_w_m2.{body}"] = SOLAR_CONSTANT * (AU_M / d) ** 2
            out[f"body_lit_fraction.{body}"] = body_lit_fraction(
                p_sun, centres[body], BODY_RADIUS_M[body], centres[occ], BODY_RADIUS_M[occ])

    codes, lits = [], []
    sep_sun = {}
    for body in SHADOW_BODIES:
        sep = angle_between(vectors["sun"], vectors[body])
        code, lit = classify_eclipse(
            out["angular_radius_rad.sun"], out[f"angular_radius_rad.{body}"], sep,
            out[f"distance_m.{body}"] < out["distance_m.sun"],
        )
        out[f"eclipse_code.{body}"] = code
        out[f"lit_fraction.{body}"] = lit
        sep_sun[body] = sep
        codes.append(code)
        lits.append(lit)
    lit_all = np.stack(lits)  # (2, N)
    code_stack = np.stack(codes)
    worst = np.argmin(lit_all, axis=0)  # ties -> moon (index 0)
    idx = np.arange(lit_all.shape[1])
    code_all = code_stack[worst, idx]
    lit_final = lit_all[worst, idx].copy()
    both = (code_stack != LIT).all(axis=0)
    partial = both & (code_stack != UMBRA).all(axis=0)
    if np.any(partial):  # Moon and Earth both over the Sun: lit area by quadrature
        lit_final[partial] = np.minimum(
            lit_final[partial],
            _lit_two_occluders(
                vectors["sun"][partial], [vectors[b][partial] for b in SHADOW_BODIES],
                out["angular_radius_rad.sun"][partial],
                [out[f"angular_radius_rad.{b}"][partial] for b in SHADOW_BODIES],
                [sep_sun[b][partial] for b in SHADOW_BODIES],
            ),
        )
    out["lit_fraction"] = lit_final
    out["eclipse_code"] = code_all
    out["eclipse_body_code"] = np.where(code_all == LIT, 0, worst + 1).astype(np.int8)
    out["both_occulting"] = both
    return out


def _arc_term(cx: float, cy: float, r: float, a: float, b: float) -> float:
    """Green's-theorem integral 1/2 (x dy - y dx) along a circle arc, counter-clockwise a -> b."""
    return 0.5 * (r * cx * (math.sin(b) - math.sin(a)) - r * cy * (math.cos(b) - math.cos(a)) + r * r * (b - a))


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
        return (x - cx) ** 2 + (y - cy) ** 2 < r * r

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
            d = math.hypot(vx, vy)
            if d == 0.0 or d >= r + rj or d <= abs(r - rj):
                continue
            base = math.atan2(vy, vx)
            half = math.acos(max(-1.0, min(1.0, (d * d + r * r - rj * rj) / (2.0 * d * r))))
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
            if on_boundary(i, cx + r * math.cos(m), cy + r * math.sin(m)):
                total += sign * _arc_term(cx, cy, r, a, b)
    return max(0.0, min(total, math.pi * r0 * r0))


def _lit_two_occluders(u_sun, u_bodies, theta_sun, theta_bodies, seps) -> np.ndarray:
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
        wn = np.linalg.norm(w, axis=1)
        wn = np.where(wn > 0.0, wn, 1.0)
        centres.append(np.stack([rowdot(w, e1), rowdot(w, e2)], axis=1) * (np.asarray(sep) / wn)[:, None])
    out = np.empty(s.shape[0])
    for m in range(s.shape[0]):
        r0 = float(theta_sun[m])
        discs = [(float(c[m, 0]), float(c[m, 1]), float(tb[m])) for c, tb in zip(centres, theta_bodies)]
        out[m] = _sun_minus_discs_area(r0, discs) / (math.pi * r0 * r0)
    return np.clip(out, 0.0, 1.0)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


# ---------------------------------------------------------------------------------------------
# Public result types


@dataclass(frozen=True)
class SkyAt:
    """The sky at one epoch, plain Python values (station frame unless named ICRF)."""

    epoch: str
    station_icrf_m: tuple[float, float, float]
    station_rel_moon_icrf_m: tuple[float, float, float]
    icrf_to_station: tuple[tuple[float, float, float], ...]
    direction: dict[str, tuple[float, float, float]]
    distance_m: dict[str, float]
    angular_radius_rad: dict[str, float]
    sun_irradiance_w_m2: float
    lit_fraction: float
    eclipse_state: str
    eclipse_body: str
    station_moon_distance_m: float
    body_sun_direction: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    body_sun_distance_m: dict[str, float] = field(default_factory=dict)
    body_sun_irradiance_w_m2: dict[str, float] = field(default_factory=dict)
    body_lit_fraction: dict[str, float] = field(default_factory=dict)
    orbit: Orbit = field(default_factory=Orbit)


@dataclass(frozen=True, eq=False)
class Sky:
    """Sky geometry for N epochs (read-only numpy arrays, length N).

    ``station_icrf_m`` is barycentric (solar-system barycentre origin, ICRF axes);
    ``station_rel_moon_icrf_m`` is station - Moon in ICRF axes. ``direction[body]`` is the unit
    vector from the station to the body centre in the STATION FRAME (see module doc), and
    ``icrf_to_station[i] @ v_icrf`` maps ICRF vectors into it. Distances are centre to centre.
    ``sun_irradiance_w_m2`` is the unocculted 1361 (1 AU / d)^2; multiply by ``lit_fraction``
    (or use :func:`sun_light`) for the light that reaches the station.
    ``body_sun_*[body]`` and ``body_lit_fraction[body]`` (for :data:`LIT_BODIES`) are the Sun as
    seen from that body's centre: direction body -> Sun in the station frame, distance, unocculted
    irradiance, and the share of it that reaches the body (:func:`body_sun_light`).
    """

    epochs: tuple[str, ...]
    station_icrf_m: np.ndarray
    station_rel_moon_icrf_m: np.ndarray
    station_vel_rel_moon_icrf_m_s: np.ndarray
    icrf_to_station: np.ndarray
    direction: dict[str, np.ndarray]
    distance_m: dict[str, np.ndarray]
    angular_radius_rad: dict[str, np.ndarray]
    sun_irradiance_w_m2: np.ndarray
    lit_fraction: np.ndarray
    eclipse_state: np.ndarray
    eclipse_body: np.ndarray
    station_moon_distance_m: np.ndarray
    body_sun_direction: dict[str, np.ndarray]
    body_sun_distance_m: dict[str, np.ndarray]
    body_sun_irradiance_w_m2: dict[str, np.ndarray]
    body_lit_fraction: dict[str, np.ndarray]
    orbit: Orbit = field(default_factory=Orbit)
    positions: str = "geometric"
    ephemeris: str = "de421.bsp"

    def __len__(self) -> int:
        return len(self.epochs)

    def at(self, i: int) -> SkyAt:
        n = len(self)
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)):
            raise IndexError(f"Sky.at takes an integer index, got {i!r}")
        if not -n <= i < n:
            raise IndexError(f"epoch index {i} out of range for {n} epochs")
        i = int(i) % n

        def vec(a: np.ndarray) -> tuple[float, float, float]:
            return tuple(float(x) for x in a[i])

        return SkyAt(
            epoch=self.epochs[i],
            station_icrf_m=vec(self.station_icrf_m),
            station_rel_moon_icrf_m=vec(self.station_rel_moon_icrf_m),
            icrf_to_station=tuple(tuple(float(x) for x in row) for row in self.icrf_to_station[i]),
            direction={b: vec(self.direction[b]) for b in BODIES},
            distance_m={b: float(self.distance_m[b][i]) for b in BODIES},
            angular_radius_rad={b: float(self.angular_radius_rad[b][i]) for b in BODIES},
            sun_irradiance_w_m2=float(self.sun_irradiance_w_m2[i]),
            lit_fraction=float(self.lit_fraction[i]),
            eclipse_state=str(self.eclipse_state[i]),
            eclipse_body=str(self.eclipse_body[i]),
            station_moon_distance_m=float(self.station_moon_distance_m[i]),
            body_sun_direction={b: vec(self.body_sun_direction[b]) for b in LIT_BODIES},
            body_sun_distance_m={b: float(self.body_sun_distance_m[b][i]) for b in LIT_BODIES},
            body_sun_irradiance_w_m2={b: float(self.body_sun_irradiance_w_m2[b][i]) for b in LIT_BODIES},
            body_lit_fraction={b: float(self.body_lit_fraction[b][i]) for b in LIT_BODIES},
            orbit=self.orbit,
        )


def _prepare_epochs(epochs: Iterable[object]) -> list[datetime]:
    if isinstance(epochs, (str, datetime)):
        epochs = [epochs]
    try:
        items = list(epochs)
    except TypeError as exc:
        raise EpochError(f"epochs must be a sequence of aware datetimes, got {type(epochs).__name__}") from exc
    if not items:
        raise EpochError("no epochs given; pass at least one timezone-aware UTC datetime")
    return [_as_utc(v, f"epoch[{k}]") for k, v in enumerate(items)]


def compute_sky(epochs: Iterable[datetime], orbit: Orbit = Orbit()) -> Sky:
    """Station, Sun, Earth, Moon and eclipse state at each epoch (one skyfield call per body).

    ``epochs``: timezone-aware datetimes (any zone; converted to UTC) or ISO strings with an
    offset/Z. Naive datetimes raise EpochError; epochs outside DE421 raise EphemerisRangeError
    naming the valid range, before any ephemeris lookup.
    """
    if not isinstance(orbit, Orbit):
        raise SkyInputError(f"orbit must be an allo_usd.sky.model.Orbit, got {type(orbit).__name__}")
    dts = _prepare_epochs(epochs)
    labels = [_iso(d) for d in dts]
    t = _time_from_utc(dts)
    _check_range(t, labels)
    g = _geometry(t, orbit)
    return Sky(
        epochs=tuple(labels),
        station_icrf_m=_readonly(g["station_icrf_m"]),
        station_rel_moon_icrf_m=_readonly(g["station_rel_moon_icrf_m"]),
        station_vel_rel_moon_icrf_m_s=_readonly(g["station_vel_rel_moon_icrf_m_s"]),
        icrf_to_station=_readonly(g["icrf_to_station"]),
        direction={b: _readonly(g[f"direction.{b}"]) for b in BODIES},
        distance_m={b: _readonly(g[f"distance_m.{b}"]) for b in BODIES},
        angular_radius_rad={b: _readonly(g[f"angular_radius_rad.{b}"]) for b in BODIES},
        sun_irradiance_w_m2=_readonly(g["sun_irradiance_w_m2"]),
        lit_fraction=_readonly(g["lit_fraction"]),
        eclipse_state=_readonly(_STATE_NAMES[g["eclipse_code"]]),
        eclipse_body=_readonly(_BODY_NAMES[g["eclipse_body_code"]]),
        station_moon_distance_m=_readonly(g["station_moon_distance_m"]),
        body_sun_direction={b: _readonly(g[f"body_sun_direction.{b}"]) for b in LIT_BODIES},
        body_sun_distance_m={b: _readonly(g[f"body_sun_distance_m.{b}"]) for b in LIT_BODIES},
        body_sun_irradiance_w_m2={b: _readonly(g[f"body_sun_irradiance_w_m2.{b}"]) for b in LIT_BODIES},
        body_lit_fraction={b: _readonly(g[f"body_lit_fraction.{b}"]) for b in LIT_BODIES},
        orbit=orbit,
    )


# ---------------------------------------------------------------------------------------------
# Rendering helpers (scheme C: true scale, station at the origin)


def _check_sky_at(sky_at: SkyAt) -> None:
    if not isinstance(sky_at, SkyAt):
        raise SkyInputError(f"expected a SkyAt (Sky.at(i)), got {type(sky_at).__name__}")
    values = [sky_at.sun_irradiance_w_m2, sky_at.lit_fraction]
    for b in BODIES:
        values += list(sky_at.direction[b]) + [sky_at.distance_m[b], sky_at.angular_radius_rad[b]]
    if not all(math.isfinite(v) for v in values):
        raise SkyInputError(f"sky at {sky_at.epoch} contains NaN or inf")


def body_placement(sky_at: SkyAt) -> dict[str, tuple[np.ndarray, float]]:
    """{body: (centre (3,) float64 m in the station frame, radius m)} for true-scale rendering."""
    _check_sky_at(sky_at)
    return {
        b: (np.asarray(sky_at.direction[b], dtype=np.float64) * sky_at.distance_m[b], BODY_RADIUS_M[b])
        for b in BODIES
    }


def sun_light(sky_at: SkyAt) -> dict:
    """Distant-light parameters: direction to the Sun (station frame), effective irradiance."""
    _check_sky_at(sky_at)
    lit = float(sky_at.lit_fraction)
    return {
        "direction_to_sun": np.asarray(sky_at.direction["sun"], dtype=np.float64),
        "irradiance_w_m2": 0.0 if sky_at.eclipse_state == "umbra" else float(sky_at.sun_irradiance_w_m2 * lit),
        "angular_diameter_rad": 2.0 * float(sky_at.angular_radius_rad["sun"]),
        "lit_fraction": lit,
        "state": sky_at.eclipse_state,
        "eclipse_body": sky_at.eclipse_body,
    }


def body_sun_light(sky_at: SkyAt) -> dict[str, dict]:
    """{body: distant-light parameters of the lamp that lights only that body} for LIT_BODIES.

    Like :func:`sun_light`, but for the Sun seen from the body's centre: ``irradiance_w_m2`` is
    1361 (1 AU / d_body_sun)^2 times the body's lit fraction (0, the lamp off, in total eclipse);
    ``state`` is lit (fraction 1), umbra (0) or penumbra (in between), and ``eclipse_body`` the
    occluder when the fraction is below 1, else ''.
    """
    _check_sky_at(sky_at)
    out = {}
    for b in LIT_BODIES:
        lit = float(sky_at.body_lit_fraction[b])
        d = float(sky_at.body_sun_distance_m[b])
        unocc = float(sky_at.body_sun_irradiance_w_m2[b])
        if not (math.isfinite(lit) and math.isfinite(d) and math.isfinite(unocc) and d > SUN_RADIUS_M):
            raise SkyInputError(f"sky at {sky_at.epoch}: the sunlight on the {b} is not finite")
        out[b] = {
            "direction_to_sun": np.asarray(sky_at.body_sun_direction[b], dtype=np.float64),
            "irradiance_w_m2": unocc * lit,
            "irradiance_unoccluded_w_m2": unocc,
            "angular_diameter_rad": 2.0 * math.asin(SUN_RADIUS_M / d),
            "distance_m": d,
            "lit_fraction": lit,
            "state": "lit" if lit == 1.0 else "umbra" if lit == 0.0 else "penumbra",
            "eclipse_body": OCCLUDER[b] if lit < 1.0 else "",
        }
    return out


# ---------------------------------------------------------------------------------------------
# Eclipse search over a span (scan + vectorised bisection of every contact)


@dataclass(frozen=True)
class EclipseEvent:
    """One continuous shadow pass by one body (penumbral contact to penumbral contact)."""

    body: str
    start: str
    end: str
    duration_s: float
    umbra_s: float
    min_lit_fraction: float
    deepest_state: str
    truncated: bool  # started before or ended after the searched span


def _span_geometry(start: datetime, offsets_s: np.ndarray, orbit: Orbit, chunk: int = 100_000) -> dict[str, np.ndarray]:
    keys = ("eclipse_code.moon", "eclipse_code.earth", "lit_fraction.moon", "lit_fraction.earth", "both_occulting")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for lo in range(0, offsets_s.size, chunk):
        off = offsets_s[lo:lo + chunk]
        t = _time_from_start(start, off)
        _check_range(t, None)
        g = _geometry(t, orbit, body_light=False)
        for k in keys:
            parts[k].append(g[k])
    return {k: np.concatenate(v) for k, v in parts.items()}


def _contact_times(start, offsets, s_idx, e_idx, predicate, orbit, tol_s):
    """Refined start and end times of runs [s_idx, e_idx) of sampled offsets where `predicate` holds;
    a run touching either end of the sampled window keeps that end's sample time."""
    has_lo = s_idx > 0
    has_hi = e_idx < offsets.size
    t_start = offsets[s_idx].astype(np.float64)
    t_end = offsets[np.minimum(e_idx, offsets.size - 1)].astype(np.float64)
    t_start[has_lo] = _refine(start, offsets[s_idx[has_lo] - 1], offsets[s_idx[has_lo]], predicate, orbit, tol_s)
    t_end[has_hi] = _refine(start, offsets[e_idx[has_hi] - 1], offsets[e_idx[has_hi]], predicate, orbit, tol_s)
    return t_start, t_end


def _refine(start: datetime, lo: np.ndarray, hi: np.ndarray, pred, orbit: Orbit, tol_s: float) -> np.ndarray:
    """Bisect all brackets [lo, hi] (pred(lo) != pred(hi)) at once; returns crossing offsets."""
    if lo.size == 0:
        return lo.copy()
    lo, hi = lo.astype(np.float64).copy(), hi.astype(np.float64).copy()
    g_lo = pred(_span_geometry(start, lo, orbit))
    while np.max(hi - lo) > tol_s:
        mid = 0.5 * (lo + hi)
        g_mid = pred(_span_geometry(start, mid, orbit))
        same = g_mid == g_lo
        lo = np.where(same, mid, lo)
        hi = np.where(same, hi, mid)
    return 0.5 * (lo + hi)


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start/stop (exclusive) indices of True runs."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def eclipse_events(
    start: datetime, stop: datetime, orbit: Orbit = Orbit(), step_s: float = 60.0, tol_s: float = 0.5,
) -> tuple[list[EclipseEvent], dict]:
    """All Moon- and Earth-shadow passes in [start, stop): scan every ``step_s`` then bisect
    each contact to ``tol_s``. Passes shorter than ``step_s`` can be missed.

    Returns (events sorted by start, info dict with the scan size and how many samples had
    both bodies over the Sun).
    """
    start = _as_utc(start, "start")
    stop = _as_utc(stop, "stop")
    step_s = _finite("step_s", step_s)
    tol_s = _finite("tol_s", tol_s)
    if step_s <= 0 or tol_s <= 0:
        raise SkyInputError("step_s and tol_s must be positive")
    span = (stop - start).total_seconds()
    if span <= 0:
        raise SkyInputError(f"stop {stop} must be after start {start}")
    offsets = np.arange(0.0, span, step_s)
    g = _span_geometry(start, offsets, orbit)
    events: list[EclipseEvent] = []
    for bi, body in enumerate(SHADOW_BODIES):
        code = g[f"eclipse_code.{body}"]
        lit = g[f"lit_fraction.{body}"]
        s_idx, e_idx = _runs(code != LIT)
        if s_idx.size == 0:
            continue
        key = f"eclipse_code.{body}"

        def shadowed(gg, key=key):
            return gg[key] != LIT

        def umbral(gg, key=key):
            return gg[key] == UMBRA

        t_start, t_end = _contact_times(start, offsets, s_idx, e_idx, shadowed, orbit, tol_s)
        # Umbra contacts inside each pass.
        u_s, u_e = _runs(code == UMBRA)
        tu_s, tu_e = _contact_times(start, offsets, u_s, u_e, umbral, orbit, tol_s)
        for k in range(s_idx.size):
            inside = (u_s >= s_idx[k]) & (u_e <= e_idx[k])
            umbra_s = float(np.sum(tu_e[inside] - tu_s[inside]))
            seg = slice(s_idx[k], e_idx[k])
            deepest = int(np.max(code[seg]))
            events.append(EclipseEvent(
                body=body,
                start=_iso(start + timedelta(seconds=float(t_start[k]))),
                end=_iso(start + timedelta(seconds=float(t_end[k]))),
                duration_s=float(t_end[k] - t_start[k]),
                umbra_s=umbra_s,
                min_lit_fraction=float(np.min(lit[seg])),
                deepest_state=ECLIPSE_STATES[deepest],
                truncated=bool(s_idx[k] == 0 or e_idx[k] >= offsets.size),
            ))
    events.sort(key=lambda ev: ev.start)
    info = {"samples": int(offsets.size), "step_s": step_s, "tol_s": tol_s,
            "both_occulting_samples": int(np.count_nonzero(g["both_occulting"]))}
    return events, info
