"""Render presets, chosen from the measured accuracy/time Pareto front: figures and targets in
docs/benchmarks/bench_accuracy.md (scripts/bench_accuracy.py).

`denoise_prefilter` / `denoise_quality` are Cycles' OIDN `denoising_prefilter` ('NONE', 'FAST',
'ACCURATE') and `denoising_quality` ('FAST', 'BALANCED', 'HIGH'), recorded in each layer as
`allo:render:denoisePrefilter` / `allo:render:denoiseQuality`. A plan's `quality.preset` must
name one of PRESETS; it fills the fields the plan leaves out, and a written plan records only
the fields its author set (allo_usd.plan.model.Quality, allo_usd.plan.io.save_plan).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from allo_usd.core.errors import AlloError
from allo_usd.core.sensor import SensorParams

DENOISE_PREFILTERS = ("NONE", "FAST", "ACCURATE")   # Cycles' OIDN denoising_prefilter
DENOISE_QUALITIES = ("FAST", "BALANCED", "HIGH")     # Cycles' OIDN denoising_quality
# The render device (allo_usd.blender.device): a run-time choice, recorded in each render's JSON, never in a layer.
DEVICES = ("auto", "cpu", "gpu")

# Render passes: a plan's quality.passes or `allo-usd render --passes` names them; each is one UsdRender.Var
# of the layer's image product (allo_usd.usd.base_stage.RENDER_VARS), written as one file:
# rgb STEM.png (8-bit sRGB), exr STEM.exr (linear, half), mask STEM_mask.png (uint8 class 0/1/2),
# depth STEM_depth.exr (float32 metres along the view axis), normal STEM_normal.exr (float32 world-space
# unit normals X, Y, Z), instance STEM_instance.png (uint16 object id, 0 background; the id -> prim table
# is in the render's JSON), amodal STEM_amodal.png (uint8 0/2: the anomaly's full silhouette, as if
# nothing hid it; a second, mask-only render of the anomaly alone: allo_usd.blender.amodal). Without rgb
# and exr the render is mask-like: 1 sample, no bounces.
PASSES = ("rgb", "exr", "mask", "depth", "normal", "instance", "amodal")
DEFAULT_PASSES = ("rgb", "exr", "mask")
COLOR_PASSES = ("rgb", "exr")


def passes_problem(passes) -> str | None:
    """What is wrong with a list of pass names (None: nothing); the message names the valid passes."""
    if isinstance(passes, str) or not all(isinstance(p, str) for p in passes or ()):
        return f"passes must be a list of names, got {passes!r}; choose from {', '.join(PASSES)}"
    bad = [p for p in passes if p not in PASSES]
    if bad:
        return f"unknown render pass(es) {', '.join(map(repr, bad))}; choose from {', '.join(PASSES)}"
    if not passes:
        return f"no render pass chosen; choose one or more of {', '.join(PASSES)}"
    if len(set(passes)) != len(passes):
        return f"render passes {', '.join(passes)} name one pass twice; name each once"
    return None


def canonical_passes(passes) -> tuple[str, ...]:
    """Passes in PASSES order (a layer's product orders them so); raises AlloError for bad names."""
    problem = passes_problem(passes)
    if problem:
        raise AlloError(problem)
    return tuple(p for p in PASSES if p in passes)


# The one declaration of the quality settings and the effect switches. RenderSpec / EffectsSpec (a
# scene's request), allo_usd.usd.description.RenderDesc / EffectsDesc (what a layer holds) inherit
# them; the plan's pydantic Quality / Effects and the presets are checked against them
# (tests/plan/test_settings.py), and each has an allo:render:* / allo:effects:* attribute
# (allo_usd.usd.attributes, `field`). Keyword-only, so subclasses keep their positional fields.
@dataclass(frozen=True, kw_only=True)
class QualitySettings:
    samples: int = 64
    adaptive_threshold: float = 0.0
    denoise: bool = True
    max_bounces: int = 8
    denoise_prefilter: str = "FAST"      # OIDN prefilter: NONE, FAST, ACCURATE
    denoise_quality: str = "BALANCED"    # OIDN quality: FAST, BALANCED, HIGH
    # The target mode (TARGET_PSNR_DB): a render spends samples in rounds until the estimated PSNR of its
    # delivered image (8-bit sRGB, against the converged image) reaches target_psnr dB, `samples` (the cap,
    # both halves together) or time_limit seconds stop it. 0: fixed samples, as the named presets.
    target_psnr: float = 0.0
    time_limit: float = 0.0             # seconds; 0: no limit


@dataclass(frozen=True, kw_only=True)
class EffectFlags:
    sensor_noise: bool = False
    glare: bool = False
    inspection_light: bool = True
    body_shine: bool = True


QUALITY_FIELDS = tuple(f.name for f in fields(QualitySettings))
TARGET_FIELDS = ("target_psnr", "time_limit")   # authored (allo:render:targetPsnr, :timeLimit) only when > 0

# The target mode's bounds, for a plan, the command line, the author and the reader alike: a target in
# (0, 100] dB (0: none; 100 dB is an 8-bit image within 1e-5 of its converged one, beyond any render),
# a time limit in [0, 1e6] s (0: none; 1e6 s is 11.6 days for one image).
TARGET_PSNR_DB = (0.0, 100.0)
TIME_LIMIT_S = (0.0, 1e6)


def _real(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def target_problem(target_psnr, time_limit, target_name: str = "target_psnr",
                   limit_name: str = "time_limit") -> str | None:
    """What is wrong with a target and a time limit (None: nothing), in one line that names the fix:
    a finite target in (0, 100] dB or 0 (fixed samples), a finite time limit in 0..1e6 s (0: none),
    and no time limit without a target (it would limit nothing)."""
    lo, hi = TARGET_PSNR_DB
    if not _real(target_psnr) or not (target_psnr == 0 or lo < target_psnr <= hi):
        return (f"{target_name} {_shown(target_psnr)} is not a PSNR in dB; fix: give a target in (0, {hi:g}] dB, "
                "e.g. 40, or 0 for fixed samples")
    lo, hi = TIME_LIMIT_S
    if not _real(time_limit) or not lo <= time_limit <= hi:
        return (f"{limit_name} {_shown(time_limit)} is not a number of seconds in {lo:g}..{hi:.0f}; fix: give the "
                "seconds one render may take, e.g. 60, or 0 for no limit")
    if time_limit > 0 and target_psnr == 0:
        return (f"{limit_name} {time_limit:g} is given without {target_name}: a time limit stops the target mode "
                f"only; fix: give {target_name} too (e.g. 40) or drop {limit_name}")
    return None


def _shown(value) -> str:
    text = f"{value:g}" if _real(value) or isinstance(value, float) else repr(value)
    return text if len(text) <= 40 else text[:40] + "..."
EFFECT_FLAGS = tuple(f.name for f in fields(EffectFlags))


def quality_of(obj) -> dict:
    """The quality settings of anything that carries them (a plan's Quality, a RenderSpec)."""
    return {name: getattr(obj, name) for name in QUALITY_FIELDS}


def effect_flags_of(obj) -> dict:
    """The effect switches of anything that carries them (a plan's Effects, an EffectsSpec)."""
    return {name: getattr(obj, name) for name in EFFECT_FLAGS}


@dataclass(frozen=True)
class RenderSpec(QualitySettings):
    resolution: tuple[int, int] = (1920, 1080)
    preset: str = "preview"
    seed: int = 0
    exposure: float = 1.0
    threads: int = 0
    passes: tuple[str, ...] = DEFAULT_PASSES   # PASSES, in that order; no rgb/exr: 1 sample, no bounces


@dataclass(frozen=True)
class EffectsSpec(EffectFlags):
    # The camera's EMVA 1288 parameters and its own seed (fixed patterns); authored, resolved
    # against the render exposure, when sensor_noise is on.
    sensor: SensorParams = field(default_factory=SensorParams)


# The named presets render fixed samples (no target): their meaning, and their layers' bytes, are as before
# the target mode; a plan sets quality.target_psnr (and time_limit) over any of them to aim at a quality.
FIXED = dict(target_psnr=0.0, time_limit=0.0)
# The target mode denoises its halves itself, after Cycles' render, where Blender composites the lens glare:
# a target with glare would lose the glare, so it is refused (author, reader, render).
TARGET_WITH_GLARE = ("a PSNR target is not rendered with lens glare (the target mode denoises after the render, where "
                     "Blender composites the glare); fix: turn lens glare off, or remove the target for fixed samples")
PRESETS: dict[str, dict] = {
    "draft": dict(samples=4, adaptive_threshold=0.0, denoise=True, max_bounces=8,
                  denoise_prefilter="FAST", denoise_quality="BALANCED", **FIXED),
    "preview": dict(samples=64, adaptive_threshold=0.05, denoise=True, max_bounces=8,
                    denoise_prefilter="FAST", denoise_quality="BALANCED", **FIXED),
    "final": dict(samples=192, adaptive_threshold=0.01, denoise=True, max_bounces=8,
                  denoise_prefilter="NONE", denoise_quality="HIGH", **FIXED),
    # The paper's setting: 256 spp, OIDN with Blender's defaults, Blender's default bounces.
    "paper": dict(samples=256, adaptive_threshold=0.0, denoise=True, max_bounces=12,
                  denoise_prefilter="ACCURATE", denoise_quality="HIGH", **FIXED),
    # The demo's setting (allo_usd.plan.model.demo_plan, `allo-usd demo`): 32 spp, no adaptive
    # sampling, the default denoiser; quick at the demo's 480x270.
    "demo": dict(samples=32, adaptive_threshold=0.0, denoise=True, max_bounces=8,
                 denoise_prefilter="FAST", denoise_quality="BALANCED", **FIXED),
}

_SPEC_FIELDS = {f.name for f in fields(RenderSpec)}


def preset_fields(name: str) -> dict:
    """A copy of preset `name`'s settings (RenderSpec field names)."""
    try:
        return dict(PRESETS[name])
    except KeyError:
        raise AlloError(f"unknown render preset {name!r}; choose one of {', '.join(PRESETS)}") from None


def preset_spec(name: str, resolution: tuple[int, int] = (1920, 1080), exposure: float = 1.0, **overrides) -> RenderSpec:
    """RenderSpec for preset `name` at `resolution` and `exposure`; `overrides` replace fields."""
    values = preset_fields(name)
    values.update(overrides)
    unknown = set(values) - _SPEC_FIELDS
    if unknown:
        raise AlloError(f"RenderSpec has no field(s) {', '.join(sorted(unknown))}")
    w, h = resolution
    if int(w) <= 0 or int(h) <= 0:
        raise AlloError(f"resolution must be positive, got {resolution!r}")
    return RenderSpec(resolution=(int(w), int(h)), preset=name, exposure=float(exposure), **values)
