"""EMVA 1288 sensor noise: statistics, determinism, and that it keeps the clean image's level."""

import numpy as np
import pytest

from allo_usd.core.sensor import SensorParams
from allo_usd.output.sensor_noise import apply_sensor_noise
from allo_usd.core.errors import AlloError

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


# --- The EMVA 1288 model's statistics -----------------------------------------------------------

def _dn(out: np.ndarray, p: SensorParams) -> np.ndarray:
    """Back from the image scale (1.0 = full well) to digital numbers."""
    p = p.resolved(EXPOSURE)
    return out.astype(np.float64) * p.gain_dn_per_e * p.full_well_e


@pytest.mark.parametrize("gain, bits", [(None, 12), (2.0, 16)])  # K = 4095/13500 DN/e-, and K = 2
@pytest.mark.parametrize("level", [0.05, 0.3, 0.7])
def test_flat_field_mean_and_variance_follow_emva_1288(level, gain, bits):
    """mu_y = K (mu_e + mu_dark), sigma_y^2 = K^2 (sigma_read^2 + mu_e + mu_dark) + 1/12 (quantisation)."""
    from allo_usd.output.sensor_noise import mean_electrons

    p = SensorParams(prnu=0.0, dsnu_e=0.0, gain_dn_per_e=gain, bits=bits)
    r = p.resolved(EXPOSURE)
    img = np.full((400, 400), level, np.float32)
    dn = _dn(apply_sensor_noise(img, EXPOSURE, seed=11, params=p), p)
    mu_e = float(mean_electrons(img, EXPOSURE, p).mean())
    assert mu_e == pytest.approx(level * p.full_well_e, rel=1e-6)  # t fills the full well at 1.0
    dark = r.dark_current_e_s * r.exposure_time_s
    k = r.gain_dn_per_e
    assert dn.mean() == pytest.approx(k * (mu_e + dark), rel=2e-3)
    assert dn.var() == pytest.approx(k ** 2 * (r.read_noise_e ** 2 + mu_e + dark) + 1 / 12, rel=0.02)


def test_prnu_and_dsnu_add_their_spatial_variance():
    base = SensorParams(prnu=0.0, dsnu_e=0.0, read_noise_e=0.0, dark_current_e_s=0.0)
    img = np.full((300, 300), 0.5, np.float32)
    mu_e = 0.5 * base.full_well_e
    k = base.resolved(EXPOSURE).gain_dn_per_e
    with_prnu = SensorParams(**{**base.as_dict(), "prnu": 0.05})
    dn = _dn(apply_sensor_noise(img, EXPOSURE, seed=3, params=with_prnu), with_prnu)
    assert dn.var() == pytest.approx(k ** 2 * (mu_e + (0.05 * mu_e) ** 2) + 1 / 12, rel=0.03)
    with_dsnu = SensorParams(**{**base.as_dict(), "dsnu_e": 60.0})
    dn = _dn(apply_sensor_noise(img, EXPOSURE, seed=3, params=with_dsnu), with_dsnu)
    assert dn.var() == pytest.approx(k ** 2 * (mu_e + 60.0 ** 2) + 1 / 12, rel=0.03)


# --- Seeds: the sensor fixes the pattern, the scene draws the temporal noise ----------------------

def _corr(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_fixed_pattern_belongs_to_the_sensor_and_temporal_noise_to_the_scene():
    from allo_usd.output.sensor_noise import fixed_patterns

    p = SensorParams(prnu=0.1, dsnu_e=0.0, read_noise_e=0.0, dark_current_e_s=0.0)
    dark_and_bright = [np.full((200, 200), v, np.float32) for v in (0.3, 0.6)]  # two different scenes
    a = apply_sensor_noise(dark_and_bright[0], EXPOSURE, seed=101, params=p) / 0.3
    b = apply_sensor_noise(dark_and_bright[1], EXPOSURE, seed=202, params=p) / 0.6
    assert not np.array_equal(a, b)
    assert _corr(a, b) > 0.9  # the same PRNU pattern in both scenes
    other_sensor = SensorParams(**{**p.as_dict(), "seed": 7})
    c = apply_sensor_noise(dark_and_bright[1], EXPOSURE, seed=202, params=other_sensor) / 0.6
    assert abs(_corr(a, c)) < 0.02  # another sensor, another pattern
    same_sensor_other_scene = SensorParams(prnu=0.1, dsnu_e=0.0, exposure_time_s=1e-3)
    for x, y in zip(fixed_patterns(p, (50, 60)), fixed_patterns(same_sensor_other_scene, (50, 60))):
        np.testing.assert_array_equal(x, y)  # drawn from the sensor's seed alone
    # The render seed draws only temporal noise: without fixed patterns two seeds are uncorrelated.
    q = SensorParams(prnu=0.0, dsnu_e=0.0)
    d, e = (apply_sensor_noise(dark_and_bright[0], EXPOSURE, seed=s, params=q) for s in (101, 102))
    assert not np.array_equal(d, e) and abs(_corr(d, e)) < 0.02
    np.testing.assert_array_equal(d, apply_sensor_noise(dark_and_bright[0], EXPOSURE, seed=101, params=q))


def test_sensor_seed_equal_to_the_render_seed_shares_no_stream():
    p = SensorParams(prnu=0.0, dsnu_e=50.0, read_noise_e=0.0, dark_current_e_s=0.0, seed=5)
    dark = apply_sensor_noise(np.zeros((200, 200), np.float32), EXPOSURE, seed=5, params=p)
    from allo_usd.output.sensor_noise import fixed_patterns

    _, dsnu = fixed_patterns(p, (200, 200))
    assert _corr(dark, np.clip(dsnu, 0, None)) > 0.9  # the dark frame shows the DSNU pattern ...
    shot = apply_sensor_noise(np.full((200, 200), 0.5, np.float32), EXPOSURE, seed=5,
                              params=SensorParams(prnu=0.0, dsnu_e=0.0, read_noise_e=0.0, seed=5))
    assert abs(_corr(shot, dsnu)) < 0.02  # ... and the temporal draws are independent of it


# --- The layer records the sensor ----------------------------------------------------------------

def _noisy_spec(render_seed: int, anomaly: bool, sensor: SensorParams = SensorParams()):
    from dataclasses import replace

    from allo_usd.plan.settings import EffectsSpec

    from tests.support.helpers import make_spec

    spec = make_spec(anomaly=anomaly, seed=render_seed)
    return replace(spec, render=replace(spec.render, seed=render_seed),
                   effects=EffectsSpec(sensor_noise=True, sensor=sensor))


def test_layer_carries_every_sensor_parameter(tiny_base, tmp_path):
    from pxr import Sdf

    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.core.sensor import exposure_time_for
    from allo_usd.usd.attributes import SENSOR_ATTRIBUTES
    from allo_usd.usd.read import read_scene

    sensor = SensorParams(quantum_efficiency=0.55, full_well_e=10_000.0, read_noise_e=4.5, bits=10, seed=99,
                          f_number=2.8)
    layer = write_scene_layer(_noisy_spec(3, False, sensor), tmp_path / "n.usda", tiny_base)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    settings = sdf.GetPrimAtPath("/Render/Settings")
    authored = {name: settings.attributes[name].default for name, _ in SENSOR_ATTRIBUTES.values()}
    assert authored["allo:effects:sensor:seed"] == 99 and authored["allo:effects:sensor:bitDepth"] == 10
    assert authored["allo:effects:sensor:gain"] == pytest.approx(1023 / 10_000)  # resolved, not 0
    assert authored["allo:effects:sensor:exposureTime"] == pytest.approx(exposure_time_for(sensor, EXPOSURE))
    assert authored["allo:effects:sensor:readNoise"] == 4.5 and authored["allo:effects:sensor:fNumber"] == 2.8
    desc = read_scene(layer)
    assert desc.render.exposure == pytest.approx(EXPOSURE, rel=1e-6)  # the camera's EV, stored as a float
    assert desc.effects.sensor == sensor.resolved(desc.render.exposure)

    from tests.support.validation import validation_errors

    assert validation_errors(layer) == []

    from dataclasses import replace

    from allo_usd.plan.settings import EffectsSpec

    quiet = write_scene_layer(replace(_noisy_spec(3, False), effects=EffectsSpec()), tmp_path / "q.usda", tiny_base)
    sdf = Sdf.Layer.FindOrOpen(str(quiet))
    settings = sdf.GetPrimAtPath("/Render/Settings")
    assert not [n for n in settings.attributes.keys() if n.startswith("allo:effects:sensor:")]
    assert read_scene(quiet).effects.sensor is None


def test_layer_without_sensor_attributes_gets_the_default_sensor(tiny_base, tmp_path):
    from pxr import Sdf

    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.usd.read import read_scene

    layer = write_scene_layer(_noisy_spec(3, False), tmp_path / "old.usda", tiny_base)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    settings = sdf.GetPrimAtPath("/Render/Settings")
    for name in [n for n in settings.attributes.keys() if n.startswith("allo:effects:sensor:")]:
        settings.RemoveProperty(settings.attributes[name])
    sdf.Save()
    sensor = read_scene(layer).effects.sensor
    assert sensor == SensorParams()  # schema fallbacks; gain and exposure time derived when applied
    assert sensor.resolved(EXPOSURE) == SensorParams().resolved(EXPOSURE)


def test_bad_sensor_in_a_layer_is_named(tiny_base, tmp_path):
    from pxr import Sdf

    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.core.errors import LayerError
    from allo_usd.usd.read import read_scene

    with pytest.raises(LayerError, match="sensor parameters"):
        write_scene_layer(_noisy_spec(3, False, SensorParams(quantum_efficiency=1.5)), tmp_path / "x.usda", tiny_base)
    assert not (tmp_path / "x.usda").exists()  # validated before authoring
    layer = write_scene_layer(_noisy_spec(3, False), tmp_path / "b.usda", tiny_base)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    sdf.GetPrimAtPath("/Render/Settings").attributes["allo:effects:sensor:fullWell"].default = -1.0
    sdf.Save()
    with pytest.raises(LayerError, match="allo:effects:sensor:fullWell"):
        read_scene(layer)


def test_two_scenes_of_one_sensor_share_the_pattern_through_their_layers(tiny_base, tmp_path):
    """From layer to noise: two different scenes (other render seed, one with an anomaly) read back
    the same sensor, so PRNU is identical while the temporal noise differs."""
    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.run.job import apply_effects
    from allo_usd.usd.read import read_scene

    sensor = SensorParams(prnu=0.1, read_noise_e=0.0, dsnu_e=0.0, dark_current_e_s=0.0)
    descs = [read_scene(write_scene_layer(_noisy_spec(s, a, sensor), tmp_path / f"{s}.usda", tiny_base))
             for s, a in ((11, False), (12, True))]
    assert descs[0].render.seed != descs[1].render.seed
    flat = np.full((120, 160, 3), 0.5, np.float32)
    (a, meta_a), (b, meta_b) = (apply_effects(d, flat) for d in descs)
    assert not np.array_equal(a, b)
    assert _corr(a, b) > 0.9
    assert meta_a["sensor_noise"]["sensor_seed"] == meta_b["sensor_noise"]["sensor_seed"] == 1288
    assert (meta_a["sensor_noise"]["temporal_seed"], meta_b["sensor_noise"]["temporal_seed"]) == (11, 12)
