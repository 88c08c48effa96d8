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

Names resolve on first use, so `import allo_usd` loads neither pxr nor bpy.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

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
    "render_scene": ("allo_usd.blender.render", "render_scene"),
    "render_layer": ("allo_usd.run.job", "render_layer"),
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
