"""Render presets: names, fields, errors (no rendering)."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from allo_usd.core.errors import AlloError
from allo_usd.plan.settings import PRESETS, preset_fields, preset_spec
from allo_usd.plan.settings import RenderSpec

EXTRA = {"denoise_prefilter", "denoise_quality"}


def test_required_presets_exist():
    assert {"draft", "preview", "final", "paper"} <= set(PRESETS)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_preset_fields_are_known(name):
    known = {f.name for f in fields(RenderSpec)} | EXTRA
    p = PRESETS[name]
    assert set(p) <= known
    assert {"samples", "adaptive_threshold", "denoise", "max_bounces"} <= set(p)
    assert p["samples"] >= 1 and p["max_bounces"] >= 1 and p["adaptive_threshold"] >= 0
    if p["denoise"]:
        assert p.get("denoise_prefilter", "FAST") in {"NONE", "FAST", "ACCURATE"}
        assert p.get("denoise_quality", "BALANCED") in {"FAST", "BALANCED", "HIGH"}


def test_paper_is_the_papers_setting():
    p = PRESETS["paper"]
    assert p["samples"] == 256 and p["denoise"] and p["adaptive_threshold"] == 0
    assert p["max_bounces"] == 12
    assert p["denoise_prefilter"] == "ACCURATE" and p["denoise_quality"] == "HIGH"


def test_presets_ordered_by_cost():
    s = [PRESETS[n]["samples"] for n in ("draft", "preview", "final")]
    assert s == sorted(s)
    assert PRESETS["final"]["samples"] <= PRESETS["paper"]["samples"]


def test_preset_spec():
    spec = preset_spec("preview", (480, 270), 0.25)
    assert isinstance(spec, RenderSpec)
    assert spec.resolution == (480, 270) and spec.exposure == 0.25 and spec.preset == "preview"
    assert spec.samples == PRESETS["preview"]["samples"]
    assert spec.denoise == PRESETS["preview"]["denoise"]
    assert spec.max_bounces == PRESETS["preview"]["max_bounces"]
    assert spec.adaptive_threshold == PRESETS["preview"]["adaptive_threshold"]
    assert preset_spec("final", (64, 36), seed=7).seed == 7


def test_preset_fields_is_a_copy():
    f = preset_fields("draft")
    f["samples"] = 99999
    assert PRESETS["draft"]["samples"] != 99999


def test_unknown_preset_names_the_choices():
    with pytest.raises(AlloError, match=r"unknown render preset 'fast'.*draft.*preview.*final.*paper"):
        preset_spec("fast", (64, 36), 1.0)


def test_bad_override_and_resolution():
    with pytest.raises(AlloError, match="no field"):
        preset_spec("draft", (64, 36), 1.0, bogus=1)
    with pytest.raises(AlloError, match="resolution"):
        preset_spec("draft", (0, 36), 1.0)


def test_bench_metrics_and_front():
    from scripts import bench_accuracy as b

    rng = np.random.default_rng(0)
    ref = rng.uniform(0, 0.8, (36, 64, 3)).astype(np.float32)
    same = b.metrics(ref, ref)
    assert same["psnr_srgb8"] == float("inf") and same["ssim_srgb8"] == pytest.approx(1.0)
    noisy = b.metrics(ref + rng.normal(0, 0.05, ref.shape).astype(np.float32), ref)
    assert 15 < noisy["psnr_linear"] < 35 and noisy["ssim_srgb8"] < 0.99
    half = b.metrics(ref.reshape(18, 2, 32, 2, 3).mean(axis=(1, 3)), ref)  # compared with the box-averaged reference
    assert half["psnr_linear"] == float("inf")
    rows = [dict(seconds=s, psnr_srgb8=p, scale=1.0) for s, p in [(1, 30), (2, 29), (3, 35), (4, 40), (5, 39)]]
    assert [r["seconds"] for r in b.pareto(rows)] == [1, 3, 4]
    for name in PRESETS:
        assert b.preset_config(name)["samples"] == PRESETS[name]["samples"]


def test_preset_spec_carries_the_denoiser():
    for name in PRESETS:
        spec = preset_spec(name, (64, 36))
        assert (spec.denoise_prefilter, spec.denoise_quality) == (PRESETS[name]["denoise_prefilter"],
                                                                  PRESETS[name]["denoise_quality"])
    # the paper's setting is Blender's OIDN defaults
    assert (preset_spec("paper", (64, 36)).denoise_prefilter, preset_spec("paper", (64, 36)).denoise_quality) == \
        ("ACCURATE", "HIGH")


def test_plan_quality_preset_fills_what_the_plan_leaves_out():
    from allo_usd.plan.model import Quality

    final = Quality(preset="final")
    assert final.samples == PRESETS["final"]["samples"] and final.adaptive_threshold == PRESETS["final"]["adaptive_threshold"]
    assert (final.denoise_prefilter, final.denoise_quality) == (PRESETS["final"]["denoise_prefilter"],
                                                                PRESETS["final"]["denoise_quality"])
    assert Quality(preset="final", samples=100).samples == 100  # what the plan says wins
    with pytest.raises(ValueError, match="preset"):                # an unknown name is refused
        Quality(preset="my-label")
    assert Quality().samples == PRESETS["preview"]["samples"]      # the default preset is preview


def test_quality_and_effects_are_declared_once():
    """QualitySettings / EffectFlags are the one declaration: a field added there (or anywhere else)
    and missed in the plan model, the presets, the scene spec, the description or the attribute
    table fails here."""
    from allo_usd.plan.model import Effects, Quality
    from allo_usd.plan.settings import (EFFECT_FLAGS, QUALITY_FIELDS, EffectFlags, EffectsSpec, QualitySettings,
                                        quality_of)
    from allo_usd.usd import attributes as A
    from allo_usd.usd.description import EffectsDesc, RenderDesc

    quality, flags = set(QUALITY_FIELDS), set(EFFECT_FLAGS)
    assert set(Quality.model_fields) == quality | {"preset", "resolution", "passes"}
    assert set(Effects.model_fields) == flags
    assert issubclass(RenderSpec, QualitySettings) and issubclass(RenderDesc, QualitySettings)
    assert issubclass(EffectsSpec, EffectFlags) and issubclass(EffectsDesc, EffectFlags)
    for name in PRESETS:
        assert set(PRESETS[name]) == quality, name
    # defaults agree: a plan's default quality and effects are the dataclasses' defaults
    assert quality_of(Quality()) == PRESETS["preview"]   # the default preset fills every quality field
    assert Effects().model_dump() == {f.name: getattr(EffectFlags(), f.name) for f in fields(EffectFlags)}
    # every field has its allo: attribute, and the render/effects attributes record nothing else
    render_fields = {a.field for a in A.RENDER_QUALITY}
    assert quality <= render_fields and render_fields - quality == {"preset", "seed", "threads"}
    assert {a.field for a in A.EFFECT_FLAGS} == flags
