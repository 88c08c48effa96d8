"""Save the Blender scene as built, so a user can open in Blender exactly what a layer became."""

from __future__ import annotations

from pathlib import Path

from allo_usd.core.errors import AlloError


def save_blend(path: Path) -> Path:
    """Write the current Blender scene to `path` (.blend) as a copy: the session keeps its own
    file name and state, so the render that follows is unchanged. A path Blender cannot write
    (a directory, an unwritable or impossible folder) is an AlloError that names it."""
    import bpy

    path = Path(path).resolve()
    if path.is_dir():
        raise AlloError(f"--save-blend {path} is a directory; fix: give a file name, e.g. {path / 'scene.blend'}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        result = bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True, check_existing=False)
    except (OSError, RuntimeError) as exc:  # bpy reports its own failures as RuntimeError
        raise AlloError(f"Blender could not save {path} ({exc}); fix: choose a writable directory") from None
    if "FINISHED" not in result or not path.is_file():
        raise AlloError(f"Blender could not save {path} ({result}); fix: choose a writable directory")
    return path
