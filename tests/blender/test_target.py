"""Rendering to a PSNR target (allo_usd.blender.target): the estimator's arithmetic, the round schedule,
and real tiny Cycles renders that stop on the target or on the cap and leave the Blender scene as it was."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from allo_usd.blender import target as tg


def test_identical_halves_estimate_an_exact_image():
    """No difference between the halves: every pixel is its converged code, rounding adds nothing, and the
    PSNR is the recorded ceiling (a finite number JSON holds)."""
    a = np.random.default_rng(1).random((6, 8, 3))
    est = tg.estimated(a, a)
    assert est.mse == 0.0 and est.stderr == 0.0
    assert est.psnr_db == est.lower_psnr_db == tg.PSNR_CEILING_DB
    assert tg.psnr_db(255.0 ** 2) == pytest.approx(0.0)
    assert tg.psnr_db(1.0 / 6) == pytest.approx(10 * math.log10(255.0 ** 2 * 6))


def test_small_noise_is_a_quarter_of_the_halves_squared_difference_in_srgb_units():
    rng = np.random.default_rng(2)
    a = rng.uniform(0.2, 0.8, (10, 12, 3))
    b = a + rng.normal(0.0, 0.01, a.shape)
    d = tg.srgb_units(a) - tg.srgb_units(b)
    sm = tg.srgb_units((a + b) / 2)
    e = tg.error_map(a, b)
    assert e == pytest.approx(np.maximum((sm - tg.srgb_units(a)) ** 2, (sm - tg.srgb_units(b)) ** 2).mean(-1))
    assert float(e.mean()) == pytest.approx(float(np.mean(d * d)) / 4, rel=0.02)
    # the transfer is IEC 61966-2-1's, 0..255 unrounded, clipped
    assert tg.srgb_units(np.array([0.0, 1.0, 2.0, -1.0, 0.0031308])).tolist() == pytest.approx(
        [0.0, 255.0, 255.0, 0.0, 255 * 12.92 * 0.0031308])


def test_the_estimate_of_independent_noise_is_the_means_true_error_in_8_bit_codes():
    """Two independent noisy halves of a known image: the estimate is the measured error of the mean's
    8-bit codes against the truth's codes (in expectation; here within 5 % on a million values), rounding
    included, at a noise of a few codes and at a fraction of one. Where the noise is large beside a dark
    value (sd a third of it) the curve bends within it and the max form errs on the safe side: above the
    truth, here by 35 % (its real renders' heavy tails, which Gaussian noise lacks, take most of that back:
    docs/benchmarks/bench_accuracy.md)."""
    rng = np.random.default_rng(3)

    def both(truth, sd):
        a, b = (truth + rng.normal(0.0, sd, truth.shape) for _ in range(2))
        codes = float(np.mean((np.round(tg.srgb_units((a + b) / 2)) - np.round(tg.srgb_units(truth))) ** 2))
        return tg.estimated(a, b).mse, codes

    for sd in (0.02, 0.0004):
        est, codes = both(rng.uniform(0.3, 0.6, (500, 700, 3)), sd)
        assert est == pytest.approx(codes, rel=0.05)
    est, codes = both(rng.uniform(0.05, 0.1, (500, 700, 3)), 0.02)
    assert codes < est < 1.5 * codes


def test_rounding_adds_a_sixth_to_noisy_pixels_and_nothing_to_exact_ones():
    """rounding_mse against a simulation: 8-bit codes of a value with a uniform place in its code, plus
    N(0, sigma**2) noise, differ from its own code by sigma**2 + rounding_mse(sigma**2) squared codes."""
    rng = np.random.default_rng(7)
    u = rng.uniform(0, 200, 2_000_000)
    for sigma in (0.0, 0.01, 0.1, 0.3, 1.0, 3.0):
        sim = float(np.mean((np.round(u + rng.normal(0, sigma, u.size)) - np.round(u)) ** 2))
        assert sigma ** 2 + float(tg.rounding_mse(np.array(sigma ** 2))) == pytest.approx(sim, rel=0.02, abs=1e-4)
    assert float(tg.rounding_mse(np.array(100.0))) == pytest.approx(1 / 6)


def test_a_glint_one_half_found_counts_its_full_error():
    """A sun glint: one sample thousands of times the pixel's value saturates one half and the mean. Its
    pixel counts (255 - s(B))**2, the error of the mean had the glint been absent from the truth, not the
    quarter (s(A) - s(B))**2 / 4 says, standing for the glints of like odds that neither half found."""
    a = np.full((4, 4, 3), 0.02)
    b = a.copy()
    a[1, 2] = 80.0
    e = tg.error_map(a, b)
    assert e[1, 2] == pytest.approx((255.0 - tg.srgb_units(0.02)) ** 2)
    assert e[0, 0] == 0.0


def test_the_standard_error_is_the_spread_of_block_means():
    """estimate_of's standard error: for independent pixel errors, the pixels' spread over the square root of
    their number; one pixel's heavy error (a glint) widens it, and the bound a target clears lies below."""
    rng = np.random.default_rng(8)
    e = rng.exponential(4.0, (160, 240))
    est = tg.estimate_of(e)
    assert est.stderr == pytest.approx(e.std() / math.sqrt(e.size), rel=0.15)
    assert est.lower_psnr_db < est.psnr_db
    assert est.upper_mse == pytest.approx(est.mse + tg.CONFIDENCE_Z * est.stderr)
    e[80, 120] = 255.0 ** 2
    assert tg.estimate_of(e).stderr > 5 * est.stderr
    assert tg.estimate_of(e[:3, :5]).stderr >= 0.0   # smaller than a block: one block each way


def test_a_denoisers_blur_is_in_the_estimate_not_only_its_variance():
    """A stand-in denoiser that blurs (a 5x5 box: less variance, a bias on every detail both halves share):
    the cross-validated estimate finds the delivered image's measured error, bias included, where the
    denoised halves' own difference alone misses most of it."""
    from scipy.ndimage import uniform_filter

    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:400, 0:600]
    truth = np.repeat((0.3 + 0.2 * np.sin(xx / 6.0) * np.sin(yy / 7.0))[..., None], 3, axis=-1)   # detail to blur
    a, b = (truth + rng.normal(0.0, 0.03, truth.shape) for _ in range(2))
    da, db = (uniform_filter(x, size=(5, 5, 1)) for x in (a, b))
    delivered = (da + db) / 2
    measured = float(np.mean((tg.srgb_units(delivered) - tg.srgb_units(truth)) ** 2))
    estimate = float(tg.error_map(a, b, da, db).mean())
    assert estimate == pytest.approx(measured, rel=0.1)
    variance_only = float(np.mean((tg.srgb_units(da) - tg.srgb_units(db)) ** 2)) / 4
    assert variance_only < 0.5 * measured


def test_a_denoiser_blob_over_black_counts_its_full_error_in_codes():
    """OIDN spreads one glint sample in one half into a bright blob where both noisy halves, and the truth,
    are black: the denoised halves split (0.5 against 0), the delivered value is 0.25, 137 codes off.
    The cross-validation has that error right in linear values; in codes it takes the secant, not the
    slope at 0.25, which would say less than half of it."""
    a = np.zeros((16, 16, 3))
    b = a.copy()
    da, db = a.copy(), a.copy()
    da[4:11, 5:12] = 0.5
    e = tg.error_map(a, b, da, db)
    truth = float(tg.srgb_units(0.25)) ** 2
    assert e[6, 8] == pytest.approx(truth, rel=1e-9) and e[0, 0] == 0.0
    tangent = float(tg.srgb_slope_sq(0.25)) * 0.25 ** 2
    assert tangent < 0.5 * truth
    # denoised halves within SPLIT_CODES of each other (149 and 156 codes) keep the slope
    da[4:11, 5:12], db[4:11, 5:12] = 0.30, 0.33
    d = 0.315
    assert tg.error_map(a, b, da, db)[6, 8] == pytest.approx(float(tg.srgb_slope_sq(d)) * d * d, rel=1e-9)


@pytest.mark.parametrize("done, mse, target, cap, expected", [
    (16, 40.0, 10.0, 4096, 16),       # needs ~4.6x: at most doubles
    (16, 12.0, 10.0, 4096, 8),        # needs a little: at least FIRST_SAMPLES // 2
    (64, 11.0, 10.0, 4096, 17),       # 64 * 1.1 * 1.15 -> 81: 17 more
    (2000, 40.0, 10.0, 2048, 48),     # the cap
    (2048, 40.0, 10.0, 2048, 0),      # at the cap: stop
])
def test_each_round_asks_for_what_the_target_needs_within_bounds(done, mse, target, cap, expected):
    assert tg.next_samples(done, mse, target, cap) == expected


def test_half_seeds_are_distinct_and_cycles_seeds():
    seeds = {tg.half_seed(2 ** 31 - 5, r, h) for r in range(50) for h in (0, 1)}
    assert len(seeds) == 100 and all(0 <= s < 2 ** 31 for s in seeds)
    assert tg.half_seed(2 ** 31 - 5, 0, 0) == 2 ** 31 - 5   # the first half is the layer's own render: its mask


@pytest.fixture(scope="module")
def tiny_scene(tiny_base, tmp_path_factory):
    from allo_usd.usd.read import read_scene
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    root = tmp_path_factory.mktemp("target")
    return read_scene(write_scene_layer(make_spec(anomaly=True, samples=256), root / "t.usda", tiny_base))


def _with_target(desc, target: float, samples: int, denoise: bool = False):
    render = dataclasses.replace(desc.render, samples=samples, denoise=denoise, target_psnr=target, time_limit=0.0)
    return dataclasses.replace(desc, render=render)


@pytest.mark.render
def test_a_target_render_stops_on_the_target_and_restores_the_scene(tiny_scene):
    import bpy

    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current

    desc = _with_target(tiny_scene, 30.0, 4096)
    build_scene(desc)
    scene = bpy.context.scene
    before = (scene.cycles.samples, scene.cycles.seed, scene.cycles.use_denoising,
              scene.cycles.use_adaptive_sampling, scene.view_layers[0].cycles.denoising_store_passes)
    result = render_current(desc)
    acc = result.accuracy
    assert acc["mode"] == "target" and acc["stopped_by"] == "target" and acc["lower_psnr_db"] >= 30.0
    assert acc["estimated_psnr_db"] >= acc["lower_psnr_db"] and acc["estimate_stderr_mse"] >= 0.0
    assert acc["samples"] <= 4096 and acc["rounds"] >= 1 and acc["samples"] % 2 == 0
    assert result.rgb.shape == (36, 64, 3) and np.isfinite(result.rgb).all() and result.rgb.max() > 0.05
    assert set(np.unique(result.mask)) == {0, 1, 2}
    after = (scene.cycles.samples, scene.cycles.seed, scene.cycles.use_denoising,
             scene.cycles.use_adaptive_sampling, scene.view_layers[0].cycles.denoising_store_passes)
    assert after == before


@pytest.mark.render
def test_a_target_beyond_the_cap_stops_on_the_samples_and_says_so(tiny_scene):
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current

    desc = _with_target(tiny_scene, 90.0, 8)
    build_scene(desc)
    acc = render_current(desc).accuracy
    assert acc["stopped_by"] == "samples" and acc["samples"] == 8 and acc["estimated_psnr_db"] < 90.0


@pytest.mark.render
def test_without_a_target_the_render_records_no_estimate(tiny_scene):
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current

    build_scene(tiny_scene)
    assert render_current(tiny_scene).accuracy is None


@pytest.mark.render
def test_a_target_renders_mask_is_the_fixed_renders(tiny_scene):
    """The first half renders with the layer's own seed: the class mask and object ids are those a fixed
    render of the layer gives (sample 0 lands in the same place)."""
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current

    build_scene(tiny_scene)
    fixed = render_current(tiny_scene)
    desc = _with_target(tiny_scene, 25.0, tiny_scene.render.samples)
    build_scene(desc)
    aimed = render_current(desc)
    assert (aimed.mask == fixed.mask).all() and (aimed.ids == fixed.ids).all()


@pytest.mark.render
@pytest.mark.parametrize("denoise", [True, False])
def test_a_fixed_renders_estimate_leaves_its_image_as_it_was(tiny_scene, denoise):
    """Asked for (allo:render:estimate), a fixed render's estimate costs one more render and changes nothing
    it delivers: the image is the one the render gives without it, bit for bit."""
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current

    plain = dataclasses.replace(tiny_scene, render=dataclasses.replace(tiny_scene.render, denoise=denoise))
    build_scene(plain)
    before = render_current(plain)
    asked = dataclasses.replace(plain, render=dataclasses.replace(plain.render, estimate=True))
    build_scene(asked)
    after = render_current(asked)
    assert (after.rgb == before.rgb).all() and (after.mask == before.mask).all()
    acc = after.accuracy
    assert acc["mode"] == "fixed" and acc["stopped_by"] == "samples" and acc["samples"] == plain.render.samples
    assert 10.0 < acc["estimated_psnr_db"] < 80.0 and ("DF" in acc["estimator"]) == denoise


@pytest.mark.render
def test_render_with_estimate_records_it_and_keeps_the_image(tiny_base, tmp_path):
    """`render_layer(..., estimate=True)` (`allo-usd render --estimate`): a finished render without an
    estimate renders again, its JSON gains `accuracy` (mode fixed) and the manifest's est_psnr_db, and its
    image files are the same bytes; without --estimate the finished render stays done."""
    from allo_usd.run.job import render_layer
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    layer = write_scene_layer(make_spec(anomaly=True), tmp_path / "layers" / "a.usda", tiny_base)
    out = tmp_path / "renders"
    plain = render_layer(layer, out)
    png = (out / plain["files"]["rgb"]).read_bytes()
    assert plain.get("accuracy") is None
    asked = render_layer(layer, out, estimate=True)
    assert asked["accuracy"]["mode"] == "fixed" and asked["accuracy"]["estimated_psnr_db"] > 10
    assert (out / asked["files"]["rgb"]).read_bytes() == png
    again = render_layer(layer, out)   # done: the estimate is kept
    assert again["accuracy"] == asked["accuracy"]


def test_a_firefly_a_denoised_half_keeps_weighs_at_most_one_pixels_worth():
    """A firefly in one half (hundreds in linear values) that its denoised image keeps, beside a dark
    delivered value: its pixel counts at most 255**2 (all an 8-bit pixel can be wrong by), not the slope's
    linearisation of a huge error, which outweighed the whole image."""
    rng = np.random.default_rng(5)
    truth = np.full((90, 160, 3), 0.01)
    a, b = (truth + rng.normal(0.0, 0.002, truth.shape) for _ in range(2))
    da, db = truth + 0.0005, truth - 0.0005
    calm = tg.estimated(a, b, da, db).mse
    b[40, 70], db[40, 70] = 650.0, 200.0
    hot = tg.estimated(a, b, da, db).mse
    assert hot - calm <= 255.0 ** 2 / (90 * 160) + 1e-9
    fixed = tg.fixed_error_map(da, db, a, b)
    assert np.abs(fixed).max() <= 255.0 ** 2
