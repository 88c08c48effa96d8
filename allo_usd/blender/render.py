"""Render the built scene with Cycles and return arrays (the caller writes files)."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..description import SceneDescription
from ..errors import AlloError
from .build import build_scene


@dataclass(frozen=True, eq=False)
class RenderResult:
    rgb: np.ndarray          # (H, W, 3) float32, linear, times the layer's exposure
    mask: np.ndarray         # (H, W) uint8: 0 background, 1 station and bodies, 2 anomaly
    depth: np.ndarray | None  # (H, W) float32 metres, when the layer asks for it
    seconds: float


def _read_multilayer_exr(path: Path) -> dict[str, np.ndarray]:
    import OpenEXR

    channels = {}
    with OpenEXR.File(str(path), separate_channels=True) as f:
        for part in f.parts:
            for name, ch in part.channels.items():
                channels[name] = np.asarray(ch.pixels)
    return channels


def _find(channels: dict, *suffixes: str) -> np.ndarray | None:
    for suffix in suffixes:
        for name, arr in channels.items():
            if name.endswith(suffix):
                return arr
    return None


def render_current(desc: SceneDescription, workdir: Path | None = None) -> RenderResult:
    import time

    import bpy

    scene = bpy.context.scene
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.image_settings.color_depth = "32"
    scene.render.image_settings.exr_codec = "ZIP"
    with tempfile.TemporaryDirectory(dir=workdir, prefix="allo-render-") as tmp:
        out = Path(tmp) / "render.exr"
        scene.render.filepath = str(out)
        t0 = time.perf_counter()
        result = bpy.ops.render.render(write_still=True)
        seconds = time.perf_counter() - t0
        if "FINISHED" not in result or not out.is_file():
            raise AlloError(f"Cycles did not produce an image for {desc.layer}; see Blender's log above")
        ch = _read_multilayer_exr(out)
    from .compositor import has_compositor

    layer = "Composite.Combined" if has_compositor() else "ViewLayer.Combined"
    r, g, b = (ch.get(f"{layer}.{c}") for c in "RGB")
    if r is None:
        raise AlloError(f"the render of {desc.layer} has no {layer} pass; channels: {sorted(ch)}")
    rgb = np.stack([r, g, b], axis=-1).astype(np.float32)  # EXR rows run top-down, like PNG
    index = _find(ch, "IndexOB.X", "Object Index.X", "IndexOB.V")
    if index is None:
        raise AlloError(f"the render of {desc.layer} has no object index pass; channels: {sorted(ch)}")
    mask = np.rint(index).astype(np.uint8)
    depth = _find(ch, "Depth.Z", "Depth.V") if "depth" in desc.render.outputs else None
    return RenderResult(rgb, mask, depth, seconds)


def render_scene(desc: SceneDescription, workdir: Path | None = None) -> RenderResult:
    build_scene(desc)
    return render_current(desc, workdir)
