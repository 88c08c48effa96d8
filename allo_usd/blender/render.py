"""Render the built scene with Cycles and return arrays (the caller writes files).

Blender writes its multilayer EXR into a temporary directory (`workdir`), and it does not report
a failed write to Python: on a full disk it logs "IMB_exr_write_channels: Failed to write pixel
data ... No space left on device", then "Saved: ..." and returns FINISHED with a cut-short file
(seen on a full tmpfs with bpy 5.0.1). So the free space of that directory's file system is
checked after every render: less free than the file Blender just wrote (or no free inode) means
the file may be cut short and our outputs would not fit either, so DiskFullError stops the run.
Any other failure to get an image is RenderFailedError, which the dispatcher retries: it is not
the layer's fault.

With the `amodal` pass, render_current renders a second time right after the main render: the
anomaly alone, mask-only (blender.amodal.anomaly_alone, which puts the scene back afterwards).
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from allo_usd.usd.description import SceneDescription
from allo_usd.core.errors import DiskFullError, RenderFailedError
from allo_usd.blender.build import build_scene, object_ids
from allo_usd.plan.settings import COLOR_PASSES

MIN_FREE_BYTES = 1 << 20  # after a failed render, less free than this on the temp device means "disk full"


@dataclass(frozen=True, eq=False)
class RenderResult:
    rgb: np.ndarray          # (H, W, 3) float32, linear, times the layer's exposure
    mask: np.ndarray         # (H, W) uint8: 0 background, 1 station and bodies, 2 anomaly
    depth: np.ndarray | None  # (H, W) float32 metres, when the layer asks for it
    seconds: float
    ids: np.ndarray | None = None      # (H, W) uint16 object id (build.object_ids), 0 background
    objects: tuple[str, ...] = ()      # prim path of object id 1, 2, ...
    normal: np.ndarray | None = None   # (H, W, 3) float32 world-space normal, when the layer asks for it
    amodal: np.ndarray | None = None   # (H, W) uint8 0/2: the anomaly alone (blender.amodal), when asked for
    amodal_seconds: float = 0.0        # that second render's time
    # the render's estimate of its own error (blender.target): {"mode": "target" | "fixed", "target_psnr_db",
    # "estimated_psnr_db", "samples", "rounds", "stopped_by": "target" | "samples" | "seconds", "estimator"};
    # None: not estimated
    accuracy: dict | None = None


def read_multilayer_exr(path: Path) -> dict[str, np.ndarray]:
    from allo_usd.core.interrupts import import_held

    OpenEXR = import_held("OpenEXR")   # a C extension that takes numpy as it loads: Ctrl-C held

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


def free_space(path: Path) -> tuple[int, int]:
    """(bytes, inodes) this process may still allocate on the file system holding `path`
    (root may use the blocks reserved for root, so it counts those too)."""
    st = os.statvfs(path)
    root = hasattr(os, "geteuid") and os.geteuid() == 0
    blocks, inodes = (st.f_bfree, st.f_ffree) if root else (st.f_bavail, st.f_favail)
    return blocks * st.f_frsize, (inodes if st.f_files else 1 << 30)  # f_files 0: no inode limit


def _disk_full(where: Path, detail: str) -> DiskFullError:
    return DiskFullError(f"no space left on the device holding {where} ({detail}); free space and re-run "
                         "(finished outputs are kept and will be skipped)")


def check_render_file(out: Path, finished: bool, desc_layer: str) -> None:
    """Raise DiskFullError if the device holding Blender's render file `out` is full, or
    RenderFailedError if Blender did not produce the file; return if it looks written."""
    size = out.stat().st_size if out.is_file() else 0
    free, inodes = free_space(out.parent)
    if inodes == 0 or (size and free < size):
        raise _disk_full(out.parent.parent, f"{free} bytes and {inodes} inodes free after Blender wrote {size} "
                         "bytes of its render; Blender does not report a failed write, so that file may be cut short")
    if not finished or not size:
        if free < MIN_FREE_BYTES:
            raise _disk_full(out.parent.parent, f"only {free} bytes free and Blender wrote no render")
        state = f"render {'finished' if finished else 'cancelled'}, file {'empty' if out.is_file() else 'missing'}"
        raise RenderFailedError(f"Blender did not write a render of {desc_layer} ({state}); see the worker's log; "
                                "the dispatcher retries it")


def unreadable_render_file(out: Path, desc_layer: str, problem: str) -> Exception:
    """A render file we cannot use: disk full if the device is (nearly) full, else a retriable failure."""
    free, inodes = free_space(out.parent)
    if inodes == 0 or free < MIN_FREE_BYTES:
        return _disk_full(out.parent.parent, f"{free} bytes free; Blender's render file {problem}")
    return RenderFailedError(f"the render of {desc_layer} {problem}; the dispatcher retries it")


def render_channels(desc: SceneDescription, workdir: Path | None = None,
                    missing=lambda ch: None) -> tuple[dict[str, np.ndarray], float]:
    """Render the current Blender scene to a multilayer EXR in a temporary folder under `workdir`; return
    its channels and the render's seconds. `missing(channels)` names a pass the caller needs that the
    file lacks (None: none), checked while the file is there: unreadable_render_file decides disk full
    or retriable failure."""
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
        free, inodes = free_space(out.parent)
        if inodes == 0 or free == 0:
            raise _disk_full(out.parent.parent, f"{free} bytes and {inodes} inodes free before rendering")
        t0 = time.perf_counter()
        result = bpy.ops.render.render(write_still=True)
        seconds = time.perf_counter() - t0
        check_render_file(out, "FINISHED" in result, desc.layer)
        try:
            ch = read_multilayer_exr(out)
        except Exception as exc:  # noqa: BLE001 - OpenEXR raises plain exceptions for cut-short files
            raise unreadable_render_file(out, desc.layer, f"cannot be read ({type(exc).__name__}: {exc})") from exc
        problem = missing(ch)
        if problem:
            raise unreadable_render_file(out, desc.layer, f"has no {problem} pass (channels: {sorted(ch)})")
    return ch, seconds


INDEX_CHANNELS = ("IndexOB.X", "Object Index.X", "IndexOB.V")


def no_object_index(ch: dict[str, np.ndarray]) -> str | None:
    """render_channels' `missing` for a render that needs only the object index pass."""
    return None if _find(ch, *INDEX_CHANNELS) is not None else "object index"


def object_index(desc: SceneDescription, ch: dict[str, np.ndarray]) -> np.ndarray:
    """The object index pass of a render's channels (checked present by render_channels' `missing`), as
    uint16 object ids (build.object_ids)."""
    return np.clip(np.rint(_find(ch, *INDEX_CHANNELS)), 0, len(object_ids(desc))).astype(np.uint16)


def result_passes(desc: SceneDescription, ch: dict[str, np.ndarray]):
    """(class mask, object ids, depth, normal, object paths) of a render's channels."""
    table = object_ids(desc)
    classes = np.array([0] + [c for _, c in table], dtype=np.uint8)   # object id -> class id
    ids = object_index(desc, ch)
    depth = _find(ch, "Depth.Z", "Depth.V") if "depth" in desc.render.outputs else None
    normal = (np.stack([_find(ch, f"Normal.{c}") for c in "XYZ"], axis=-1).astype(np.float32)
              if "normal" in desc.render.outputs else None)
    return classes[ids], ids, depth, normal, tuple(p for p, _ in table)


def _missing(desc: SceneDescription, layer: str):
    """render_channels' `missing` for a colour render: the `layer` Combined pass, the object index, and the
    normal when the layer orders it."""
    wants_normal = "normal" in desc.render.outputs

    def missing(ch) -> str | None:
        if f"{layer}.R" not in ch:
            return layer
        if no_object_index(ch):
            return "object index"
        if wants_normal and any(_find(ch, f"Normal.{c}") is None for c in "XYZ"):
            return "normal"
        return None
    return missing


def render_current(desc: SceneDescription, workdir: Path | None = None) -> RenderResult:
    """Render the scene Blender holds (built from `desc`): one render of the layer's samples, or, with a
    PSNR target (allo:render:targetPsnr), rounds of two halves until the estimate reaches it
    (blender.target); then the amodal pass's second render when the layer asks for it."""
    from allo_usd.blender.compositor import has_compositor

    colour = bool(set(COLOR_PASSES) & set(desc.render.outputs))
    aimed = desc.render.target_psnr > 0 and colour
    # the target mode reads the view layer's passes (it refuses a compositor: blender.target)
    layer = "Composite.Combined" if not aimed and has_compositor() else "ViewLayer.Combined"
    missing = _missing(desc, layer)
    if aimed:
        from allo_usd.blender.target import render_to_target

        rgb, ch, seconds, accuracy = render_to_target(desc, lambda m: render_channels(desc, workdir, m), missing)
    else:
        estimate = desc.render.estimate and colour
        if estimate:   # the same render, its noisy image stored beside it (blender.target.estimate_fixed)
            from allo_usd.blender.target import estimate_fixed, noisy_image_stored

            with noisy_image_stored():
                ch, seconds = render_channels(desc, workdir, missing)
        else:
            ch, seconds = render_channels(desc, workdir, missing)
        rgb = np.stack([ch[f"{layer}.{c}"] for c in "RGB"], axis=-1).astype(np.float32)  # EXR rows run top-down
        accuracy = estimate_fixed(desc, ch, lambda m: render_channels(desc, workdir, m), missing) if estimate else None
    mask, ids, depth, normal, objects = result_passes(desc, ch)
    result = RenderResult(rgb, mask, depth, seconds, ids=ids, objects=objects, normal=normal, accuracy=accuracy)
    if "amodal" in desc.render.outputs:   # a second render: the anomaly alone (the scene is restored after it)
        from allo_usd.blender.amodal import amodal_mask, anomaly_alone

        with anomaly_alone(desc):
            ch, amodal_seconds = render_channels(desc, workdir, no_object_index)
        result = replace(result, amodal=amodal_mask(desc, object_index(desc, ch)), amodal_seconds=amodal_seconds)
    return result


def render_scene(desc: SceneDescription, workdir: Path | None = None) -> RenderResult:
    build_scene(desc)
    return render_current(desc, workdir)
