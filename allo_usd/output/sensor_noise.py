"""EMVA 1288 sensor noise on linear radiance (docs/physics.md section 8).

electrons = Poisson(eta * mu_p * PRNU + I_dark * t) + DSNU + N(0, sigma_read^2), clipped to
[0, full well], times the gain K (DN per electron), rounded and clipped to the ADC range. PRNU is
a per-pixel gain 1 + prnu * z, DSNU a per-pixel signed offset dsnu * z (z ~ N(0, 1), fixed). Photons
per pixel from radiance L: mu_p = (pi/4) tau L A_pix t / (N^2 h c / lambda). Shot noise is Poisson
on the signal itself (not added on top of it, which would double the mean).

Two seeds, two kinds of noise:
- the SENSOR's seed (`SensorParams.seed`, default 1288) draws the fixed patterns, PRNU (gain per
  pixel) and DSNU (dark offset per pixel): one sensor, one pattern, the same in every scene it
  takes (for a given resolution);
- the scene's render seed draws the temporal noise (shot and read noise), new in every image.

Every parameter is recorded in the scene layer (`allo:effects:sensor:*` on the render settings,
AlloEffectsAPI). Two are derived when left at 0 (None here): the exposure time, chosen so that the
radiance the layer's film exposure maps to linear 1.0 fills the full well (the noisy image keeps
the clean image's brightness), and the gain, which maps the full well to the ADC's full scale.
The author writes them resolved, so a layer holds concrete values. The result is the ADC output
on the clean image's scale: DN / (K * full well), so 1.0 still means a full well.
"""

from __future__ import annotations


import numpy as np

from allo_usd.core.sensor import SensorParams, photons_per_radiance

# Stream tags: the fixed-pattern and temporal generators never share a bit stream, even when the
# sensor seed equals a render seed.
_FIXED_PATTERN_STREAM = 0x5EED_F1ED
_TEMPORAL_STREAM = 0x7E4_90A1


def fixed_patterns(params: SensorParams, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(PRNU gain, DSNU offset in electrons) per pixel, drawn from the sensor's seed alone."""
    z = np.random.default_rng([params.seed, _FIXED_PATTERN_STREAM]).standard_normal((2, *shape))
    return 1.0 + params.prnu * z[0], params.dsnu_e * z[1]


def mean_electrons(image: np.ndarray, film_exposure: float, params: SensorParams) -> np.ndarray:
    """Expected photo-electrons per pixel (before fixed patterns and dark signal) of a clean image."""
    p = params.resolved(film_exposure)
    radiance = np.clip(np.nan_to_num(np.asarray(image, np.float64), nan=0.0), 0.0, None) / film_exposure
    return p.quantum_efficiency * radiance * photons_per_radiance(p, p.exposure_time_s)


def apply_sensor_noise(image: np.ndarray, film_exposure: float, seed: int,
                       params: SensorParams = SensorParams()) -> np.ndarray:
    """Noisy linear image (same scale as `image`, float32) from a clean linear render.

    `image` holds radiance x film_exposure (what Cycles wrote); `seed` (the scene's render seed)
    draws the temporal noise, `params.seed` the sensor's fixed patterns.
    """
    p = params.resolved(film_exposure)
    mu_e = mean_electrons(image, film_exposure, p)
    prnu, dsnu = fixed_patterns(p, image.shape[:2])
    if image.ndim == 3:
        prnu, dsnu = prnu[..., None], dsnu[..., None]
    mean = np.clip(mu_e * prnu + p.dark_current_e_s * p.exposure_time_s, 0, 10 * p.full_well_e)
    rng = np.random.default_rng([int(seed) % 2 ** 63, _TEMPORAL_STREAM])
    # DSNU is a signed fixed offset, like the read noise a temporal one: both act after the Poisson draw.
    electrons = rng.poisson(mean).astype(np.float64) + dsnu + rng.normal(0.0, p.read_noise_e, mean.shape)
    electrons = np.clip(electrons, 0.0, p.full_well_e)
    k = p.gain_dn_per_e
    dn = np.clip(np.rint(electrons * k), 0, (1 << p.bits) - 1)
    return (dn / (k * p.full_well_e)).astype(np.float32)
