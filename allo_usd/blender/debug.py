"""Save the Blender scene as built, so a user can open in Blender exactly what a layer became.

`render LAYER --save-blend FILE` writes a file the user names, so nothing already there may be
lost: `check_blend_target` refuses, before anything renders, a FILE that exists (unless
replacing is asked for), that is not a regular file (a directory, a FIFO, /dev/null), that is a
symbolic link (never written through, even when replacing: a link to a system file would make
that file a Blender scene) or that does not end in `.blend`. `save_blend` then writes the scene
beside FILE under a temporary name and renames it over FILE (allo_usd.core.files), so FILE is the
old file or the whole new scene, and Blender's own leftovers (its `@` temporary and the `.blend1`
backup it keeps of a file it overwrites) never appear.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from allo_usd.core.errors import AlloError, DiskFullError

BLEND_SUFFIX = ".blend"


def check_blend_target(path: Path, replace: bool = False, what: str = "--save-blend") -> Path:
    """`path` made absolute (its last part not resolved: a link there is refused, not followed) once
    it may receive a saved scene; else an AlloError naming it and the fix. Its directory is created
    and probed for writing (allo_usd.core.files.ensure_output_dir). `replace` (the command's
    --force) allows replacing an existing regular file, never anything else."""
    from allo_usd.core.files import ensure_output_dir

    path = Path(os.path.abspath(path))
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    except NotADirectoryError:   # a part of the path is a file: the directory check below names it
        st = None
    if st is not None:
        if stat.S_ISLNK(st.st_mode):
            raise AlloError(f"{what} {path} is a symbolic link; allo-usd never writes through one, even with --force; "
                            "fix: remove the link or choose another path")
        if stat.S_ISDIR(st.st_mode):
            raise AlloError(f"{what} {path} is a directory; fix: give a file name, e.g. {path / 'scene.blend'}")
        if not stat.S_ISREG(st.st_mode):
            raise AlloError(f"{what} {path} exists and is not a regular file (a device, a FIFO or a socket); fix: "
                            "choose a new file name ending in .blend")
        if not replace:
            raise AlloError(f"{what} {path} exists; fix: pass --force to replace it, or choose another name")
    if path.suffix.lower() != BLEND_SUFFIX:
        raise AlloError(f"{what} {path} does not end in {BLEND_SUFFIX}; fix: name the file "
                        f"{path.with_suffix(BLEND_SUFFIX).name} (Blender opens .blend files)")
    try:
        ensure_output_dir(path.parent, "its directory")
    except DiskFullError:
        raise
    except AlloError as exc:
        reason = str(exc).split(";")[0]
        raise AlloError(f"{what} {path}: could not save there: {reason}; fix: choose a path in a directory "
                        "you can write") from None
    return path


def save_blend(path: Path, replace: bool = False) -> Path:
    """Write the current Blender scene to `path` (.blend, check_blend_target) as a copy: the session
    keeps its own file name and state, so the render that follows is unchanged. Blender saves to a
    temporary beside `path` that does not exist yet (it would keep an existing one as a .blend1
    backup), which is renamed over `path`; a failure leaves `path` as it was and no temporary."""
    import bpy

    from allo_usd.core.files import commit_temp, temp_beside

    path = check_blend_target(path, replace)
    tmp = temp_beside(path, BLEND_SUFFIX)
    tmp.unlink()   # a unique name, free: Blender writes TMP@ and renames it to TMP
    leftovers = (tmp, Path(f"{tmp}1"), Path(f"{tmp}@"))
    try:
        try:
            result = bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True, check_existing=False)
        except (OSError, RuntimeError) as exc:  # bpy reports its own failures as RuntimeError
            raise AlloError(f"Blender could not save {path} ({exc}); fix: choose a writable directory") from None
        if "FINISHED" not in result or not tmp.is_file():
            raise AlloError(f"Blender could not save {path} ({result}); fix: choose a writable directory")
        check_blend_target(path, replace)   # still no link or directory there (it was checked before the render)
        commit_temp(tmp, path)
    finally:
        for p in leftovers:
            p.unlink(missing_ok=True)
    return path
