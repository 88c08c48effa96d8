"""The dataset's annotation files, rebuilt from the manifest's rows at the end of every
`allo-usd dataset` run (allo_usd.output.dataset calls write_annotation_files):

    OUT/annotations/instances_train.json, instances_test.json   COCO (allo_usd.output.coco)
    OUT/bop/CATEGORY/...                                        BOP-shaped pose files (allo_usd.output.bop)
    OUT/instances.json                                          per image: instance id -> prim path
    OUT/annotations/records.json                                the per-image cache the files above are built from,
                                                                and the dataset's own (render checks, contact sheets)

Why a cache: an image's record (its COCO RLE, BOP entries, the per-image BOP files it wrote) is
computed once from the tree's mask and depth and its render JSON, and kept in records.json under
a key of the image's whole manifest row; a re-run recomputes only the records whose row changed
(a re-rendered or moved scene, a new one) or whose files went missing, and rebuilds the JSON
files from the records. A file whose bytes would not change is not rewritten, so a re-run that
adds scenes leaves the other images' files, and unchanged BOP chunks, untouched. Deleting
records.json only costs the next run a full recompute. Every write is atomic.

records.json also keeps what allo_usd.output.dataset hands it to keep between runs (`state`: the
stat at which each render record passed check_render, the rows each contact sheet was drawn
from), so that a re-run does not decode every mask again; it lives here so that the dataset's
caches are one file, rewritten only when a run changes something.

Cost: an image's record decodes its 3-class mask only when it is anomalous or has a depth pass (a
normal image's size is read from the PNG header), and an anomaly's mask_visib is a hard link to
its ground-truth mask (the same 0/255 pixels, written once by the dataset).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np

from allo_usd.core.files import MAX_RECORD_BYTES, read_user_json, write_text_atomic
from allo_usd.core.labels import ANOMALY
from allo_usd.core.scene_labels import SPLITS
from allo_usd.output import bop, coco
from allo_usd.output.contact import read_pixels
from allo_usd.output.dataset_files import COLUMNS, Refused, place, source_file
from allo_usd.output.writers import write_png
from allo_usd.output.pass_files import PASS_COLUMNS
from allo_usd.output.record import RenderRecord

RECORDS = "annotations/records.json"
INSTANCES = "instances.json"
RECORDS_VERSION = 2   # 2: a record lists every anomaly object (coco and bop.gt are lists)

BOP_FILE = re.compile(r"^(?:\d{6}(?:_\d{6})?\.png|scene_(?:camera|gt|gt_info)\.json)$")
PASS_FILE = re.compile(r"^\d{6}_.+\.(?:exr|png)$")


def row_key(row: dict) -> str:
    """A digest of the row as the manifest stores it (None as "", values as str): equal iff the row is."""

    text = "\x1f".join("" if row.get(c) is None else str(row.get(c)) for c in COLUMNS)
    return hashlib.sha256(text.encode()).hexdigest()


def write_if_changed(path: Path, text: str) -> bool:
    """Write `text` atomically unless the file already holds exactly it; returns whether it wrote."""
    try:
        if path.is_file() and path.read_text(encoding="utf-8") == text:
            return False
    except (OSError, UnicodeDecodeError):
        pass
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, text, encoding="utf-8", newline="\n")
    return True


def read_depth_exr(path: Path) -> np.ndarray:
    """The Z channel of a float depth EXR (the render's STEM_depth.exr), metres."""
    from allo_usd.core.interrupts import import_held

    OpenEXR = import_held("OpenEXR")   # a C extension that takes numpy as it loads: Ctrl-C held

    with OpenEXR.File(str(path), separate_channels=True) as f:
        channels = f.parts[0].channels
        name = "Z" if "Z" in channels else next(iter(channels))
        return np.asarray(channels[name].pixels, dtype=np.float32)


def _render_json(out: Path, row: dict) -> tuple[RenderRecord, Path | None]:
    """(the row's render record, its path), (an empty record, None) when it is gone or unreadable."""

    if not row.get("source"):
        return RenderRecord(), None
    path = Path(out) / row["source"]
    try:
        meta = read_user_json(path, MAX_RECORD_BYTES, "render record")
    except Exception:  # noqa: BLE001 - a missing or hostile record only costs its pose
        return RenderRecord(), None
    return (RenderRecord.of(meta), path) if isinstance(meta, dict) else (RenderRecord(), None)


def _amodal_mask(meta: RenderRecord, meta_path: Path | None, shape) -> np.ndarray | None:
    """The render's STEM_amodal.png as a boolean mask (labels.ANOMALY pixels), None if not rendered."""

    files = meta.files if isinstance(meta.files, dict) else {}
    if meta_path is None or "amodal" not in files:
        return None
    try:
        pixels = read_pixels(source_file(meta_path.parent, files["amodal"]))
    except (Refused, OSError, ValueError):
        return None
    return pixels == ANOMALY if pixels.shape == tuple(shape) else None


def _model_path(path: str | None, row: dict, out: Path) -> str | None:
    """The model file, relative to the dataset root (the render records it relative to the layer's folder)."""
    if not path or not row.get("layer"):
        return None
    full = os.path.normpath(Path(out) / Path(row["layer"]).parent / path)
    return Path(os.path.relpath(full, os.path.normpath(out))).as_posix()


def _anomaly_objects(annotations: dict) -> list[dict]:
    """The render JSON's anomaly objects: `anomalies` (the planned anomaly first), or, from a render
    recorded before objects were listed, its one `anomaly` ([{}] when it records none: the class
    mask is then the one object's pixels, and the scene's asset names it)."""
    listed = annotations.get("anomalies")
    if isinstance(listed, list) and listed and all(isinstance(o, dict) for o in listed):
        return listed
    one = annotations.get("anomaly")
    return [one if isinstance(one, dict) else {}]


def _object_pixels(obj: dict, shape) -> np.ndarray:
    """An anomaly object's visible pixels from its recorded COCO RLE (`segmentation`; none: no pixel)."""
    from pycocotools import mask as mask_utils

    seg = obj.get("segmentation")
    try:
        if isinstance(seg, dict) and list(seg.get("size", ())) == list(shape) and isinstance(seg.get("counts"), str):
            return mask_utils.decode({"size": list(shape), "counts": seg["counts"].encode("ascii")}).astype(bool)
    except (ValueError, TypeError):
        pass
    return np.zeros(shape, dtype=bool)


def _link(src: Path, dst: Path) -> None:

    place(src, dst, link=True)


def compute_record(out: Path, row: dict, mask: np.ndarray | None = None, meta: RenderRecord | dict | None = None,
                   visible=None) -> dict:
    """One image's record: COCO instance, BOP entries and the per-image BOP files (written here).
    `mask`: the row's 3-class mask when the caller has it decoded; `visible`: its anomaly pixels
    (dataset_files.AnomalyPixels) when the caller has them (the dataset, placing an anomaly);
    `meta`: the row's render record (or its JSON object) when the caller has it read (else it is
    read here)."""

    from PIL import Image

    out = Path(out)
    index, anomalous = int(row["index"]), row["kind"] == "anomaly"
    if visible is not None and mask is None:
        height, width = visible.shape
    elif mask is not None or anomalous or row.get("depth"):
        mask = read_pixels(out / row["allo_mask"]) if mask is None else mask
        height, width = mask.shape
    else:   # a normal image without depth needs only the size: the header, not 2 MB of pixels
        with Image.open(out / row["allo_mask"]) as im:
            width, height = im.size
    shape = (height, width)
    if meta is None:
        meta, meta_path = _render_json(out, row)
    else:
        meta, meta_path = RenderRecord.given(meta), out / row["source"] if row.get("source") else None
    annotations = meta.annotations if isinstance(meta.annotations, dict) else {}
    folder = f"bop/{row['category']}/{row['split']}/{bop.chunk_of(index)}"
    rgb = f"{folder}/rgb/{index:06d}.png"
    _link(out / row["image"], out / rgb)
    files = [rgb]
    depth_units = None
    if row.get("depth"):
        depth = read_depth_exr(out / row["depth"])
        if depth.shape == shape:
            depth_units = bop.depth_png(depth)
            files.append(f"{folder}/depth/{index:06d}.png")
            write_png(out / files[-1], depth_units)
    rec = {"key": row_key(row), "category": row["category"], "name": row["name"], "index": index,
           "split": row["split"], "kind": row["kind"], "image": row["image"], "width": width, "height": height,
           "coco": [], "bop": {"folder": folder, "camera": bop.camera_entry(annotations.get("camera")), "gt": []},
           "instances": None}
    if anomalous:
        scene_anomaly = (meta.scene or {}).get("anomaly") if isinstance(meta.scene, dict) else None
        whole = visible.full() if visible is not None and mask is None else mask == ANOMALY
        amodal = _amodal_mask(meta, meta_path, shape)
        objects = _anomaly_objects(annotations)
        for gt_id, obj in enumerate(objects):
            planned = gt_id == 0   # the scene's planned anomaly (/World/Anomaly) comes first
            mine = whole if len(objects) == 1 else _object_pixels(obj, shape) & whole
            model = bop.model(obj, scene_anomaly if planned else None)
            model["path"] = _model_path(model["path"], row, out)
            instance = coco.instance(mine)
            if instance is not None:   # the category: the object's asset (the planned one's: the row's)
                asset, variant = ((row.get("anomaly_asset", ""), row.get("anomaly_variant", "")) if planned
                                  else (model["asset"], model["variant"]))
                rec["coco"].append({"asset": asset, "variant": variant, **instance}
                                   | ({"path": obj["path"]} if len(objects) > 1 else {}))
            full = amodal if planned else None
            rec["bop"]["gt"].append({"pose": bop.pose(obj), "model": model,
                                     "info": bop.gt_info(mine, full, obj, depth_units)})
            files.append(f"{folder}/mask_visib/{index:06d}_{gt_id:06d}.png")
            truth = out / row["mask"] if row.get("mask") else None
            if len(objects) == 1 and truth is not None and truth.is_file():   # the same 0/255 pixels
                _link(truth, out / files[-1])
            else:
                write_png(out / files[-1], mine.astype(np.uint8) * np.uint8(255))
            if full is not None:
                files.append(f"{folder}/mask/{index:06d}_{gt_id:06d}.png")
                write_png(out / files[-1], full.astype(np.uint8) * np.uint8(255))
    table = meta.instances
    if row.get("instance") and isinstance(table, dict):
        rec["instances"] = {"instance": row["instance"], "objects": {str(k): str(v) for k, v in table.items()}}
    rec["files"] = files
    return rec


def load_cache(out: Path) -> dict:
    """records.json's content ({} when missing, unreadable or of another version): pass it back to
    write_annotation_files, and read the dataset's `state` from it."""
    return _load(Path(out))


def _load(out: Path) -> dict:
    try:
        cache = json.loads((out / RECORDS).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return cache if isinstance(cache, dict) and cache.get("version") == RECORDS_VERSION else {}


def _records(out: Path, rows, cache: dict, early: dict | None = None) -> tuple[dict, int]:
    """{category/name: record} of every row, from the cache where its key holds; (records, recomputed).
    `early`: records computed this run (by the dataset, at placement), used where their key holds."""
    old = cache.get("records") if isinstance(cache.get("records"), dict) else {}
    early = early or {}
    records, recomputed = {}, 0
    for row in sorted(rows, key=lambda r: (r["category"], int(r["index"]))):
        name = f"{row['category']}/{row['name']}"
        key = row_key(row)
        rec = early.get(name)
        if isinstance(rec, dict) and rec.get("key") == key and all((out / f).is_file() for f in rec["files"]):
            recomputed += 1
        else:
            rec = old.get(name)
            if not (isinstance(rec, dict) and rec.get("key") == key
                    and all((out / f).is_file() for f in rec.get("files", ()))):
                rec = compute_record(out, row)
                recomputed += 1
        records[name] = rec
    return records, recomputed


def _coco_files(out: Path, records: dict, categories: dict[str, int]) -> None:

    for split in SPLITS:
        images, anns = [], []
        for rec in records.values():
            if rec["split"] != split:
                continue
            image_id = len(images) + 1
            images.append({"id": image_id, "file_name": rec["image"], "width": rec["width"], "height": rec["height"],
                           "scene": rec["name"], "allo_category": rec["category"], "index": rec["index"]})
            for inst in rec["coco"]:
                anns.append({"id": len(anns) + 1, "image_id": image_id, "category_id": categories[inst["asset"]],
                             **{k: v for k, v in inst.items() if k != "asset"}})
        text = json.dumps(coco.document(split, images, anns, categories), sort_keys=True, separators=(",", ":")) + "\n"
        write_if_changed(out / "annotations" / f"instances_{split}.json", text)


def _bop_files(out: Path, records: dict, models: dict[str, dict[str, int]]) -> set[str]:
    """Write each chunk's scene_*.json, each category's models.json and camera.json; the set of BOP files."""
    chunks: dict[str, dict[str, dict]] = {}
    expected: set[str] = set()
    tables: dict[str, dict] = {}
    for rec in records.values():
        b = rec["bop"]
        chunk = chunks.setdefault(b["folder"], {"scene_camera": {}, "scene_gt": {}, "scene_gt_info": {}})
        im = str(rec["index"])
        if b["camera"] is not None:
            chunk["scene_camera"][im] = b["camera"]
            tables.setdefault(rec["category"], {}).setdefault("camera", (b["camera"], rec["width"], rec["height"]))
        posed = [g for g in b["gt"] if g["pose"] is not None and g["model"] is not None]
        chunk["scene_gt"][im] = [{"obj_id": models[rec["category"]][g["model"]["model_id"]], **g["pose"]} for g in posed]
        chunk["scene_gt_info"][im] = [g["info"] for g in posed]
        expected.update(rec["files"])
    for folder, files in chunks.items():
        for name, content in files.items():
            expected.add(f"{folder}/{name}.json")
            write_if_changed(out / folder / f"{name}.json", bop.dumps(content))
    for category, ids in models.items():
        seen = {g["model"]["model_id"]: g["model"] for rec in records.values() if rec["category"] == category
                for g in rec["bop"]["gt"] if g["model"]}
        table = {str(i): seen[m] for m, i in sorted(ids.items(), key=lambda kv: kv[1])}
        write_if_changed(out / "bop" / category / "models.json", json.dumps(table, indent=1, sort_keys=True) + "\n")
    for category, t in tables.items():
        write_if_changed(out / "bop" / category / "camera.json",
                         json.dumps(bop.sensor(*t["camera"]), indent=1, sort_keys=True) + "\n")
    return expected


def _prune(out: Path, top: str, keep: set[str], pattern: re.Pattern) -> None:
    """Remove files under OUT/top named like ours that no record or row lists (scenes dropped or moved),
    then the emptied folders."""
    root = out / top
    if not root.is_dir():
        return
    for d, _, names in os.walk(root, topdown=False):
        prefix = os.path.relpath(d, out).replace(os.sep, "/") + "/"
        for name in names:
            rel = prefix + name
            if pattern.match(name) and rel not in keep:
                Path(d, name).unlink(missing_ok=True)
        if Path(d) != root and not any(Path(d).iterdir()):
            Path(d).rmdir()


def write_annotation_files(out: Path, rows, cache: dict | None = None, state: dict | None = None,
                           early: dict | None = None) -> dict:
    """Write COCO, BOP and instances.json for the manifest's `rows`; returns counts (summary_line
    says them to a user). `cache`: records.json as load_cache read it (read here if None);
    `state`: what the dataset keeps in records.json until the next run (module doc); `early`:
    records the dataset computed at placement ({category/name: compute_record's})."""
    out = Path(out)
    rows = list(rows)
    cache = _load(out) if cache is None else cache
    records, recomputed = _records(out, rows, cache, early)
    categories = coco.category_ids({i["asset"] for r in records.values() for i in r["coco"]}, cache.get("categories"))
    models = {}
    for category in sorted({r["category"] for r in records.values()}):
        used = {g["model"]["model_id"] for r in records.values() if r["category"] == category
                for g in r["bop"]["gt"] if g["model"]}
        models[category] = coco.category_ids(used, (cache.get("models") or {}).get(category))
    _coco_files(out, records, categories)
    expected = _bop_files(out, records, models)
    _prune(out, "bop", expected, BOP_FILE)
    listed = {r[k] for r in rows for k in PASS_COLUMNS if r.get(k)}
    for name in PASS_COLUMNS:
        _prune(out, name, listed, PASS_FILE)
    tables = {rec["image"]: rec["instances"] for rec in records.values() if rec["instances"] is not None}
    write_if_changed(out / INSTANCES, json.dumps(
        {"about": "per image (key: its path): its instance-id PNG and the prim path of each id (0 is background); "
                  "ids number the scene's objects in sorted prim path order, so they differ between images",
         "images": tables}, indent=1, sort_keys=True) + "\n")
    write_if_changed(out / RECORDS, json.dumps({"version": RECORDS_VERSION, "categories": categories,
                                                "models": models, "records": records, "state": state or {}},
                                               sort_keys=True, separators=(",", ":")) + "\n")
    anomalous = [r for r in records.values() if r["kind"] == "anomaly"]
    counts = {"images": len(records), "anomalous": len(anomalous), "recomputed": recomputed,
              "posed": sum(_planned(r)["pose"] is not None for r in anomalous),
              "amodal": sum(_amodal_passed(r) for r in anomalous),
              "depth": sum(any("/depth/" in f for f in r["files"]) for r in records.values())}
    return counts


def _planned(rec: dict) -> dict:
    """The BOP entry of a record's planned anomaly (its first object), {"pose": None, ...} without one."""
    return rec["bop"]["gt"][0] if rec["bop"]["gt"] else {"pose": None, "model": None, "info": None}


def _amodal_passed(rec: dict) -> bool:
    info = _planned(rec)["info"]
    return bool(info) and info.get("visib_source") == "amodal_pass"


def summary_line(out: Path) -> str:
    """One line on what the annotation files hold, from records.json: images, anomalies with a BOP
    pose (an older render records none: re-render it), amodal masks (else visib_fract comes from
    the ray cast), depth PNGs (render the depth pass for them)."""
    records = list((_load(Path(out)).get("records") or {}).values())
    anomalous = [r for r in records if r.get("kind") == "anomaly"]
    posed = [r for r in anomalous if _planned(r)["pose"] is not None]
    amodal = sum(_amodal_passed(r) for r in anomalous)
    depth = sum(any("/depth/" in f for f in r["files"]) for r in records)
    line = (f"annotations: COCO {len(records)} images, {len(anomalous)} anomalies; BOP poses {len(posed)} of "
            f"{len(anomalous)}, amodal masks {amodal} of {len(anomalous)}, depth {depth} of {len(records)} images")
    missing = [r["name"] for r in anomalous if _planned(r)["pose"] is None]
    if missing:
        line += (f" ({len(missing)} render(s) record no pose, rendered before poses were: their scene_gt entries are "
                 f"empty; re-render them: {', '.join(missing[:5])})")
    return line
