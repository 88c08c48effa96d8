"""What a rendered scene leaves behind and when it counts as done: one rule for `allo-usd render
LAYER`, the dispatcher's resume and the demo, so they never disagree about what to skip."""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

from allo_usd.core.errors import DiskFullError
from allo_usd.core.files import DISK_FULL_ERRNOS, atomic_path, sha256_file, temp_name_re
from allo_usd.usd.read import layer_outputs

MANIFEST = "manifest.jsonl"
WORKDIR = ".allo-tmp"  # Blender's render files, one directory per worker pid


def output_paths(layer: Path, out_dir: Path, outputs: tuple[str, ...] | None = None) -> dict[str, Path]:
    """Files one scene produces, by the render vars it orders (PNG + EXR for color, the class mask,
    a float32 depth EXR), plus the metadata JSON."""
    stem = Path(layer).stem
    out_dir = Path(out_dir)
    outputs = layer_outputs(layer) if outputs is None else outputs
    paths = {}
    if "color" in outputs:
        paths.update(rgb=out_dir / f"{stem}.png", exr=out_dir / f"{stem}.exr")
    paths["mask"] = out_dir / f"{stem}_mask.png"
    if "depth" in outputs:
        paths["depth"] = out_dir / f"{stem}_depth.exr"
    paths["meta"] = out_dir / f"{stem}.json"
    return paths


def is_done(layer: Path, out_dir: Path, manifest: dict[str, dict] | None = None) -> bool:
    """True when `out_dir` holds every output of `layer` rendered from its current bytes.

    With a `manifest` (scene name -> row, from load_manifest: a dispatch run) the scene must have
    a row there, and every output's checksum must match it. Without one (a single layer, the demo)
    every output must exist and the metadata JSON, written last, must name the layer's sha256:
    a changed layer (another resolution, say) is rendered again."""
    if manifest is not None:
        return is_verified(manifest.get(Path(layer).stem), layer, out_dir)
    paths = output_paths(layer, out_dir)
    if not all(p.is_file() for p in paths.values()):
        return False
    try:
        recorded = json.loads(paths["meta"].read_text()).get("layer_sha256")
    except (OSError, json.JSONDecodeError, UnicodeDecodeError, AttributeError):
        return False
    return recorded == sha256_file(layer)


def is_verified(row: dict | None, layer: Path, out_dir: Path) -> bool:
    """The manifest row matches the current layer and every output exists with its checksum."""
    if not row or row.get("layer_sha256") != sha256_file(layer):
        return False
    files = row.get("files") or {}
    expected = {p.name for p in output_paths(layer, out_dir).values()}
    if set(files) != expected:
        return False
    return all((Path(out_dir) / name).is_file() and sha256_file(Path(out_dir) / name) == digest
               for name, digest in files.items())


# ---------------------------------------------------------------- manifest.jsonl

def read_jsonl(path: Path) -> list[dict]:
    rows = []
    if path.is_file():
        for line in path.read_text(errors="replace").splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line torn by a crash mid-append
            if isinstance(row, dict) and "scene" in row:
                rows.append(row)
    return rows


def load_manifest(out_dir: Path) -> dict[str, dict]:
    """Finished scenes by name (the last row of a scene wins)."""
    return {row["scene"]: row for row in read_jsonl(Path(out_dir) / MANIFEST)}


def append_jsonl(path: Path, row: dict) -> None:
    """One os.write of one line on an O_APPEND descriptor, then fsync: a crash loses at most the line.
    A line torn by an earlier crash is ended first, so it cannot swallow this one; a write cut
    short by a full disk is truncated away, so the file never ends in half a line."""
    data = (json.dumps(row, sort_keys=True) + "\n").encode()
    fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        size = os.fstat(fd).st_size
        try:
            if size and os.pread(fd, 1, size - 1) != b"\n":
                data = b"\n" + data
            if os.write(fd, data) != len(data):
                raise OSError(errno.ENOSPC, "short write", str(path))
            os.fsync(fd)
        except OSError as exc:
            if exc.errno in DISK_FULL_ERRNOS:
                try:
                    os.ftruncate(fd, size)
                except OSError:
                    pass
                raise DiskFullError(f"no space left on the device while appending to {path}; free space and "
                                    "re-run") from exc
            raise
    finally:
        os.close(fd)


def compact_manifest(out_dir: Path) -> None:
    """Rewrite the manifest with one row per scene (atomically), dropping torn lines and repeats."""
    path = Path(out_dir) / MANIFEST
    if not path.is_file():
        return
    rows = load_manifest(out_dir)
    text = "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows.values())
    if text != path.read_text(errors="replace"):
        with atomic_path(path) as tmp:
            tmp.write_text(text)


def clean_stale(out_dir: Path, pid: int | None = None) -> int:
    """Remove temporaries left by killed writers (only those of writer `pid` when given: the
    others may belong to live workers); returns how many files beside the outputs went."""
    out_dir = Path(out_dir)
    pattern = temp_name_re(pid)
    n = 0
    if out_dir.is_dir():
        for p in out_dir.iterdir():
            if pattern.match(p.name) and p.is_file():
                p.unlink(missing_ok=True)
                n += 1
    shutil.rmtree(out_dir / WORKDIR if pid is None else out_dir / WORKDIR / str(int(pid)), ignore_errors=True)
    return n
