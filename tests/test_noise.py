"""EMVA 1288 sensor noise: statistics, determinism, and that it keeps the clean image's level."""

import numpy as np
import pytest

from allo_usd.effects.noise import SensorParams, apply_sensor_noise
from allo_usd.errors import AlloError

EXPOSURE = 0.9 * np.pi / 1361.0


def test_mean_is_kept_and_shot_noise_follows_poisson():
    p = SensorParams(prnu=0.0, dsnu_e=0.0, dark_current_e_s=0.0, read_noise_e=0.0)
    level = 0.5
    img = np.full((200, 200), level, dtype=np.float32)
    out = apply_sensor_noise(img, EXPOSURE, seed=1, params=p)
    assert out.mean() == pytest.approx(level, rel=2e-3)  # Poisson on the signal, not added to it
    electrons = level * p.full_well_e
    assert out.std() == pytest.approx(np.sqrt(electrons) / p.full_well_e, rel=0.05)


def test_read_noise_dominates_in_the_dark_and_values_stay_in_range():
    p = SensorParams(prnu=0.0, dsnu_e=0.0, dark_current_e_s=0.0, read_noise_e=13.0)
    out = apply_sensor_noise(np.zeros((256, 256), np.float32), EXPOSURE, seed=2, params=p)
    assert 0.0 <= out.min() and out.max() <= 1.0
    assert out.max() > 0  # read noise shows up above zero after clipping negatives
    saturated = apply_sensor_noise(np.full((8, 8, 3), 50.0, np.float32), EXPOSURE, seed=2, params=p)
    assert (saturated == 1.0).all()  # full well clips


def test_seeded_and_different_per_seed():
    img = np.random.default_rng(0).random((32, 48, 3)).astype(np.float32)
    a = apply_sensor_noise(img, EXPOSURE, seed=5)
    assert np.array_equal(a, apply_sensor_noise(img, EXPOSURE, seed=5))
    assert not np.array_equal(a, apply_sensor_noise(img, EXPOSURE, seed=6))
    assert a.shape == img.shape and a.dtype == np.float32


def test_bad_parameters_are_named():
    with pytest.raises(AlloError, match="sensor parameters"):
        apply_sensor_noise(np.zeros((4, 4)), EXPOSURE, 0, SensorParams(full_well_e=-1))
    with pytest.raises(AlloError, match="exposure"):
        apply_sensor_noise(np.zeros((4, 4)), 0.0, 0)
