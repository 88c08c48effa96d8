"""Render records for the dataset tests: fabricated ones (`fake_render`, `edit`), four real 64x36
Cycles renders of the tiny base stage (the `renders` fixture) and copies of them under other names
(`fabricate`)."""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from allo_usd.run.job import render_layer
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec


def fake_render(d: Path, name: str, split: str = "train", variant: str = "normal", size=(64, 36),
                station: int = 600, anomaly: int = 0, black: bool = False, **scene) -> Path:
    """A render record as allo_usd.run.job writes it: NAME.png, NAME_mask.png, NAME.json."""
    d.mkdir(parents=True, exist_ok=True)
    w, h = size
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    rgb = np.zeros((h, w, 3), np.uint8) if black else rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    mask = np.zeros(w * h, np.uint8)
    mask[:station] = 1
    mask[station:station + anomaly] = 2
    Image.fromarray(rgb).save(d / f"{name}.png")
    Image.fromarray(mask.reshape(h, w)).save(d / f"{name}_mask.png")
    counts = {"background": w * h - station - anomaly, "station_and_bodies": station, "anomaly": anomaly}
    meta = {"layer": str(d / f"{name}.usda"), "layer_sha256": hashlib.sha256(name.encode()).hexdigest(),
            "package_version": "0", "render_seconds": 0.1, "resolution": [w, h], "class_pixels": counts,
            "anomaly_fraction": anomaly / (w * h), "effects": {},
            "scene": {"sceneId": name, "split": split, "variant": variant, "pose": 1, "day": 0, "seed": 1,
                      "seedPath": "1/0/1/1", "provenance": {},
                      **({"anomaly": {"asset": "crate", "assetVariant": "blue", "depthIndex": 0}}
                         if variant == "anomaly" else {}), **scene},
            "files": {"rgb": f"{name}.png", "exr": f"{name}.exr", "mask": f"{name}_mask.png",
                      "meta": f"{name}.json"}}
    (d / f"{name}.json").write_text(json.dumps(meta))
    return d / f"{name}.json"


def edit(meta_path: Path, change) -> None:
    meta = json.loads(meta_path.read_text())
    change(meta)
    meta_path.write_text(json.dumps(meta))


SCENES = {  # name: (spec kwargs, split override)
    "d000_p01": (dict(day=0, pose=1, seed=11), None),
    "d001_p02": (dict(day=1, pose=2, seed=12), None),
    "d002_p41": (dict(day=2, seed=13), ("test", 41)),
    "d003_p41_crate_z0": (dict(day=3, seed=14, anomaly=True), ("test", 41)),
}


@pytest.fixture(scope="module")
def renders(tiny_base, tmp_path_factory):
    """Four real 64x36 Cycles renders: 2 normal train, 1 normal test, 1 anomalous test."""
    root = tmp_path_factory.mktemp("ds_render")
    for name, (kw, split) in SCENES.items():
        spec = make_spec(scene_id=name, **kw)
        if split:
            spec = replace(spec, split=split[0], pose=split[1])
        render_layer(write_scene_layer(spec, root / "layers" / f"{name}.usda", tiny_base), root / "renders")
    return root / "renders"


def fabricate(src_dir: Path, src_name: str, dst_dir: Path, name: str, **scene) -> Path:
    """A render record in job.py's exact format, copied from a real one under a new name."""
    meta = json.loads((src_dir / f"{src_name}.json").read_text())
    dst_dir.mkdir(parents=True, exist_ok=True)
    files = {"rgb": f"{name}.png", "exr": f"{name}.exr", "mask": f"{name}_mask.png", "meta": f"{name}.json"}
    for key in ("rgb", "exr", "mask"):
        shutil.copyfile(src_dir / meta["files"][key], dst_dir / files[key])
    meta["files"], meta["layer_sha256"] = files, hashlib.sha256(name.encode()).hexdigest()
    meta["scene"].update(sceneId=name, **scene)
    (dst_dir / f"{name}.json").write_text(json.dumps(meta))
    return dst_dir
