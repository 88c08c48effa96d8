"""Sky geometry for every scene: station orbit (NRHO approximation), Sun/Earth/Moon, eclipses.

numpy + skyfield only (no pxr, no bpy), so it can be tested and benchmarked on its own.
Numbers and conventions follow ``docs/physics.md`` sections 1-7 and 11.

The pieces live beside it: ephemeris (DE421, epochs), orbit (the station's ellipse), eclipse
(disc geometry) and events (eclipse search over a span); this module puts them together.

Station frame (fixed convention; "LVLH-like", relative to the Moon)
    +Z = unit(station - Moon) (zenith, away from the Moon), +X = the station's velocity
    relative to the Moon in ICRF, orthogonalised against Z, +Y = Z x X. The Moon's geometric
    centre is therefore always toward -Z (its apparent one within ~1e-5 rad). The velocity is the analytic derivative of station - Moon: Kepler rate
    plus the rotation of the Earth-Moon frame (x from the ephemeris position and velocity; z
    from h_dot = r x a with a = the Sun's tidal acceleration, which is what turns the Moon's
    orbit normal; tests compare it with a central finite difference). Near apolune the speed
    is only ~90 m/s, so ignoring z_dot would tilt X by up to 3e-3 rad.
    ``Sky.icrf_to_station[i] @ v_icrf`` gives a vector in the station frame; its rows are the
    station X, Y, Z axes in ICRF.

Apparent directions (docs/physics.md section 11)
    The bodies and the sun lamps are placed where a camera on the station sees them: light time
    (the body where it was when the light now arriving left it) plus aberration from the station's
    barycentric velocity (the Moon's + the orbit model's velocity relative to the Moon). Distances
    are the light-time distances. The geometric directions are kept alongside for the record.
    The station's eclipse uses the light-time vectors of the Sun and the occluder.

Rendering placement (docs/physics.md section 4, scheme C)
    True scale, station at the origin of the station frame: body centre = apparent direction *
    light-time distance.
    Casting the centres to float32 (Blender) moves the direction seen from a camera within 100 m
    of the origin by at most ~4e-8 rad (Sun, Earth) and the angular radius by ~1e-7 relative;
    tests hold it to 1e-5 rad and 1e-4.

Sunlight on the bodies (docs/physics.md sections 5 and 7)
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

import math
from dataclasses import dataclass, field
from datetime import datetime
from typing import Iterable

import numpy as np

from allo_usd.core.constants import (AU_M, EARTH_RADIUS_M, GM_SUN_M3_S2, MOON_RADIUS_M, SECONDS_PER_DAY, SOLAR_CONSTANT,
                                     SUN_RADIUS_M)
from allo_usd.core.errors import EpochError, SkyInputError
from allo_usd.core.geometry import angle_between, rowdot, unit_rows
from allo_usd.sky.eclipse import (ECLIPSE_STATES, LIT, SHADOW_BODIES, UMBRA, lit_two_occluders, body_lit_fraction,
                                  classify_eclipse)
from allo_usd.sky.ephemeris import (apparent_vectors, as_utc, check_range, light_time_vectors, load_de421, iso_utc,
                                    quiet_expiry, time_from_utc, _translate_range_error)
from allo_usd.sky.orbit import Orbit
from allo_usd.core import fixedmath as fm

# ---------------------------------------------------------------------------------------------
# Constants (docs/physics.md sections 3 and 5)

BODIES: tuple[str, ...] = ("sun", "earth", "moon")
BODY_RADIUS_M: dict[str, float] = {"sun": SUN_RADIUS_M, "earth": EARTH_RADIUS_M, "moon": MOON_RADIUS_M}
LIT_BODIES: tuple[str, ...] = ("earth", "moon")  # bodies with a sun lamp of their own
OCCLUDER: dict[str, str] = {"earth": "moon", "moon": "earth"}  # what can shadow each lit body
_STATE_NAMES = np.array(ECLIPSE_STATES)
_BODY_NAMES = np.array(("",) + SHADOW_BODIES)  # 0 -> '', 1 -> moon, 2 -> earth


# ---------------------------------------------------------------------------------------------
# Core geometry


def sky_geometry(t, orbit: Orbit, body_light: bool = True) -> dict[str, np.ndarray]:
    """Everything for the (already range-checked) skyfield Time array ``t`` (the sunlight on the
    Earth and the Moon only with ``body_light``; eclipse scans of the station skip it)."""
    (p_sun, v_sun), (p_earth, v_earth), (p_moon, v_moon), tp = _ephemeris_states(t, orbit)
    frame = _earth_moon_frame(p_sun, p_earth, v_earth, p_moon, v_moon)
    dt_s = ((np.atleast_1d(t.whole) - tp.whole) + (np.atleast_1d(t.tt_fraction) - tp.tt_fraction)) * SECONDS_PER_DAY
    rel, vel = _station_state(orbit, dt_s, *frame)
    icrf_to_station = _station_frame(rel, vel)

    geometric = {"sun": (p_sun - p_moon) - rel, "earth": (p_earth - p_moon) - rel, "moon": -rel}
    velocity = {"sun": v_sun, "earth": v_earth, "moon": v_moon}
    out: dict[str, np.ndarray] = {
        "station_icrf_m": p_moon + rel,
        "station_rel_moon_icrf_m": rel,
        "station_vel_rel_moon_icrf_m_s": vel,
        "station_vel_icrf_m_s": v_moon + vel,
        "icrf_to_station": icrf_to_station,
        "station_moon_distance_m": fm.norm(rel, axis=1),
        "seconds_since_perilune": dt_s,
    }
    seen, retarded = _bodies_seen(geometric, velocity, v_moon + vel, icrf_to_station)
    out.update(seen)
    if body_light:  # the Sun as each body sees it, for the lamp that lights only that body
        out.update(_sunlight_on_bodies((p_sun, v_sun), {"earth": (p_earth, v_earth), "moon": (p_moon, v_moon)},
                                       icrf_to_station))
    out.update(_station_eclipse(retarded, out))
    return out


def _ephemeris_states(t, orbit: Orbit):
    """Barycentric ICRF positions (m) and velocities (m/s) of the Sun, the Earth and the Moon,
    and the perilune epoch as a skyfield Time."""
    e = load_de421()
    with quiet_expiry(), _translate_range_error():
        sun = e.sun.at(t)
        earth = e.earth.at(t)
        moon = e.moon.at(t)
        tp = e.ts.from_datetime(orbit.perilune_epoch)
    return ((sun.position.m.T, sun.velocity.m_per_s.T), (earth.position.m.T, earth.velocity.m_per_s.T),
            (moon.position.m.T, moon.velocity.m_per_s.T), tp)


def _cube(x: np.ndarray) -> np.ndarray:
    """x**3 as two products (numpy's `** 3` calls pow, which rounds by CPU on AVX-512)."""
    return x * x * x


def _earth_moon_frame(p_sun, p_earth, v_earth, p_moon, v_moon):
    """The Earth-Moon rotating frame's x and z axes per epoch and their time derivatives."""
    r = p_moon - p_earth
    v = v_moon - v_earth
    r_norm = fm.norm(r, axis=1, keepdims=True)
    x = r / r_norm
    z = unit_rows(np.cross(r, v))
    x_dot = (v - x * rowdot(x, v)[:, None]) / r_norm
    # z_dot from h_dot = r x a: the Earth-Moon central pull drops out, the Sun's tide remains.
    h = np.cross(r, v)
    h_norm = fm.norm(h, axis=1, keepdims=True)
    to_sun_m, to_sun_e = p_sun - p_moon, p_sun - p_earth
    a_tide = GM_SUN_M3_S2 * (
        to_sun_m / _cube(fm.norm(to_sun_m, axis=1, keepdims=True))
        - to_sun_e / _cube(fm.norm(to_sun_e, axis=1, keepdims=True))
    )
    h_dot = np.cross(r, a_tide)
    z_dot = (h_dot - z * rowdot(z, h_dot)[:, None]) / h_norm
    return x, z, x_dot, z_dot


def _station_state(orbit: Orbit, dt_s, x, z, x_dot, z_dot):
    """Station - Moon position and velocity in ICRF axes, `dt_s` seconds after perilune."""
    pos_rot, vel_rot = orbit.rotating_state(dt_s)
    rel = pos_rot[:, :1] * x + pos_rot[:, 2:] * z
    vel = vel_rot[:, :1] * x + vel_rot[:, 2:] * z + pos_rot[:, :1] * x_dot + pos_rot[:, 2:] * z_dot
    return rel, vel


def _station_frame(rel, vel) -> np.ndarray:
    """Rows = station axes in ICRF: Z zenith (away from the Moon), X along velocity relative to the Moon."""
    zs = unit_rows(rel)
    xs = unit_rows(vel - zs * rowdot(zs, vel)[:, None])
    ys = np.cross(zs, xs)
    return np.stack([xs, ys, zs], axis=1)


def _bodies_seen(geometric: dict, velocity: dict, observer_velocity, icrf_to_station) -> tuple[dict, dict]:
    """Each body as the station sees it (docs/physics.md section 11): the apparent direction (light
    time and aberration) in the station frame, the light-time distance |body(t - tau) - station(t)|
    (what sets the angular radius and the Sun's irradiance), the geometric direction for the record;
    and the light-time (retarded) vectors in ICRF, for the eclipse."""
    out, retarded = {}, {}
    for body, g in geometric.items():
        apparent, ret, _ = apparent_vectors(g, velocity[body], observer_velocity)
        d = fm.norm(ret, axis=1)
        retarded[body] = ret
        out[f"distance_m.{body}"] = d
        out[f"direction.{body}"] = fm.dot(icrf_to_station, apparent[:, None, :])
        out[f"geometric_direction.{body}"] = fm.dot(icrf_to_station, g[:, None, :]) / fm.norm(
            g, axis=1)[:, None]
        out[f"angular_radius_rad.{body}"] = fm.arcsin(BODY_RADIUS_M[body] / d)
    out["sun_irradiance_w_m2"] = SOLAR_CONSTANT * np.square(AU_M / out["distance_m.sun"])
    return out, retarded


def _sunlight_on_bodies(sun: tuple, centres: dict, icrf_to_station) -> dict[str, np.ndarray]:
    """The Sun as each of LIT_BODIES sees it from its centre (apparent: light time and the body's own
    aberration), with its lit fraction under OCCLUDER (light-time positions of the Sun and the
    occluder as seen from the body)."""
    out = {}
    p_sun, v_sun = sun
    for body in LIT_BODIES:
        p_b, v_b = centres[body]
        occ = OCCLUDER[body]
        p_o, v_o = centres[occ]
        apparent, to_sun, _ = apparent_vectors(p_sun - p_b, v_sun, v_b)
        to_occ, _ = light_time_vectors(p_o - p_b, v_o)
        d = fm.norm(to_sun, axis=1)
        out[f"body_sun_distance_m.{body}"] = d
        out[f"body_sun_direction.{body}"] = fm.dot(icrf_to_station, apparent[:, None, :])
        out[f"body_sun_irradiance_w_m2.{body}"] = SOLAR_CONSTANT * np.square(AU_M / d)
        out[f"body_lit_fraction.{body}"] = body_lit_fraction(
            p_b + to_sun, p_b, BODY_RADIUS_M[body], p_b + to_occ, BODY_RADIUS_M[occ])
    return out


def _station_eclipse(vectors: dict, seen: dict) -> dict[str, np.ndarray]:
    """The station's eclipse by each of SHADOW_BODIES, and overall: the body leaving less light,
    with the exact lit area when both cover part of the Sun. ``vectors`` are the light-time
    (retarded) vectors: where the Sun and the occluder were when the light now arriving passed them;
    aberration moves both discs together and leaves the overlap alone (docs/physics.md section 11)."""
    out = {}
    codes, lits = [], []
    sep_sun = {}
    for body in SHADOW_BODIES:
        sep = angle_between(vectors["sun"], vectors[body])
        code, lit = classify_eclipse(
            seen["angular_radius_rad.sun"], seen[f"angular_radius_rad.{body}"], sep,
            seen[f"distance_m.{body}"] < seen["distance_m.sun"],
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
            lit_two_occluders(
                vectors["sun"][partial], [vectors[b][partial] for b in SHADOW_BODIES],
                seen["angular_radius_rad.sun"][partial],
                [seen[f"angular_radius_rad.{b}"][partial] for b in SHADOW_BODIES],
                [sep_sun[b][partial] for b in SHADOW_BODIES],
            ),
        )
    out["lit_fraction"] = lit_final
    out["eclipse_code"] = code_all
    out["eclipse_body_code"] = np.where(code_all == LIT, 0, worst + 1).astype(np.int8)
    out["both_occulting"] = both
    return out


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
    geometric_direction: dict[str, tuple[float, float, float]]
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
    vector from the station to the body centre in the STATION FRAME (see module doc) as the
    station sees it (apparent: light time and aberration, docs/physics.md section 11);
    ``geometric_direction[body]`` is the same without them (body(t) - station(t)), for the record.
    ``icrf_to_station[i] @ v_icrf`` maps ICRF vectors into the station frame. Distances are centre
    to centre, light-time distances |body(t - tau) - station(t)|.
    ``sun_irradiance_w_m2`` is the unocculted 1361 (1 AU / d)^2; multiply by ``lit_fraction``
    (or use :func:`sun_light`) for the light that reaches the station.
    ``body_sun_*[body]`` and ``body_lit_fraction[body]`` (for :data:`LIT_BODIES`) are the Sun as
    seen from that body's centre: apparent direction body -> Sun in the station frame, distance, unocculted
    irradiance, and the share of it that reaches the body (:func:`body_sun_light`).
    """

    epochs: tuple[str, ...]
    station_icrf_m: np.ndarray
    station_rel_moon_icrf_m: np.ndarray
    station_vel_rel_moon_icrf_m_s: np.ndarray
    icrf_to_station: np.ndarray
    direction: dict[str, np.ndarray]
    geometric_direction: dict[str, np.ndarray]
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
    positions: str = "apparent"
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
            geometric_direction={b: vec(self.geometric_direction[b]) for b in BODIES},
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
    return [as_utc(v, f"epoch[{k}]") for k, v in enumerate(items)]


def compute_sky(epochs: Iterable[datetime], orbit: Orbit = Orbit()) -> Sky:
    """Station, Sun, Earth, Moon and eclipse state at each epoch (one skyfield call per body).

    ``epochs``: timezone-aware datetimes (any zone; converted to UTC) or ISO strings with an
    offset/Z. Naive datetimes raise EpochError; epochs outside DE421 raise EphemerisRangeError
    naming the valid range, before any ephemeris lookup.
    """
    if not isinstance(orbit, Orbit):
        raise SkyInputError(f"orbit must be an allo_usd.sky.model.Orbit, got {type(orbit).__name__}")
    dts = _prepare_epochs(epochs)
    labels = [iso_utc(d) for d in dts]
    t = time_from_utc(dts)
    check_range(t, labels)
    g = sky_geometry(t, orbit)
    return Sky(
        epochs=tuple(labels),
        station_icrf_m=_readonly(g["station_icrf_m"]),
        station_rel_moon_icrf_m=_readonly(g["station_rel_moon_icrf_m"]),
        station_vel_rel_moon_icrf_m_s=_readonly(g["station_vel_rel_moon_icrf_m_s"]),
        icrf_to_station=_readonly(g["icrf_to_station"]),
        direction={b: _readonly(g[f"direction.{b}"]) for b in BODIES},
        geometric_direction={b: _readonly(g[f"geometric_direction.{b}"]) for b in BODIES},
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


def station_observer(orbit: Orbit = Orbit(), offset_station_m=(0.0, 0.0, 0.0)):
    """The station (plus a fixed offset in the station frame, metres) as a skyfield observer, for
    checking the layers independently: ``station_observer(orbit).at(t).observe(body).apparent()``.
    Its barycentric position and velocity come from the orbit model (the velocity is the station's,
    also for an offset point: the frame's rotation adds under 1 cm/s at 100 m)."""
    from skyfield.vectorlib import VectorFunction

    offset = np.asarray(offset_station_m, dtype=np.float64)
    au_m, day_s = AU_M, SECONDS_PER_DAY

    class Station(VectorFunction):
        center, target = 0, -1_000_001  # barycentric; a made-up NAIF id
        ephemeris = load_de421().eph

        def _at(self, t):
            g = sky_geometry(t, orbit, body_light=False)
            p = g["station_icrf_m"] + fm.dot(np.swapaxes(g["icrf_to_station"], 1, 2), np.asarray(offset, dtype=np.float64))
            return (p / au_m).T, (g["station_vel_icrf_m_s"] / au_m * day_s).T, None, None

    return Station()


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
            "angular_diameter_rad": 2.0 * fm.arcsin(SUN_RADIUS_M / d),
            "distance_m": d,
            "lit_fraction": lit,
            "state": "lit" if lit == 1.0 else "umbra" if lit == 0.0 else "penumbra",
            "eclipse_body": OCCLUDER[b] if lit < 1.0 else "",
        }
    return out
