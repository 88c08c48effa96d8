"""The dataset tree's shared rules, used by the assembler (output.dataset) and by the writers of
the files beside its images (output.pass_files, output.annotation_files): the manifest's columns,
which render file may be read (source_file), where a dataset file may be written (inside), and how
it gets there (place)."""

from __future__ import annotations

import os
import shutil
from contextvars import ContextVar
from pathlib import Path

from allo_usd.core.errors import AlloError
from allo_usd.core.files import atomic_path, sha256_file
from allo_usd.output.annotations import ANNOTATION_COLUMNS, CAMERA_COLUMNS

# Manifest columns, in groups; a new group is a tuple here and a function in dataset._row.
PASS_COLUMNS = ("depth", "normal", "instance")     # the passes' paths (output.pass_files): names and top folders
FILE_COLUMNS = ("category", "index", "name", "image", "mask", "allo_mask", "split", "kind") + PASS_COLUMNS
SCENE_COLUMNS = ("scene_id", "pose", "day", "epoch", "anomaly_asset", "anomaly_variant", "depth_index",
                 "depth_offset", "anomaly_fraction")
PROVENANCE_COLUMNS = ("seed", "plan_seed", "seed_path", "layer", "layer_sha256", "sha256", "source")
# CAMERA_COLUMNS and ANNOTATION_COLUMNS (K, pose, clipping; anomaly box and place, pixel counts, bodies
# in view) are defined beside the JSON block they flatten: allo_usd.output.annotations.
COLUMNS = FILE_COLUMNS + SCENE_COLUMNS + CAMERA_COLUMNS + ANNOTATION_COLUMNS + PROVENANCE_COLUMNS


def place(src: Path, dst: Path, link: bool = True) -> str:
    """Put src at dst atomically: a hard link if allowed and possible, else a copy. Returns how."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        same = os.path.samefile(src, dst)
        if (link and same) or (not link and not same and sha256_file(src) == sha256_file(dst)):
            return "kept"  # a copy run replaces earlier links by copies, and keeps equal copies
    if link:
        try:
            with atomic_path(dst, suffix=".tmp", mode=None) as tmp:  # never chmod the linked source
                tmp.unlink()
                os.link(src, tmp)
            return "link"
        except OSError:  # other file system, or links not allowed: copy instead
            pass
    with atomic_path(dst, suffix=".tmp") as tmp:  # .tmp: no loader globbing *.png sees it
        shutil.copyfile(src, tmp)
    return "copy"


class Refused(Exception):
    """Why a render record is left out of the dataset (its JSON contradicts itself or its files)."""


FOLDERS: ContextVar[dict | None] = ContextVar("allo_dataset_folders", default=None)


def real_folder(path) -> str:
    """os.path.realpath of OUT or a render folder, once per assembly run (assemble sets the memo;
    elsewhere it is computed each call): the rules below compare every file's real path with its
    folder's, ~10 times a scene. Within a run the folder's first answer stands: a folder swapped for
    a link meanwhile puts its files' fresh real paths outside it, so they are refused."""
    memo = FOLDERS.get()
    if memo is None:
        return os.path.realpath(path)
    key = os.fspath(path)
    if key not in memo:
        memo[key] = os.path.realpath(path)
    return memo[key]


def source_file(render_dir: Path, name) -> Path:
    """`name` from a render JSON's "files" as a file of `render_dir`: a plain name (no separator,
    not . or ..) of a regular file whose real path lies in the render directory itself."""
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name \
            or "\0" in name:
        raise Refused(f"file name {name!r} is not a plain file name in its render directory")
    path = render_dir / name
    real = os.path.realpath(path)
    if os.path.dirname(real) != real_folder(render_dir):
        raise Refused(f"file {name!r} resolves to {real}, outside its render directory {render_dir}")
    if not os.path.isfile(real):
        raise Refused(f"file {name!r} is missing or not a regular file")
    return path


def inside(out: Path, rel: str) -> Path:
    """`out / rel`, refused (AlloError) unless its real path stays inside `out`: nothing is written
    or removed outside the dataset, whatever the manifest says or a symlinked folder points at."""
    path = Path(out) / rel
    top, real = real_folder(out), os.path.realpath(path)
    if Path(rel).is_absolute() or os.path.commonpath([top, real]) != top:
        raise AlloError(f"{path} resolves to {real}, outside the dataset {out} (a symlinked folder, or a manifest "
                        f"row naming another place); fix: remove it, or assemble into a fresh --out")
    return path
