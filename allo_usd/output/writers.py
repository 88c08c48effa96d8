"""Write render arrays to files, atomically: PNG (8-bit sRGB), linear EXR (half), float32 EXR (depth,
normals), masks (uint8 classes, uint16 object ids).

Every file goes to a temporary name in its target directory and is renamed into place, so a
crash or a full disk never leaves a truncated output under a final name.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from allo_usd.core import fixedmath as fm
from allo_usd.core.errors import AlloError
from allo_usd.core.files import atomic_path

MASK_PALETTE = np.array([[0, 0, 0], [70, 130, 255], [255, 40, 40]], dtype=np.uint8)


def _srgb8_thresholds() -> np.ndarray:
    """The 255 linear values where the 8-bit sRGB code steps up: the inverse IEC 61966-2-1 transfer of
    each half-way level (k - 0.5) / 255, in float64 with core.fixedmath's power."""
    s = (np.arange(1, 256, dtype=np.float64) - 0.5) / 255.0
    return np.where(s <= 0.04045, s / 12.92, fm.power((s + 0.055) / 1.055, 2.4))


_SRGB8_THRESHOLDS = _srgb8_thresholds()


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer on clipped linear values, rounded to 8 bits (no dither): each value's code
    is the number of level thresholds it reaches, so the PNG is decided by comparisons alone, the same
    on every CPU (numpy's `power` rounds by CPU: SVML on AVX-512)."""
    c = np.clip(np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0), 0.0, 1.0)
    return np.searchsorted(_SRGB8_THRESHOLDS, c, side="right").astype(np.uint8)


def write_png(path: Path, array: np.ndarray) -> Path:
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(array)).save(tmp, format="PNG")
    return Path(path)


def write_rgb_png(path: Path, rgb_linear: np.ndarray) -> Path:
    return write_png(path, linear_to_srgb8(rgb_linear))


def write_mask_png(path: Path, mask: np.ndarray) -> Path:
    """Single-channel uint8 class mask (0, 1, 2)."""
    if mask.dtype != np.uint8 or mask.ndim != 2:
        raise AlloError(f"mask must be a 2-D uint8 array, got {mask.dtype} {mask.shape}")
    return write_png(path, mask)


def write_instance_png(path: Path, ids: np.ndarray) -> Path:
    """Single-channel 16-bit object-id mask (0 background)."""
    if ids.dtype != np.uint16 or ids.ndim != 2:
        raise AlloError(f"instance mask must be a 2-D uint16 array, got {ids.dtype} {ids.shape}")
    return write_png(path, ids)


def write_exr(path: Path, channels: dict[str, np.ndarray], half: bool = True, attributes: dict | None = None) -> Path:
    from allo_usd.core.interrupts import import_held

    OpenEXR = import_held("OpenEXR")   # a C extension that takes numpy as it loads: Ctrl-C held

    if half:  # the Sun's disc and its specular glints exceed half's range: saturate, never inf
        hmax = float(np.finfo(np.float16).max)
        data = {k: np.ascontiguousarray(np.clip(v, -hmax, hmax).astype(np.float16)) for k, v in channels.items()}
    else:
        data = {k: np.ascontiguousarray(v.astype(np.float32)) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attributes or {}).items():
        header[k] = v
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, data) as f:
            f.write(str(tmp))
    return Path(path)


def write_rgb_exr(path: Path, rgb_linear: np.ndarray, attributes: dict | None = None) -> Path:
    return write_exr(path, {"R": rgb_linear[..., 0], "G": rgb_linear[..., 1], "B": rgb_linear[..., 2]},
                     half=True, attributes=attributes)


def write_json(path: Path, obj) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(json_text(obj))
    return Path(path)


def json_text(obj) -> str:
    """The text write_json writes: indented, keys sorted (the bytes depend on the values only)."""
    return json.dumps(obj, indent=2, sort_keys=True, default=_jsonable) + "\n"


def _jsonable(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if hasattr(v, "__iter__"):
        return list(v)
    return str(v)


def mask_overlay(rgb8: np.ndarray, mask: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """The image with non-background classes tinted by MASK_PALETTE, for eyes only."""
    colour = MASK_PALETTE[np.clip(mask, 0, 2)].astype(np.float32)
    a = (mask > 0)[..., None] * alpha
    return np.rint(rgb8 * (1 - a) + colour * a).astype(np.uint8)


