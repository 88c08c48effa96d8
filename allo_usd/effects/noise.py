"""EMVA 1288 sensor noise on linear radiance (PHYSICS.md section 7).

electrons = Poisson(eta * mu_p + I_dark * t) + N(0, sigma_read^2), clipped to the full well,
times the gain K, quantised to the ADC range. Photons per pixel from radiance L:
mu_p = (pi/4) tau L A_pix t / (N^2 h c / lambda). The exposure time t is chosen so that the
radiance the layer's exposure maps to linear 1.0 fills the full well: the noisy image keeps the
clean image's brightness, and the noise is what that camera would show at that exposure.
Shot noise is Poisson on the signal itself (not added on top of it, which would double the mean).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..errors import AlloError

PHOTON_ENERGY_J = 3.6e-19  # h c / lambda at 550 nm


@dataclass(frozen=True)
class SensorParams:
    """Typical space CMOS (CMV4000 class; unverified figures from PHYSICS.md)."""

    full_well_e: float = 13_500.0
    read_noise_e: float = 13.0
    quantum_efficiency: float = 0.6
    dark_current_e_s: float = 125.0
    bits: int = 12
    f_number: float = 4.0
    pixel_pitch_m: float = 5.5e-6
    transmission: float = 0.9
    prnu: float = 0.01        # photo-response non-uniformity (relative, fixed pattern)
    dsnu_e: float = 5.0       # dark-signal non-uniformity (electrons, fixed pattern)

    def as_dict(self) -> dict:
        return asdict(self)

    def validate(self) -> None:
        bad = {k: v for k, v in asdict(self).items() if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0)}
        if bad or self.full_well_e <= 0 or not 1 <= self.bits <= 24 or self.quantum_efficiency > 1:
            raise AlloError(f"sensor parameters out of range: {bad or asdict(self)}; use finite, non-negative "
                            "values, 0 < QE <= 1, 1..24 bits")


def photons_per_radiance(p: SensorParams, exposure_time_s: float) -> float:
    area = p.pixel_pitch_m ** 2
    return (math.pi / 4.0) * p.transmission * area * exposure_time_s / (p.f_number ** 2 * PHOTON_ENERGY_J)


def exposure_time_for(p: SensorParams, film_exposure: float) -> float:
    """Exposure time at which radiance 1/film_exposure (linear 1.0 in the image) fills the full well."""
    white_radiance = 1.0 / film_exposure
    return p.full_well_e / (p.quantum_efficiency * white_radiance * photons_per_radiance(p, 1.0))


def apply_sensor_noise(image: np.ndarray, film_exposure: float, seed: int,
                       params: SensorParams = SensorParams()) -> np.ndarray:
    """Noisy linear image (same scale as `image`, float32) from a clean linear render.

    `image` holds radiance x film_exposure (what Cycles wrote); the result is the ADC output
    mapped back to that scale, so 1.0 still means full well.
    """
    params.validate()
    if not (math.isfinite(film_exposure) and film_exposure > 0):
        raise AlloError(f"film exposure must be positive, got {film_exposure}")
    rng = np.random.default_rng(seed)
    t = exposure_time_for(params, film_exposure)
    radiance = np.clip(np.nan_to_num(image.astype(np.float64), nan=0.0), 0.0, None) / film_exposure
    mu_e = params.quantum_efficiency * radiance * photons_per_radiance(params, t)
    h, w = image.shape[:2]
    fixed = np.random.default_rng(seed ^ 0x5EED).standard_normal((2, h, w))  # PRNU, DSNU patterns
    prnu = 1.0 + params.prnu * fixed[0]
    dark = params.dark_current_e_s * t + params.dsnu_e * fixed[1]
    if image.ndim == 3:
        prnu, dark = prnu[..., None], dark[..., None]
    mean = np.clip(mu_e * prnu + np.clip(dark, 0, None), 0, 10 * params.full_well_e)
    electrons = rng.poisson(mean).astype(np.float64) + rng.normal(0.0, params.read_noise_e, mean.shape)
    electrons = np.clip(electrons, 0.0, params.full_well_e)
    levels = 2 ** params.bits - 1
    gain = levels / params.full_well_e  # K in DN per electron: full well = full scale
    dn = np.rint(electrons * gain)
    return (dn / levels).astype(np.float32)
