"""Every rendered pass in the dataset: a scene's depth, normal and instance-id files go into
depth/, normal/ and instance/ beside the MVTec folders, mirroring the image's path, and the manifest
gets their paths (columns PASS_COLUMNS, empty when the pass was not rendered):

    OUT/depth/CATEGORY/SPLIT/FOLDER/NNNNNN_NAME.exr     float32 EXR, channel Z: metres along the view axis
    OUT/normal/CATEGORY/SPLIT/FOLDER/NNNNNN_NAME.exr    float32 EXR, channels X, Y, Z: world-space normal
    OUT/instance/CATEGORY/SPLIT/FOLDER/NNNNNN_NAME.png  uint16 PNG: object id, 0 background

Why: the passes stay byte-identical to the render's (placed like the images: hard links, else
copies), outside the category folder that anomaly loaders glob, and a path is found from the
image's by swapping the top folder and the extension. The object ids of one image are its
scene's objects in sorted prim path order (allo_usd.blender.build.object_ids), so an id means
another prim in another image: the id -> prim tables are per image, in OUT/instances.json.
"""

from __future__ import annotations

from pathlib import Path

from allo_usd.output.dataset_files import PASS_COLUMNS, Refused, inside, place, source_file
from allo_usd.output.record import RenderRecord

SUFFIXES = {"depth": ".exr", "normal": ".exr", "instance": ".png"}


def pass_path(image: str, name: str) -> str:
    """The dataset path of pass `name` of the image at `image` (both relative to the dataset root)."""
    return str(Path(name) / Path(image).with_suffix(SUFFIXES[name])).replace("\\", "/")


def pass_sources(meta_path: Path, meta: RenderRecord) -> dict[str, Path]:
    """{pass: its file in the render folder} for each pass of PASS_COLUMNS the record names and
    that is a regular file of its render folder (dataset_files.source_file); others are left out."""
    files = meta.files if isinstance(meta.files, dict) else {}
    found = {}
    for name in PASS_COLUMNS:
        if name in files:
            try:
                found[name] = source_file(Path(meta_path).parent, files[name])
            except Refused:
                continue
    return found


def pass_columns(image: str, meta_path: Path, meta: RenderRecord) -> dict:
    """The row's PASS_COLUMNS: each rendered pass's dataset path, "" for a pass not rendered."""
    found = pass_sources(meta_path, meta)
    return {name: pass_path(image, name) if name in found else "" for name in PASS_COLUMNS}


def place_passes(row: dict, meta_path: Path, meta: RenderRecord, out: Path, link: bool) -> None:
    """Put the row's pass files in the tree (dataset_files.place: atomic, links when allowed)."""
    for name, src in pass_sources(meta_path, meta).items():
        if row.get(name):
            place(src, inside(out, row[name]), link)


def passes_missing(old: dict, meta_path: Path, meta: RenderRecord, out: Path) -> bool:
    """Does the render have a pass that the old row does not list (a row from before these columns,
    or a scene re-rendered with more passes) or whose file left the tree? Then the row is placed again."""
    return any(not old.get(name) or not (Path(out) / old[name]).is_file() for name in pass_sources(meta_path, meta))
