"""The dataset tree's shared rules, used by the assembler (output.dataset) and by the writers of
the files beside its images (output.pass_files, output.annotation_files): the manifest's columns,
which render file may be read (source_file), where a dataset file may be written (inside), and how
it gets there (place)."""

from __future__ import annotations

import os
import shutil
import stat
from contextvars import ContextVar
from pathlib import Path

import numpy as np

from allo_usd.core.errors import AlloError
from allo_usd.core.files import atomic_path, folder_realpath, memo_realpath, sha256_file
from allo_usd.output.annotations import ACCURACY_COLUMNS, ANNOTATION_COLUMNS, CAMERA_COLUMNS

# Manifest columns, in groups; a new group is a tuple here and a function in dataset._row.
PASS_COLUMNS = ("depth", "normal", "instance")     # the passes' paths (output.pass_files): names and top folders
FILE_COLUMNS = ("category", "index", "name", "image", "mask", "allo_mask", "split", "kind") + PASS_COLUMNS
SCENE_COLUMNS = ("scene_id", "pose", "day", "epoch", "anomaly_asset", "anomaly_variant", "depth_index",
                 "depth_offset", "anomaly_fraction")
PROVENANCE_COLUMNS = ("seed", "plan_seed", "seed_path", "layer", "layer_sha256", "sha256", "source")
# CAMERA_COLUMNS and ANNOTATION_COLUMNS (K, pose, clipping; anomaly box and place, pixel counts, bodies
# in view) and ACCURACY_COLUMNS (the render's estimated PSNR) are defined beside the JSON blocks they
# flatten: allo_usd.output.annotations. ACCURACY_COLUMNS come last: the columns before keep their places.
COLUMNS = FILE_COLUMNS + SCENE_COLUMNS + CAMERA_COLUMNS + ANNOTATION_COLUMNS + PROVENANCE_COLUMNS + ACCURACY_COLUMNS


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


class AnomalyPixels:
    """The anomaly class (2) of a 3-class mask, kept small between the check that decodes the mask
    and the writers that need it (the binary ground truth, the COCO and BOP annotations): the
    mask's shape, the anomaly's box (row0, col0, row1, col1, inclusive) and its pixels inside the
    box, bit-packed. A dataset run holds one for every new anomalous scene until it is placed."""

    __slots__ = ("shape", "box", "count", "_packed", "_crop_shape")

    def __init__(self, shape, box, crop):
        self.shape, self.box = tuple(int(v) for v in shape), box
        self.count = int(np.count_nonzero(crop)) if crop is not None else 0
        self._crop_shape = None if crop is None else crop.shape
        self._packed = None if crop is None else np.packbits(crop, axis=None)

    @classmethod
    def of(cls, mask: np.ndarray) -> "AnomalyPixels":
        visible = np.asarray(mask) == 2
        rows = np.flatnonzero(visible.any(axis=1))
        if not rows.size:
            return cls(visible.shape, None, None)
        cols = np.flatnonzero(visible[rows[0]:rows[-1] + 1].any(axis=0))
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])
        return cls(visible.shape, (r0, c0, r1, c1), visible[r0:r1 + 1, c0:c1 + 1])

    def crop(self) -> np.ndarray | None:
        """The box's pixels (bool), None when no pixel is set."""
        if self._packed is None:
            return None
        size = self._crop_shape[0] * self._crop_shape[1]
        return np.unpackbits(self._packed, count=size).astype(bool).reshape(self._crop_shape)

    def full(self) -> np.ndarray:
        """The whole mask's anomaly pixels (bool, the mask's shape)."""
        out = np.zeros(self.shape, dtype=bool)
        if self.box is not None:
            r0, c0, r1, c1 = self.box
            out[r0:r1 + 1, c0:c1 + 1] = self.crop()
        return out


class Refused(Exception):
    """Why a render record is left out of the dataset (its JSON contradicts itself or its files)."""


FOLDERS: ContextVar[dict | None] = ContextVar("allo_dataset_folders", default=None)


def real_folder(path) -> str:
    """os.path.realpath of OUT or a render folder, once per assembly run (assemble sets the memo;
    elsewhere it is computed each call): the rules below compare every file's real path with its
    folder's, ~10 times a scene. Within a run the folder's first answer stands: a folder swapped for
    a link meanwhile puts its files' fresh real paths outside it, so they are refused."""
    return folder_realpath(path, FOLDERS.get())


def real_path(path) -> str:
    """os.path.realpath(path), from one lstat where it can (the dataset asks ~10 times a
    scene, and realpath lstats every component of the path): a path whose last component exists and
    is no link has its folder's real path plus that name, the folder's from real_folder (a memo within
    an assembly run). Anything else (a link, a missing file, '.' or '..') goes to realpath."""
    return memo_realpath(path, FOLDERS.get())


def source_file(render_dir: Path, name) -> Path:
    """`name` from a render JSON's "files" as a file of `render_dir`: a plain name (no separator,
    not . or ..) of a regular file whose real path lies in the render directory itself."""
    return source_entry(render_dir, name)[0]


def source_entry(render_dir: Path, name) -> tuple[Path, list[int]]:
    """source_file's path and its stat [size, mtime_ns, inode, device], from one lstat when the file
    is no link (the usual render folder: the dataset's re-run stats every record's image and mask)."""
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name \
            or "\0" in name:
        raise Refused(f"file name {name!r} is not a plain file name in its render directory")
    path = render_dir / name
    try:
        st = os.lstat(path)
    except OSError:
        st = None
    if st is not None and stat.S_ISREG(st.st_mode):   # no link: its real path is its folder's plus the name
        real = os.path.join(real_folder(render_dir), name)
    else:
        real = os.path.realpath(path)
        st = None
    if os.path.dirname(real) != real_folder(render_dir):
        raise Refused(f"file {name!r} resolves to {real}, outside its render directory {render_dir}")
    if st is None:
        try:
            st = os.stat(real)
        except OSError:
            st = None
        if st is None or not stat.S_ISREG(st.st_mode):
            raise Refused(f"file {name!r} is missing or not a regular file")
    return path, [st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev]


def inside(out: Path, rel: str) -> Path:
    """`out / rel`, refused (AlloError) unless its real path stays inside `out`: nothing is written
    or removed outside the dataset, whatever the manifest says or a symlinked folder points at."""
    path = Path(out) / rel
    top, real = real_folder(out), real_path(path)
    if os.path.isabs(rel) or not (real == top or real.startswith(top.rstrip(os.sep) + os.sep)):
        raise AlloError(f"{path} resolves to {real}, outside the dataset {out} (a symlinked folder, or a manifest "
                        f"row naming another place); fix: remove it, or assemble into a fresh --out")
    return path
