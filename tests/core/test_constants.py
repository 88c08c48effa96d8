"""The physical constants are the values their sources publish (docs/physics.md, "Radii" and "Sun colour").

The cited values are written here once, with their source, independently of allo_usd.core.constants.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from allo_usd.core import constants as C

# IAU 2015 Resolution B3, "On recommended nominal conversion constants for selected solar and planetary
# properties" (XXIXth General Assembly, Honolulu, 2015). Nominal values, exact by definition.
IAU_2015_B3 = {
    "solar_radius_m": 6.957e8,
    "total_solar_irradiance_w_m2": 1361.0,
    "terrestrial_equatorial_radius_m": 6.3781e6,
    "terrestrial_polar_radius_m": 6.3568e6,
}

# Report of the IAU Working Group on Cartographic Coordinates and Rotational Elements: 2009 (Archinal et
# al., Celestial Mechanics and Dynamical Astronomy 109:101-135, 2011), kept in the 2015 report (130:22,
# 2018): mean radii.
WGCCRE_MEAN_RADIUS_M = {"earth": 6_371.0084e3, "moon": 1_737.4e3}

# The Moon's sky: in 2030 the station sees the Earth from within 35 degrees of the Earth's equator plane
# (test_the_station_sees_the_earth_from_low_latitudes), and the Sun lights the Earth from within 23.44.
EARTH_VIEW_LATITUDE_DEG = 35.0


def test_radii_are_the_cited_values():
    assert C.SUN_RADIUS_M == IAU_2015_B3["solar_radius_m"]
    assert C.EARTH_RADIUS_M == WGCCRE_MEAN_RADIUS_M["earth"]
    assert C.MOON_RADIUS_M == WGCCRE_MEAN_RADIUS_M["moon"]
    assert C.SOLAR_CONSTANT == IAU_2015_B3["total_solar_irradiance_w_m2"]


def test_code_uses_the_constants():
    """The sky, its eclipses and the base stage take their radii from the constants, not copies."""
    from allo_usd.sky import eclipse, model

    assert model.BODY_RADIUS_M == {"sun": C.SUN_RADIUS_M, "earth": C.EARTH_RADIUS_M, "moon": C.MOON_RADIUS_M}
    assert eclipse.SUN_RADIUS_M == C.SUN_RADIUS_M and eclipse.MOON_RADIUS_M == C.MOON_RADIUS_M


def _mean_outline_radius(latitude_deg: float) -> float:
    """Mean radius (over azimuth) of the oblate Earth's outline seen from far at `latitude_deg`
    (IAU 2015 B3 nominal equatorial and polar radii)."""
    a, b = IAU_2015_B3["terrestrial_equatorial_radius_m"], IAU_2015_B3["terrestrial_polar_radius_m"]
    lat = math.radians(latitude_deg)
    b_seen = math.hypot(a * math.sin(lat), b * math.cos(lat))
    az = np.linspace(0.0, 2 * np.pi, 20_000, endpoint=False)
    return float(np.mean(a * b_seen / np.hypot(b_seen * np.cos(az), a * np.sin(az))))


def test_the_mean_radius_is_the_better_sphere_for_the_moons_sky():
    """docs/physics.md section 12: seen from within 35 degrees of the equator plane (and as the shadow's
    cross-section), a sphere of the mean radius errs by at most 5.6e-4 on the outline's mean radius,
    the equatorial radius by 1.1e-3 to 1.7e-3."""
    lats = np.linspace(0.0, EARTH_VIEW_LATITUDE_DEG, 8)
    mean_err = [C.EARTH_RADIUS_M / _mean_outline_radius(lat) - 1 for lat in lats]
    equatorial_err = [IAU_2015_B3["terrestrial_equatorial_radius_m"] / _mean_outline_radius(lat) - 1 for lat in lats]
    assert 0.0 < min(mean_err) and max(mean_err) < 5.7e-4
    assert 1.1e-3 < min(equatorial_err) and max(equatorial_err) < 1.7e-3


def test_the_station_sees_the_earth_from_low_latitudes():
    """The latitude range the choice above rests on, hourly over 2030 (ICRF's equator stands for the Earth's)."""
    from datetime import datetime, timedelta, timezone

    from allo_usd.sky.model import compute_sky

    t0 = datetime(2030, 1, 1, tzinfo=timezone.utc)
    sky = compute_sky([t0 + timedelta(hours=h) for h in range(365 * 24)])
    to_earth = np.einsum("nji,nj->ni", np.asarray(sky.icrf_to_station), np.asarray(sky.direction["earth"]))
    latitude = np.degrees(np.arcsin(-to_earth[:, 2] / np.linalg.norm(to_earth, axis=1)))
    assert np.abs(latitude).max() < EARTH_VIEW_LATITUDE_DEG
    assert np.abs(latitude).max() > EARTH_VIEW_LATITUDE_DEG - 2  # the bound is not loose


def test_sun_colour_is_white():
    """One colour for the Sun's light and its disc (docs/physics.md, "Sun colour"): the lamps' intensity is the
    total solar irradiance over the whole spectrum, in a colour-neutral RGB."""
    assert C.SUN_COLOR == (1.0, 1.0, 1.0)


@pytest.mark.parametrize("name", ["SUN_RADIUS_M", "EARTH_RADIUS_M", "MOON_RADIUS_M"])
def test_radii_are_plain_floats(name):
    value = getattr(C, name)
    assert isinstance(value, float) and math.isfinite(value) and value > 0
