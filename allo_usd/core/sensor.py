"""The camera sensor's EMVA 1288 parameters, shared by plans, scene layers and the noise effect
(docs/physics.md section 8, sensor model). Applying the noise is allo_usd.output.sensor_noise."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

from allo_usd.core.errors import AlloError


PHOTON_ENERGY_J = 3.6e-19  # h c / lambda at 550 nm


DEFAULT_SENSOR_SEED = 1288  # EMVA 1288


DERIVED_WHEN_ZERO = ("gain_dn_per_e", "exposure_time_s")  # a 0 in a layer means "derive it"


@dataclass(frozen=True)
class SensorParams:
    """A camera's EMVA 1288 parameters; the defaults are a typical space CMOS (CMV4000 class,
    unverified figures, docs/physics.md section 8). Each maps to one `allo:effects:sensor:*` attribute."""

    quantum_efficiency: float = 0.6
    full_well_e: float = 13_500.0
    read_noise_e: float = 13.0
    dark_current_e_s: float = 125.0
    bits: int = 12
    gain_dn_per_e: float | None = None     # K; None: (2^bits - 1) / full well
    prnu: float = 0.01                     # photo-response non-uniformity (relative, fixed pattern)
    dsnu_e: float = 5.0                    # dark-signal non-uniformity (electrons rms, fixed pattern)
    seed: int = DEFAULT_SENSOR_SEED        # draws PRNU and DSNU: the same pattern in every scene
    exposure_time_s: float | None = None   # None: linear 1.0 of the film exposure fills the full well
    f_number: float = 4.0
    pixel_pitch_m: float = 5.5e-6
    transmission: float = 0.9

    def as_dict(self) -> dict:
        return asdict(self)

    def validate(self) -> None:
        values = {k: v for k, v in asdict(self).items() if v is not None}
        bad = {k: v for k, v in values.items()
               if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0}
        positive = ("full_well_e", "quantum_efficiency", "f_number", "pixel_pitch_m", "transmission",
                    "gain_dn_per_e", "exposure_time_s")
        bad.update({k: values[k] for k in positive if k in values and values[k] == 0})
        if not isinstance(self.bits, int) or not 1 <= self.bits <= 24:
            bad["bits"] = self.bits
        if self.quantum_efficiency > 1 or self.transmission > 1:
            bad.update(quantum_efficiency=self.quantum_efficiency, transmission=self.transmission)
        if not isinstance(self.seed, int) or not 0 <= self.seed < 2 ** 63:
            bad["seed"] = self.seed
        if bad:
            raise AlloError(f"sensor parameters out of range: {bad}; use finite values, positive full well, QE, "
                            "f-number, pitch, transmission, gain and exposure time, QE and transmission <= 1, "
                            "1..24 bits, a seed in 0..2^63-1")

    def gain(self) -> float:
        return ((1 << self.bits) - 1) / self.full_well_e if self.gain_dn_per_e is None else self.gain_dn_per_e

    def resolved(self, film_exposure: float) -> SensorParams:
        """These parameters with the derived ones (gain, exposure time) made concrete."""
        self.validate()
        t = exposure_time_for(self, film_exposure) if self.exposure_time_s is None else self.exposure_time_s
        return replace(self, gain_dn_per_e=self.gain(), exposure_time_s=t)


def photons_per_radiance(p: SensorParams, exposure_time_s: float) -> float:
    area = p.pixel_pitch_m * p.pixel_pitch_m   # squares as products: `** 2` is glibc's pow, which rounds by CPU
    return (math.pi / 4.0) * p.transmission * area * exposure_time_s / (p.f_number * p.f_number * PHOTON_ENERGY_J)


def exposure_time_for(p: SensorParams, film_exposure: float) -> float:
    """Exposure time at which radiance 1/film_exposure (linear 1.0 in the image) fills the full well."""
    if not (math.isfinite(film_exposure) and film_exposure > 0):
        raise AlloError(f"film exposure must be positive, got {film_exposure}")
    white_radiance = 1.0 / film_exposure
    return p.full_well_e / (p.quantum_efficiency * white_radiance * photons_per_radiance(p, 1.0))
