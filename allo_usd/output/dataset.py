"""Assemble rendered scenes into an MVTec-AD-style tree that anomaly-detection libraries load as is.

Input: render directories as `allo_usd.run.job` writes them (NAME.json last, so a JSON marks a
finished scene; its "scene" holds split/variant/pose/day/anomaly/seed read from the layer).
Output, under OUT:

    OUT/<category>/train/good/NNNNNN_NAME.png          normal training images
    OUT/<category>/test/good/NNNNNN_NAME.png           normal test images
    OUT/<category>/test/<defect>/NNNNNN_NAME.png       anomalous test images, one folder per defect
    OUT/<category>/ground_truth/<defect>/NNNNNN_NAME_mask.png   binary 0/255, anomaly class only
    OUT/allo_masks/<category>/<split>/<folder>/NNNNNN_NAME_mask.png   ALLO 3-class masks (0, 1, 2)
    OUT/manifest.csv (and manifest.parquet if pandas and pyarrow are installed)
    OUT/contact_sheets/<category>_<split>.png (then _2.png, ... ; allo_usd.output.contact)

<defect> is the anomaly's asset (`defects="per-asset"`, the default: test/power_drill/, as
MVTec AD has test/scratch/), or `anomaly` for every hazard (`defects="merged"`). A re-run with
the other choice moves the files (same indices) and removes the emptied folders.

Why these choices:
- anomalib's MVTec and Folder loaders glob EVERY image under the category directory, label an
  image normal if its folder is `good` (so no defect folder may be called that), and pair
  sorted anomalous images with sorted masks by position (tests/output/test_dataset_anomalib.py). So the category directory holds
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
  pixel would be a wrong label: both are left out of the tree with a warning. So are mask-only
  renders (RenderSpec.mask_only): they have no image to train or test on.
- A render JSON is not trusted (check_render): split and kind come from fixed sets, names are
  plain tokens, every file it names must be a regular file of its own render folder, its images
  must agree in size, with its resolution and with its class pixels, and its kind with its mask.
  A record that fails is left out with a warning naming it and why (one bad render among
  thousands does not stop a dataset). Every destination's real path must lie inside OUT, or
  the run stops (AlloError). A folder with no render record, or renders of different
  resolutions in one category, stop the run before anything is placed. Scenes with no station
  or body pixel, and all-black images, are kept and flagged in a warning.
- The manifest is written ahead: before a batch of scenes gets its files, manifest.csv is
  atomically rewritten with their rows, so however a run ends (Ctrl-C, kill -9, a crash) no
  file in the tree is missing from the manifest. A row whose files did not arrive is completed
  (same index) by the next run, or dropped at its end if its render is gone. Each run starts by
  removing stale hidden temporaries (a killed writer's `.NAME.png.XXXXXXXX.png`, which
  anomalib's recursive glob would otherwise load as an image) and indexed images that no row
  lists. Ctrl-C stops after the scene in hand (a second Ctrl-C stops at once, still safely)
  and raises AssemblyInterrupted; manifest.parquet is rewritten when a run ends.
- Re-runs cost what changed: a record that passed check_render is trusted while it and
  the image and mask it names keep the stat (size, mtime_ns, inode) recorded then, in
  annotations/records.json's state (make's and the render manifest's quick check: a re-render
  replaces the files, an edit changes size or mtime), so its mask is not decoded again; a split's
  contact sheets are redrawn only when the rows they are drawn from changed; an unchanged row is
  not placed again (_unchanged), and annotation records are recomputed only for changed rows.
- Manifest paths (image, mask, allo_mask) are relative to OUT, so the tree moves as a whole;
  source and layer name the render record and scene layer it came from (absolute: they lie
  outside OUT). Lines end in LF. The run's lock file (LOCK) is removed when the run ends.
"""

from __future__ import annotations

import csv
import importlib.util
import io
import json
import os
import re
import signal
import stat
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image

from allo_usd.core.errors import AlloError
from allo_usd.core.files import (MAX_RECORD_BYTES, InputRefused, RunLock, atomic_path, read_user_json, sha256_file,
                                 write_bytes_atomic)
from allo_usd.core.scene_labels import SPLITS, VARIANTS, label_problem
from allo_usd.output.annotations import accuracy_columns, annotation_columns
from allo_usd.output.contact import PER_SHEET, read_pixels, sheet_paths, split_sheets
from allo_usd.output.annotation_files import (ENTRY_KEYS, compute_record, load_cache, load_records,
                                             write_annotation_files)
from allo_usd.output.dataset_files import (COLUMNS, FOLDERS, AnomalyPixels, Refused, inside, place, real_folder, real_path,
                                          source_entry, source_file)
from allo_usd.output.pass_files import PASS_COLUMNS, pass_columns, passes_missing, place_passes
from allo_usd.output.record import RenderRecord
from allo_usd.output.writers import write_png

LAYOUTS = ("mvtec",)
DEFECTS = ("per-asset", "merged")   # one test/<asset>/ folder per anomaly asset, or one test/anomaly/
MERGED = "anomaly"                  # the defect folder of every anomaly with defects="merged"
NORMAL = "good"                     # the folder MVTec loaders read as normal
MANIFEST = "manifest.csv"
FILE_KEYS = PASS_COLUMNS + ("allo_mask", "mask", "image")  # placement order: the image, which loaders glob, last
# Temporaries of core.files.atomic_path (mkstemp: .NAME.<8 chars>.SUFFIX) and of earlier place() (.NAME.<32 hex>.tmp).
TEMPORARY = re.compile(r"^\..+\.(?:[0-9a-f]{32}\.tmp|[a-z0-9_]{8}\.(?:png|csv|parquet|json|tmp))$")
INDEXED = re.compile(r"^\d{6}_.+\.png$")


class AssemblyInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped assembly; the manifest lists every file in the tree, and a re-run goes on."""


def plan_seed(seed_path: str) -> int | str:
    """The plan seed (the pipeline run) of a scene: the first part of its seed path
    ("2031/45/42/..." -> 2031; allo_usd.scene.resolve.scene_seed), or "" if the path has none."""
    head = str(seed_path or "").split("/", 1)[0]
    return int(head) if head.isdigit() else ""


class RefusedRenders(UserWarning):
    """Render records refused as untrustworthy (left out of the dataset; `allo-usd dataset` exits 1)."""


class Brief(RenderRecord):
    """What planning reads of a render record whose JSON kept the stat at which it passed
    check_render (a re-run does not parse 51,409 JSONs to find 1,000 new ones): its scene's split,
    variant and anomaly, its files, the class pixel counts _kind and the dark warning read, its
    layer_sha256, whether it has an annotations table, and the accuracy's estimated_psnr_db and
    lower_psnr_db (the manifest's est_psnr_db and est_psnr_low_db, which _unchanged compares). A
    RenderRecord with only those fields,
    kept in records.json's state (as_dict) beside the stat and read back with Brief.of; a record
    that is placed again is read whole (_whole)."""

    @classmethod
    def of_record(cls, meta: RenderRecord) -> "Brief":
        scene, pixels = meta.scene, meta.class_pixels
        scene, pixels = (scene if isinstance(scene, dict) else {}), (pixels if isinstance(pixels, dict) else {})
        return cls(files=meta.files, layer_sha256=meta.layer_sha256,
                   scene={k: scene[k] for k in ("split", "variant", "anomaly") if k in scene},
                   class_pixels={k: pixels[k] for k in ("station_and_bodies", "anomaly") if k in pixels},
                   annotations={} if isinstance(meta.annotations, dict) else None,
                   accuracy=({k: meta.accuracy.get(k) for k in ("estimated_psnr_db", "lower_psnr_db")}
                             if isinstance(meta.accuracy, dict) else None))


def _json_stat(path: Path) -> list[int] | None:
    """[size, mtime_ns, inode, device] of a render record that is a regular file, not a link (its
    real path is then its folder's plus its name, inside its render directory), else None."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev] if stat.S_ISREG(st.st_mode) else None


def _read_record(meta_path: Path, root: Path, refused: list | None) -> RenderRecord | None:
    """A render record through the read gate (core.files.read_user_json), None when it is not one
    (RenderRecord.from_json; refusals appended to `refused` as "PATH: why"; scan's rules)."""
    try:
        meta = read_user_json(meta_path, MAX_RECORD_BYTES, "render record", roots=(root,))
    except InputRefused as exc:
        if exc.kind in ("not_json", "not_utf8", "missing"):
            return None  # not ours (job.py writes its JSON atomically, so it is never partial), or gone
        if refused is not None:
            refused.append(f"{meta_path}: {exc.reason}")
        return None
    return RenderRecord.from_json(meta)  # None: not a render record (e.g. a plan or report beside the renders)


def scan(render_dirs, progress: bool = False, refused: list | None = None, known: dict | None = None,
         stats: dict | None = None) -> list[tuple[Path, RenderRecord]]:
    """(json path, metadata) of every finished scene in the render directories, by name. Each
    NAME.json is read through the read gate (core.files.read_user_json): a FIFO, a device such as
    /dev/zero, a directory, a link out of its render folder, a file over MAX_RECORD_BYTES or JSON
    nested over MAX_JSON_DEPTH is never parsed; it is appended to `refused` as "PATH: why" (left out
    with a warning, like a record check_render refuses). A file that is not JSON is not ours: skipped.
    `known`: {json path: (stat, Brief)} of records that passed check_render; one whose file (a
    regular file, no link) still has that stat is not read: its Brief stands for it. `stats` gets
    {json path: its stat taken before it was read}, the evidence _check keeps."""
    from tqdm import tqdm

    known = known or {}
    found: dict[str, tuple[Path, RenderRecord]] = {}
    for d in map(Path, render_dirs):
        if not d.is_dir():
            raise AlloError(f"render directory {d} does not exist; pass directories that `allo-usd render` wrote")
        names = sorted(e.name for e in os.scandir(d) if e.name.endswith(".json"))
        for name in tqdm(names, desc=f"reading {d.name}", unit="file", disable=not progress, leave=False):
            meta_path = d / name
            st = _json_stat(meta_path)
            prior = known.get(str(meta_path))
            if st is not None and prior is not None and prior[0] == st:
                meta = prior[1]
            else:
                meta = _read_record(meta_path, d, refused)
                if meta is None:
                    continue
            if stats is not None:
                stats[str(meta_path)] = st
            name = meta_path.stem
            if name in found and found[name][1].layer_sha256 != meta.layer_sha256:
                raise AlloError(f"two different scenes are named {name!r}: {found[name][0]} and {meta_path}; "
                                "rename one layer (names must be unique within a dataset)")
            found[name] = (meta_path, meta)
    return [found[k] for k in sorted(found)]


MAX_MANIFEST_BYTES = 1 << 30   # the paper's 51,409 rows take about 60 MB


def read_manifest(path: Path) -> list[dict]:
    """The rows of an existing manifest.csv ([] when there is none), read through the read gate (a
    regular file on disk, bounded, UTF-8) and its index column checked (_check_indices)."""
    from allo_usd.core.files import read_user_text

    if not os.path.lexists(path):
        return []
    text = read_user_text(path, MAX_MANIFEST_BYTES, "the dataset's manifest",
                          "remove it (and the dataset folder it indexes) to assemble the dataset afresh", error=AlloError)
    rows = list(csv.DictReader(io.StringIO(text, newline="")))
    _check_indices(path, rows)
    for r in rows:  # manifests written before the plan_seed column
        if not r.get("plan_seed"):
            r["plan_seed"] = plan_seed(r.get("seed_path", ""))
    return rows


MAX_INDEX = 10 ** 6 - 1   # file names start with the index in six digits (sorted order is index order)
INDEX = re.compile(r"^[0-9]{1,6}$")


def _check_indices(path: Path, rows: list[dict]) -> None:
    """Refuse (AlloError, one line) a manifest whose index column is not what the dataset writes: a
    whole number from 0 to MAX_INDEX (plain digits), once per category. Every BOP folder and file
    name is derived from it: a `-5` or `1e30` is never trusted."""
    seen = set()
    for line, r in enumerate(rows, start=2):
        index = r.get("index")
        problem = None
        if not isinstance(index, str) or not INDEX.match(index):
            problem = f"its index is not a whole number from 0 to {MAX_INDEX:,}"
        elif (r.get("category"), int(index)) in seen:
            problem = f"its index {int(index)} is another row's of its category"
        if problem:
            raise AlloError(f"{path} line {line}: {problem} (the manifest was edited); fix: restore manifest.csv, "
                            "or assemble into a fresh --out")
        seen.add((r.get("category"), int(index)))


_WRITTEN: set[Path] = set()   # manifests written within an assembly run (write_manifest's parquet follows)
_LINES: dict[int, tuple[dict, str]] = {}   # id(row): (row, its CSV line), within an assembly run (_csv_text)


def _csv_line(row: dict) -> str:
    """The row's manifest line as csv.DictWriter writes it, made once per row object within a run
    (the manifest is rewritten ahead of every batch of a run: O(log n) times)."""
    held = _LINES.get(id(row))
    if held is not None and held[0] is row:
        return held[1]
    buffer = io.StringIO()
    csv.DictWriter(buffer, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n").writerow(row)
    _LINES[id(row)] = (row, buffer.getvalue())
    return _LINES[id(row)][1]


def _csv_text(rows) -> str:
    buffer = io.StringIO()
    csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n").writeheader()
    rows = sorted(rows, key=lambda r: (r["category"], int(r["index"])))
    return buffer.getvalue() + "".join(map(_csv_line, rows))


def _write_csv(path: Path, rows) -> bool:
    """Write manifest.csv (atomically) unless it holds these rows already; returns whether it wrote."""
    data = _csv_text(rows).encode("utf-8")
    try:
        if path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data:
            return False
    except OSError:
        pass
    write_bytes_atomic(path, data)
    _WRITTEN.add(path)
    return True


def write_manifest(path: Path, rows: list[dict]) -> Path:
    """manifest.csv (atomically), and manifest.parquet beside it if pandas and pyarrow are installed
    (made again only when the CSV changed or the parquet file is missing)."""
    wrote = _write_csv(path, rows)
    parquet = path.with_suffix(".parquet")
    try:   # behind the CSV: written ahead this run, or by a run killed before its parquet
        stale = wrote or path in _WRITTEN or parquet.stat().st_mtime_ns < path.stat().st_mtime_ns
    except OSError:
        stale = True
    if importlib.util.find_spec("pandas") and importlib.util.find_spec("pyarrow") and stale:
        import pandas as pd

        with atomic_path(parquet) as tmp:
            pd.read_csv(path).to_parquet(tmp, index=False)
    return path


def remove_temporaries(out: Path) -> int:
    """Remove hidden temporaries that killed writers left anywhere under `out`; returns how many."""
    n = 0
    for d, _, files in os.walk(out):
        for name in files:
            if TEMPORARY.match(name):
                Path(d, name).unlink(missing_ok=True)
                n += 1
    return n


def remove_unlisted(out: Path, category: str, rows) -> list[str]:
    """Remove indexed images and masks of `category` that no manifest row lists (an older run
    killed between placing a refreshed scene's new files and removing its old ones); returns them."""
    listed = {r[k] for r in rows if r["category"] == category for k in FILE_KEYS if r.get(k)}
    gone = []
    root = os.fspath(out)
    for top in (out / category, out / "allo_masks" / category):
        for d, _, files in os.walk(top):
            prefix = os.path.relpath(d, root).replace(os.sep, "/") + "/"
            for name in files:
                rel = prefix + name
                if INDEXED.match(name) and rel not in listed:
                    Path(d, name).unlink(missing_ok=True)
                    gone.append(rel)
    return gone


# SPLITS (a scene's split, the split folders) and VARIANTS (a scene's variant -> the row's kind): core.scene_labels
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")    # a scene name, the category: a plain file name


def _count(value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise Refused(f"class_pixels holds {value!r}, not a pixel count")
    return value


def image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise Refused(f"{path.name} is not a readable image ({exc})") from None


def check_render(meta_path: Path, meta: RenderRecord) -> tuple[str, tuple[int, int], AnomalyPixels | None]:
    """(kind, (width, height), the anomaly's pixels of the mask it decoded or None) of a render record
    with an image, or Refused saying why it cannot be filed. The record is not trusted: its split and
    variant come from fixed sets (SPLITS, VARIANTS), names are plain tokens, every file it names is a
    regular file of its own render directory, its images agree in size with each other and with its
    resolution, its class pixels add up to the image, and the kind agrees with the mask (an anomalous
    scene's mask, read here, must show the anomaly; a normal scene's pixel counts must show none).
    `_kind` then leaves out anomalous training scenes and invisible anomalies. The anomaly's pixels
    (an anomalous scene with anomaly pixels) are kept so that placing the scene does not decode its
    mask again."""
    name, scene, files = meta_path.stem, meta.scene, meta.files
    if not NAME.match(name):
        raise Refused(f"scene name {name!r} is not a plain name ([A-Za-z0-9_.-])")
    if not isinstance(scene, dict) or not isinstance(files, dict):
        raise Refused("its JSON has no scene or files table")
    problem = label_problem(scene)   # the reader's check too: render never records what is refused here
    if problem:
        raise Refused(problem)
    anomaly = scene.get("anomaly")
    src = meta_path.parent
    rgb, mask = (source_file(src, files.get(k)) for k in ("rgb", "mask"))
    size = image_size(rgb)
    if image_size(mask) != size:
        raise Refused(f"its mask is {'x'.join(map(str, image_size(mask)))}, its image {'x'.join(map(str, size))}")
    resolution = meta.resolution
    if resolution is not None and list(resolution) != list(size):
        raise Refused(f"its JSON says {resolution}, its image is {'x'.join(map(str, size))}")
    pixels = meta.class_pixels
    if not isinstance(pixels, dict):
        raise Refused("its JSON has no class_pixels")
    counts = {k: _count(pixels.get(k, 0)) for k in ("background", "station_and_bodies", "anomaly")}
    if sum(counts.values()) != size[0] * size[1]:
        raise Refused(f"class_pixels add up to {sum(counts.values())}, not its {size[0]}x{size[1]} pixels")
    if scene["variant"] == "normal" and counts["anomaly"]:
        raise Refused(f"a normal scene whose mask has {counts['anomaly']} anomaly pixels")
    if scene["variant"] == "anomaly" and counts["anomaly"]:
        if anomaly is None:
            raise Refused("an anomalous scene that records no anomaly asset")
        visible = AnomalyPixels.of(read_pixels(mask))
        if visible.count != counts["anomaly"]:
            raise Refused(f"its JSON counts {counts['anomaly']} anomaly pixels, its mask {visible.count}")
        return VARIANTS[scene["variant"]], size, visible
    return VARIANTS[scene["variant"]], size, None


def _kind(scene: dict, meta: RenderRecord, kind: str) -> str | None:
    """`kind`, or None for a scene the dataset leaves out: anomalous in the train split, or an
    anomaly with no visible pixel (a wrong label either way)."""
    if kind == "anomaly" and (scene["split"] != "test" or meta.class_pixels.get("anomaly", 0) == 0):
        return None
    return kind


def all_black(path: Path, size: tuple[int, int]) -> bool:
    """Is the PNG at `path` black everywhere? Decoded only when its file is small enough to be (a
    black image compresses to almost nothing), so a large dataset is not decoded twice."""
    if os.path.getsize(path) > size[0] * size[1] * 3 // 100 + 4096:
        return False
    return not read_pixels(path).any()


def folder(scene: dict, kind: str, defects: str) -> str:
    """The folder of a scene's image under its split: `good` for a normal one, else its anomaly's
    asset (defects="per-asset") or `anomaly` (defects="merged")."""
    if kind != "anomaly":
        return NORMAL
    return MERGED if defects == "merged" else scene["anomaly"]["asset"]


def file_columns(category: str, index: int, name: str, split: str, kind: str, where: str) -> dict:
    """The row's identity and its files, relative to the dataset root: the image in
    CATEGORY/SPLIT/WHERE/, its 0/255 mask (anomalies) in CATEGORY/ground_truth/WHERE/ under the
    image's stem + `_mask` (MVTec AD's naming), its 3-class mask under allo_masks/."""
    stem = f"{index:06d}_{name}"
    mask = f"{category}/ground_truth/{where}/{stem}_mask.png" if kind == "anomaly" else ""
    return {"category": category, "index": index, "name": name, "image": f"{category}/{split}/{where}/{stem}.png",
            "mask": mask, "allo_mask": f"allo_masks/{category}/{split}/{where}/{stem}_mask.png", "split": split,
            "kind": kind}


def scene_columns(name: str, meta: RenderRecord) -> dict:
    """What the scene is: its pose, day and anomaly (from the render's JSON)."""
    scene = meta.scene
    anomaly = scene.get("anomaly") or {}
    return {"scene_id": scene.get("sceneId", name), "pose": scene.get("pose"), "day": scene.get("day"),
            "epoch": scene.get("epoch"), "anomaly_asset": anomaly.get("asset", ""),
            "anomaly_variant": anomaly.get("assetVariant", ""), "depth_index": anomaly.get("depthIndex", ""),
            "depth_offset": anomaly.get("depthOffset", ""),
            "anomaly_fraction": 0.0 if meta.anomaly_fraction is None else meta.anomaly_fraction}


def from_root(path, out: Path) -> str:
    """`path` relative to the dataset root `out` (symlinks resolved), so the manifest holds no
    machine's absolute paths and stays right when the dataset and its renders move together.
    Within a run each folder's path from the root is worked out once (FOLDERS' memo)."""
    if not path:
        return ""
    real, top, memo = real_path(path), real_folder(out), FOLDERS.get()
    head, tail = os.path.split(real)
    if memo is None or real == top or not tail:
        return os.path.relpath(real, top)
    key = ("from_root", head, top)
    if key not in memo:
        memo[key] = os.path.relpath(head, top)
    return tail if memo[key] == "." else f"{memo[key]}/{tail}"


def provenance_columns(meta_path: Path, meta: RenderRecord, out: Path) -> dict:
    """Where the image came from: seeds, the scene layer, the render record, the image's hash
    (layer and source relative to the dataset root)."""
    scene = meta.scene
    seed_path = scene.get("seedPath", "")
    return {"seed": scene.get("seed"), "plan_seed": plan_seed(seed_path), "seed_path": seed_path,
            "layer": from_root(meta.layer or "", out), "layer_sha256": _or_blank(meta.layer_sha256),
            "sha256": sha256_file(meta_path.parent / meta.files["rgb"]), "source": from_root(meta_path, out)}


def _or_blank(value):
    """A record's value for a manifest cell, "" when the record has none."""
    return "" if value is None else value


def _row(category, index, name, meta_path: Path, meta: RenderRecord, kind: str, where: str, out: Path) -> dict:
    """The manifest row of one scene (its files are placed by _place_row)."""
    files = file_columns(category, index, name, meta.scene["split"], kind, where)
    return (files | pass_columns(files["image"], meta_path, meta)   # depth/, normal/, instance/ (output.pass_files)
            | scene_columns(name, meta) | annotation_columns(meta) | provenance_columns(meta_path, meta, out)
            | accuracy_columns(meta))


def _place_row(row: dict, meta_path: Path, meta: RenderRecord, out: Path, link: bool,
               visible: AnomalyPixels | None = None) -> AnomalyPixels | None:
    """Put one scene's files in the tree: its passes, 3-class mask, binary ground truth, then the
    image. Returns the anomaly's pixels when it has a ground truth (`visible`: check_render's, else
    its mask decoded here), so its annotation record is computed from them rather than from
    another decode."""
    src = meta_path.parent
    place_passes(row, meta_path, meta, out, link)
    mask_src, rgb_src = (source_file(src, meta.files[k]) for k in ("mask", "rgb"))
    place(mask_src, inside(out, row["allo_mask"]), link)
    if row["mask"]:
        visible = visible if visible is not None else AnomalyPixels.of(read_pixels(mask_src))
        write_png(inside(out, row["mask"]), visible.full().astype(np.uint8) * np.uint8(255))
    else:
        visible = None
    place(rgb_src, inside(out, row["image"]), link)
    return visible


def _unchanged(old: dict, meta_path: Path, meta: RenderRecord, kind: str, where: str, out: Path) -> bool:
    """A row whose source, layer, kind and folder are the same and whose files are links to the
    render: skip hashing again (job.py replaces outputs by rename, so a linked file never changes
    content). A row in another folder (the other `defects` choice) is placed again."""
    split = meta.scene["split"]
    if isinstance(meta.annotations, dict) and not old.get("fx"):
        return False  # a row from before the camera/annotation columns: fill them in
    if any(str(old.get(k) or "") != str(v) for k, v in accuracy_columns(meta).items()):
        return False  # the render's estimate is not the row's (a row from before a column reads it as "")
    if passes_missing(old, meta_path, meta, out):
        return False  # a pass the row lacks (a row from before the pass columns, or a file gone)
    if (old["source"], old["layer_sha256"], old["kind"], old["split"], old["image"]) != (
            from_root(meta_path, out), _or_blank(meta.layer_sha256), kind, split,
            file_columns(old["category"], int(old["index"]), old["name"], split, kind, where)["image"]):
        return False
    src = meta_path.parent
    try:
        return (os.path.samefile(out / old["image"], src / meta.files["rgb"])
                and os.path.samefile(out / old["allo_mask"], src / meta.files["mask"])
                and (not old["mask"] or (out / old["mask"]).is_file()))
    except OSError:
        return False


def _remove_files(out: Path, row: dict) -> None:
    for key in FILE_KEYS:
        if row.get(key):
            inside(out, row[key]).unlink(missing_ok=True)


def _complete(out: Path, row: dict) -> bool:
    return all(os.path.isfile(inside(out, row[k])) for k in FILE_KEYS if row.get(k))


@contextmanager
def _stop_at_scene_boundary():
    """While active, a first Ctrl-C sets the returned event (the loop stops after the scene in
    hand); a second raises KeyboardInterrupt at once. Only the main thread can own SIGINT."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        from tqdm import tqdm

        tqdm.write("Ctrl-C: stopping after this scene (Ctrl-C again stops at once; nothing is lost either way)")

    old = signal.signal(signal.SIGINT, handler)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, old if old is not None else signal.SIG_DFL)


LOCK = ".allo-dataset.lock"


class _Lock(RunLock):
    """RunLock on OUT/LOCK, whose file is removed when the run ends (no lock file is left behind).
    A run that opened the file just before the holder removed it would lock a file no longer in
    the directory, beside a third run locking a new one: so a lock counts only if the path still
    names the locked file, else it is taken again."""

    def __enter__(self):
        for _ in range(8):
            super().__enter__()
            try:
                if os.path.samestat(os.fstat(self.fd), os.stat(self.path)):
                    return self
            except FileNotFoundError:
                pass
            os.close(self.fd)
        raise AlloError(f"could not lock {self.path}: other dataset runs keep starting and ending there; "
                        "wait for them or use another --out")

    def __exit__(self, *exc):
        self.path.unlink(missing_ok=True)  # while still holding it
        super().__exit__(*exc)


def assemble(render_dirs, out_dir, layout: str = "mvtec", link: bool = True, category: str = "allo",
             sheet_limit: int = 48, progress: bool = False, on_scene=None, defects: str = "per-asset") -> Path:
    """Build (or update) the dataset tree under out_dir from render directories; returns the manifest.

    `defects` is "per-asset" (test/<asset>/ and ground_truth/<asset>/, as MVTec AD has one
    folder per defect type) or "merged" (every anomaly in test/anomaly/). `sheet_limit` caps the
    images drawn on each split's contact sheets (sampled evenly). `progress` shows bars (counts,
    ETA) for reading the renders and placing the scenes; `on_scene(name)` is called after each
    scene's files are in place. Ctrl-C raises AssemblyInterrupted once the manifest is final for
    what was placed. One run at a time per out_dir (`LOCK`): a second would remove the first
    one's temporaries and unlisted images."""
    if defects not in DEFECTS:
        raise AlloError(f"unknown defects layout {defects!r}; choose one of {', '.join(DEFECTS)}")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    token = FOLDERS.set({})   # this run's folders' real paths (real_folder)
    try:
        with _Lock(out_dir, LOCK, "dataset"):
            return _assemble(render_dirs, out_dir, layout, link, category, sheet_limit, progress, on_scene, defects)
    finally:
        FOLDERS.reset(token)
        _LINES.clear()
        _WRITTEN.clear()


def _assemble(render_dirs, out_dir, layout, link, category, sheet_limit, progress, on_scene, defects) -> Path:
    if layout not in LAYOUTS:
        raise AlloError(f"unknown dataset layout {layout!r}; choose one of {LAYOUTS}")
    if not NAME.match(category or "") or category in ("allo_masks", "contact_sheets"):
        raise AlloError(f"category {category!r} must be a plain directory name ([A-Za-z0-9_.-], not allo_masks or "
                        "contact_sheets); fix: e.g. --category allo")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    manifest = out / MANIFEST
    rows = _clean_tree(out, manifest, category)
    cache = load_cache(out, len(rows))   # annotations/records.json: the annotation records and the dataset's state
    state = cache.get("state") if isinstance(cache.get("state"), dict) else {}
    todo, checks = _plan_rows(render_dirs, progress, rows, category, link, out, defects, state.get("checks"))
    early: dict[str, dict] = {}   # annotation records computed at placement from the mask in hand
    placed, stop_now = _place_all(todo, rows, manifest, out, category, link, progress, on_scene, early)
    if stop_now:
        write_manifest(manifest, list(rows.values()))
        raise AssemblyInterrupted(f"interrupted after {placed} of {len(todo)} scenes; {manifest} lists every file "
                                  "in the tree; re-run the same command to add the rest")
    _finish(out, manifest, rows, category, sheet_limit, cache, {**state, "checks": checks}, early)
    return manifest


def _clean_tree(out: Path, manifest: Path, category: str) -> dict[tuple, dict]:
    """The manifest's rows by (category, name), after removing what an interrupted run left that no
    row lists, so the tree and its manifest agree before anything is added."""
    removed = remove_temporaries(out)
    rows = {(r["category"], r["name"]): r for r in read_manifest(manifest)}
    unlisted = remove_unlisted(out, category, rows.values())
    if removed or unlisted:
        warnings.warn(f"removed {removed} stale temporary file(s) and {len(unlisted)} image(s) no manifest row "
                      f"lists, left by an interrupted run", stacklevel=3)
    return rows


def _stat_of(path) -> list[int]:
    st = os.stat(path)
    return [st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev]


def _check(meta_path: Path, meta: RenderRecord, prior, json_stat: list[int] | None = None
           ) -> tuple[str, tuple[int, int], dict | None, AnomalyPixels | None]:
    """check_render's (kind, size) of a record, the evidence to keep for the next run (the stat
    (size, mtime_ns, inode, device) of the record, its image and its mask, taken before the check,
    and the record's Brief), and the anomaly's pixels when its mask was decoded.
    An earlier run's answer (`prior`) stands while all three stats are the ones it recorded (the
    quick check of make, rsync and the render manifest: a rewrite changes size or mtime, a
    re-render replaces the files), so a re-run does not read every image header and decode every
    anomalous mask again; the file-name rules (source_file) are applied every time. `json_stat`:
    the record's stat taken before scan read it. `meta` may be a Brief only where `prior` holds
    (_plan_rows reads the whole record otherwise)."""
    files = meta.files
    try:
        evidence = {"json": json_stat if json_stat is not None else _stat_of(meta_path),
                    **{k: source_entry(meta_path.parent, files.get(k))[1] for k in ("rgb", "mask")}}
    except (Refused, OSError, AttributeError):
        evidence = None   # check_render says why
    if _holds(evidence, prior):
        if "brief" not in prior and not isinstance(meta, Brief):   # kept by a run before Briefs
            prior = {**prior, "brief": Brief.of_record(meta).as_dict()}
        return prior["kind"], (prior["size"][0], prior["size"][1]), prior, None
    if isinstance(meta, Brief):
        raise _Stale(meta_path)
    kind, size, visible = check_render(meta_path, meta)
    proof = None if evidence is None else {**evidence, "kind": kind, "size": list(size),
                                           "brief": Brief.of_record(meta).as_dict()}
    return kind, size, proof, visible


class _Stale(Exception):
    """A record's files changed since its Brief was kept: it is read whole and checked again."""


def _holds(evidence: dict | None, prior) -> bool:
    """Does an earlier run's check (`prior`) stand for a record with this evidence?"""
    if evidence is None or not isinstance(prior, dict) or not all(prior.get(k) == v for k, v in evidence.items()):
        return False
    kind, size = prior.get("kind"), prior.get("size")
    return kind in VARIANTS.values() and isinstance(size, list) and len(size) == 2 \
        and all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 65535 for v in size) \
        and _brief_agrees(prior.get("brief"), kind, size)


def _brief_agrees(brief, kind: str, size: list[int]) -> bool:
    """Is a kept Brief (records.json's state: a cache, checked as any input) one check_render could
    have passed with this kind and size: its scene's labels valid (label_problem), its variant this
    kind, its files a table, its pixel counts whole numbers within the image? A state from before
    Briefs has none (None: the record in hand stands)."""
    if brief is None:
        return True
    if not isinstance(brief, dict) or not isinstance(brief.get("scene"), dict) \
            or not isinstance(brief.get("files"), dict) or not isinstance(brief.get("class_pixels"), dict) \
            or not all(isinstance(brief["files"].get(k), str) for k in ("rgb", "mask")):
        return False
    scene, pixels = brief["scene"], brief["class_pixels"]
    counts = [pixels.get(k, 0) for k in ("station_and_bodies", "anomaly")]
    return label_problem(scene) is None and VARIANTS[scene["variant"]] == kind \
        and all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v for v in counts) \
        and sum(counts) <= size[0] * size[1] and (kind == "anomaly" or counts[1] == 0)


def _whole(meta_path: Path, refused: list, stats: dict) -> RenderRecord | None:
    """The whole render record in place of its Brief (its stat taken again before it is read)."""
    stats[str(meta_path)] = _json_stat(meta_path)
    return _read_record(meta_path, meta_path.parent, refused)


def _known(checked: dict, out: Path, render_dirs) -> dict:
    """{json path as scan names it: (stat, Brief)} of the records an earlier run checked."""
    known = {}
    for d in map(Path, render_dirs):
        rel = os.path.relpath(os.path.abspath(d), os.path.abspath(out))
        prefix = "" if rel == "." else rel + "/"
        for key, proof in checked.items():
            name = key[len(prefix):]
            if key.startswith(prefix) and "/" not in name and isinstance(proof, dict) \
                    and isinstance(proof.get("brief"), dict) and isinstance(proof.get("json"), list) \
                    and _holds({"json": proof["json"]}, proof):   # its kind, size and Brief agree
                known[str(d / name)] = (proof["json"], Brief.of(proof["brief"]))
    return known


def _plan_rows(render_dirs, progress, rows: dict[tuple, dict], category: str, link, out: Path,
               defects: str, checked=None) -> tuple[list[tuple], dict]:
    """(name, meta path, meta, kind, index, folder, anomaly pixels or None) of each render to place: new scenes get the
    next free indices, changed or moved ones keep theirs, unchanged linked ones are skipped; the
    rest are reported. An anomaly asset named like the normal folder stops the run.
    Render records that check_render refuses are left out with a warning; renders of another
    resolution than the rest (or than the category's images already in the tree) stop the run.
    With them, the records' check evidence ({record path from OUT: _check's}) for records.json's state;
    `checked` is the last run's."""
    checked = checked if isinstance(checked, dict) else {}
    evidence: dict[str, dict] = {}
    next_index = 1 + max((int(r["index"]) for r in rows.values() if r["category"] == category), default=-1)
    refused: list[str] = []   # "JSON: why" of each record left out (the read gate's, then check_render's)
    stats: dict[str, list | None] = {}   # json path: its stat before it was read (scan, _whole)
    found = scan(render_dirs, progress, refused, _known(checked, out, render_dirs), stats)
    if not found and not refused:
        raise AlloError(f"no renders in {', '.join(map(str, render_dirs))}: no NAME.json render record there; fix: "
                        "pass the directories `allo-usd render` wrote (its --out; for a plan, OUT/renders)")
    left_out, mask_only, todo, sizes, dark, black = [], [], [], {}, [], []
    prefixes = {}   # render folder: its path from OUT (the state's keys: no machine's path)
    for meta_path, meta in found:
        name = meta_path.stem
        if isinstance(meta.files, dict) and "rgb" not in meta.files:
            mask_only.append(name)
            continue
        if meta_path.parent not in prefixes:
            rel = os.path.relpath(os.path.abspath(meta_path.parent), os.path.abspath(out))
            prefixes[meta_path.parent] = "" if rel == "." else rel + "/"
        key = prefixes[meta_path.parent] + meta_path.name
        try:
            try:
                kind, size, proof, visible = _check(meta_path, meta, checked.get(key), stats.get(str(meta_path)))
            except _Stale:   # its image or mask changed since its Brief was kept: read it whole
                meta = _whole(meta_path, refused, stats)
                if meta is None:
                    continue
                kind, size, proof, visible = _check(meta_path, meta, None, stats.get(str(meta_path)))
        except Refused as exc:
            refused.append(f"{meta_path}: {exc}")
            continue
        if proof is not None:
            evidence[key] = proof
        kind = _kind(meta.scene, meta, kind)
        if kind is None:
            left_out.append(name)
            continue
        where = folder(meta.scene, kind, defects)
        if kind == "anomaly" and where.lower() == NORMAL:
            raise AlloError(f"{meta_path}: its anomaly asset is named {where!r}, and MVTec loaders read a folder of "
                            f"that name as normal images; fix: --defects merged, or rename the asset")
        sizes.setdefault(size, []).append(name)
        if meta.class_pixels.get("station_and_bodies", 0) == 0:
            dark.append(name)
        old = rows.get((category, name))
        if old and link and _unchanged(old, meta_path, meta, kind, where, out):
            continue
        if isinstance(meta, Brief):   # to be placed: its row needs the whole record
            whole = _whole(meta_path, refused, stats)
            if whole is None or Brief.of_record(whole) != meta or stats.get(str(meta_path)) != evidence[key]["json"]:
                refused.append(f"{meta_path}: it changed while the dataset was being assembled; run again")
                evidence.pop(key, None)
                continue
            meta = whole
        if all_black(source_file(meta_path.parent, meta.files["rgb"]), size):
            black.append(name)
        index = int(old["index"]) if old else next_index
        next_index += old is None
        if index > MAX_INDEX:
            raise AlloError(f"{out / category} would hold more than {MAX_INDEX + 1:,} images (file names start with "
                            "a six-digit index); fix: assemble the rest into another --category")
        todo.append((name, meta_path, meta, kind, index, where, visible))
    _one_resolution(sizes, rows, category, out)
    if refused:
        warnings.warn(f"{len(refused)} render(s) refused and left out, their JSON unreadable (not a regular file, too "
                      f"big, too deep), contradicting itself or naming files outside its render directory: "
                      f"{'; '.join(refused[:5])}", RefusedRenders, stacklevel=3)
    if left_out:
        warnings.warn(f"{len(left_out)} scene(s) left out (anomalous in the train split, or anomaly not visible): "
                      f"{', '.join(left_out[:10])}", stacklevel=3)
    if mask_only:
        warnings.warn(f"{len(mask_only)} mask-only render(s) left out: they have no color image to train or test "
                      f"on (render their layers with color to include them): {', '.join(mask_only[:10])}",
                      stacklevel=3)
    if dark:
        warnings.warn(f"SUSPICIOUS: {len(dark)} scene(s) show no station or body pixel (class_pixels "
                      f"station_and_bodies = 0): a camera looking away or a failed render; check them: "
                      f"{', '.join(dark[:10])}", stacklevel=3)
    if black:
        warnings.warn(f"{len(black)} scene(s) have an all-black image (an umbra scene without the inspection light "
                      f"is black in the PNG, lit only in the EXR; otherwise a failed render): {', '.join(black[:10])}",
                      stacklevel=3)
    return todo, evidence


def _one_resolution(sizes: dict[tuple, list[str]], rows: dict[tuple, dict], category: str, out: Path) -> None:
    """Refuse to mix image sizes in one category (models train on one size): the renders among
    themselves, and against an image the category already holds."""
    held = next((r for r in rows.values() if r["category"] == category and _complete(out, r)), None)
    try:
        size = image_size(inside(out, held["image"])) if held is not None else None
    except Refused:
        size = None   # unreadable: its render replaces it, or _finish drops it
    if size is not None:
        sizes = {size: [f"{held['name']} and the rest of {category}/ already in the dataset"]} | sizes
    if len(sizes) > 1:
        shown = "; ".join(f"{w}x{h}: {len(names)} (e.g. {names[0]})" for (w, h), names in sizes.items())
        raise AlloError(f"renders of different resolutions would be mixed in {out / category} ({shown}); fix: "
                        f"assemble each resolution into its own --out (or --category)")


def _place_all(todo: list[tuple], rows: dict[tuple, dict], manifest: Path, out: Path, category: str, link,
               progress, on_scene, early: dict | None = None) -> tuple[int, bool]:
    """(scenes placed, stopped early) after placing `todo` in batches, each batch's rows written to the
    manifest before any of its files exists, so an interrupted run leaves a manifest listing every
    file; on a stop, rows not placed go back to what the manifest said before."""
    from tqdm import tqdm

    ahead: dict[tuple, dict | None] = {}  # rows written ahead whose scene is not placed yet: key -> old row
    in_hand = None
    placed = 0
    try:
        with _stop_at_scene_boundary() as stop, tqdm(total=len(todo), unit="scene", desc=f"assembling {category}",
                                                     disable=not progress) as bar:
            i = 0
            while i < len(todo) and not stop.is_set():
                batch = todo[i:i + max(64, min(4096, len(rows) // 8))]  # amortised: O(log n) rewrites
                i += len(batch)
                new = [(t, _row(category, t[4], t[0], t[1], t[2], t[3], t[5], out)) for t in batch]
                for (name, *_), row in new:
                    key = (category, name)
                    ahead[key] = rows.get(key)
                    rows[key] = row
                _write_csv(manifest, rows.values())  # before any of the batch's files exists
                for (name, meta_path, meta, *_, visible), row in new:
                    if stop.is_set():
                        break
                    key = in_hand = (category, name)
                    old = ahead[key]
                    visible = _place_row(row, meta_path, meta, out, link, visible)
                    if early is not None:
                        early[f"{category}/{name}"] = compute_record(out, row, meta=meta, visible=visible)
                    if old:
                        _remove_files(out, {k: old[k] for k in FILE_KEYS if old.get(k) and old[k] != str(row[k])})
                    del ahead[key]
                    in_hand = None
                    placed += 1
                    bar.update(1)
                    if on_scene is not None:
                        on_scene(name)
    except KeyboardInterrupt:
        stop_now = True
    else:
        stop_now = stop.is_set()
    finally:
        for key, old in ahead.items():  # not placed: back to what the manifest said before
            if key == in_hand:
                continue  # stopped at once mid-scene: its row lists the files that may exist
            if old is None:
                rows.pop(key, None)
            else:
                rows[key] = old
    return placed, stop_now


def _sheet_key(category: str, split: str, rows: list[dict], limit) -> str:
    """What a split's contact sheets are drawn from (every row shown or counted in the header, with
    its image's checksum): equal keys draw equal sheets."""
    import hashlib

    shown = sorted((r["image"], r["allo_mask"], r["kind"], str(r["index"]), r["name"], str(r["anomaly_fraction"]),
                    r.get("sha256", "")) for r in rows)
    text = json.dumps([category, split, limit, PER_SHEET, shown], separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _finish(out: Path, manifest: Path, rows: dict[tuple, dict], category: str, sheet_limit, cache: dict,
            state: dict, early: dict | None = None) -> None:
    """Drop rows whose files are gone (and not re-rendered), write the final manifest, redraw the
    category's contact sheets whose rows changed (the rows each was drawn from are kept in the
    state), then the annotation files with the state, so the tree ends complete and consistent."""
    gone = [key for key, r in rows.items() if not _complete(out, r)]
    if gone:
        warnings.warn(f"{len(gone)} manifest row(s) dropped: their files are missing and their renders were not "
                      f"given: {', '.join(name for _, name in gone[:10])}", stacklevel=3)
        for key in gone:
            _remove_files(out, rows.pop(key))
    all_rows = list(rows.values())
    write_manifest(manifest, all_rows)
    remove_empty_folders(out, category)
    sheets = inside(out, "contact_sheets")
    drawn = dict(state.get("sheets") or {}) if isinstance(state.get("sheets"), dict) else {}
    for split in SPLITS:
        picked = [r for r in all_rows if r["category"] == category and r["split"] == split]
        if picked:
            key, name = _sheet_key(category, split, picked, sheet_limit), f"{category}/{split}"
            pages = -(-min(len(picked), sheet_limit) // PER_SHEET)
            if drawn.get(name) == key and all(p.is_file() for p in sheet_paths(sheets, category, split, pages)):
                continue   # drawn from these very rows by an earlier run
            sheets.mkdir(exist_ok=True)
            drawn.pop(name, None)
            split_sheets(out, picked, sheets, category, split, sheet_limit)
            drawn[name] = key
        else:
            drawn.pop(f"{category}/{split}", None)
    # COCO, BOP, instances.json (allo_usd.output.annotation_files), and the state for the next run
    write_annotation_files(out, all_rows, cache, {**state, "sheets": drawn}, early)


def remove_empty_folders(out: Path, category: str) -> None:
    """Remove the category's emptied image folders (after a re-run with the other `defects`
    choice, test/anomaly/ or test/<asset>/ is left empty; a Folder loader given it would fail)."""
    for top in (out / category, out / "allo_masks" / category):
        for d in sorted(top.glob("*/*"), reverse=True):
            if d.is_dir() and not d.is_symlink() and not any(d.iterdir()):
                d.rmdir()


def summary_line(out: Path) -> str:
    """One line on what the annotation files hold, from records.json: images, anomalies with a BOP
    pose (an older render records none: re-render it), amodal masks (else visib_fract comes from
    the ray cast), depth PNGs (render the depth pass for them), and the renders whose full
    silhouette is counted inside the image only (recorded before the BOP toolkit's canvas was). Entries are read as entry_of wrote
    them (an anomaly: an entry with objects); one that is not such an entry is not counted."""
    entries = {name: e for name, e in (load_records(Path(out), len(read_manifest(Path(out) / MANIFEST))).get("records")
                                        or {}).items() if isinstance(e, dict) and set(e) == ENTRY_KEYS
               and isinstance(e["gt"], list) and all(isinstance(g, dict) and isinstance(g.get("info"), dict)
                                                     for g in e["gt"])}
    anomalous = {name: e for name, e in entries.items() if e["gt"]}
    posed = [name for name, e in anomalous.items() if e["gt"][0].get("pose") is not None]
    amodal = sum(e["gt"][0]["info"].get("visib_source") == "amodal_pass" for e in anomalous.values())
    depth = sum(e["depth"] is True for e in entries.values())
    line = (f"annotations: COCO {len(entries)} images, {len(anomalous)} anomalies; BOP poses {len(posed)} of "
            f"{len(anomalous)}, amodal masks {amodal} of {len(anomalous)}, depth {depth} of {len(entries)} images")
    missing = [name.split("/", 1)[-1] for name in anomalous if name not in posed]
    if missing:
        line += (f" ({len(missing)} render(s) record no pose, rendered before poses were: their scene_gt entries are "
                 f"empty; re-render them: {', '.join(missing[:5])})")
    clipped = [name.split("/", 1)[-1] for name, e in anomalous.items()
               if any(g["info"].get("silhouette") == "image" for g in e["gt"])]
    if clipped:
        line += (f" ({len(clipped)} render(s) record the full silhouette inside the image only, rendered before it was "
                 f"counted on the BOP toolkit's canvas: their px_count_all, visib_fract and bbox_obj are clipped to "
                 f"the image (scene_gt_info's silhouette \"image\"); re-render them: {', '.join(clipped[:5])})")
    return line
