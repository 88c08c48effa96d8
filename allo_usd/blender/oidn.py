"""Intel Open Image Denoise on numpy arrays, as Cycles denoises a render.

`denoise(color, albedo, normal, quality, prefilter)` calls, through ctypes, the OIDN library that
bpy bundles (2.3.3, `bpy/lib/libOpenImageDenoise.so.2` next to bpy's own module; bpy itself is
not imported), with the filter settings Cycles' CPU denoiser uses (Blender 5.0,
intern/cycles/integrator/denoiser_oidn.cpp, OIDNDenoiseContext::denoise_pass):

- one CPU device, `setAffinity` false (and `numThreads` when `threads` > 0; Cycles leaves it at
  OIDN's default, which uses every core);
- an "RT" filter on color (+ albedo, + normal), `hdr` true, `srgb` false, `quality` the layer's
  `denoise_quality` (HIGH: OIDN_QUALITY_HIGH 6, BALANCED: 5, FAST: 4), no inputScale (OIDN's
  auto-exposure, as Cycles);
- `denoise_prefilter` NONE: the albedo and normal are used as given and `cleanAux` is true
  (they are taken as noise-free); FAST: as given, `cleanAux` false (the main filter expects
  noisy auxiliaries); ACCURATE: the albedo and the normal are each denoised first by an RT filter
  of their own (that image as "albedo" or "normal", written in place, same quality, no hdr), and
  the main filter takes them with `cleanAux` true.

Cycles hands OIDN its render buffers, whose rows run bottom-up; the arrays here (as Blender's EXR and
RenderResult) run top-down. The network is not symmetric under a vertical flip, so denoise() flips
the rows before the filter and back after it: without that the result differs from Cycles' by up to
0.1 on a 0..1 image. Without adaptive sampling Cycles denoises the raw sum of the samples, before
the film exposure, and multiplies the filter's output by film exposure / samples; OIDN's
auto-exposure makes the filter blind to that factor but for float32 rounding, so the mean image
given here yields Cycles' image to a few units in the last place (measured on the tiny test scene at
160x90 and 480x270, every quality and prefilter: max abs difference below 5e-6 on a 0..1 image,
130.6-132.7 dB; feeding the sum rebuilt
from the written image does not come closer, since the sum cannot be rebuilt exactly). Albedo and
normal are the per-sample means in both (Cycles divides them by the sample count before denoising).

Which Blender passes to render and read (names as they appear in the multilayer EXR that
allo_usd.blender.render.render_channels returns, with Cycles' denoiser off,
scene.cycles.use_denoising = False, and view_layer.cycles.denoising_store_passes = True):

- color: "ViewLayer.Combined.R", ".G", ".B" (the noisy image; with the compositor on, the
  denoiser must be fed the view layer's Combined, not "Composite.Combined");
- albedo: "ViewLayer.Denoising Albedo.R", ".G", ".B";
- normal: "ViewLayer.Denoising Normal.X", ".Y", ".Z".
(`denoising_store_passes` also writes "Denoising Depth.Z", unused here; with Cycles' denoiser on it
adds "Noisy Image.R/G/B/A", the Combined before denoising.) Stack the three channels of each on
the last axis as float32 (H, W, 3); the EXR's rows run top-down, as the arrays here. Cycles feeds
albedo and normal whenever scene.cycles.denoising_input_passes is RGB_ALBEDO_NORMAL (Blender's
default, which allo_usd.blender.build leaves as is).

The library is loaded once per process; a device per thread count and the filters per (size,
settings) are kept and reused (the last two sets only: a filter holds working memory in proportion to
its image).
Every OIDN call is checked with oidnGetDeviceError: an error is raised as DenoiseError, one line
naming it.
"""

from __future__ import annotations

import ctypes
import sys
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from allo_usd.core.errors import AlloError

QUALITIES = {"FAST": 4, "BALANCED": 5, "HIGH": 6}      # OIDNQuality (oidn.h 2.3)
PREFILTERS = ("NONE", "FAST", "ACCURATE")
_DEVICE_CPU = 1                                       # OIDN_DEVICE_TYPE_CPU
_FLOAT3 = 3                                           # OIDN_FORMAT_FLOAT3
_ERRORS = {1: "unknown error", 2: "invalid argument", 3: "invalid operation", 4: "out of memory",
           5: "unsupported hardware", 6: "cancelled"}
_LIBRARY_NAMES = {"linux": "libOpenImageDenoise.so.2", "darwin": "libOpenImageDenoise.2.dylib",
                  "win32": "OpenImageDenoise.dll"}
_KEEP_FILTERS = 2                                     # filter sets kept (per size and settings)


class DenoiseError(AlloError, RuntimeError):
    """Open Image Denoise cannot be loaded, refuses its inputs or fails to run."""


_lock = threading.Lock()
_lib = None
_devices: dict[int, "_Device"] = {}
_filters: OrderedDict = OrderedDict()


def library_path() -> Path:
    """The OIDN library bpy bundles: bpy/lib/ of the bpy package on sys.path (found without importing bpy;
    once bpy is imported, sys.path also holds Blender's scripts/modules, whose inner `bpy` package has no
    lib/ folder: the first bpy/ that holds the library is the one)."""
    name = _LIBRARY_NAMES.get(sys.platform, _LIBRARY_NAMES["linux"])
    for entry in sys.path:
        candidate = Path(entry or ".") / "bpy" / "lib" / name
        if candidate.is_file():
            return candidate
    raise DenoiseError("the denoiser needs bpy (its bundled Open Image Denoise library) and bpy is not "
                       "installed in this Python; fix: install the locked environment (make run creates .venv)")


def load_library(path: Path | None = None):
    """The OIDN library (ctypes), loaded once per process from `path` (None: library_path())."""
    global _lib
    if _lib is not None and path is None:
        return _lib
    path = library_path() if path is None else Path(path)
    try:
        lib = ctypes.CDLL(str(path))
        _declare(lib)
    except (OSError, AttributeError) as exc:
        raise DenoiseError(f"cannot load Open Image Denoise from {path} ({type(exc).__name__}: {str(exc)[:160]}); "
                           "fix: reinstall bpy 5.0.1 (make run rebuilds .venv from the lock), which bundles "
                           "OIDN 2.3") from None
    if path == library_path():
        _lib = lib
    return lib


def _declare(lib) -> None:
    vp, cp, sz = ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t
    sig = {"oidnNewDevice": (vp, [ctypes.c_int]),
           "oidnSetDeviceBool": (None, [vp, cp, ctypes.c_bool]),
           "oidnSetDeviceInt": (None, [vp, cp, ctypes.c_int]),
           "oidnCommitDevice": (None, [vp]),
           "oidnGetDeviceError": (ctypes.c_int, [vp, ctypes.POINTER(cp)]),
           "oidnReleaseDevice": (None, [vp]),
           "oidnNewFilter": (vp, [vp, cp]),
           "oidnSetSharedFilterImage": (None, [vp, cp, vp, ctypes.c_int, sz, sz, sz, sz, sz]),
           "oidnSetFilterBool": (None, [vp, cp, ctypes.c_bool]),
           "oidnSetFilterInt": (None, [vp, cp, ctypes.c_int]),
           "oidnCommitFilter": (None, [vp]),
           "oidnExecuteFilter": (None, [vp]),
           "oidnReleaseFilter": (None, [vp])}
    for name, (res, args) in sig.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args


class _Device:
    def __init__(self, lib, threads: int):
        self.lib = lib
        self.handle = lib.oidnNewDevice(_DEVICE_CPU)
        if not self.handle:
            raise DenoiseError("Open Image Denoise made no CPU device; fix: run on a CPU with SSE4.1 or newer "
                               "(OIDN's minimum)")
        lib.oidnSetDeviceBool(self.handle, b"setAffinity", False)
        if threads > 0:
            lib.oidnSetDeviceInt(self.handle, b"numThreads", int(threads))
        lib.oidnCommitDevice(self.handle)
        self.check("making its CPU device")

    def check(self, doing: str) -> None:
        msg = ctypes.c_char_p()
        code = self.lib.oidnGetDeviceError(self.handle, ctypes.byref(msg))
        if code:
            text = (msg.value or b"").decode("utf-8", "replace").replace("\n", " ").strip()
            raise DenoiseError(f"Open Image Denoise failed {doing}: {_ERRORS.get(code, f'error {code}')}"
                               f"{': ' + text if text else ''}; fix: check the inputs' size and the free memory")


class _Filters:
    """The filters (and their shared float32 images) of one size and setting: the main RT filter and,
    with ACCURATE, one RT filter per auxiliary image that denoises it in place first."""

    def __init__(self, device: _Device, h: int, w: int, quality: str, prefilter: str, aux: tuple[bool, bool]):
        self.device, lib = device, device.lib
        self.images = {"color": np.zeros((h, w, 3), np.float32), "output": np.zeros((h, w, 3), np.float32)}
        for name, present in zip(("albedo", "normal"), aux):
            if present:
                self.images[name] = np.zeros((h, w, 3), np.float32)
        self.handles = []
        main = self._filter({n: n for n in self.images}, quality, device, h, w)
        lib.oidnSetFilterBool(main, b"hdr", True)
        lib.oidnSetFilterBool(main, b"srgb", False)
        if prefilter in ("NONE", "ACCURATE") and any(aux):
            lib.oidnSetFilterBool(main, b"cleanAux", True)
        lib.oidnCommitFilter(main)
        device.check("committing its filter")
        self.prefilters = []
        if prefilter == "ACCURATE":
            for name in ("albedo", "normal"):
                if name in self.images:
                    f = self._filter({name: name, "output": name}, quality, device, h, w)
                    lib.oidnCommitFilter(f)
                    device.check(f"committing its {name} prefilter")
                    self.prefilters.append(f)
        self.main = main

    def _filter(self, images: dict, quality: str, device: _Device, h: int, w: int):
        lib = device.lib
        f = lib.oidnNewFilter(device.handle, b"RT")
        device.check("making an RT filter")
        self.handles.append(f)
        for slot, name in images.items():
            a = self.images[name]
            lib.oidnSetSharedFilterImage(f, slot.encode(), a.ctypes.data, _FLOAT3, w, h, 0, 0, 0)
        lib.oidnSetFilterInt(f, b"quality", QUALITIES[quality])
        device.check("setting its filter's images")
        return f

    def run(self) -> np.ndarray:
        lib = self.device.lib
        for f in self.prefilters:
            lib.oidnExecuteFilter(f)
            self.device.check("prefiltering an auxiliary image")
        lib.oidnExecuteFilter(self.main)
        self.device.check("denoising")
        return self.images["output"]

    def release(self) -> None:
        for f in self.handles:
            self.device.lib.oidnReleaseFilter(f)
        self.handles = []


def _image(name: str, a, shape: tuple | None) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1 or (shape and a.shape != shape):
        want = f"{shape[0]}x{shape[1]}x3 like the color" if shape else "(height, width, 3)"
        raise DenoiseError(f"denoise: {name} has shape {a.shape}, not {want}; fix: pass float (H, W, 3) arrays "
                           "of one size")
    if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
        raise DenoiseError(f"denoise: {name} has dtype {a.dtype}, not a number; fix: pass float32 arrays")
    a = a.astype(np.float32, copy=False)
    bad = ~np.isfinite(a)
    if bad.any():
        raise DenoiseError(f"denoise: {name} has {int(bad.any(axis=2).sum())} pixels with NaN or infinite values; "
                           "fix: replace them (e.g. np.nan_to_num) before denoising")
    return a


def denoise(color, albedo=None, normal=None, quality: str = "HIGH", prefilter: str = "ACCURATE",
            threads: int = 0) -> np.ndarray:
    """`color` denoised as Cycles' OIDN denoiser would with these settings: float32 (H, W, 3).
    `albedo` and `normal` (optional; a normal needs an albedo) are Cycles' Denoising Albedo and
    Denoising Normal passes; `threads` 0: OIDN's default (every core). Rows run top-down, as in
    Blender's EXR; they are handed to OIDN bottom-up, as Cycles' render buffers hold them."""
    if quality not in QUALITIES:
        raise DenoiseError(f"denoise: quality {quality!r} is not one of {', '.join(QUALITIES)}; fix: pass Cycles' "
                           "denoising_quality")
    if prefilter not in PREFILTERS:
        raise DenoiseError(f"denoise: prefilter {prefilter!r} is not one of {', '.join(PREFILTERS)}; fix: pass "
                           "Cycles' denoising_prefilter")
    if normal is not None and albedo is None:
        raise DenoiseError("denoise: a normal without an albedo (OIDN needs the albedo with the normal, and Cycles "
                           "never passes one alone); fix: pass the Denoising Albedo pass too")
    if not (isinstance(threads, (int, np.integer)) and 0 <= threads <= 1024):
        raise DenoiseError(f"denoise: threads {threads!r} is not a count from 0 to 1024; fix: pass 0 (every core) "
                           "or a positive count")
    color = _image("color", color, None)
    shape = color.shape
    albedo = None if albedo is None else _image("albedo", albedo, shape)
    normal = None if normal is None else _image("normal", normal, shape)
    h, w = shape[:2]
    key = (h, w, quality, prefilter, albedo is not None, normal is not None, int(threads))
    with _lock:
        lib = load_library()
        device = _devices.get(int(threads))
        if device is None:
            device = _devices[int(threads)] = _Device(lib, int(threads))
        filters = _filters.pop(key, None)
        if filters is None:
            while len(_filters) >= _KEEP_FILTERS:
                _filters.popitem(last=False)[1].release()
            filters = _Filters(device, h, w, quality, prefilter, (albedo is not None, normal is not None))
        _filters[key] = filters
        for name, a in (("color", color), ("albedo", albedo), ("normal", normal)):
            if a is not None:
                np.copyto(filters.images[name], a[::-1])   # bottom-up, as Cycles' buffers
        return filters.run()[::-1].copy()   # top-down again, our own array
