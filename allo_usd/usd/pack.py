"""One scene as one file: a scene layer and every file its composition reads, as a USD package
(.usdz), to send one sample to a colleague or attach it to a bug report. Uses pxr only.

`pack(LAYER, OUT)` (`allo-usd pack LAYER --out SCENE.usdz`):

- the layer passes the gate a render applies first (allo_usd.usd.read.open_stage: the sandbox walk
  of allo_usd.usd.dependencies, a stage that composes, the composed stage inside the roots);
- every file USD's packager would take (`UsdUtils.ComputeAllDependencies`: it also follows asset
  paths in metadata, which a render never reads) must be one the walk checked, and none may be
  unresolved: a hostile layer cannot pull an outside file into the package, and a package never
  lacks a file;
- `UsdUtils.CreateNewUsdzPackage` writes it (paths inside rewritten relative to the package; a
  flattened layer would hold absolute texture paths instead) to a temporary beside OUT, with its zip
  timestamps fixed so that the same scene packs to the same bytes; the temporary is opened as a
  package scene (below) before it takes OUT's name: atomically, and never over an existing file
  unless `replace`, never through a symbolic link, never over anything but a regular file.

A package given as a scene (`allo-usd render SCENE.usdz`, `inspect`, `diff`) is one file whose
contents are its own: the walk checks that every path inside resolves inside the package
(allo_usd.usd.dependencies), the render identity hashes the package file, and textures, which
Blender reads from files only, are read through copies (allo_usd.usd.dependencies.unpacked_file)
in a private temporary directory removed when the process exits.
"""

from __future__ import annotations

import errno
import os
import re
import stat
import struct
from pathlib import Path

from allo_usd.core.errors import AlloError, DiskFullError, LayerError
from allo_usd.core.files import DISK_FULL_ERRNOS, ensure_output_file, temp_beside
from allo_usd.usd.dependencies import PACKAGE_EXTENSION, is_package

DOS_EPOCH = (0, (0 << 9) | (1 << 5) | 1)  # zip (time, date) fields: 1980-01-01 00:00, the earliest a zip says


CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")  # what USD refuses in an asset path (C0, DEL, C1)


def shown(path) -> str:
    """`path` on one line: each control character written as its escape (a newline as \\n)."""
    return CONTROL.sub(lambda m: repr(m[0])[1:-1], str(path))


def check_destination(out: str | Path, replace: bool = False, option: str = "--out") -> Path:
    """`out` may take a new package: its path holds no control character (USD refuses them in asset
    paths, so the packed temporary could not be opened); its name ends in .usdz; it is not a symbolic link (never
    followed, wherever it points); it does not exist, or (with `replace`) is a regular file; its
    directory can be written (created if missing). Else an AlloError naming the fix."""
    out = Path(out)
    control = CONTROL.search(os.path.abspath(out))
    if control:
        raise AlloError(f"{option} {shown(out)}: a package's path may not hold control characters (here "
                        f"{shown(control[0])}): USD refuses them in the paths it reads; choose a name without them")
    if out.suffix.lower() != PACKAGE_EXTENSION:
        raise AlloError(f"{option} {out}: a package's name must end in {PACKAGE_EXTENSION} (USD picks the file "
                        f"format by it); e.g. {option} {out.with_name(out.name + PACKAGE_EXTENSION)}")
    if os.path.islink(out):
        raise AlloError(f"{option} {out} is a symbolic link, which allo-usd never writes through; remove the link or "
                        "choose another name")
    if os.path.lexists(out):
        if not stat.S_ISREG(os.lstat(out).st_mode):
            raise AlloError(f"{option} {out} exists and is not a regular file (a directory, FIFO, device or socket); "
                            "choose another name")
        if not replace:
            raise AlloError(f"{option} {out} exists; pass --force to replace it, or choose another name")
    ensure_output_file(out, option)
    return out


def _walked_real(files) -> set[str]:
    return {os.path.realpath(f) for f in files}


def _metadata_assets(value, out: list) -> None:
    from pxr import Sdf

    if isinstance(value, Sdf.AssetPath):
        out.append(value)
    elif isinstance(value, dict):
        for v in value.values():
            _metadata_assets(v, out)
    elif isinstance(value, (list, tuple)) or type(value).__name__ == "AssetArray":
        for v in value:
            _metadata_assets(v, out)


def _check_metadata(layer_path: Path, files: list[str], read: set[str]) -> None:
    """An asset path held in metadata (customLayerData, assetInfo, ...), which the packager follows
    and a render never reads, must name a file the walk already checked: the packager would open
    it before anything else could refuse it."""
    from pxr import Ar, Sdf

    from allo_usd.usd.dependencies import LAYER_EXTENSIONS

    handled = {"default", "timeSamples", "references", "payload", "subLayers", "subLayerOffsets"}
    resolver = Ar.GetResolver()
    for f in files:
        if os.path.splitext(f)[1].lower() not in LAYER_EXTENSIONS:
            continue
        layer = Sdf.Layer.FindOrOpen(f)
        paths: list = [Sdf.Path.absoluteRootPath]
        layer.Traverse(Sdf.Path.absoluteRootPath, paths.append)
        for p in paths:
            spec = layer.GetObjectAtPath(p)
            for key in (spec.ListInfoKeys() if spec is not None else ()):
                if key in handled:
                    continue
                try:
                    value = spec.GetInfo(key)
                except TypeError:  # a type pxr has no Python form for (never an asset path)
                    continue
                found: list = []
                _metadata_assets(value, found)
                for asset in found:
                    if not asset.path:
                        continue
                    resolved = str(resolver.Resolve(layer.ComputeAbsolutePath(asset.path)))
                    if not resolved or os.path.realpath(resolved) not in read:
                        raise LayerError(f"{layer_path}: {f} holds the asset path {asset.path} in its metadata "
                                         f"({p} {key}), which a render never reads and a package would take in; "
                                         "remove it from the layer (a package holds only what the render reads)")


def _check_dependencies(layer_path: Path, read: set[str]) -> int:
    """What USD's packager takes is what the render reads: each of its files one the walk checked,
    none unresolved. Returns how many files it takes."""
    from pxr import Sdf, UsdUtils

    delegate = UsdUtils.CoalescingDiagnosticDelegate()  # its warnings are ours to word
    layers, assets, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(layer_path)))
    del delegate
    if unresolved:
        raise LayerError(f"{layer_path} names {len(unresolved)} file(s) that do not resolve, e.g. {unresolved[0]}; "
                         "restore them (or fix the paths) before packing: a package must hold every file")
    taken = [layer.realPath for layer in layers] + [str(a) for a in assets]
    for path in taken:
        if os.path.realpath(path) not in read:
            raise LayerError(f"{layer_path}: USD's packager would take {path}, which the render does not read; "
                             "remove the path from the layer (a package holds only what the render reads)")
    return len(taken)


def fix_timestamps(path: Path) -> None:
    """Set the modification time of every zip entry (local and central headers) to DOS_EPOCH, so
    that one scene packs to the same bytes at any time. Only those 4-byte fields change."""
    import zipfile

    with zipfile.ZipFile(path) as zf:
        infos = zf.infolist()
        central = zf.start_dir
    fields = struct.pack("<HH", *DOS_EPOCH)
    with open(path, "r+b") as f:
        for info in infos:
            f.seek(info.header_offset)
            if f.read(4) != b"PK\x03\x04":
                raise LayerError(f"{path}: USD wrote an unexpected zip layout; report this")
            f.seek(info.header_offset + 10)
            f.write(fields)
        offset = central
        for _ in infos:
            f.seek(offset)
            head = f.read(46)
            if head[:4] != b"PK\x01\x02":
                raise LayerError(f"{path}: USD wrote an unexpected zip layout; report this")
            f.seek(offset + 12)
            f.write(fields)
            n, m, k = struct.unpack("<HHH", head[28:34])
            offset += 46 + n + m + k


def _free_bytes(path: Path) -> int:
    """Bytes this process may still write on the device holding `path` (root counts the reserve)."""
    st = os.statvfs(path)
    return (st.f_bfree if os.geteuid() == 0 else st.f_bavail) * st.f_frsize


def _write_package(layer: Path, tmp: Path, out: Path, content: int) -> None:
    """USD's packager writes `layer`'s package to `tmp`. It reports no failed write: a full device
    leaves a package cut short (no zip directory at its end) that it calls a success. A package
    that is not a whole zip, or smaller than the `content` bytes it stores, is a DiskFullError
    naming `out` when the device is short of those bytes, else a LayerError."""
    import zipfile

    from pxr import Sdf, UsdUtils

    delegate = UsdUtils.CoalescingDiagnosticDelegate()  # the packager warns about paths it has just rewritten
    ok = UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(layer)), str(tmp))
    said = [d.commentary for d in delegate.TakeUncoalescedDiagnostics()]
    del delegate
    size = tmp.stat().st_size if tmp.is_file() else 0

    def full() -> DiskFullError | None:
        free = _free_bytes(tmp.parent)
        if free < max(content - size, 0) + (1 << 20):
            return DiskFullError(f"--out {out}: no space left on its device ({size:,} of about {content:,} bytes "
                                 f"written, {free:,} bytes free); free space or choose another directory, and re-run")
        return None

    if not ok or size == 0:
        raise full() or LayerError(f"USD could not write the package of {layer} "
                                   f"({said[-1] if said else 'no reason given'}); check the layer with `allo-usd "
                                   "inspect` and the --out directory")
    try:
        fix_timestamps(tmp)
    except (zipfile.BadZipFile, LayerError, EOFError, struct.error) as exc:
        raise full() or LayerError(f"--out {out}: USD wrote a package that is not a whole zip file ({size:,} bytes); "
                                   "check the --out directory's device and re-run") from exc


def pack(layer: str | Path, out: str | Path, replace: bool = False) -> dict:
    """Write the scene `layer` and every file its composition reads as the package `out` (see the
    module doc); returns {"path", "files", "bytes"}. Refuses (LayerError) a layer the render would
    refuse and (AlloError) an `out` that `check_destination` refuses."""
    from allo_usd.usd.dependencies import walk
    from allo_usd.usd.read import open_stage

    layer = Path(layer)
    if is_package(layer):
        raise AlloError(f"{layer} is already a package; copy it, or pack its scene layer")
    if not layer.exists():
        raise LayerError(f"scene layer {layer} does not exist; check the path")
    out = check_destination(out, replace)
    found = walk(layer)  # the render's gate: every file checked before USD opens it
    stage = open_stage(layer)  # composes, and stays inside its roots
    del stage
    read = _walked_real(found.files)
    _check_metadata(layer, found.files, read)
    files = _check_dependencies(layer, read)
    content = sum(os.stat(f).st_size for f in read)  # what the package stores, uncompressed
    tmp = temp_beside(out)
    try:
        _write_package(layer, tmp, out, content)
        open_stage(tmp)  # the package is a scene on its own: nothing outside it, nothing missing
        os.chmod(tmp, 0o644)
        if replace:
            os.replace(tmp, out)
        else:
            _link_new(tmp, out)
    except OSError as exc:
        if exc.errno in DISK_FULL_ERRNOS:
            raise DiskFullError(f"no space left on the device while writing {out}; free space and re-run") from exc
        raise
    finally:
        tmp.unlink(missing_ok=True)
    return {"path": out, "files": files, "bytes": out.stat().st_size}


def _link_new(tmp: Path, out: Path) -> None:
    """Give `tmp` the name `out` only if no file took that name meanwhile (a hard link fails on an
    existing name, where a rename would replace it); on a file system without hard links, check
    and rename."""
    try:
        os.link(tmp, out)
    except FileExistsError:
        raise AlloError(f"--out {out} exists (it appeared while packing); pass --force to replace it, or choose "
                        "another name") from None
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
            raise
        if os.path.lexists(out):
            raise AlloError(f"--out {out} exists (it appeared while packing); pass --force to replace it, or choose "
                            "another name") from None
        os.replace(tmp, out)


__all__ = ["pack", "check_destination", "fix_timestamps"]
