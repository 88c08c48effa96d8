"""allo-usd: the ALLO lunar-orbit anomaly dataset, authored as USD layers and rendered with Cycles.

The public API, in the order data flows (everything else is internal and may change):

    plan = allo_usd.load_plan("plan.toml")            # or paper_plan(), demo_plan(); save_plan(plan, path)
    tree = allo_usd.author_plan(plan, "out/tree")     # a self-contained tree of scene layers (Authored)
    layer = allo_usd.author_scene(plan, scene_id, "out/tree")  # one scene of a plan, with its shared layers
    desc = allo_usd.read_scene(layer)                 # the plain SceneDescription Blender builds (pxr only)
    result = allo_usd.render_scene(desc)              # Cycles -> arrays: RenderResult(rgb, mask, depth)
    meta = allo_usd.render_layer(layer, "out/renders")   # one layer -> PNG, EXR, mask, JSON files
    summary = allo_usd.render("out/tree", "out/renders", workers=2)  # many layers: local pool or Dask
    allo_usd.assemble_dataset(["out/renders"], "out/dataset")         # MVTec-AD layout + manifest

Names resolve on first use, so `import allo_usd` loads neither pxr nor bpy. Blender's own output
(its log lines, "Saved: ...", the GPU probe's CUEW/HIPEW warnings) goes to a log file, as from the
command line: OUT/logs/render.log for render_layer, OUT/logs/worker-N.log for render's workers, and
for render_scene (no output directory) $TMPDIR/allo-usd-UID/render.log; `log=` picks another file.
`render(..., workers=N)` starts its workers as their own programs, so a script that calls it needs
no `if __name__ == "__main__":` guard.
"""

from __future__ import annotations

from allo_usd.core.interrupts import Held as _Held

# A Ctrl-C while `allo-usd` starts (this package, then the command line's imports: typer) ends the
# command with one line and exit 130 (allo_usd.cli._loaded) instead of a traceback: held from here.
# Imported by anything else, the package hands a Ctrl-C that came meanwhile on at its end.
_LOADING = _Held().start()

import importlib  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

from allo_usd.core.version import __version__  # noqa: E402

# public name -> (module, attribute)
_API = {
    "Plan": ("allo_usd.plan.model", "Plan"),
    "load_plan": ("allo_usd.plan.io", "load_plan"),
    "save_plan": ("allo_usd.plan.io", "save_plan"),
    "paper_plan": ("allo_usd.plan.model", "paper_plan"),
    "demo_plan": ("allo_usd.plan.model", "demo_plan"),
    "enumerate_scenes": ("allo_usd.plan.enumeration", "enumerate_scenes"),
    "author_plan": ("allo_usd.run.author", "author"),
    "author_scene": ("allo_usd.run.author", "author_scene"),
    "read_scene": ("allo_usd.usd.read", "read_scene"),
    "SceneDescription": ("allo_usd.usd.description", "SceneDescription"),
    "render_scene": (__name__, "render_scene"),   # defined below: Blender's output to a log file
    "render_layer": (__name__, "render_layer"),
    "render": ("allo_usd.run.dispatch", "dispatch"),
    "assemble_dataset": ("allo_usd.output.dataset", "assemble"),
    "AlloError": ("allo_usd.core.errors", "AlloError"),
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    try:
        module, attr = _API[name]
    except KeyError:
        raise AttributeError(f"module 'allo_usd' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


def render_scene(desc, workdir=None, *, log=None):
    """Build `desc` (a SceneDescription) in Blender and render it with Cycles: a RenderResult of
    arrays (rgb linear, mask, depth), no files (allo_usd.blender.render.render_scene). Blender's own
    output goes to `log`, by default $TMPDIR/allo-usd-UID/render.log, not to the terminal."""
    if log is None:
        user = os.getuid() if hasattr(os, "getuid") else "user"
        log = Path(tempfile.gettempdir()) / f"allo-usd-{user}" / "render.log"
    return _logged(log, "allo_usd.blender.render", "render_scene", desc, workdir, first="bpy")


def render_layer(layer, out_dir, *args, log=None, **kwargs) -> dict:
    """Render one scene layer into `out_dir`: PNG, EXR, mask and the JSON metadata it returns (the
    arguments of allo_usd.run.job.render_layer: force, threads, device, passes, ...). Blender's own
    output goes to `log`, by default OUT_DIR/logs/render.log (as `allo-usd render LAYER`), not to the
    terminal; a device notice (an `auto` without a GPU) is shown once on stderr."""
    return _logged(Path(out_dir) / "logs" / "render.log" if log is None else log, "allo_usd.run.job", "render_layer",
                   layer, out_dir, *args, **kwargs)


def _logged(log, module: str, name: str, *args, first: str | None = None, **kwargs):
    """module.name(*args, **kwargs) with this process's stdout and stderr (file descriptors: Blender
    prints from C) appended to `log` (allo_usd.run.worker.output_to, what the CLI uses); the device
    notices printed meanwhile are shown on stderr afterwards, once each, as the CLI does. `first` is a
    library imported before, with Ctrl-C held (bpy swallows one that lands while it loads:
    allo_usd.core.interrupts)."""
    from allo_usd.core.interrupts import import_held
    from allo_usd.run.worker import output_to

    shown = set(_notices())
    try:
        with output_to(Path(log)):  # the imports too: bpy may print as it loads
            if first is not None:
                import_held(first)
            return getattr(importlib.import_module(module), name)(*args, **kwargs)
    finally:
        for text in _notices():
            if text not in shown:
                print(f"note: {text}", file=sys.stderr, flush=True)


def _notices() -> list[str]:
    device = sys.modules.get("allo_usd.blender.device")  # not loaded: no notice yet (and bpy stays unloaded)
    return device.noticed() if device is not None else []


if Path(getattr(sys, "argv", None) and sys.argv[0] or "").name != "allo-usd":   # not the console script
    _LOADING.release()
