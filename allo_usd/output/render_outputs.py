"""The files a render of a scene layer writes, by name: one rule for the render job, the dispatcher's
index and the done rule (allo_usd.output.identity), so they never disagree about what a scene leaves.

A layer STEM writes STEM.png, STEM.exr, STEM_mask.png, STEM_depth.exr, STEM_normal.exr,
STEM_instance.png, STEM_amodal.png (those of its passes) and STEM.json (its render record,
allo_usd.output.record). They are collision-free by construction: a stem ending in a reserved suffix
(`_mask`, `_depth`, `_normal`, `_instance`, `_amodal`, in any case) is refused, and so are two stems
of one run equal up to case (file systems that ignore case). Then no name of one layer can be a name
of another (tests/run/test_render_identity.py checks every pair).
"""

from __future__ import annotations

import os
from pathlib import Path

from allo_usd.core.errors import LayerError
from allo_usd.usd.sniff import layer_outputs

RESERVED_SUFFIXES = ("_mask", "_depth", "_normal", "_instance", "_amodal")  # what output_paths appends to a stem
PASS_FILES = {"rgb": ".png", "exr": ".exr", "mask": "_mask.png", "depth": "_depth.exr", "normal": "_normal.exr",
              "instance": "_instance.png", "amodal": "_amodal.png"}  # pass -> what output_paths appends to a stem


def layer_stem(layer) -> str:
    """A layer's stem (Path.stem) without building a Path: a 51,409-layer run asks for it often."""
    if isinstance(layer, Path):
        return layer.stem
    name = os.path.basename(os.fspath(layer))
    i = name.rfind(".")
    return name[:i] if 0 < i < len(name) - 1 else name


def stem_problem(layer: Path) -> str | None:
    """Why `layer`'s outputs could take another layer's names (its stem ends in a reserved suffix), or None."""
    low = layer_stem(layer).lower()
    suffix = next((s for s in RESERVED_SUFFIXES if low.endswith(s)), None)
    if suffix is None:
        return None
    return (f"{layer}: a layer named ...{suffix} (in any case) is refused, since its outputs could take the "
            f"names of a layer {Path(layer).stem[:-len(suffix)]}.usda's {suffix[1:]} (outputs are STEM.png, "
            f"STEM.exr, STEM_mask.png, STEM_depth.exr, STEM_normal.exr, STEM_instance.png, STEM_amodal.png, "
            f"STEM.json); rename the layer so that its name does not end "
            f"in {' or '.join(RESERVED_SUFFIXES)}")


def check_output_names(layers) -> None:
    """Refuse, before anything renders, layers whose output names could collide: a stem ending in a
    reserved suffix, or two stems equal up to case (one output directory takes them all)."""
    seen: dict[str, Path] = {}
    for layer in layers:
        layer = layer if isinstance(layer, Path) else Path(layer)
        problem = stem_problem(layer)
        if problem:
            raise LayerError(problem)
        low = layer.stem.lower()
        if low in seen and seen[low] != layer:
            raise LayerError(f"layers {seen[low]} and {layer} have names that differ only in case; their outputs "
                             "would overwrite each other on a file system that ignores case: rename one")
        seen[low] = layer


def output_paths(layer: Path, out_dir: Path, outputs: tuple[str, ...] | None = None) -> dict[str, Path]:
    """Files one scene produces, one per pass it orders (PASS_FILES), plus the metadata JSON. A stem
    with a reserved suffix is a LayerError."""
    problem = stem_problem(Path(layer))
    if problem:
        raise LayerError(problem)
    stem = Path(layer).stem
    out_dir = Path(out_dir)
    outputs = layer_outputs(layer) if outputs is None else outputs
    paths = {p: out_dir / f"{stem}{PASS_FILES[p]}" for p in PASS_FILES if p in outputs}
    paths["meta"] = out_dir / f"{stem}.json"
    return paths

