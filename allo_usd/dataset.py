"""Assemble rendered scenes into an MVTec-AD-style tree that anomaly-detection libraries load as is.

Input: render directories as `allo_usd.job` writes them (NAME.json last, so a JSON marks a
finished scene; its "scene" holds split/variant/pose/day/anomaly/seed read from the layer).
Output, under OUT:

    OUT/<category>/train/good/NNNNNN_NAME.png          normal training images
    OUT/<category>/test/good/NNNNNN_NAME.png           normal test images
    OUT/<category>/test/anomaly/NNNNNN_NAME.png        anomalous test images
    OUT/<category>/ground_truth/anomaly/NNNNNN_NAME_mask.png   binary 0/255, anomaly class only
    OUT/allo_masks/<category>/<split>/<kind>/NNNNNN_NAME_mask.png   ALLO 3-class masks (0, 1, 2)
    OUT/manifest.csv (and manifest.parquet if pandas and pyarrow are installed)
    OUT/contact_sheets/<category>_<split>.png

Why these choices:
- anomalib's MVTec and Folder loaders glob EVERY image under the category directory and pair
  sorted anomalous images with sorted masks by position. So the category directory holds
  nothing but train/, test/ and ground_truth/ (the 3-class masks, sheets and manifest live
  beside it), and every file name starts with a unique fixed-width index: sorting images and
  masks then gives the same order whatever the scene names are (a bare `a.png`/`a_b.png` pair
  would sort differently from `a_mask.png`/`a_b_mask.png`). The scene name follows the index
  so that a person can read the tree.
- Indices, and rows, are keyed by scene name (NAME), kept in the manifest: re-running adds new
  scenes, refreshes re-rendered ones in place and never duplicates a row.
- Images and 3-class masks are hard links (no copy, no space) when possible; job.py replaces
  outputs by rename, so re-rendering never alters a linked dataset file. Every write is atomic.
- The paper's training set is normal only, and an anomalous scene whose anomaly has no visible
  pixel would be a wrong label: both are left out of the tree with a warning.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import shutil
import uuid
import warnings
from pathlib import Path

import numpy as np
from PIL import Image

from .errors import AlloError
from .write import atomic_path, mask_overlay, sha256_file, write_png

LAYOUTS = ("mvtec",)
COLUMNS = ("category", "index", "name", "image", "mask", "allo_mask", "split", "kind", "scene_id", "pose", "day",
           "epoch", "anomaly_asset", "anomaly_variant", "depth_index", "depth_offset", "anomaly_fraction",
           "seed", "seed_path", "layer", "layer_sha256", "sha256", "source")
MANIFEST = "manifest.csv"


def place(src: Path, dst: Path, link: bool = True) -> str:
    """Put src at dst atomically: a hard link if allowed and possible, else a copy. Returns how."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        same = os.path.samefile(src, dst)
        if (link and same) or (not link and not same and sha256_file(src) == sha256_file(dst)):
            return "kept"  # a copy run replaces earlier links by copies, and keeps equal copies
    if link:
        tmp = dst.parent / f".{dst.name}.{uuid.uuid4().hex}.tmp"
        try:
            os.link(src, tmp)
            os.replace(tmp, dst)
            return "link"
        except OSError:  # other file system, or links not allowed: copy instead
            tmp.unlink(missing_ok=True)
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
    return "copy"


def scan(render_dirs) -> list[tuple[Path, dict]]:
    """(json path, metadata) of every finished scene in the render directories, by name."""
    found: dict[str, tuple[Path, dict]] = {}
    for d in map(Path, render_dirs):
        if not d.is_dir():
            raise AlloError(f"render directory {d} does not exist; pass directories that `allo-usd render` wrote")
        for meta_path in sorted(d.glob("*.json")):
            try:
                meta = json.loads(meta_path.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError):
                continue  # not ours: job.py writes its JSON atomically, so it is never partial
            if not isinstance(meta, dict) or "scene" not in meta or "files" not in meta:
                continue  # not a render record (e.g. a plan or report beside the renders)
            name = meta_path.stem
            if name in found and found[name][1].get("layer_sha256") != meta.get("layer_sha256"):
                raise AlloError(f"two different scenes are named {name!r}: {found[name][0]} and {meta_path}; "
                                "rename one layer (names must be unique within a dataset)")
            found[name] = (meta_path, meta)
    return [found[k] for k in sorted(found)]


def read_manifest(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def write_manifest(path: Path, rows: list[dict]) -> Path:
    rows = sorted(rows, key=lambda r: (r["category"], int(r["index"])))
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(rows)
    if importlib.util.find_spec("pandas") and importlib.util.find_spec("pyarrow"):
        import pandas as pd

        with atomic_path(path.with_suffix(".parquet")) as tmp:
            pd.read_csv(path).to_parquet(tmp, index=False)
    return path


def _kind(scene: dict, meta: dict) -> str | None:
    kind = "anomaly" if scene.get("variant") == "anomaly" else "good"
    if kind == "anomaly" and scene.get("split") != "test":
        return None
    if kind == "anomaly" and meta.get("class_pixels", {}).get("anomaly", 0) == 0:
        return None
    return kind


def _row(category, index, name, meta_path: Path, meta: dict, kind: str, out: Path, link: bool) -> dict:
    scene, src = meta["scene"], meta_path.parent
    split = scene["split"]
    stem = f"{index:06d}_{name}"
    image = out / category / split / kind / f"{stem}.png"
    allo_mask = out / "allo_masks" / category / split / kind / f"{stem}_mask.png"
    rgb, mask_src = src / meta["files"]["rgb"], src / meta["files"]["mask"]
    place(rgb, image, link)
    place(mask_src, allo_mask, link)
    mask = ""
    if kind == "anomaly":
        mask_path = out / category / "ground_truth" / kind / f"{stem}_mask.png"
        write_png(mask_path, np.where(np.asarray(Image.open(mask_src)) == 2, 255, 0).astype(np.uint8))
        mask = mask_path.relative_to(out).as_posix()
    anomaly = scene.get("anomaly") or {}
    return {"category": category, "index": index, "name": name, "image": image.relative_to(out).as_posix(),
            "mask": mask, "allo_mask": allo_mask.relative_to(out).as_posix(), "split": split, "kind": kind,
            "scene_id": scene.get("sceneId", name), "pose": scene.get("pose"), "day": scene.get("day"),
            "epoch": scene.get("epoch"), "anomaly_asset": anomaly.get("asset", ""),
            "anomaly_variant": anomaly.get("assetVariant", ""), "depth_index": anomaly.get("depthIndex", ""),
            "depth_offset": anomaly.get("depthOffset", ""), "anomaly_fraction": meta.get("anomaly_fraction", 0.0),
            "seed": scene.get("seed"), "seed_path": scene.get("seedPath", ""), "layer": meta.get("layer", ""),
            "layer_sha256": meta.get("layer_sha256", ""), "sha256": sha256_file(rgb), "source": str(meta_path.resolve())}


def _unchanged(old: dict, meta_path: Path, meta: dict, kind: str, out: Path) -> bool:
    """A row whose source, layer and kind are the same and whose files are links to the render: skip
    hashing again (job.py replaces outputs by rename, so a linked file never changes content)."""
    if (old["source"], old["layer_sha256"], old["kind"], old["split"]) != (
            str(meta_path.resolve()), meta.get("layer_sha256", ""), kind, meta["scene"]["split"]):
        return False
    src = meta_path.parent
    try:
        return (os.path.samefile(out / old["image"], src / meta["files"]["rgb"])
                and os.path.samefile(out / old["allo_mask"], src / meta["files"]["mask"])
                and (not old["mask"] or (out / old["mask"]).is_file()))
    except OSError:
        return False


def _remove_files(out: Path, row: dict) -> None:
    for key in ("image", "mask", "allo_mask"):
        if row.get(key):
            (out / row[key]).unlink(missing_ok=True)


def assemble(render_dirs, out_dir, layout: str = "mvtec", link: bool = True, category: str = "allo",
             sheet_limit: int = 48) -> Path:
    """Build (or update) the dataset tree under out_dir from render directories; returns the manifest."""
    if layout not in LAYOUTS:
        raise AlloError(f"unknown dataset layout {layout!r}; choose one of {LAYOUTS}")
    if not category or "/" in category or category in ("allo_masks", "contact_sheets"):
        raise AlloError(f"category {category!r} must be a plain directory name")
    out = Path(out_dir)
    manifest = out / MANIFEST
    rows = {(r["category"], r["name"]): r for r in read_manifest(manifest)}
    next_index = 1 + max((int(r["index"]) for r in rows.values() if r["category"] == category), default=-1)
    skipped = []
    for meta_path, meta in scan(render_dirs):
        name = meta_path.stem
        kind = _kind(meta["scene"], meta)
        if kind is None:
            skipped.append(name)
            continue
        old = rows.get((category, name))
        if old and link and _unchanged(old, meta_path, meta, kind, out):
            continue
        index = int(old["index"]) if old else next_index
        next_index += old is None
        row = _row(category, index, name, meta_path, meta, kind, out, link)
        if old and any(old.get(k) != str(row[k]) for k in ("image", "mask", "allo_mask")):
            _remove_files(out, {k: old[k] for k in ("image", "mask", "allo_mask") if old[k] != str(row[k])})
        rows[(category, name)] = row
    if skipped:
        warnings.warn(f"{len(skipped)} scene(s) left out (anomalous in the train split, or anomaly not visible): "
                      f"{', '.join(skipped[:10])}", stacklevel=2)
    all_rows = list(rows.values())
    write_manifest(manifest, all_rows)
    for split in ("train", "test"):
        picked = [r for r in all_rows if r["category"] == category and r["split"] == split]
        if picked:
            grid_sheet(out, picked, out / "contact_sheets" / f"{category}_{split}.png", sheet_limit)
    return manifest


def grid_sheet(out: Path, rows: list[dict], path: Path, limit: int = 48, thumb_w: int = 160, cols: int = 6) -> Path:
    """A grid of thumbnails with mask overlays (blue station/bodies, red anomaly), anomalies first."""
    from PIL import ImageDraw

    rows = sorted(rows, key=lambda r: (r["kind"] != "anomaly", int(r["index"])))
    if len(rows) > limit:  # an even sample keeps the sheet small for big datasets
        rows = [rows[i] for i in np.linspace(0, len(rows) - 1, limit).round().astype(int)]
    first = Image.open(out / rows[0]["image"])
    thumb_h = max(1, round(thumb_w * first.height / first.width))
    label_h, pad = 14, 4
    cols = min(cols, len(rows))
    nrows = -(-len(rows) // cols)
    sheet = Image.new("RGB", (cols * (thumb_w + pad) + pad, nrows * (thumb_h + label_h + pad) + pad), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    for i, r in enumerate(rows):
        x, y = pad + (i % cols) * (thumb_w + pad), pad + (i // cols) * (thumb_h + label_h + pad)
        rgb = np.asarray(Image.open(out / r["image"]).convert("RGB"))
        mask = np.asarray(Image.open(out / r["allo_mask"]))
        tile = Image.fromarray(mask_overlay(rgb, mask)).resize((thumb_w, thumb_h), Image.Resampling.NEAREST)
        sheet.paste(tile, (x, y + label_h))
        draw.text((x, y), r["name"][:26], fill=(255, 120, 120) if r["kind"] == "anomaly"
                  else (220, 220, 220))
    return write_png(path, np.asarray(sheet))
