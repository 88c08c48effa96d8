"""The dataset's annotation files, rebuilt from the manifest's rows at the end of every
`allo-usd dataset` run (allo_usd.output.dataset calls write_annotation_files):

    OUT/annotations/instances_train.json, instances_test.json   COCO (allo_usd.output.coco)
    OUT/bop/CATEGORY/...                                        BOP-shaped pose files (allo_usd.output.bop)
    OUT/instances.json                                          per image: instance id -> prim path
    OUT/annotations/records.json                                the per-image cache the files above are built from,
                                                                and the dataset's own (render checks, contact sheets)

Why a cache: an image's record (its COCO RLE, BOP entries, the per-image BOP files it wrote) is
computed once from the tree's mask and depth and its render JSON; a re-run recomputes only the
records whose row changed (a re-rendered or moved scene, a new one) or whose files went missing,
and rebuilds the JSON files from the records. A file whose bytes would not change is not
rewritten, so a re-run that adds scenes leaves the other images' files, and unchanged BOP chunks,
untouched. Deleting records.json only costs the next run a full recompute. Every write is atomic.

The cache is a derivation, never a source (docs/reliability/reliability.md, "The dataset's cache"):
- an entry keeps only what is computed from the files (image size, COCO instances, the BOP camera
  and objects, the instance table, whether depth and amodal PNGs were written); everything that
  names a place (category, index, split, image, the BOP folder and file names) is derived from the
  manifest row each run, inside OUT, and never read from the cache;
- an entry is bound (`bind`) to the code's RECORDS_VERSION, its whole manifest row and the stat of
  the files it was computed from (3-class mask, ground truth, depth, render JSON: make's quick
  check); an entry whose binding differs is recomputed;
- its values are checked as any input is (types, ranges, finite numbers, boxes inside the image --
  BOP's bbox_obj inside the toolkit's 3W x 3H canvas --, each COCO bbox and area those of its RLE);
  an entry that fails is recomputed, with one warning;
- records.json is read through the read gate (a regular file inside OUT, at most cache_limit(rows)
  bytes, nested at most MAX_JSON_DEPTH); refused, or of the wrong shape, it is recomputed whole,
  with one warning.

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
import math
import os
import re
import stat
import warnings
from pathlib import Path

import numpy as np

from allo_usd.core.files import (MAX_RECORD_BYTES, InputRefused, read_user_bytes, read_user_json, write_bytes_atomic,
                                 write_text_atomic)
from allo_usd.core.errors import AlloError
from allo_usd.core.labels import ANOMALY
from allo_usd.core.scene_labels import SPLITS
from allo_usd.output import bop, bop_models, coco
from allo_usd.output.contact import read_pixels
from allo_usd.output.dataset_files import COLUMNS, Refused, inside, place, source_file
from allo_usd.output.writers import write_png
from allo_usd.output.pass_files import PASS_COLUMNS
from allo_usd.output.record import RenderRecord

RECORDS = "annotations/records.json"
INSTANCES = "instances.json"
RECORDS_VERSION = 6   # 2: a record lists every anomaly object; 3: entries keep no path, bound to their files;
                      # 4: scene_gt_info counted on the BOP toolkit's canvas (bop.gt_info)
                      # 5: every anomaly object's full silhouette in the image (mask/, px_count_valid)
                      # 6: a record's accuracy keeps its lower bound (est_psnr_low_db)
CACHE_BYTES = 16 << 20        # records.json's bound: this much, plus CACHE_ROW_BYTES per manifest row
MAX_MODEL_BYTES = 256 << 20  # an earlier run's PLY read back when its asset is gone (assets: under 1 MB)
CACHE_ROW_BYTES = 256 << 10   # an entry is ~1 KB; an anomaly's RLE a few KB

BOP_FILE = re.compile(r"^(?:\d{6}(?:_\d{6})?\.png|scene_(?:camera|gt|gt_info)\.json|obj_\d{6}\.ply|models_info\.json"
                      r"|test_targets_bop19\.json)$")
PASS_FILE = re.compile(r"^\d{6}_.+\.(?:exr|png)$")


def row_key(row: dict) -> str:
    """A digest of the row as the manifest stores it (None as "", values as str): equal iff the row is."""

    text = "\x1f".join("" if row.get(c) is None else str(row.get(c)) for c in COLUMNS)
    return hashlib.sha256(text.encode()).hexdigest()


def write_if_changed(path: Path, text: str | bytes) -> bool:
    """Write `text` (str as UTF-8, or bytes) atomically unless the file already holds exactly it;
    returns whether it wrote.
    Only a regular file (no link) of exactly the new size is read to compare (through the read
    gate: a link to /dev/zero or a huge file in its place is replaced, never read). A directory
    in its place is refused in one line (AlloError) naming it."""
    data = text if isinstance(text, bytes) else text.encode("utf-8")
    try:
        st = os.lstat(path)
    except OSError:
        st = None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise AlloError(f"{path} is a directory where the dataset writes a file; fix: remove it (the dataset "
                        "writes it again)")
    if st is not None and stat.S_ISREG(st.st_mode) and st.st_size == len(data):
        try:
            if read_user_bytes(path, len(data), "dataset file") == data:
                return False
        except InputRefused:
            pass
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(text, bytes):
        write_bytes_atomic(path, data)
    else:
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


def _recorded_silhouette(obj: dict, shape, visible: np.ndarray) -> np.ndarray | None:
    """An anomaly object's full silhouette in the image from its recorded `amodal_segmentation` (COCO
    RLE), None when it records none or one that cannot be its silhouette: not `amodal_pixels` pixels,
    or missing a visible pixel (the render JSON is not trusted)."""
    seg, count = obj.get("amodal_segmentation"), obj.get("amodal_pixels")
    if not isinstance(seg, dict) or isinstance(count, bool) or not isinstance(count, int):
        return None
    full = _object_pixels({"segmentation": seg}, shape)
    if int(np.count_nonzero(full)) != count or (visible & ~full).any():
        return None
    return full


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
    _link(inside(out, row["image"]), inside(out, rgb))
    files = [rgb]
    depth_units = None
    if row.get("depth"):
        depth = read_depth_exr(out / row["depth"])
        if depth.shape == shape:
            depth_units = bop.depth_png(depth)
            files.append(f"{folder}/depth/{index:06d}.png")
            write_png(inside(out, files[-1]), depth_units)
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
            full, source = (amodal, "amodal_pass") if planned and amodal is not None else (
                _recorded_silhouette(obj, shape, mine), str(obj.get("visib_source") or "raycast"))
            rec["bop"]["gt"].append({"pose": bop.pose(obj), "model": model,
                                     "info": bop.gt_info(mine, full, obj, depth_units, source)})
            files.append(f"{folder}/mask_visib/{index:06d}_{gt_id:06d}.png")
            truth = out / row["mask"] if row.get("mask") else None
            if len(objects) == 1 and truth is not None and truth.is_file():   # the same 0/255 pixels
                _link(truth, inside(out, files[-1]))
            else:
                write_png(inside(out, files[-1]), mine.astype(np.uint8) * np.uint8(255))
            if full is not None:
                files.append(f"{folder}/mask/{index:06d}_{gt_id:06d}.png")
                write_png(inside(out, files[-1]), full.astype(np.uint8) * np.uint8(255))
    table = meta.instances
    if row.get("instance") and isinstance(table, dict):
        rec["instances"] = {"instance": row["instance"], "objects": {str(k): str(v) for k, v in table.items()}}
    rec["files"] = files
    return rec


def cache_limit(rows: int) -> int:
    """records.json's size bound for a manifest of `rows` rows (the read gate's limit)."""
    return CACHE_BYTES + CACHE_ROW_BYTES * max(0, int(rows))


def load_cache(out: Path, rows: int = 0) -> dict:
    """records.json's content, checked ({} when missing or of another version; {} and one warning
    when the read gate refuses it or its shape is wrong): pass it back to write_annotation_files,
    and read the dataset's `state` from it. `rows`: the manifest's rows (cache_limit)."""
    return load_records(Path(out), rows, warn=True)


def load_records(out: Path, rows: int, warn: bool = False) -> dict:
    """records.json read through the read gate (bounded by `rows`, inside `out`): its parsed top level,
    or {} when it is absent, refused by the gate, of another RECORDS_VERSION or malformed (with one
    note when `warn`, except for an absent file or another version)."""
    path = out / RECORDS
    try:
        cache = read_user_json(path, cache_limit(rows), "the dataset's cache", roots=(out,))
    except InputRefused as exc:
        if exc.kind != "missing" and warn:
            _recomputed(f"{path} {exc.reason}")
        return {}
    except OSError as exc:   # the gate says why for what it knows; anything else reads as unreadable
        if warn:
            _recomputed(f"{path} cannot be read ({exc.strerror})")
        return {}
    if not isinstance(cache, dict) or cache.get("version") != RECORDS_VERSION:
        return {}   # another version's cache (an upgrade): recomputed, nothing to say
    problem = _cache_problem(cache)
    if problem:
        if warn:
            _recomputed(f"{path} {problem}")
        return {}
    return cache


def _recomputed(why: str, which: str = "every annotation record is") -> None:
    warnings.warn(f"the dataset's cache {why}: {which} recomputed from the renders, and the cache written again "
                  "(nothing to fix)", stacklevel=4)


def _cache_problem(cache: dict) -> str | None:
    """Why records.json's top level cannot be used, or None (its entries are checked one by one)."""
    if not isinstance(cache.get("records", {}), dict) or not isinstance(cache.get("state", {}), dict):
        return "does not hold a records table and a state table"
    if _ids_problem(cache.get("categories", {})):
        return "holds category ids that are not distinct positive whole numbers"
    models = cache.get("models", {})
    if not isinstance(models, dict) or any(_ids_problem(v) for v in models.values()):
        return "holds model ids that are not distinct positive whole numbers"
    return None


def _ids_problem(ids) -> bool:
    return not isinstance(ids, dict) or not all(_whole_number(v, 1) for v in ids.values()) \
        or len(set(ids.values())) != len(ids)


def _whole_number(value, low: int = 0, high: int | None = None) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low and (high is None or value <= high)


def _finite(value, n: int) -> bool:
    return isinstance(value, list) and len(value) == n and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)


def _file_stat(path: str) -> list[int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev]


def binding(out: Path, row: dict, key: str | None = None) -> str:
    """What a cache entry of `row` is bound to: the code's RECORDS_VERSION, the whole row, and the stat
    (size, mtime_ns, inode, device) of the files its record is computed from: the 3-class mask, the
    ground truth, the depth pass and the render JSON (which a re-render rewrites with every other
    file of the render). Equal bindings: the entry stands for what compute_record would give.
    `key`: the row's row_key when the caller has it."""
    top = os.fspath(out)
    files = map(row.get, ("allo_mask", "mask", "depth", "source"))
    stats = [_file_stat(os.path.join(top, f)) if f else None for f in files]
    text = json.dumps([RECORDS_VERSION, key or row_key(row), stats], separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


ENTRY_KEYS = {"bind", "width", "height", "coco", "camera", "gt", "objects", "depth", "amodal"}


def entry_of(rec: dict, bind: str) -> dict:
    """The cache entry of a record: what compute_record computed from the files, without a path."""
    files = rec["files"]
    return {"bind": bind, "width": rec["width"], "height": rec["height"], "coco": rec["coco"],
            "camera": rec["bop"]["camera"], "gt": rec["bop"]["gt"],
            "objects": None if rec["instances"] is None else rec["instances"]["objects"],
            "depth": any("/depth/" in f for f in files),
            "amodal": [int(f.rsplit("_", 1)[1][:6]) for f in files if "/mask/" in f]}


def record_of(row: dict, entry: dict, key: str | None = None) -> dict:
    """The record of `row` from its cache entry: every place (image, BOP folder and files) derived
    from the row, as compute_record names them."""
    index = int(row["index"])
    folder = f"bop/{row['category']}/{row['split']}/{bop.chunk_of(index)}"
    files = [f"{folder}/rgb/{index:06d}.png"] + ([f"{folder}/depth/{index:06d}.png"] if entry["depth"] else [])
    for gt_id in range(len(entry["gt"])):
        files.append(f"{folder}/mask_visib/{index:06d}_{gt_id:06d}.png")
        if gt_id in entry["amodal"]:
            files.append(f"{folder}/mask/{index:06d}_{gt_id:06d}.png")
    instances = None if entry["objects"] is None else {"instance": row["instance"], "objects": entry["objects"]}
    return {"key": key or row_key(row), "category": row["category"], "name": row["name"], "index": index,
            "split": row["split"], "kind": row["kind"], "image": row["image"], "width": entry["width"],
            "height": entry["height"], "coco": entry["coco"],
            "bop": {"folder": folder, "camera": entry["camera"], "gt": entry["gt"]}, "instances": instances,
            "files": files}


_RLE = re.compile(r"^[0-o]*$")   # pycocotools' compressed RLE alphabet: characters 48 + 0..63


def entry_problem(entry, row: dict) -> str | None:
    """Why a cache entry cannot stand for `row`'s record (its values checked as any input is), or None."""
    if not isinstance(entry, dict) or set(entry) != ENTRY_KEYS:
        return "not an entry of this version"
    width, height = entry["width"], entry["height"]
    if not (_whole_number(width, 1, 65535) and _whole_number(height, 1, 65535)):
        return "its image size is not two whole numbers of pixels"
    amodal = entry["amodal"]
    if not (isinstance(entry["depth"], bool) and isinstance(amodal, list)
            and all(_whole_number(i) for i in amodal) and amodal == sorted(set(amodal))) \
            or (entry["depth"] and not row.get("depth")):
        return "its depth flag and full-silhouette objects are not those of its row"
    gt, items = entry["gt"], entry["coco"]
    if not isinstance(gt, list) or not isinstance(items, list) \
            or (row["kind"] == "anomaly") != bool(gt) or len(items) > len(gt) or (amodal and amodal[-1] >= len(gt)):
        return "its objects do not agree with its row's kind"
    if entry["camera"] is not None and _camera_problem(entry["camera"]):
        return "its camera is not a BOP camera entry"
    if any(_coco_problem(i, width, height) for i in items):
        return "a COCO instance is not its RLE's (size, bbox inside the image, area)"
    if any(_gt_problem(g, width, height) for g in gt):
        return "a BOP object is not a pose, model and visibility entry"
    objects = entry["objects"]
    if objects is not None and not (row.get("instance") and isinstance(objects, dict)
                                    and all(isinstance(v, str) for v in objects.values())):
        return "its instance table is not one of its row"
    return None


def _camera_problem(camera) -> bool:
    return not (isinstance(camera, dict) and set(camera) == {"cam_K", "depth_scale", "cam_R_w2c", "cam_t_w2c"}
                and _finite(camera["cam_K"], 9) and _finite(camera["cam_R_w2c"], 9)
                and _finite(camera["cam_t_w2c"], 3) and camera["depth_scale"] == bop.DEPTH_SCALE)


def _coco_problem(item, width: int, height: int) -> bool:
    from pycocotools import mask as mask_utils

    if not (isinstance(item, dict) and {"asset", "variant", "segmentation", "area", "bbox", "iscrowd"} <= set(item)
            <= {"asset", "variant", "segmentation", "area", "bbox", "iscrowd", "path"}
            and all(isinstance(item.get(k, ""), str) for k in ("asset", "variant", "path")) and item["iscrowd"] == 0):
        return True
    seg, box = item["segmentation"], item["bbox"]
    if not (isinstance(seg, dict) and set(seg) == {"size", "counts"} and seg["size"] == [height, width]
            and isinstance(seg["counts"], str) and _RLE.match(seg["counts"])
            and isinstance(box, list) and len(box) == 4 and all(_whole_number(v) for v in box)):
        return True
    x, y, w, h = box
    if w < 1 or h < 1 or x + w > width or y + h > height or not _whole_number(item["area"], 1, w * h):
        return True
    rle = {"size": [height, width], "counts": seg["counts"].encode("ascii")}
    try:
        area, found = int(mask_utils.area(rle)), [int(v) for v in mask_utils.toBbox(rle)]
    except (ValueError, TypeError, OverflowError):
        return True
    return area != item["area"] or found != box


def _gt_problem(g, width: int, height: int) -> bool:
    if not (isinstance(g, dict) and set(g) == {"pose", "model", "info"}):
        return True
    pose, model, info = g["pose"], g["model"], g["info"]
    if pose is not None and not (isinstance(pose, dict) and set(pose) == {"cam_R_m2c", "cam_t_m2c", "model_scale"}
                                 and _finite(pose["cam_R_m2c"], 9) and _finite(pose["cam_t_m2c"], 3)
                                 and _finite(pose["model_scale"], 3)):
        return True
    if model is not None and not (isinstance(model, dict) and set(model) == {"model_id", "asset", "variant", "path"}
                                  and all(isinstance(model[k], str) for k in ("model_id", "asset", "variant"))
                                  and (model["path"] is None or isinstance(model["path"], str))):
        return True
    known = {"bbox_visib", "px_count_visib", "bbox_obj", "px_count_all", "visib_source", "px_count_valid",
             "visib_fract", "silhouette"}
    if not (isinstance(info, dict) and {"bbox_visib", "px_count_visib"} <= set(info) <= known):
        return True
    counts = [info[k] for k in ("px_count_visib", "px_count_all", "px_count_valid") if k in info]
    return not (_box_ok(info["bbox_visib"], 0, width, height)   # bbox_obj: on the toolkit's 3W x 3H canvas
                and ("bbox_obj" not in info or _box_ok(info["bbox_obj"], 1, width, height))
                and all(_whole_number(c) for c in counts) and info["px_count_visib"] <= width * height
                and info.get("px_count_all", 0) <= 9 * width * height
                and isinstance(info.get("visib_source", ""), str) and info.get("silhouette", "canvas") in ("canvas", "image")
                and ("visib_fract" not in info or _finite([info["visib_fract"]], 1) and info["visib_fract"] >= 0))


def _box_ok(box, margin: int, width: int, height: int) -> bool:
    """A BOP box [x, y, w, h] of whole numbers, or [-1, -1, -1, -1], its pixels within `margin` images
    of the image on every side (0: inside the image; 1: on the toolkit's canvas)."""
    if box == bop.NO_BOX:
        return True
    if not (isinstance(box, list) and len(box) == 4 and all(_whole_number(v, -margin * max(width, height)) for v in box)):
        return False
    x, y, w, h = box
    return (w >= 0 and h >= 0 and -margin * width <= x and x + w < (1 + margin) * width
            and -margin * height <= y and y + h < (1 + margin) * height)


def _records(out: Path, rows, cache: dict, early: dict | None = None) -> tuple[dict, dict, int]:
    """({category/name: record}, {category/name: cache entry}) of every row, from the cache where its
    entry's binding holds and its values pass entry_problem (paths from the row: record_of), else
    computed; and how many were computed. `early`: records computed this run (by the dataset, at
    placement), used where their key holds. Entries whose binding holds but whose values fail are
    recomputed with one warning."""
    old = cache.get("records") if isinstance(cache.get("records"), dict) else {}
    early = early or {}
    records, entries, recomputed, failed = {}, {}, 0, []
    for row in sorted(rows, key=lambda r: (r["category"], int(r["index"]))):
        name = f"{row['category']}/{row['name']}"
        key = row_key(row)
        bind = binding(out, row, key)
        rec = early.get(name)
        if isinstance(rec, dict) and rec.get("key") == key and all((out / f).is_file() for f in rec["files"]):
            recomputed += 1
        else:
            rec, entry = None, old.get(name)
            if isinstance(entry, dict) and entry.get("bind") == bind:
                problem = entry_problem(entry, row)
                if problem is None:
                    rec = record_of(row, entry, key)
                    rec = rec if all((out / f).is_file() for f in rec["files"]) else None
                else:
                    failed.append(f"{name}: {problem}")
            if rec is None:
                rec = compute_record(out, row)
                recomputed += 1
        records[name] = rec
        entries[name] = entry_of(rec, bind)
    if failed:
        some = "1 entry that fails" if len(failed) == 1 else f"{len(failed)} entries that fail"
        _recomputed(f"{out / RECORDS} has {some} its checks ({'; '.join(failed[:3])})",
                    "those are" if len(failed) > 1 else "it is")
    return records, entries, recomputed


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


def _bop_files(out: Path, records: dict, models: dict[str, dict[str, int]], infos: dict | None = None) -> set[str]:
    """Write each chunk's scene_*.json, each category's models.json, camera.json, object models
    (allo_usd.output.bop_models) and test targets; the set of BOP files. `infos`: {PLY sha256:
    models_info entry} kept between runs (read from the cache, checked; updated here)."""
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
            write_if_changed(inside(out, f"{folder}/{name}.json"), bop.dumps(content))
    for category, ids in models.items():
        seen = {g["model"]["model_id"]: g["model"] for rec in records.values() if rec["category"] == category
                for g in rec["bop"]["gt"] if g["model"]}
        table = {str(i): seen[m] for m, i in sorted(ids.items(), key=lambda kv: kv[1])}
        write_if_changed(inside(out, f"bop/{category}/models.json"), json.dumps(table, indent=1, sort_keys=True) + "\n")
        expected |= _model_files(out, category, table, {} if infos is None else infos)
        test = {Path(folder).name: (files["scene_gt"], files["scene_gt_info"]) for folder, files in chunks.items()
                if folder.startswith(f"bop/{category}/test/")}
        targets = f"bop/{category}/{bop_models.TARGETS}"
        expected.add(targets)
        write_if_changed(inside(out, targets), bop_models.dumps_list(bop_models.test_targets(test)))
    for category, t in tables.items():
        write_if_changed(inside(out, f"bop/{category}/camera.json"),
                         json.dumps(bop.sensor(*t["camera"]), indent=1, sort_keys=True) + "\n")
    return expected


def _model_files(out: Path, category: str, table: dict, infos: dict) -> set[str]:
    """Write models/ and models_eval/ (obj_NNNNNN.ply, models_info.json) of a category's models.json
    `table`; the files written. A model whose asset cannot be read keeps its earlier PLY (one warning)."""
    from allo_usd.usd.model_mesh import read_model

    files, info, failed = set(), {}, []
    for obj_id, model in table.items():
        name = bop_models.ply_name(int(obj_id))
        old = out / "bop" / category / bop_models.MODELS / name
        if not model.get("path"):   # a render recorded before models were: no asset to read
            continue
        try:
            mesh = read_model(os.path.normpath(out / model["path"]), model.get("variant") or None)
            data = bop_models.ply_bytes(mesh.points, mesh.triangles)
        except (AlloError, OSError) as exc:
            failed.append(f"{model.get('model_id')}: {exc}")
            try:   # the PLY an earlier run wrote stays, as it is
                data = read_user_bytes(old, MAX_MODEL_BYTES, "BOP model") if old.is_file() else None
            except InputRefused:
                data = None
            if data is None:
                continue
        key = bop_models.digest(data)
        entry = infos.get(key)
        if bop_models.info_problem(entry):
            try:
                entry = infos[key] = bop_models.model_info(data)
            except (ValueError, IndexError, StopIteration):   # an earlier PLY that is not ours any more
                continue
        info[int(obj_id)] = entry
        for folder in (bop_models.MODELS, bop_models.MODELS_EVAL):
            rel = f"bop/{category}/{folder}/{name}"
            files.add(rel)
            write_if_changed(inside(out, rel), data)
    if failed:
        more = f" (and {len(failed) - 1} more)" if len(failed) > 1 else ""
        warnings.warn(f"{len(failed)} BOP model(s) of {category} not written from their assets (a PLY an earlier "
                      f"run wrote is kept): {failed[0]}{more}", stacklevel=3)
    text = "{\n" + ",\n".join(f'  "{k}": {json.dumps(v, sort_keys=True)}' for k, v in sorted(info.items())) \
        + ("\n" if info else "") + "}"
    for folder in (bop_models.MODELS, bop_models.MODELS_EVAL):
        rel = f"bop/{category}/{folder}/{bop_models.MODELS_INFO}"
        files.add(rel)
        write_if_changed(inside(out, rel), text)
    return files


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
    cache = load_cache(out, len(rows)) if cache is None else cache
    records, entries, recomputed = _records(out, rows, cache, early)
    categories = coco.category_ids({i["asset"] for r in records.values() for i in r["coco"]}, cache.get("categories"))
    models = {}
    for category in sorted({r["category"] for r in records.values()}):
        used = {g["model"]["model_id"] for r in records.values() if r["category"] == category
                for g in r["bop"]["gt"] if g["model"]}
        models[category] = coco.category_ids(used, (cache.get("models") or {}).get(category))
    _coco_files(out, records, categories)
    infos = cache.get("model_info") if isinstance(cache.get("model_info"), dict) else {}
    infos = {k: v for k, v in infos.items() if not bop_models.info_problem(v)}
    expected = _bop_files(out, records, models, infos)
    _prune(out, "bop", expected, BOP_FILE)
    listed = {r[k] for r in rows for k in PASS_COLUMNS if r.get(k)}
    for name in PASS_COLUMNS:
        _prune(out, name, listed, PASS_FILE)
    tables = {rec["image"]: rec["instances"] for rec in records.values() if rec["instances"] is not None}
    write_if_changed(out / INSTANCES, json.dumps(
        {"about": "per image (key: its path): its instance-id PNG and the prim path of each id (0 is background); "
                  "ids number the scene's objects in sorted prim path order, so they differ between images",
         "images": tables}, indent=1, sort_keys=True) + "\n")
    try:
        write_if_changed(out / RECORDS, json.dumps({"version": RECORDS_VERSION, "categories": categories,
                                                    "models": models, "records": entries, "state": state or {},
                                                    "model_info": infos},
                                                   sort_keys=True, separators=(",", ":")) + "\n")
    except AlloError as exc:   # the dataset is complete: only its next run's shortcut is lost
        warnings.warn(f"the dataset's cache is not kept: {exc}; the next run recomputes every record", stacklevel=2)
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
