"""One render job: a scene layer in, its files out (PNG, EXR, mask, metadata).

The unit of work for local pools and Dask alike. Outputs are written atomically and the
metadata JSON goes last, so its presence marks a finished scene and re-runs skip it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from . import __version__
from .write import write_json, write_mask_png, write_rgb_exr, write_rgb_png


def output_paths(layer: Path, out_dir: Path) -> dict[str, Path]:
    stem = Path(layer).stem
    out_dir = Path(out_dir)
    return {"rgb": out_dir / f"{stem}.png", "exr": out_dir / f"{stem}.exr",
            "mask": out_dir / f"{stem}_mask.png", "meta": out_dir / f"{stem}.json"}


def is_done(layer: Path, out_dir: Path) -> bool:
    paths = output_paths(layer, out_dir)
    return all(p.is_file() for p in paths.values())


def apply_effects(desc, rgb: np.ndarray) -> tuple[np.ndarray, dict]:
    """Post-render effects the layer declares, on linear data; each absent effect costs nothing."""
    applied = {}
    if desc.effects.sensor_noise:
        from .effects.noise import SensorParams, apply_sensor_noise

        params = SensorParams()
        rgb = apply_sensor_noise(rgb, desc.render.exposure, seed=desc.render.seed, params=params)
        applied["sensor_noise"] = {"model": "EMVA 1288", "seed": desc.render.seed, **params.as_dict()}
    return rgb, applied


def render_layer(layer: Path, out_dir: Path, force: bool = False, threads: int | None = None,
                 workdir: Path | None = None, session=None) -> dict:
    """Render one layer into out_dir; returns its metadata (also written as JSON).

    `threads` overrides the layer's allo:render:threads for this process only (the layer is not
    edited): a pool of N workers on C cores runs each with C // N threads. Cycles gives the same
    image for any thread count. `workdir` holds Blender's temporary render file. `session` (an
    allo_usd.blender.session.Session) keeps the Blender scene warm and applies only what differs
    from its previous scene; the files are byte-identical to a from-scratch build.
    """
    import dataclasses
    import json

    from .blender.render import render_scene
    from .read import read_scene

    paths = output_paths(layer, out_dir)
    if not force and is_done(layer, out_dir):
        return json.loads(paths["meta"].read_text())
    desc = read_scene(layer)
    if threads is not None:
        desc = dataclasses.replace(desc, render=dataclasses.replace(desc.render, threads=int(threads)))
    result = render_scene(desc, workdir) if session is None else session.render(desc, workdir)
    rgb, effects = apply_effects(desc, result.rgb)
    write_rgb_png(paths["rgb"], rgb)
    write_rgb_exr(paths["exr"], rgb)
    write_mask_png(paths["mask"], result.mask)
    counts = np.bincount(result.mask.ravel(), minlength=3)
    meta = {
        "layer": str(Path(layer).resolve()),
        "layer_sha256": hashlib.sha256(Path(layer).read_bytes()).hexdigest(),
        "package_version": __version__,
        "render_seconds": round(result.seconds, 3),
        "resolution": list(desc.render.resolution),
        "class_pixels": {"background": int(counts[0]), "station_and_bodies": int(counts[1]),
                         "anomaly": int(counts[2])},
        "anomaly_fraction": float(counts[2] / result.mask.size),
        "scene": desc.meta,
        "effects": effects,
        "files": {k: p.name for k, p in paths.items()},
    }
    write_json(paths["meta"], meta)
    return meta
