"""Sky geometry: orbit timing, ephemeris range, station frame, float32 budget, eclipses, report."""

from __future__ import annotations

import csv
import math
import warnings
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from allo_usd.core import constants as C
from allo_usd.sky import eclipse as X
from allo_usd.sky import ephemeris as E
from allo_usd.sky import model as S
from allo_usd.core.errors import AlloError, EphemerisRangeError, EpochError, SkyInputError
from allo_usd.core.geometry import angle_between
from allo_usd.sky.eclipse import classify_eclipse, disc_overlap_area, eclipse_from_vectors
from allo_usd.sky.ephemeris import default_epochs
from allo_usd.sky.model import BODIES, BODY_RADIUS_M, body_placement, compute_sky, sun_light
from allo_usd.sky.orbit import Orbit, solve_kepler
from allo_usd.sky.report import CSV_COLUMNS, write_sky_report

UTC = timezone.utc
PERIOD_D = 2 * 29.530589 / 9
FAST = settings(deadline=None, max_examples=40, derandomize=True)


@pytest.fixture(scope="module")
def year():
    return compute_sky(default_epochs(2030, 365))


def _span(start: datetime, step: timedelta, n: int) -> list[datetime]:
    return [start + k * step for k in range(n)]


# ------------------------------------------------------------------------------------- orbit


def test_orbit_constants():
    o = Orbit()
    assert o.semi_major_axis_m == pytest.approx(37_112e3)
    assert o.eccentricity == pytest.approx(0.91246, abs=1e-5)
    assert o.period_days == pytest.approx(6.5624, abs=1e-4)


@FAST
@given(m=st.floats(-50.0, 50.0), e=st.floats(0.0, 0.995))
@pytest.mark.slow
def test_kepler_solver_converges(m, e):
    big_e = solve_kepler(np.array([m]), e)
    wrapped = math.remainder(m, 2 * math.pi)
    assert abs(big_e[0] - e * math.sin(big_e[0]) - wrapped) < 1e-11


def test_period_and_distance_range():
    o = Orbit()
    step = timedelta(minutes=10)
    sky = compute_sky(_span(o.perilune_epoch, step, int(3.2 * PERIOD_D * 144)))
    d = np.asarray(sky.station_moon_distance_m)
    assert d.min() >= o.perilune_radius_m * (1 - 1e-9)
    assert d.max() <= o.apolune_radius_m * (1 + 1e-9)
    assert d.max() > 0.999 * o.apolune_radius_m
    # perilune passages are the local minima; they must sit at k * 6.5624 d (within one step)
    minima = np.flatnonzero((d[1:-1] < d[:-2]) & (d[1:-1] < d[2:])) + 1
    times_d = np.concatenate([[0], minima]) * step.total_seconds() / 86400
    gaps = np.diff(times_d)
    assert len(gaps) == 3
    assert np.all(np.abs(gaps - PERIOD_D) < 2 * step.total_seconds() / 86400)
    # exactly at k periods the station is at perilune
    at = compute_sky([o.perilune_epoch + timedelta(days=k * PERIOD_D) for k in range(4)])
    np.testing.assert_allclose(at.station_moon_distance_m, o.perilune_radius_m, rtol=1e-9)


def test_perilune_over_north_pole_of_rotating_frame():
    o = Orbit(perilune_epoch=datetime(2030, 5, 17, 6, tzinfo=UTC))
    sky = compute_sky([o.perilune_epoch], o)
    eph = E.load_de421()
    t = eph.ts.from_datetime(o.perilune_epoch)
    r = (eph.moon.at(t).position.m - eph.earth.at(t).position.m)
    v = (eph.moon.at(t).velocity.m_per_s - eph.earth.at(t).velocity.m_per_s)
    z = np.cross(r, v)
    rel = sky.station_rel_moon_icrf_m[0]
    assert abs(np.dot(rel, r / np.linalg.norm(r))) < 1e-6 * o.perilune_radius_m
    assert np.dot(rel, z / np.linalg.norm(z)) == pytest.approx(o.perilune_radius_m, rel=1e-9)


def test_fraction_of_time_near_moon_is_small():
    # 2030 at 1-hour resolution: real Kepler timing gives ~3% within 10,000 km (upstream: 64%)
    sky = compute_sky(_span(datetime(2030, 1, 1, tzinfo=UTC), timedelta(hours=1), 24 * 365))
    d = np.asarray(sky.station_moon_distance_m)
    frac = np.mean(d < 10_000e3)
    assert 0.02 < frac < 0.045
    assert len(np.unique(np.round(d, -3))) > 1000  # not 7 distinct distances


# --------------------------------------------------------------------------------- ephemeris


def test_de421_range_edges():
    inside = [datetime(1899, 7, 29, 0, 1, tzinfo=UTC), datetime(2053, 10, 8, 23, 58, tzinfo=UTC)]
    sky = compute_sky(inside)
    assert np.all(np.isfinite(sky.station_icrf_m))
    for bad in (datetime(1899, 7, 28, 23, 58, tzinfo=UTC), datetime(2053, 10, 9, 0, 0, tzinfo=UTC),
                datetime(2100, 1, 1, tzinfo=UTC)):
        with pytest.raises(EphemerisRangeError) as info:
            compute_sky([inside[0], bad])
        msg = str(info.value)
        assert "1899-07-29" in msg and "2053-10-09" in msg
        assert bad.strftime("%Y-%m-%dT%H:%M:%SZ") in msg
        assert isinstance(info.value, ValueError) and isinstance(info.value, AlloError)


def test_skyfield_range_error_is_translated():
    eph = E.load_de421()
    t = eph.ts.utc(np.array([2060]), 1, 1)  # bypass the pre-check on purpose
    with pytest.raises(EphemerisRangeError, match="1899-07-29"):
        S.sky_geometry(t, Orbit())


def test_bad_epochs_raise_clear_errors():
    with pytest.raises(EpochError, match="timezone"):
        compute_sky([datetime(2030, 1, 1)])
    with pytest.raises(EpochError):
        compute_sky([float("nan")])
    with pytest.raises(EpochError):
        compute_sky([])
    with pytest.raises(EpochError, match="timezone"):
        Orbit(perilune_epoch=datetime(2030, 1, 1))
    for kw in ({"perilune_radius_m": float("nan")}, {"period_days": float("inf")},
               {"perilune_radius_m": 1000e3}, {"apolune_radius_m": 1000e3}):
        with pytest.raises(SkyInputError):
            Orbit(**kw)
    with pytest.raises(SkyInputError):
        disc_overlap_area(1.0, float("nan"), 0.5)
    assert issubclass(EpochError, ValueError) and issubclass(SkyInputError, AlloError)


def test_aware_non_utc_and_iso_strings_are_converted():
    plus2 = timezone(timedelta(hours=2))
    a = compute_sky([datetime(2030, 3, 1, 2, tzinfo=plus2), "2030-03-01T00:00:00Z"])
    assert a.epochs == ("2030-03-01T00:00:00Z", "2030-03-01T00:00:00Z")
    np.testing.assert_array_equal(a.station_icrf_m[0], a.station_icrf_m[1])


def test_no_expired_warning_leaks(recwarn):
    E.load_de421.cache_clear()
    before = list(warnings.filters)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        compute_sky(default_epochs(2030, 3))
    assert not [w for w in caught if "finals2000A" in str(w.message)]
    assert list(warnings.filters) == before


def test_default_epochs():
    e = default_epochs(2030, 365)
    assert len(e) == 365 and e[0] == datetime(2030, 1, 1, tzinfo=UTC) and e[-1] == datetime(2030, 12, 31, tzinfo=UTC)
    with pytest.raises(EpochError):
        default_epochs(2030, 0)


# ------------------------------------------------------------------------------ station frame


def test_directions_are_unit_and_moon_is_down(year):
    for b in BODIES:
        np.testing.assert_allclose(np.linalg.norm(year.direction[b], axis=1), 1.0, atol=1e-14)
        np.testing.assert_allclose(np.linalg.norm(year.geometric_direction[b], axis=1), 1.0, atol=1e-14)
        assert np.all(year.angular_radius_rad[b] > 0)
    # The Moon's geometric centre is straight down; the light-time distance differs from the geometric
    # one by at most the Moon's barycentric speed (< 31 km/s) times the light time (d / c).
    np.testing.assert_allclose(year.geometric_direction["moon"], np.tile([0.0, 0.0, -1.0], (len(year), 1)), atol=1e-12)
    d = year.station_moon_distance_m
    assert np.all(np.abs(year.distance_m["moon"] - d) <= 31e3 * d / E.SPEED_OF_LIGHT_M_S)
    # Apparent and geometric directions differ by light time and aberration (~1e-4 rad at most: v/c).
    for b, lo, hi in (("sun", 9e-5, 1.1e-4), ("earth", 1e-6, 1e-5), ("moon", 1e-6, 1e-5)):
        diff = angle_between(year.direction[b], year.geometric_direction[b])
        assert lo < diff.max() < hi, (b, diff.max())


def test_sky_is_read_only_and_at_gives_plain_values(year):
    with pytest.raises(ValueError):
        year.lit_fraction[0] = 0.5
    a = year.at(-1)
    assert a.epoch == "2030-12-31T00:00:00Z"
    assert isinstance(a.lit_fraction, float) and isinstance(a.direction["sun"], tuple)
    assert isinstance(a.direction["sun"][0], float) and isinstance(a.eclipse_state, str)
    with pytest.raises(IndexError):
        year.at(365)


@FAST
@given(when=st.datetimes(min_value=datetime(1900, 1, 1), max_value=datetime(2053, 10, 1),
                         timezones=st.just(UTC)))
@pytest.mark.slow
def test_icrf_to_station_is_a_rotation(when):
    sky = compute_sky([when])
    m = sky.icrf_to_station[0]
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(m) == pytest.approx(1.0, abs=1e-12)
    # +Z is zenith (away from the Moon), +X along the velocity relative to the Moon
    rel = sky.station_rel_moon_icrf_m[0]
    np.testing.assert_allclose(m[2], rel / np.linalg.norm(rel), atol=1e-12)
    assert np.dot(m[0], sky.station_vel_rel_moon_icrf_m_s[0]) > 0


def test_x_axis_matches_finite_difference_velocity():
    ep = _span(datetime(2030, 3, 1, tzinfo=UTC), timedelta(hours=7.3), 60)
    h = timedelta(seconds=1)
    a = compute_sky(ep)
    plus = compute_sky([e + h for e in ep])
    minus = compute_sky([e - h for e in ep])
    fd = (plus.station_rel_moon_icrf_m - minus.station_rel_moon_icrf_m) / 2.0
    v = a.station_vel_rel_moon_icrf_m_s
    assert angle_between(v, fd).max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), np.linalg.norm(fd, axis=1), rtol=1e-5)


# -------------------------------------------------------------------------- rendering budget


def test_body_placement_and_sun_light(year):
    i = int(np.argmin(year.station_moon_distance_m))
    a = year.at(i)
    place = body_placement(a)
    for b in BODIES:
        pos, radius = place[b]
        assert pos.dtype == np.float64 and pos.shape == (3,)
        assert radius == BODY_RADIUS_M[b]
        assert np.linalg.norm(pos) == pytest.approx(a.distance_m[b], rel=1e-12)
    light = sun_light(a)
    assert set(light) >= {"direction_to_sun", "irradiance_w_m2", "angular_diameter_rad", "lit_fraction", "state"}
    assert light["angular_diameter_rad"] == pytest.approx(math.radians(0.533), rel=0.03)


def test_umbra_day_gives_zero_irradiance(year):
    shadowed = np.flatnonzero(np.asarray(year.eclipse_state) == "umbra")
    assert shadowed.size >= 1
    for i in shadowed:
        light = sun_light(year.at(int(i)))
        assert light["irradiance_w_m2"] == 0.0 and light["lit_fraction"] == 0.0
    lit = np.flatnonzero(np.asarray(year.eclipse_state) == "lit")
    assert np.all(np.asarray(year.lit_fraction)[lit] == 1.0)
    assert np.all(np.asarray(year.eclipse_body)[lit] == "")


def test_each_body_sees_its_own_sun(year):
    """The body lamps' Sun: the apparent direction and light-time distance from the body's centre
    (skyfield's observe().apparent() from that centre, in the station frame), irradiance
    1361 (1 AU / d)^2, and a lit fraction of 1 outside eclipses."""
    eph = E.load_de421()
    t = E.time_from_utc([datetime.fromisoformat(x.replace("Z", "+00:00")) for x in year.epochs])
    for b in S.LIT_BODIES:
        with E.quiet_expiry():
            seen = getattr(eph, b).at(t).observe(eph.sun)
            v = np.einsum("nij,nj->ni", year.icrf_to_station, seen.apparent().position.m.T)
            d = np.linalg.norm(seen.position.m.T, axis=1)
        np.testing.assert_allclose(year.body_sun_distance_m[b], d, rtol=1e-12)
        assert angle_between(year.body_sun_direction[b], v).max() < 1e-10
        np.testing.assert_allclose(year.body_sun_irradiance_w_m2[b], 1361.0 * (C.AU_M / d) ** 2, rtol=1e-12)
        # A different Sun from the station's: the parallax is the body's distance over 1 AU at most.
        parallax = angle_between(year.body_sun_direction[b], year.direction["sun"])
        assert 0 < parallax.max() <= np.arcsin(year.distance_m[b] / year.distance_m["sun"]).max() * 1.001
    assert np.all(year.body_lit_fraction["earth"] == 1.0)
    moon_eclipsed = np.flatnonzero(year.body_lit_fraction["moon"] < 1.0)
    assert [year.epochs[i] for i in moon_eclipsed] == ["2030-12-10T00:00:00Z"]  # penumbral lunar eclipse
    lamps = S.body_sun_light(year.at(int(moon_eclipsed[0])))
    moon = lamps["moon"]
    assert 0.9 < moon["lit_fraction"] < 0.99 and (moon["state"], moon["eclipse_body"]) == ("penumbra", "earth")
    assert moon["irradiance_w_m2"] == pytest.approx(moon["irradiance_unoccluded_w_m2"] * moon["lit_fraction"])
    assert (lamps["earth"]["state"], lamps["earth"]["eclipse_body"]) == ("lit", "")
    assert moon["angular_diameter_rad"] == pytest.approx(math.radians(0.533), rel=0.03)
    assert year.lit_fraction[int(moon_eclipsed[0])] == 1.0  # the station itself is in sunlight


def test_total_lunar_eclipse_turns_the_moon_lamp_off_and_a_solar_eclipse_barely_dims_the_earth():
    sky = compute_sky(["2029-12-20T22:40:00Z", "2030-11-25T06:50:00Z", "2030-11-25T12:00:00Z"])
    lunar, solar, after = (S.body_sun_light(sky.at(i)) for i in range(3))
    assert lunar["moon"]["lit_fraction"] == 0.0 and lunar["moon"]["irradiance_w_m2"] == 0.0
    assert lunar["moon"]["state"] == "umbra" and lunar["earth"]["lit_fraction"] == 1.0
    assert sky.lit_fraction[0] == 1.0  # the station, 60,000 km off the Moon, is out of the Earth's shadow
    # The Moon's shadow covers a patch of the Earth's face: the Earth loses a few per cent, not all.
    assert 0.85 < solar["earth"]["lit_fraction"] < 0.99 and solar["earth"]["state"] == "penumbra"
    assert solar["moon"]["lit_fraction"] == 1.0 and after["earth"]["lit_fraction"] == 1.0


@FAST
@given(sep=st.floats(0.0, 0.02), dist=st.floats(3.6e8, 4.1e8), r=st.floats(1.0, 100.0))
@pytest.mark.slow
def test_body_lit_fraction_of_a_small_body_is_the_point_value(sep, dist, r):
    """A body much smaller than the shadow sees what its centre sees (the two-disc lit fraction)."""
    sun = np.array([[C.AU_M, 0.0, 0.0]])
    occ = dist * np.array([[math.cos(sep), math.sin(sep), 0.0]])
    got = X.body_lit_fraction(sun, np.zeros((1, 3)), r, occ, C.EARTH_RADIUS_M)
    _, point, *_ = eclipse_from_vectors(sun, occ, C.SUN_RADIUS_M, C.EARTH_RADIUS_M)
    assert 0.0 <= got[0] <= 1.0
    assert got[0] == pytest.approx(point[0], abs=1e-4)


@pytest.mark.slow
def test_body_lit_fraction_quadrature_converges():
    """256 points against 4,096 through a lunar and a solar eclipse: within 0.005."""
    from datetime import timedelta

    e = E.load_de421()
    start = datetime(2029, 12, 20, 20, 0, tzinfo=UTC)
    dts = [start + timedelta(minutes=6 * k) for k in range(50)] + [datetime(2030, 11, 25, 6, 50, tzinfo=UTC)]
    t = E.time_from_utc(dts)
    p_sun, p_earth, p_moon = (body.at(t).position.m.T for body in (e.sun, e.earth, e.moon))
    for body, occ, rb, ro in ((p_moon, p_earth, C.MOON_RADIUS_M, C.EARTH_RADIUS_M),
                              (p_earth, p_moon, C.EARTH_RADIUS_M, C.MOON_RADIUS_M)):
        coarse = X.body_lit_fraction(p_sun, body, rb, occ, ro)
        fine = X.body_lit_fraction(p_sun, body, rb, occ, ro, points=4096)
        assert np.abs(coarse - fine).max() < 0.005
        assert (fine < 1.0).any()
    with pytest.raises(SkyInputError, match="overlap"):
        X.body_lit_fraction(p_sun[:1], p_moon[:1], rb, p_moon[:1] + 1.0, ro)


@FAST
@given(day=st.integers(0, 364), cam=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
       dist=st.floats(0.0, 100.0))
def test_float32_round_trip_budget(year, day, cam, dist):
    c = np.asarray(cam, dtype=np.float64)
    n = np.linalg.norm(c)
    c = c / n * dist if n > 1e-6 else np.zeros(3)
    c32 = c.astype(np.float32).astype(np.float64)
    for body, (pos, radius) in body_placement(year.at(day)).items():
        p32 = pos.astype(np.float32).astype(np.float64)
        r32 = float(np.float32(radius))
        exact = pos - c
        stored = p32 - c32
        err = float(angle_between(exact, stored))
        assert err <= 1e-5, (body, err)
        ar = math.asin(radius / np.linalg.norm(exact))
        ar32 = math.asin(r32 / np.linalg.norm(stored))
        assert abs(ar32 / ar - 1.0) <= 1e-4, body


def test_sun_irradiance_over_2030(year):
    irr = np.asarray(year.sun_irradiance_w_m2)
    assert 1311.0 <= irr.min() < 1315.0
    assert 1410.0 < irr.max() <= 1415.0


# ---------------------------------------------------------------------------------- eclipses

radius = st.floats(1e-4, 0.6)


@FAST
@given(r1=radius, r2=radius, d=st.floats(0.0, 1.5))
@pytest.mark.slow
def test_overlap_symmetric_and_bounded(r1, r2, d):
    a = disc_overlap_area(r1, r2, d)
    assert a == pytest.approx(disc_overlap_area(r2, r1, d), rel=1e-12, abs=1e-300)
    assert 0.0 <= a <= math.pi * min(r1, r2) ** 2 * (1 + 1e-12)


@FAST
@given(r1=st.floats(0.01, 1.0), r2=st.floats(0.01, 1.0), f=st.floats(0.0, 1.0))
def test_overlap_matches_textbook_lens(r1, r2, f):
    lo, hi = abs(r1 - r2), r1 + r2
    d = lo + f * (hi - lo)
    assume(lo * 1.001 < d < hi * 0.999 and min(r1, r2) / max(r1, r2) > 0.1)
    textbook = (r1 * r1 * math.acos((d * d + r1 * r1 - r2 * r2) / (2 * d * r1))
                + r2 * r2 * math.acos((d * d + r2 * r2 - r1 * r1) / (2 * d * r2))
                - 0.5 * math.sqrt((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2)))
    assert disc_overlap_area(r1, r2, d) == pytest.approx(textbook, rel=1e-8, abs=1e-15)


@FAST
@given(ts=st.floats(0.001, 0.02), tb=radius, s1=st.floats(0.0, 1.5), s2=st.floats(0.0, 1.5))
def test_lit_fraction_monotone_in_separation(ts, tb, s1, s2):
    lo, hi = sorted((s1, s2))
    _, lit = classify_eclipse(ts, tb, np.array([lo, hi]))
    assert 0.0 <= lit[0] <= 1.0 and 0.0 <= lit[1] <= 1.0
    assert lit[0] <= lit[1] + 1e-12


@FAST
@given(ts=st.floats(0.001, 0.02), tb=radius, extra=st.floats(0.0, 1.0))
def test_far_apart_is_lit_and_full_cover_is_umbra(ts, tb, extra):
    code, lit = classify_eclipse(ts, tb, ts + tb + extra + 1e-12)
    assert code == X.LIT and lit == 1.0
    assume(tb > ts * 1.0001)
    sep = extra * (tb - ts) * 0.999
    code, lit = classify_eclipse(ts, tb, sep)
    assert code == X.UMBRA and lit == 0.0
    # body not nearer than the Sun casts no shadow
    code, lit = classify_eclipse(ts, tb, sep, body_nearer=False)
    assert code == X.LIT and lit == 1.0


@FAST
@given(ts=st.floats(0.002, 0.02), k=st.floats(0.05, 0.95), f=st.floats(0.0, 0.99))
def test_annular_lit_fraction(ts, k, f):
    tb = k * ts
    code, lit = classify_eclipse(ts, tb, f * (ts - tb))
    assert code == X.ANNULAR
    assert lit == pytest.approx(1 - k * k, rel=1e-9)


def _rotated(axis_dir: np.ndarray, angle: float, rng: np.random.Generator) -> np.ndarray:
    perp = np.cross(axis_dir, rng.normal(size=3))
    perp /= np.linalg.norm(perp)
    return math.cos(angle) * axis_dir + math.sin(angle) * perp


def test_angle_between_is_accurate_near_zero():
    rng = np.random.default_rng(3)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    for sep in (1e-12, 1e-9, 1e-7):
        v = _rotated(d, sep, rng)
        assert abs(float(angle_between(d * 1.496e11, v * 6.0e6)) - sep) < 1e-6 * sep + 1e-15


@FAST
@given(seed=st.integers(0, 2**31), dist_b=st.floats(2.0e6, 4.0e8), frac=st.floats(0.0, 3.0),
       body=st.sampled_from(["moon", "earth"]))
@pytest.mark.slow
def test_classification_stable_under_tiny_perturbation(seed, dist_b, frac, body):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    r_b = BODY_RADIUS_M[body]
    assume(dist_b > 1.5 * r_b)
    ts = math.asin(C.SUN_RADIUS_M / 1.496e11)
    tb = math.asin(r_b / dist_b)
    sep = frac * (ts + tb)  # from exact alignment (frac 0) to far outside
    margins = [abs(sep - (ts + tb)), abs(sep - abs(tb - ts))]
    assume(min(margins) > 1e-6 * (ts + tb))
    u_sun = d * 1.496e11
    u_b = _rotated(d, sep, rng) * dist_b
    code0, lit0, *_ = eclipse_from_vectors(u_sun, u_b, C.SUN_RADIUS_M, r_b)
    for _ in range(20):
        ps = u_sun * (1 + 1e-9 * rng.uniform(-1, 1, 3))
        pb = u_b * (1 + 1e-9 * rng.uniform(-1, 1, 3))
        code, lit, *_ = eclipse_from_vectors(ps, pb, C.SUN_RADIUS_M, r_b)
        assert code == code0
        assert abs(lit - lit0) < 1e-4
        if code0 == X.UMBRA:
            assert lit == 0.0


def test_two_occluders_exact_area():
    r0 = 0.00465
    # one occluder far away: equals the single-disc exact answer
    single = 1 - disc_overlap_area(r0, 0.01, 0.012) / (math.pi * r0 * r0)
    both = X._sun_minus_discs_area(r0, [(0.012, 0.0, 0.01), (1.0, 0.0, 0.01)]) / (math.pi * r0 * r0)
    assert both == pytest.approx(single, rel=1e-12)
    # two occluders on opposite limbs, not touching each other: areas add
    a1 = disc_overlap_area(r0, 0.01, 0.013)
    a2 = disc_overlap_area(r0, 0.004, 0.006)
    rest = X._sun_minus_discs_area(r0, [(0.013, 0.0, 0.01), (-0.006, 0.0, 0.004)])
    assert rest == pytest.approx(math.pi * r0 * r0 - a1 - a2, rel=1e-10)
    # identical occluders: union = one of them
    same = X._sun_minus_discs_area(r0, [(0.0, 0.008, 0.006), (0.0, 0.008, 0.006)])
    assert same == pytest.approx(math.pi * r0 * r0 - disc_overlap_area(r0, 0.006, 0.008), rel=1e-10)


# ------------------------------------------------------------------------------------ report


@pytest.mark.slow
def test_write_sky_report(tmp_path, year):
    csv_path, png_path = write_sky_report(year, tmp_path / "out" / "sky.csv", tmp_path / "out" / "sky.png")
    with open(csv_path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 366
    assert rows[1][0] == "2030-01-01T00:00:00Z"
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["sky.csv", "sky.png"]
