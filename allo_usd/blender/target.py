"""Rendering to a target accuracy: samples spent in rounds of two independent halves until the delivered
image is, with confidence, at the layer's `allo:render:targetPsnr` (or its sample cap or time limit stops it).

Why halves: nothing in one Monte Carlo render says how far it is from the converged image, but two renders
of the same scene and settings with independent seeds are two independent draws of the same noise. Their
difference has twice the variance of either, four times that of their mean, so per pixel

    estimated squared error of the mean = mean over channels of (s(A) - s(B))**2 / 4

where A and B are the halves (each the running mean of its rounds' samples) and s the delivered image's own
transfer: the film's exposure is in the render, then IEC 61966-2-1 sRGB on clipped values, in 8-bit units,
not rounded. The PSNR it gives is that of the benchmark (scripts/bench_accuracy.py: the 8-bit sRGB image
against the converged image's 8-bit codes, peak 255). Rounding to 8 bits adds to each pixel's squared error
what rounding_mse says: up to 1/6 for a noisy pixel, nothing for an exact one.

How sure: a render's error is heavy-tailed (a glint or a sun caustic that a few samples in a thousand
find), so the mean over pixels is itself uncertain; its standard error is measured from the spread of
8x8-block means (Estimate). The target is reached when the estimate plus CONFIDENCE_Z standard errors is
within it: the record keeps the point estimate (`estimated_psnr_db`) and that bound (`lower_psnr_db`).

Denoised layers (`allo:render:denoise`): each half is denoised (OIDN with the layer's quality and prefilter,
allo_usd.blender.oidn, as Cycles would) and the delivered image is the mean of the two denoised halves. A
denoiser also blurs, a bias both halves share that their difference cannot see, so the estimate checks each
denoised half against the other half's noisy image (error_map), which sees it;
docs/benchmarks/bench_accuracy.md measures how the estimate relates to the true error.

Rounds: the first gives each half `FIRST_SAMPLES` samples; after each, the samples the target needs are
predicted from the bound the target must clear (a Monte Carlo error's variance falls as 1/N: N_needed = N * MSE / MSE_target,
with HEADROOM), at most doubling the samples so far, within the cap. Adaptive sampling is off in this mode
(the rounds are the adaptation; per-pixel sample counts would make the halves' means unweighable). The
mask, object ids, depth and normal passes are those of the first half of the first round, rendered with the
layer's own seed (its first sample lands where a fixed render's does, so the mask is the fixed render's).
Everything changed on the Blender scene is put back afterwards, value for value, so a warm session
(blender.session) keeps patching the scene it believes it shows.
"""

from __future__ import annotations

import functools
import math
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from allo_usd.core.errors import AlloError
from allo_usd.usd.description import SceneDescription

FIRST_SAMPLES = 16            # per half, the first round
HEADROOM = 1.15               # the next round aims this far past the predicted need
SPLIT_CODES = 32.0            # denoised halves this far apart (8-bit codes): a denoiser artifact in one (_in_codes)
STDERR_BLOCK = 8              # the estimate's standard error is taken over means of 8x8-pixel blocks
PSNR_CEILING_DB = 100.0       # the PSNR an estimated-exact image is recorded at
CONFIDENCE_Z = 2.0            # the bound a target must clear: the estimated MSE plus 2 standard errors
SEED_STEP = 7919              # half h of round r renders with seed + SEED_STEP * (2 r + h) (mod 2**31)
_IN_CODES = "times the sRGB slope squared (the secant where {} and {} differ by more than %g codes)" % SPLIT_CODES
_ERROR_BARS = "plus each pixel's rounding; standard error from %dx%d-block means" % (STDERR_BLOCK, STDERR_BLOCK)
ESTIMATOR_DENOISED = ("two independent halves A, B, denoised DA, DB: per pixel ((DA-B)^2 + (DB-A)^2 - (A-B)^2)/2 "
                      "- (DA-DB)^2/4 in linear values " + _IN_CODES.format("DA", "DB"))
ESTIMATOR_NOISY = ("two independent halves A, B, delivered M = (A+B)/2: per pixel max((s(M)-s(A))^2, (s(M)-s(B))^2) "
                   "in 8-bit sRGB")
ESTIMATOR_BOUND = f"; {_ERROR_BARS}; the target is met when the mean plus {CONFIDENCE_Z:g} standard errors is within it"

_SRGB_PEAK = 255.0


def srgb_units(rgb: np.ndarray) -> np.ndarray:
    """The delivered transfer in 8-bit units, not rounded: IEC 61966-2-1 on values clipped to [0, 1] (an
    estimate of this machine's image: numpy's power, not fixedmath's, is fast enough for 6M values)."""
    c = np.clip(np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0), 0.0, 1.0)
    return _SRGB_PEAK * np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def srgb_slope_sq(rgb: np.ndarray) -> np.ndarray:
    """(d srgb_units / d linear)**2 at each value: how a small linear error shows in the 8-bit image; 0 where
    the value is clipped (>= 1: a brighter or darker-but-still-clipped truth shows the same code)."""
    c = np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=1.0)
    slope = np.where(c <= 0.0031308, 12.92, 1.055 / 2.4 * np.power(np.clip(c, 0.0031308, 1.0), 1.0 / 2.4 - 1.0))
    return np.where(c >= 1.0, 0.0, _SRGB_PEAK * slope) ** 2


def error_map(noisy_a: np.ndarray, noisy_b: np.ndarray, den_a: np.ndarray | None = None,
              den_b: np.ndarray | None = None) -> np.ndarray:
    """(H, W) estimated squared error, 8-bit sRGB units (mean over channels), of the delivered image
    (den_a + den_b) / 2 against the converged one, from two independent noisy halves and the same halves
    denoised (None: not denoised, delivered = their mean). In linear values, per pixel, with A, B the noisy
    halves and DA, DB the denoised ones (T the converged value; A, B unbiased and independent):

        E (DA - B)**2 = E (DA - T)**2 + E (B - T)**2        (B's noise is independent of DA)
        E (A - B)**2  = E (A - T)**2 + E (B - T)**2
        ((DA + DB)/2 - T)**2 = ((DA - T)**2 + (DB - T)**2) / 2 - (DA - DB)**2 / 4   (an identity)

    so  e = ((DA - B)**2 + (DB - A)**2 - (A - B)**2) / 2 - (DA - DB)**2 / 4  has the delivered image's
    squared error as its expectation, the denoiser's blur (a bias both halves share, which DA - DB alone
    cannot see) included; a firefly in either noisy half cancels within its own pixel. Linear errors become
    8-bit sRGB errors by the transfer's slope at the delivered value (srgb_slope_sq): small errors, as at
    the targets this mode is for, and by the secant where the denoised halves split (_in_codes: a denoiser
    artifact, an error as large as the value).

    Without a denoiser the delivered image is M = (A + B)/2 and, in the delivered transfer s itself,
    e = max((s(M) - s(A))**2, (s(M) - s(B))**2). For small errors both terms are (s(A) - s(B))**2 / 4,
    the mean's variance. The max matters where clipping does: a sun glint, one sample of thousands of
    times the pixel's value, saturates M and one half. Then e is the full (255 - s(B))**2 where
    (s(A) - s(B))**2 / 4 would say a quarter of it. A glint one half found stands for the glints of
    similar odds that neither found (a pixel with one hit is as likely as one with none when the odds
    are one in N samples), whose error the halves cannot see at all.

    docs/benchmarks/bench_accuracy.md measures both forms against references on five views."""
    if den_a is None:   # the halves' distance from their mean in the delivered transfer: clipping included
        sa, sb = srgb_units(noisy_a), srgb_units(noisy_b)
        sm = srgb_units((np.asarray(noisy_a, dtype=np.float64) + noisy_b) / 2.0)
        return np.maximum((sm - sa) ** 2, (sm - sb) ** 2).mean(axis=-1)
    a, b, da, db = (np.asarray(x, dtype=np.float64) for x in (noisy_a, noisy_b, den_a, den_b))
    lin = ((da - b) ** 2 + (db - a) ** 2 - (a - b) ** 2) / 2.0 - (da - db) ** 2 / 4.0
    return _bounded(_in_codes(lin, (da + db) / 2.0, da, db).mean(axis=-1))


def _in_codes(lin: np.ndarray, delivered: np.ndarray, den_a: np.ndarray, den_b: np.ndarray) -> np.ndarray:
    """A linear squared error `lin` of each delivered value in squared 8-bit codes: by the curve's slope at
    the value (small errors), except where the two denoised images differ by more than SPLIT_CODES. There
    one of them holds a denoiser artifact, a blob spread from a glint its half found, an error as large as
    the value itself. The tangent undercounts that on the concave curve (a 0.5 blob over black is 188
    codes; the slope at 0.5 says 84), so it takes the larger secant from the value to the value -+
    sqrt(lin). SPLIT_CODES was chosen on 41 rounds of captured halves of the benchmark's shaded, dark and
    close-up views: the estimate's mean error against the reference is -0.8 dB (the slope alone: +1.5),
    and its bound stands above the measured PSNR in 1 round of 41 (the slope alone: 16)."""
    tangent = srgb_slope_sq(delivered) * lin
    split = np.abs(srgb_units(den_a) - srgb_units(den_b)) > SPLIT_CODES
    if not split.any():
        return tangent
    d = np.sqrt(np.clip(lin, 0.0, None))
    s = srgb_units(delivered)
    secant = np.maximum((s - srgb_units(delivered - d)) ** 2, (srgb_units(delivered + d) - s) ** 2)
    return np.where(split & (lin > 0.0), np.maximum(secant, tangent), tangent)


def _bounded(e: np.ndarray) -> np.ndarray:
    """A pixel's estimated squared error within what an 8-bit pixel can be wrong by (+-255**2): the slope
    linearisation holds for small errors, and a firefly that a denoised half keeps (hundreds in linear values
    beside a dark delivered value) would otherwise outweigh the whole image."""
    return np.clip(e, -_SRGB_PEAK * _SRGB_PEAK, _SRGB_PEAK * _SRGB_PEAK)


def rounding_mse(e: np.ndarray) -> np.ndarray:
    """What rounding adds to the squared error between the delivered image's 8-bit codes and the converged
    image's, given e, a squared error before rounding (8-bit units; estimate_of passes block means): with
    the converged value's place within its code uniform and the error eps ~ N(0, e), the codes differ by
    floor(eps) or ceil(eps), so E(code difference)**2 = e + E frac(eps) (1 - frac(eps)). The second term is
    1/6 for errors of a code or more (two independent roundings, 1/12 each), sigma sqrt(2/pi) for small
    ones, and 0 where the image is exact (a black sky rounds to the same code as its converged image)."""
    sigma = np.sqrt(np.clip(np.nan_to_num(np.asarray(e, dtype=np.float64)), 0.0, None))
    return np.interp(sigma, *_rounding_table())


@functools.cache
def _rounding_table() -> tuple[np.ndarray, np.ndarray]:
    """E frac(eps) (1 - frac(eps)) for eps ~ N(0, sigma**2) on a sigma grid, by its Fourier series:
    frac(x) (1 - frac(x)) = 1/6 - sum_k cos(2 pi k x) / (pi k)**2 and E cos(2 pi k eps) = exp(-2 (pi k sigma)**2).
    Built on first use (0.1 s), not when the module loads."""
    sigma = np.concatenate([[0.0], np.geomspace(1e-3, 3.0, 600)])
    k = np.arange(1, 4001, dtype=np.float64)[:, None]
    extra = 1.0 / 6.0 - (np.exp(-2.0 * (np.pi * k * sigma) ** 2) / (np.pi * k) ** 2).sum(axis=0)
    extra[0] = 0.0   # an exact pixel rounds to its converged code (the truncated series leaves 2.5e-5)
    return sigma, np.clip(extra, 0.0, 1.0 / 6.0)


@dataclass(frozen=True)
class Estimate:
    """The delivered image's estimated MSE against the converged image (8-bit sRGB units, rounding
    included) and that estimate's standard error. Both come from the pixels: a render's error is heavy-
    tailed (a sun glint a few samples find), so the estimate of one image is itself uncertain, and how
    uncertain is measured, not assumed."""
    mse: float
    stderr: float

    @property
    def psnr_db(self) -> float:
        return psnr_db(self.mse)

    @property
    def upper_mse(self) -> float:
        """The MSE the image is within at CONFIDENCE_Z standard errors: what a target must clear."""
        return self.mse + CONFIDENCE_Z * self.stderr

    @property
    def lower_psnr_db(self) -> float:
        return psnr_db(self.upper_mse)


def estimate_of(e: np.ndarray) -> Estimate:
    """The Estimate of an (H, W) error map (error_map, fixed_error_map), from the means of its
    STDERR_BLOCK x STDERR_BLOCK blocks (block_means). Each block's mean is its pixels' squared
    error, plus the rounding its noise level adds (rounding_mse of the block mean, not of each pixel: one
    pixel's error is too noisy a measure of its noise level, and rounding_mse bends, so per-pixel values
    would bias it low). The estimate is the blocks' mean, at least 0; its standard error is their spread
    over the square root of their number (a denoiser's errors are correlated across a few pixels; block
    means 8 apart are nearly independent)."""
    blocks = block_means(e)
    blocks = blocks + rounding_mse(blocks)
    return Estimate(max(float(blocks.mean()), 0.0), stderr_of(blocks))


def block_means(e: np.ndarray) -> np.ndarray:
    """The means of an (H, W) map's STDERR_BLOCK x STDERR_BLOCK blocks (a side shorter than a block is one
    block that way; the rows and columns that make no whole block are left out)."""
    e = np.asarray(e, dtype=np.float64)
    bh, bw = (min(STDERR_BLOCK, n) for n in e.shape)
    h, w = e.shape[0] - e.shape[0] % bh, e.shape[1] - e.shape[1] % bw
    return e[:h, :w].reshape(h // bh, bh, w // bw, bw).mean(axis=(1, 3))


def stderr_of(blocks: np.ndarray) -> float:
    """The standard error of the mean of nearly independent block means: their spread over the root of
    their number (0 for a single block)."""
    return float(blocks.std(ddof=1) / math.sqrt(blocks.size)) if blocks.size > 1 else 0.0


def estimated(noisy_a: np.ndarray, noisy_b: np.ndarray, den_a: np.ndarray | None = None,
              den_b: np.ndarray | None = None) -> Estimate:
    """The Estimate of the delivered image (den_a + den_b) / 2 (or (noisy_a + noisy_b) / 2) from its halves."""
    return estimate_of(error_map(noisy_a, noisy_b, den_a, den_b))


def _record(est: Estimate) -> dict:
    """The render JSON's estimate fields: the point estimate, the bound a target must clear (the PSNR
    the image is at least, at CONFIDENCE_Z standard errors), and the standard error in 8-bit units**2."""
    return {"estimated_psnr_db": est.psnr_db, "lower_psnr_db": est.lower_psnr_db, "estimated_mse": est.mse,
            "estimate_stderr_mse": est.stderr}


def psnr_db(mse: float) -> float:
    """10 log10(255**2 / mse), at most PSNR_CEILING_DB: an image estimated exact in every code (a black sky
    rounds to its converged codes) is recorded at the ceiling, a finite number JSON and the manifest hold."""
    if not mse > 0.0:
        return PSNR_CEILING_DB
    return min(10.0 * math.log10(_SRGB_PEAK * _SRGB_PEAK / mse), PSNR_CEILING_DB)


def next_samples(done_per_half: int, mse: float, target_mse: float, cap_per_half: int) -> int:
    """Samples per half for the next round: the 1/N prediction of what the target needs, with HEADROOM,
    at least FIRST_SAMPLES // 2, at most doubling what each half has, within the cap."""
    needed = math.ceil(done_per_half * mse / target_mse * HEADROOM) - done_per_half
    return max(0, min(max(needed, FIRST_SAMPLES // 2), done_per_half, cap_per_half - done_per_half))


def half_seed(seed: int, round_: int, half: int) -> int:
    """Cycles' seed of half `half` of round `round_`: the layer's own for the first (whose mask, ids, depth
    and normal the result keeps: those of a fixed render of the layer), distinct for every other."""
    return (int(seed) + SEED_STEP * (2 * round_ + half)) % (2 ** 31)


@contextmanager
def _noisy_halves_settings():
    """Within: Cycles' denoiser and adaptive sampling off, the denoising passes stored; after: as before."""
    import bpy

    scene = bpy.context.scene
    layer = scene.view_layers[0]
    saved = [(scene.cycles, p, getattr(scene.cycles, p)) for p in ("samples", "seed", "use_denoising",
                                                                     "use_adaptive_sampling")]
    saved.append((layer.cycles, "denoising_store_passes", layer.cycles.denoising_store_passes))
    try:
        scene.cycles.use_denoising = False
        scene.cycles.use_adaptive_sampling = False
        layer.cycles.denoising_store_passes = True
        yield scene
    finally:
        for owner, prop, value in reversed(saved):
            setattr(owner, prop, value)


class _Half:
    """One half's running sums (colour, and the denoiser's albedo and normal), weighted by samples."""

    def __init__(self) -> None:
        self.samples = 0
        self.color = self.albedo = self.normal = None

    def add(self, n: int, color: np.ndarray, albedo: np.ndarray | None, normal: np.ndarray | None) -> None:
        def acc(total, value):
            value = np.asarray(value, dtype=np.float64) * n
            return value if total is None else total + value
        self.color = acc(self.color, color)
        self.albedo = None if albedo is None else acc(self.albedo, albedo)
        self.normal = None if normal is None else acc(self.normal, normal)
        self.samples += n

    def mean(self, what: str) -> np.ndarray | None:
        total = getattr(self, what)
        return None if total is None else (total / self.samples).astype(np.float32)


def _stack(ch: dict, name: str, comps: str) -> np.ndarray | None:
    if f"ViewLayer.{name}.{comps[0]}" not in ch:
        return None
    return np.stack([ch[f"ViewLayer.{name}.{c}"] for c in comps], axis=-1)


def render_to_target(desc: SceneDescription, render_once, missing) -> tuple[np.ndarray, dict, float, dict]:
    """Render the current Blender scene (built from `desc`) to desc.render.target_psnr (module docstring).
    `render_once(missing)`: one render of the scene as it is set, (its channels, seconds) (render.py's
    render_channels); `missing(channels)`: the pass a channel set lacks, or None (render.py's, which asks
    for the view layer's Combined, the object index and the normal the layer orders). Returns (the delivered
    linear RGB, the first render's channels (for the mask, ids, depth and normal), render seconds, the
    accuracy record)."""
    from allo_usd.blender.compositor import has_compositor

    render = desc.render
    if has_compositor():
        from allo_usd.plan.settings import TARGET_WITH_GLARE

        raise AlloError(f"{desc.layer}: {TARGET_WITH_GLARE}")
    target_mse = _SRGB_PEAK * _SRGB_PEAK / 10.0 ** (render.target_psnr / 10.0)
    cap_per_half = max(1, int(render.samples) // 2)
    limit = float(render.time_limit)
    halves = (_Half(), _Half())
    first = None
    rounds, seconds, est, stopped = 0, 0.0, Estimate(math.inf, 0.0), "samples"
    start = time.perf_counter()
    n = min(FIRST_SAMPLES, cap_per_half)

    with _noisy_halves_settings() as scene:
        while n > 0:
            for h, half in enumerate(halves):
                scene.cycles.samples = n
                scene.cycles.seed = half_seed(render.seed, rounds, h)
                ch, s = render_once(missing)
                seconds += s
                if first is None:
                    first = ch
                half.add(n, _stack(ch, "Combined", "RGB"), _stack(ch, "Denoising Albedo", "RGB"),
                         _stack(ch, "Denoising Normal", "XYZ"))
            rounds += 1
            noisy = (halves[0].mean("color"), halves[1].mean("color"))
            delivered_a, delivered_b = _delivered_halves(halves, noisy, render)
            est = estimated(*noisy, *((delivered_a, delivered_b) if render.denoise else (None, None)))
            if est.upper_mse <= target_mse:
                stopped = "target"
                break
            if limit and time.perf_counter() - start >= limit:
                stopped = "seconds"
                break
            n = next_samples(halves[0].samples, est.upper_mse, target_mse, cap_per_half)
    rgb = ((delivered_a.astype(np.float64) + delivered_b) / 2.0).astype(np.float32)
    accuracy = {"mode": "target", "target_psnr_db": float(render.target_psnr), **_record(est),
                "samples": halves[0].samples + halves[1].samples, "rounds": rounds, "stopped_by": stopped,
                "estimator": (ESTIMATOR_DENOISED if render.denoise else ESTIMATOR_NOISY) + ESTIMATOR_BOUND}
    return rgb, first, seconds, accuracy


def fixed_error_map(delivered_f: np.ndarray, delivered_g: np.ndarray, noisy_f: np.ndarray | None = None,
                    noisy_g: np.ndarray | None = None) -> np.ndarray:
    """(H, W) estimated squared error (8-bit sRGB units, mean over channels) of a fixed render F, from a
    second render G of the same settings with an independent seed: two draws of the same process. Without a
    denoiser E (s(F) - s(G))**2 = 2 E (s(F) - s(T))**2; with one (DF, DG delivered, Fn, Gn their noisy
    images), as error_map: e = ((DF - Gn)**2 + (DG - Fn)**2 - (Fn - Gn)**2) / 2 in linear values is the
    mean of DF's and DG's squared errors in expectation, which are the same; in codes as error_map's
    (_in_codes)."""
    if noisy_f is None:
        d = srgb_units(delivered_f) - srgb_units(delivered_g)
        return (d * d / 2.0).mean(axis=-1)
    df, dg, fn, gn = (np.asarray(x, dtype=np.float64) for x in (delivered_f, delivered_g, noisy_f, noisy_g))
    lin = ((df - gn) ** 2 + (dg - fn) ** 2 - (fn - gn) ** 2) / 2.0
    return _bounded(_in_codes(lin, df, df, dg).mean(axis=-1))


@contextmanager
def noisy_image_stored():
    """Within: Cycles stores its denoising passes (the Noisy Image beside the denoised Combined; the
    Combined itself is unchanged); after: as before."""
    import bpy

    layer = bpy.context.scene.view_layers[0]
    saved = layer.cycles.denoising_store_passes
    try:
        layer.cycles.denoising_store_passes = True
        yield
    finally:
        layer.cycles.denoising_store_passes = saved


def estimate_fixed(desc: SceneDescription, first: dict, render_once, missing) -> dict:
    """The accuracy record of a fixed-sample render, whose channels (`first`, rendered within
    noisy_image_stored) are delivered unchanged, from one more render of the same settings with an
    independent seed (`render_once(missing)`: (channels, seconds)), by fixed_error_map. The estimate is of
    the render before any lens glare (the view layer's Combined). It doubles the render's cost: it runs only
    when asked (`allo:render:estimate`, `allo-usd render --estimate`)."""
    import bpy

    scene = bpy.context.scene
    saved = scene.cycles.seed
    try:
        scene.cycles.seed = half_seed(desc.render.seed, 0, 1)
        with noisy_image_stored():
            second, seconds = render_once(missing)
    finally:
        scene.cycles.seed = saved
    f, g = _stack(first, "Combined", "RGB"), _stack(second, "Combined", "RGB")
    fn, gn = _stack(first, "Noisy Image", "RGB"), _stack(second, "Noisy Image", "RGB")
    denoised = desc.render.denoise and fn is not None and gn is not None
    est = estimate_of(fixed_error_map(f, g, fn if denoised else None, gn if denoised else None))
    return {"mode": "fixed", "target_psnr_db": None, **_record(est),
            "samples": int(desc.render.samples), "rounds": 1, "stopped_by": "samples",
            "estimator": ("a second render G of the same settings, independent seed: per pixel ((DF-Gn)^2 + (DG-Fn)^2 "
                          "- (Fn-Gn)^2)/2 in linear values " + _IN_CODES.format("DF", "DG") if denoised else
                          "a second render G of the same settings, independent seed: (s(F) - s(G))^2 / 2")
                         + ", " + _ERROR_BARS,
            "estimate_seconds": seconds}


def _delivered_halves(halves, noisy, render) -> tuple[np.ndarray, np.ndarray]:
    """Each half as it would be delivered: its running mean (`noisy`), denoised when the layer denoises."""
    if not render.denoise:
        return noisy
    from allo_usd.blender.oidn import denoise

    return tuple(denoise(color, h.mean("albedo"), h.mean("normal"), quality=render.denoise_quality,
                         prefilter=render.denoise_prefilter, threads=render.threads) for h, color in zip(halves, noisy))
