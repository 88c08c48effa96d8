"""The ephemeris and epochs of the sky: DE421 opened offline, UTC epochs as skyfield times.

Ephemeris
    JPL DE421 from the ``skyfield-data`` package, opened offline
    (``Loader(skyfield_data.get_skyfield_data_path())``, ``load.timescale(builtin=True)``).
    Barycentric geometric states (``body.at(t)``, ICRF axes) are computed in ONE vectorised
    skyfield call per body (Sun, Earth, Moon); :func:`apparent_vectors` turns them into what an
    observer sees (light time and aberration, docs/physics.md section 11). Valid range: DE421's 1899-07-29 .. 2053-10-09
    (TDB); epochs outside raise :class:`~allo_usd.core.errors.EphemerisRangeError` before skyfield is
    asked for a position.

"""

from __future__ import annotations

import atexit
import contextlib
import functools
import math
import os
import warnings
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import Sequence

import numpy as np

from allo_usd.core.constants import SECONDS_PER_DAY
from allo_usd.core.errors import EphemerisRangeError, EpochError, SkyInputError
from allo_usd.core.interrupts import interrupt_held
from allo_usd.core.timefmt import format_utc, parse_utc
from allo_usd.sky.ephemeris_range import DE421_END_UTC, DE421_START_UTC
from allo_usd.core import fixedmath as fm

_EXPIRED_WARNING = r".*finals2000A\.all has expired.*"
SPEED_OF_LIGHT_M_S = 299_792_458.0  # exact (SI definition of the metre)
_LIGHT_TIME_ITERATIONS = 3  # each gains a factor v/c ~ 1e-4: 3 leave < 1e-12 of the light time
ISO_FORMAT = "%Y-%m-%dT%H:%M:%SZ"


# ---------------------------------------------------------------------------------------------
# Ephemeris (offline, cached)


@contextlib.contextmanager
def quiet_expiry():
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
def load_de421() -> _Ephemeris:
    """Open DE421 and the builtin timescale from skyfield-data; never touches the network."""
    with quiet_expiry():
        with interrupt_held():   # skyfield's iokit tries urllib under a bare `except:`: a Ctrl-C landing there
            import skyfield_data   # came out as "No module named 'urlparse'" (a traceback, not exit 130)
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


def as_utc(value: object, what: str = "epoch") -> datetime:
    """One epoch as an aware UTC datetime. Naive datetimes are refused, never guessed."""
    if isinstance(value, str):
        return parse_utc(value, what)
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


def iso_utc(dt: datetime) -> str:
    """The recorded text of an epoch, exact to the microsecond (allo_usd.core.timefmt)."""
    return format_utc(dt)


def default_epochs(year: int = 2030, days: int = 365) -> list[datetime]:
    """``days`` consecutive days at 00:00 UTC from 1 January of ``year`` (aware datetimes)."""
    if isinstance(year, bool) or not isinstance(year, (int, np.integer)):
        raise EpochError(f"year must be an integer, got {year!r}")
    if isinstance(days, bool) or not isinstance(days, (int, np.integer)) or days < 1:
        raise EpochError(f"days must be a positive integer, got {days!r}")
    start = datetime(int(year), 1, 1, tzinfo=timezone.utc)
    return [start + timedelta(days=k) for k in range(int(days))]


def time_from_utc(dts: Sequence[datetime], offsets_s: np.ndarray | None = None):
    """Vectorised skyfield Time from aware UTC datetimes (plus optional second offsets)."""
    e = load_de421()
    n = len(dts)
    y = np.fromiter((d.year for d in dts), dtype=np.int64, count=n)
    mo = np.fromiter((d.month for d in dts), dtype=np.int64, count=n)
    da = np.fromiter((d.day for d in dts), dtype=np.int64, count=n)
    h = np.fromiter((d.hour for d in dts), dtype=np.int64, count=n)
    mi = np.fromiter((d.minute for d in dts), dtype=np.int64, count=n)
    s = np.fromiter((d.second + d.microsecond * 1e-6 for d in dts), dtype=np.float64, count=n)
    if offsets_s is not None:
        s = s + offsets_s
    with quiet_expiry():
        return _with_tdb(e.ts.utc(y, mo, da, h, mi, s))


def time_from_start(start: datetime, offsets_s: np.ndarray):
    """Vectorised skyfield Time at ``start`` + offsets (seconds, UTC; skyfield normalises)."""
    e = load_de421()
    sec = start.second + start.microsecond * 1e-6 + np.asarray(offsets_s, dtype=np.float64)
    with quiet_expiry():
        return _with_tdb(e.ts.utc(start.year, start.month, start.day, start.hour, start.minute, sec))


def tdb_minus_tt_s(whole, fraction) -> np.ndarray:
    """TDB - TT in seconds at TT (or TDB) Julian date whole + fraction: skyfield's own series (USNO
    Circular 179, eq. 2.6), term for term, with core.fixedmath's sine instead of numpy's (which
    rounds differently on AVX-512 CPUs)."""
    t = (np.asarray(whole, dtype=np.float64) - 2451545.0 + np.asarray(fraction, dtype=np.float64)) / 36525.0
    return (0.001657 * fm.sin(628.3076 * t + 6.2401)
            + 0.000022 * fm.sin(575.3385 * t + 4.2970)
            + 0.000014 * fm.sin(1256.6152 * t + 6.1969)
            + 0.000005 * fm.sin(606.9777 * t + 4.0212)
            + 0.000005 * fm.sin(52.9691 * t + 0.4444)
            + 0.000002 * fm.sin(21.3299 * t + 5.5431)
            + 0.000010 * t * fm.sin(628.3076 * t + 4.2490))


def _with_tdb(t):
    """`t` with its TDB fraction set before skyfield computes it: the ephemeris is read at TDB, and
    skyfield's own conversion calls numpy's sine, whose last bit depends on the CPU."""
    t.tdb_fraction = t.tt_fraction + tdb_minus_tt_s(t.whole, t.tt_fraction) / SECONDS_PER_DAY
    return t


def check_range(t, labels: Sequence[str] | None) -> None:
    """Raise EphemerisRangeError (with the valid range) before skyfield touches DE421."""
    e = load_de421()
    whole = np.atleast_1d(t.whole)
    frac = np.atleast_1d(t.tdb_fraction)
    bad = ((whole - e.start_tdb_jd) + frac < 0.0) | ((whole - e.end_tdb_jd) + frac > 0.0)
    if bad.any():
        idx = np.flatnonzero(bad)
        if labels is None:
            with quiet_expiry():
                shown = [t[int(i)].utc_strftime(ISO_FORMAT) for i in idx[:3]]
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


def finite_number(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise SkyInputError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(v):
        raise SkyInputError(f"{name} must be finite, got {value!r}")
    return v


# ---------------------------------------------------------------------------------------------
# Apparent places (docs/physics.md section 11)


def light_time_vectors(geometric, target_velocity) -> tuple[np.ndarray, np.ndarray]:
    """(retarded vector, light time s): the target where it was when the light now arriving left it.

    ``geometric`` (N, 3) m is target(t) - observer(t), ``target_velocity`` (N, 3) m/s the target's
    barycentric velocity. Solves tau = |geometric - tau v| / c by fixed-point iteration, moving the
    target back along its velocity: the acceleration term 0.5 a tau^2 is under 0.03 m for the Sun
    (tau ~ 500 s) and under 1 cm for the Earth and the Moon.
    """
    g = np.asarray(geometric, dtype=np.float64)
    v = np.asarray(target_velocity, dtype=np.float64)
    tau = fm.norm(g, axis=-1) / SPEED_OF_LIGHT_M_S
    for _ in range(_LIGHT_TIME_ITERATIONS):
        tau = fm.norm(g - tau[..., None] * v, axis=-1) / SPEED_OF_LIGHT_M_S
    return g - tau[..., None] * v, tau


def aberrate(retarded, observer_velocity) -> np.ndarray:
    """Unit apparent directions: the retarded vectors (N, 3) seen by an observer moving at
    ``observer_velocity`` (N, 3) m/s (barycentric). Special-relativistic aberration in the form
    skyfield and NOVAS use (``add_aberration``)."""
    p = np.asarray(retarded, dtype=np.float64)
    v = np.asarray(observer_velocity, dtype=np.float64)
    dist = fm.norm(p, axis=-1)
    beta_vec = v / SPEED_OF_LIGHT_M_S
    beta = fm.norm(beta_vec, axis=-1)
    cosd = fm.dot(p, beta_vec) / (dist * np.where(beta > 0.0, beta, 1.0))
    gamma_inv = np.sqrt(1.0 - beta * beta)
    pb = beta * cosd
    q = (1.0 + pb / (1.0 + gamma_inv)) * dist
    out = gamma_inv[..., None] * p + q[..., None] * beta_vec
    return out / fm.norm(out, axis=-1, keepdims=True)


def apparent_vectors(geometric, target_velocity, observer_velocity) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit apparent direction, retarded vector, light time s) of targets seen by a moving observer:
    light time (:func:`light_time_vectors`), then aberration (:func:`aberrate`). Gravitational
    deflection is left out: the Sun bends the light of the Earth and the Moon by under 1e-10 rad
    here, and its own not at all (docs/physics.md section 11)."""
    retarded, tau = light_time_vectors(geometric, target_velocity)
    return aberrate(retarded, observer_velocity), retarded, tau
