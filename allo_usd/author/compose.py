"""Authoring by composition: shared sky and camera-sample layers, and small scene layers over them.

A plan of 51,409 scenes has only 365 skies and ~39,000 camera samples, so what a day or a
camera sample decides is written once and reused:

    OUT/sky/dDDD.usda                          sun light, bodies, eclipse state, epoch (per day)
    OUT/poses/sSEED/dDDD_pPP[_ASSET-VARIANT].usda  camera transform, offsets, attempts (per sample)
    OUT/scenes/SPLIT/KIND/SCENE_ID.usda        subLayers = [its pose layer, its sky layer, base]

A scene layer adds only its own opinions (identity and seed, anomaly, effects, render settings),
so it stays under 4 KB, and the five depths of one anomaly placement share one pose layer. Every
layer carries defaultPrim, upAxis and metersPerUnit, and every path in it is relative, so the
output directory can be moved as a whole (with the base stage at the same relative place).
"""

from __future__ import annotations

import os
from pathlib import Path

from ..spec import CameraSpec, SceneSpec, SunSpec
from .scene import (anomaly_asset_path, check_base_stage, pose_prims, scene_custom, scene_prims, sky_prims,
                    validate_spec, write_layer)

SKY_DIR, POSE_DIR, SCENE_DIR = "sky", "poses", "scenes"


def sky_layer_path(out_dir: Path, day: int) -> Path:
    return Path(out_dir) / SKY_DIR / f"d{day:03d}.usda"


def pose_layer_path(out_dir: Path, seed: int, sample_id: str) -> Path:
    return Path(out_dir) / POSE_DIR / f"s{seed}" / f"{sample_id.split('_', 1)[1]}.usda"


def scene_layer_path(out_dir: Path, split: str, kind: str, scene_id: str) -> Path:
    return Path(out_dir) / SCENE_DIR / split / kind / f"{scene_id}.usda"


def _rel(target: Path, start: Path) -> str:
    rel = os.path.relpath(os.path.abspath(target), os.path.abspath(start))
    return rel if rel.startswith(".") else f"./{rel}"


def write_sky_layer(path: Path, *, day: int, epoch: str, perilune_epoch: str, sun: SunSpec, bodies: dict) -> Path:
    """The shared layer of one day: everything the sky decides."""
    return write_layer(path, sky_prims(epoch, perilune_epoch, day, sun, bodies), [],
                       {"day": int(day), "epoch": epoch}, f"allo-usd sky of day {day} ({epoch})")


def write_pose_layer(path: Path, *, pose: int, camera: CameraSpec, seed: int, seed_path: str, sample_id: str) -> Path:
    """The shared layer of one perturbed camera sample (all depths of a placement use it)."""
    return write_layer(path, pose_prims(pose, camera), [],
                       {"seed": int(seed), "seedPath": seed_path, "sampleId": sample_id},
                       f"allo-usd camera sample {sample_id}")


def write_composed_scene(spec: SceneSpec, path: Path, *, pose_layer: Path, sky_layer: Path,
                         base_stage: Path) -> Path:
    """A scene layer holding only its own opinions, stacked on its pose, sky and base layers."""
    validate_spec(spec)
    path = Path(path)
    base_stage = check_base_stage(base_stage)
    here = path.parent
    ref = "" if spec.anomaly is None else _rel(anomaly_asset_path(base_stage, spec.anomaly.asset), here)
    sublayers = [_rel(pose_layer, here), _rel(sky_layer, here), _rel(base_stage, here)]
    return write_layer(path, scene_prims(spec, ref), sublayers, scene_custom(spec),
                       f"allo-usd scene {spec.scene_id}")


def author_plan(plan, out_dir: Path, limit: int | None = None, progress: bool = True, workers: int | None = None):
    """Author every scene of `plan` under `out_dir` (see allo_usd.authoring.author_plan)."""
    from ..authoring import author_plan as _author_plan

    return _author_plan(plan, out_dir, limit=limit, progress=progress, workers=workers)
