"""Authoring by composition: shared sky and camera-sample layers, and small scene layers over them.

A plan of 51,409 scenes has only 365 skies and ~39,000 camera samples, so what a day or a
camera sample decides is written once and reused (each folder's and file's name, and each layer's
path: allo_usd.usd.tree):

    OUT/stages/base.usda (+ station/, bodies/, anomalies/)  the tree's own copy of the base stage
    OUT/sky/dDDD.usda                          sun light, bodies, eclipse state, epoch (per day)
    OUT/poses/sSEED/dDDD_pPP[_ASSET-VARIANT].usda  camera transform, offsets, attempts (per sample)
    OUT/scenes/SPLIT/KIND/SCENE_ID.usda        subLayers = [its pose layer, its sky layer, base]
    OUT/hazards/ID/ID.usda (+ ID/, source.json) a plan's own hazard, converted (allo_usd.usd.hazard)
    OUT/schema/plugInfo.json, generatedSchema.usda  the Allo*API schemas' codeless plugin

A scene layer adds only its own opinions (identity and seed, anomaly, effects, render settings),
so it stays under 4 KB, and the five depths of one anomaly placement share one pose layer. Every
layer carries defaultPrim, upAxis and metersPerUnit. The tree is self-contained: it holds its
own byte copy of the base stage and its assets (`copy_base_stage`), and every sublayer and
reference is a relative path that stays inside the tree. So the same plan gives the same bytes
wherever it is authored, and a copied or moved tree opens in any USD tool as it is. A tool
that should also see the Allo*API schemas applied (their fallbacks, `HasAPI`) points USD at the
tree's plugin, `PXR_PLUGINPATH_NAME=OUT/schema` (`copy_schema`): its paths are relative to its
own folder, so it moves with the tree. It is not a composition input (no layer names it).
"""

from __future__ import annotations

import filecmp
import os
import shutil
from pathlib import Path

from allo_usd.core.files import atomic_directory, folder_realpath, memo_realpath, relpath
from allo_usd.scene.spec import CameraSpec, SceneSpec, SunSpec
from allo_usd.usd.scene_layer import (anomaly_asset_path, check_base_stage, pose_prims, scene_custom, scene_prims,
                                      sky_prims, validate_spec)
from allo_usd.usd.usda_writer import write_layer
from allo_usd.usd.tree import tree_base_stage, tree_schema


def base_stage_files(base_stage: Path) -> list[str]:
    """Every file the base stage and its anomaly assets use, relative to the base stage's directory
    (usd-core's dependency walk). A file outside that directory cannot be copied along with it."""
    from pxr import Sdf, UsdUtils

    from allo_usd.core.errors import LayerError

    base_stage = check_base_stage(base_stage).resolve()
    root = base_stage.parent
    files: set[str] = set()
    for src in (base_stage, *sorted((root / "anomalies").glob("*.usda"))):
        layers, assets, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(src)))
        if unresolved:
            raise LayerError(f"{src} refers to files that do not exist: {', '.join(unresolved[:3])}; "
                             "regenerate the base stage (scripts/make_base_stage.py)")
        for f in [layer.realPath for layer in layers] + list(assets):
            rel = os.path.relpath(os.path.realpath(f), root)
            if rel.startswith(".."):
                raise LayerError(f"{src} uses {f}, outside its directory {root}; a base stage must hold "
                                 "every file it uses below its own directory so that it can be copied")
            files.add(Path(rel).as_posix())
    return sorted(files)


def copy_base_stage(base_stage: Path, out_dir: Path) -> Path:
    """Give the tree under `out_dir` its own byte copy of `base_stage` and the files it uses, at
    `out_dir/stages` (`_copy_into_tree`)."""
    base_stage = check_base_stage(base_stage).resolve()
    dest = tree_base_stage(out_dir)
    if dest.is_file() and os.path.samefile(dest, base_stage):
        return dest  # the plan already names the tree's own copy
    _copy_into_tree(base_stage.parent, base_stage_files(base_stage), dest.parent, out_dir)
    return dest


def copy_schema(out_dir: Path) -> Path:
    """Give the tree under `out_dir` a byte copy of the codeless schema plugin (plugInfo.json and
    generatedSchema.usda, allo_usd.usd.schema.PLUGIN) at `out_dir/schema`, so that plain usd-core
    with `PXR_PLUGINPATH_NAME=out_dir/schema` applies the Allo*API schemas (`_copy_into_tree`)."""
    from allo_usd.usd.schema import PLUGIN, PLUGIN_FILES

    from allo_usd.usd.schema import extends_copy

    dest = tree_schema(out_dir)
    _copy_into_tree(PLUGIN, list(PLUGIN_FILES), dest, out_dir, older=extends_copy)
    return dest


def _copy_into_tree(src: Path, files: list[str], dest: Path, out_dir: Path, older=None) -> None:
    """Copy `files` (relative to `src`) to `dest` (copied to a temporary directory, then renamed: a
    killed copy leaves nothing under the final name). An existing copy is kept if it matches the
    source byte for byte; one that differs is an error, since the tree's layers were authored with it,
    unless `older(dest)` says the source extends it (the schema, whose later versions only add
    attributes): then each differing file is replaced by the source's, atomically."""
    from allo_usd.core.errors import LayerError
    from allo_usd.core.files import atomic_path

    if dest.exists():
        differ = [f for f in files if not (dest / f).is_file()
                  or not filecmp.cmp(src / f, dest / f, shallow=False)]
        if differ and older is not None and not os.path.islink(dest) and older(dest):
            for f in differ:
                with atomic_path(dest / f) as tmp:
                    shutil.copyfile(src / f, tmp)
            return
        if differ:
            raise LayerError(f"{dest} is not a copy of {src} ({len(differ)} files differ, "
                             f"e.g. {differ[0]}); the layers under {out_dir} were authored with that copy. "
                             "Fix: author into a new directory, or delete the old tree")
        return
    with atomic_directory(dest) as tmp:
        for f in files:
            (tmp / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / f, tmp / f)


def _inside(top: str, target: str, once) -> bool:
    """Whether absolute, normalised `target` is `top` or lies below it (os.path.commonpath's rule),
    decided per folder (`once`: TreeLinks.once, so a run's few folders are each decided once): a
    path below `top` is `top` itself or one whose folder is `top` or below it."""
    folder = os.path.dirname(target)
    return target == top or once(("inside", top, folder), lambda: os.path.commonpath([top, folder]) == top)


def _uncached(key: tuple, make):
    """TreeLinks.once without a run to remember answers in: make()."""
    return make()


def write_sky_layer(path: Path, *, day: int, epoch: str, perilune_epoch: str, sun: SunSpec, bodies: dict,
                    joints: dict[str, float] | None = None) -> Path:
    """The shared layer of one day: everything the sky decides, and with `joints` (a plan that
    tracks the Sun) the station's joint angles that day."""
    return write_layer(path, sky_prims(epoch, perilune_epoch, day, sun, bodies, joints), [],
                       {"day": int(day), "epoch": epoch}, f"allo-usd sky of day {day} ({epoch})")


def write_pose_layer(path: Path, *, pose: int, camera: CameraSpec, seed: int, seed_path: str, sample_id: str) -> Path:
    """The shared layer of one perturbed camera sample (all depths of a placement use it)."""
    return write_layer(path, pose_prims(pose, camera), [],
                       {"seed": int(seed), "seedPath": seed_path, "sampleId": sample_id},
                       f"allo-usd camera sample {sample_id}")


class TreeLinks:
    """`allo_usd.core.files.relpath` for the many layers of one authoring run, each directory resolved
    once. relpath resolves both ends with every symlink followed: about 1 ms for the three or four
    paths of each scene layer, the largest single cost of a normal scene. A layer's directory is one
    of a handful (scenes/SPLIT/KIND, poses/sSEED, sky, stages, ...), so its resolution is kept; the
    file itself is resolved in full when it is a symlink, so the result is relpath's in every case
    (tests/usd/test_compose.py compares them, symlinked trees included)."""

    def __init__(self):
        self._dirs: dict = {}   # core.files.folder_realpath's memo
        self._once: dict = {}   # once()'s answers, by key

    def once(self, key: tuple, make):
        """make()'s answer for `key`, computed the first time it is asked in this run: a scene layer's
        checks and paths that repeat over thousands of layers (the base stage exists, a built-in
        asset's file, a target lies inside the tree, a relative path). An error is not kept."""
        try:
            return self._once[key]
        except KeyError:
            value = self._once[key] = make()
            return value

    @staticmethod
    def _absolute(path) -> str:
        """`path` made absolute but not normalised, as realpath takes it (it resolves a link before the
        ".." after it)."""
        p = os.fspath(path)
        return p if os.path.isabs(p) else os.path.join(os.getcwd(), p)

    def real(self, path) -> str:
        """os.path.realpath(path), its directory's resolution cached."""
        return memo_realpath(path, self._dirs)

    def relpath(self, target, start) -> str:
        """`allo_usd.core.files.relpath(target, start)` (the same string)."""
        rel = os.path.relpath(self.real(target), folder_realpath(self._absolute(start), self._dirs))
        rel = rel if os.sep == "/" else Path(rel).as_posix()   # a string op: ~20,000 layers name ~90,000 paths
        return rel if rel.startswith(".") else f"./{rel}"


def write_composed_scene(spec: SceneSpec, path: Path, *, pose_layer: Path, sky_layer: Path,
                         base_stage: Path, root: Path | None = None, anomaly_asset: Path | None = None,
                         links: TreeLinks | None = None) -> Path:
    """A scene layer holding only its own opinions, stacked on its pose, sky and base layers.
    With `root` (the top of the output tree), every file the layer names must lie inside it.
    `anomaly_asset`: the interface layer of a plan's own hazard (allo_usd.usd.hazard), else the base
    stage's built-in asset is referenced. `links`: a run's TreeLinks (the same paths, computed faster)."""
    validate_spec(spec)
    path = Path(path)
    once = _uncached if links is None else links.once
    base_stage = once(("base", os.fspath(base_stage)), lambda: check_base_stage(base_stage))
    here = path.parent
    targets = [pose_layer, sky_layer, base_stage]
    if spec.anomaly is not None:
        asset = spec.anomaly.asset
        targets.append(Path(anomaly_asset) if anomaly_asset is not None else
                       once(("asset", os.fspath(base_stage), asset), lambda: anomaly_asset_path(base_stage, asset)))
    if root is not None:
        from allo_usd.core.errors import LayerError

        top = os.path.abspath(root)
        for t in (path, *targets):
            if not _inside(top, os.path.abspath(t), once):
                raise LayerError(f"{path} would refer to {t}, outside its tree {root}; fix: copy the base stage "
                                 f"into the tree first (allo_usd.usd.compose.copy_base_stage)")
    own = relpath if links is None else links.relpath

    def rel(t) -> str:   # a target many layers name (sky, base stage, asset): its path kept for the run
        return once(("relpath", os.fspath(t), os.fspath(here)), lambda: own(t, here))

    ref = "" if spec.anomaly is None else rel(targets[3])
    sublayers = [own(pose_layer, here), rel(sky_layer), rel(base_stage)]
    return write_layer(path, scene_prims(spec, ref), sublayers, scene_custom(spec),
                       f"allo-usd scene {spec.scene_id}")
