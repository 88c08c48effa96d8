"""Open Image Denoise through ctypes (allo_usd.blender.oidn): Cycles' own denoised image reproduced
from a render with the denoiser off, for each prefilter the presets use; errors as one line."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from allo_usd.blender import oidn
from allo_usd.blender.oidn import DenoiseError, denoise

from tests.support.helpers import make_spec


def _image(h=12, w=20, seed=0):
    rng = np.random.default_rng(seed)
    return rng.random((h, w, 3), dtype=np.float32)


# ---------------------------------------------------------------- the unit tier (the library, no Blender)

def test_denoises_a_small_image_deterministically_and_reuses_its_filters():
    color, albedo = _image(), np.full((12, 20, 3), 0.5, np.float32)
    normal = np.dstack([np.zeros((12, 20)), np.zeros((12, 20)), np.ones((12, 20))]).astype(np.float32)
    a = denoise(color, albedo, normal, "FAST", "ACCURATE")
    filters = next(f for k, f in oidn._filters.items() if k[:4] == (12, 20, "FAST", "ACCURATE"))
    b = denoise(color.astype(np.float64), albedo, normal, "FAST", "ACCURATE")   # a float64 copy in
    assert a.dtype == np.float32 and a.shape == (12, 20, 3) and a.flags.c_contiguous
    assert np.array_equal(a, b)
    assert next(f for k, f in oidn._filters.items() if k[:4] == (12, 20, "FAST", "ACCURATE")) is filters
    assert a.std() < color.std()   # it smooths the noise
    assert not np.shares_memory(a, filters.images["output"])


def test_rows_reach_the_filter_bottom_up_as_cycles_buffers_hold_them():
    """The network is not symmetric under a vertical flip: denoise() flips the rows (EXR top-down,
    Cycles bottom-up) before the filter and back after it."""
    color = _image(16, 16, 1)
    flipped = denoise(np.ascontiguousarray(color[::-1]), quality="FAST", prefilter="NONE")[::-1]
    straight = denoise(color, quality="FAST", prefilter="NONE")
    assert np.abs(flipped - straight).max() > 1e-4


def test_threads_are_honoured():
    color = _image(8, 8, 2)
    one = denoise(color, quality="FAST", threads=1)
    lib = oidn.load_library()
    lib.oidnGetDeviceInt.restype, lib.oidnGetDeviceInt.argtypes = oidn.ctypes.c_int, [oidn.ctypes.c_void_p,
                                                                                      oidn.ctypes.c_char_p]
    assert lib.oidnGetDeviceInt(oidn._devices[1].handle, b"numThreads") == 1
    assert np.array_equal(one, denoise(color, quality="FAST", threads=0))   # OIDN is thread-count stable


@pytest.mark.parametrize("kw, words", [
    (dict(color=np.zeros((4, 4))), ["color", "shape (4, 4)", "fix"]),
    (dict(color=np.zeros((4, 4, 4))), ["color", "(4, 4, 4)", "fix"]),
    (dict(color=np.zeros((0, 4, 3))), ["color", "fix"]),
    (dict(color=np.zeros((4, 4, 3)), albedo=np.zeros((4, 5, 3))), ["albedo", "4x4x3 like the color", "fix"]),
    (dict(color=np.zeros((4, 4, 3)), albedo=np.zeros((4, 4, 3)), normal=np.zeros((3, 4, 3))), ["normal", "fix"]),
    (dict(color=np.zeros((4, 4, 3)), normal=np.zeros((4, 4, 3))), ["normal without an albedo", "fix"]),
    (dict(color=np.full((4, 4, 3), "x")), ["dtype", "fix"]),
    (dict(color=np.zeros((4, 4, 3)), quality="ULTRA"), ["quality 'ULTRA'", "HIGH", "fix"]),
    (dict(color=np.zeros((4, 4, 3)), prefilter="SLOW"), ["prefilter 'SLOW'", "ACCURATE", "fix"]),
    (dict(color=np.zeros((4, 4, 3)), threads=-1), ["threads -1", "fix"]),
    (dict(color=np.zeros((4, 4, 3)), threads=2.5), ["threads 2.5", "fix"]),
])
def test_bad_inputs_are_one_line_errors(kw, words):
    with pytest.raises(DenoiseError) as e:
        denoise(**kw)
    msg = str(e.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


@pytest.mark.parametrize("where, bad", [("color", np.nan), ("color", np.inf), ("albedo", np.nan), ("normal", -np.inf)])
def test_non_finite_inputs_are_refused(where, bad):
    images = {"color": _image(6, 6), "albedo": _image(6, 6, 1), "normal": _image(6, 6, 2)}
    images[where][2, 3, 1] = bad
    with pytest.raises(DenoiseError, match=f"{where} has 1 pixels with NaN or infinite values; fix: replace them"):
        denoise(**images)


def test_a_library_that_cannot_load_names_the_fix(tmp_path, monkeypatch):
    fake = tmp_path / "libOpenImageDenoise.so.2"
    fake.write_bytes(b"not a shared library")
    with pytest.raises(DenoiseError) as e:
        oidn.load_library(fake)
    msg = str(e.value)
    assert "\n" not in msg and str(fake) in msg and "fix: reinstall bpy 5.0.1" in msg
    with pytest.raises(DenoiseError, match="fix: reinstall bpy"):
        oidn.load_library(tmp_path / "missing.so")
    monkeypatch.setattr(oidn.sys, "path", [str(tmp_path)])   # no bpy/lib/ on the path
    monkeypatch.setattr(oidn, "_lib", None)
    with pytest.raises(DenoiseError, match="bpy is not installed in this Python; fix: install the locked"):
        denoise(_image())


@pytest.mark.bpy
def test_the_library_is_found_after_bpy_is_imported_too():
    """Once bpy is imported, sys.path also holds Blender's scripts/modules (an inner bpy package without
    lib/): the library is still bpy's own."""
    import bpy  # noqa: F401

    path = oidn.library_path()
    assert path.is_file() and path.parent.name == "lib" and path.parent.parent.name == "bpy"


def test_an_oidn_error_is_raised_as_one_line_naming_it():
    device = oidn._Device(oidn.load_library(), 0)
    device.lib.oidnNewFilter(device.handle, b"NO_SUCH_FILTER")
    with pytest.raises(DenoiseError) as e:
        device.check("making a filter")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("Open Image Denoise failed making a filter: invalid argument"), msg
    device.check("after the error was read")   # reading an error clears it


# ---------------------------------------------------------------- against Cycles itself

# The (prefilter, quality) pairs of the presets (allo_usd.plan.settings.PRESETS).
PRESET_SETTINGS = (("FAST", "BALANCED"), ("NONE", "HIGH"), ("ACCURATE", "HIGH"))


def _render(tiny_base, tmp_path, name, **render):
    import bpy

    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_channels
    from allo_usd.usd.read import read_scene
    from allo_usd.usd.scene_layer import write_scene_layer

    base = make_spec(anomaly=True, resolution=(96, 54), samples=8)
    spec = replace(base, render=replace(base.render, **render))
    desc = read_scene(write_scene_layer(spec, tmp_path / f"{name}.usda", tiny_base))
    build_scene(desc)
    bpy.context.scene.view_layers[0].cycles.denoising_store_passes = True
    ch, _ = render_channels(desc, tmp_path)

    def image(p, c="RGB"):
        return np.stack([ch[f"ViewLayer.{p}.{x}"] for x in c], axis=-1).astype(np.float32)
    return {"combined": image("Combined"), "albedo": image("Denoising Albedo"),
            "normal": image("Denoising Normal", "XYZ"), "noisy": image("Noisy Image") if render["denoise"] else None}


@pytest.mark.render
def test_reproduces_cycles_denoiser_for_each_preset_setting(tiny_base, tmp_path):
    """A render with Cycles' denoiser off (its passes stored) denoised here equals Cycles' own denoised
    render of the same seed to float32 rounding: Cycles denoises the sum of the samples before the
    film exposure, the mean given here differs from it by rounding only."""
    off = _render(tiny_base, tmp_path, "off", denoise=False)
    for prefilter, quality in PRESET_SETTINGS:
        on = _render(tiny_base, tmp_path, f"{prefilter}_{quality}", denoise=True, denoise_prefilter=prefilter,
                     denoise_quality=quality)
        assert np.array_equal(on["noisy"], off["combined"])   # the same samples
        assert np.array_equal(on["albedo"], off["albedo"]) and np.array_equal(on["normal"], off["normal"])
        ours = denoise(off["combined"], off["albedo"], off["normal"], quality, prefilter)
        diff = np.abs(ours - on["combined"])
        psnr = 10 * np.log10(1.0 / max(float(np.mean(diff.astype(np.float64) ** 2)), 1e-30))
        assert diff.max() < 2e-5 and psnr > 110, (prefilter, quality, diff.max(), psnr)
        assert np.abs(off["combined"] - on["combined"]).max() > 1e-2   # the denoiser did change the image
