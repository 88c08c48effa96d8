"""The station's orbit: an NRHO approximation timed by Kepler's equation.

Station orbit (docs/physics.md section 2)
    Ellipse (perilune/apolune radii of :class:`Orbit`) fixed in the Earth-Moon *rotating* frame
    rebuilt at each epoch: x = unit(Moon - Earth), z = unit(r x v) of the Moon about the Earth,
    y = z x x. The ellipse lies in the x-z plane with perilune along +z (over the lunar north
    pole) and apolune along -z. Timing by Kepler's equation with the mean motion forced to
    2 pi / period; after perilune the station moves toward +x (away from the Earth). The
    station is Moon + [x y z] . r_rot in ICRF axes. (The approximation puts apolune straight
    below the south pole; the real NRHO's apolune lies ~12,900 km beyond the Moon.)

"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from allo_usd.core.constants import MOON_RADIUS_M, SECONDS_PER_DAY
from allo_usd.core.errors import SkyInputError
from allo_usd.sky.ephemeris import as_utc, finite_number, iso_utc
from allo_usd.core import fixedmath as fm


# ---------------------------------------------------------------------------------------------
# Orbit


def solve_kepler(mean_anomaly, eccentricity: float, tol: float = 1e-12, max_iter: int = 60) -> np.ndarray:
    """Eccentric anomaly E with E - e sin E = M, vectorised Newton to |dE| < ``tol``.

    M is wrapped to [-pi, pi) first, so E is returned in [-pi, pi]. Starts from Danby's
    E0 = M + 0.85 e sign(M), which converges for every 0 <= e < 1.
    """
    e = finite_number("eccentricity", eccentricity)
    if not 0.0 <= e < 1.0:
        raise SkyInputError(f"eccentricity must be in [0, 1), got {e}")
    m = np.asarray(mean_anomaly, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise SkyInputError("mean anomaly contains NaN or inf")
    m = np.remainder(m + np.pi, 2.0 * np.pi) - np.pi
    big_e = m + 0.85 * e * np.where(m >= 0.0, 1.0, -1.0)
    for _ in range(max_iter):
        d = (big_e - e * fm.sin(big_e) - m) / (1.0 - e * fm.cos(big_e))
        big_e = big_e - d
        if not np.any(np.abs(d) >= tol):
            return big_e
    raise SkyInputError(f"Kepler's equation did not converge to {tol} in {max_iter} iterations (e={e})")


@dataclass(frozen=True)
class Orbit:
    """NRHO approximation (docs/physics.md section 2): ellipse in the Earth-Moon rotating x-z plane.

    ``perilune_epoch`` is the UTC instant of perilune passage; record it in every layer.
    """

    perilune_radius_m: float = 3_249e3
    apolune_radius_m: float = 70_975e3
    period_days: float = 2 * 29.530589 / 9
    perilune_epoch: datetime = datetime(2030, 1, 1, tzinfo=timezone.utc)

    def __post_init__(self) -> None:
        rp = finite_number("perilune_radius_m", self.perilune_radius_m)
        ra = finite_number("apolune_radius_m", self.apolune_radius_m)
        p = finite_number("period_days", self.period_days)
        if rp <= MOON_RADIUS_M:
            raise SkyInputError(f"perilune_radius_m {rp} must exceed the Moon's radius {MOON_RADIUS_M} m")
        if ra < rp:
            raise SkyInputError(f"apolune_radius_m {ra} must be >= perilune_radius_m {rp}")
        if p <= 0.0:
            raise SkyInputError(f"period_days must be positive, got {p}")
        object.__setattr__(self, "perilune_radius_m", rp)
        object.__setattr__(self, "apolune_radius_m", ra)
        object.__setattr__(self, "period_days", p)
        object.__setattr__(self, "perilune_epoch", as_utc(self.perilune_epoch, "perilune_epoch"))

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
        s, c = fm.sin(big_e), fm.cos(big_e)
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
            "perilune_epoch": iso_utc(self.perilune_epoch),
            "model": "NRHO approx: Kepler ellipse in Earth-Moon rotating x-z plane, perilune +z",
        }

