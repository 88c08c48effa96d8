"""Where a scene layer may reach: every file a composed stage uses must lie under an allowed root.

A layer is data handed around (a dataset, a bug report), so opening one must not read files
elsewhere on the machine: no sublayer, reference, payload or texture may resolve outside

- the project's `stages/` directory (the shipped base stage and assets);
- the directory of the layer being opened (a scene layer and its neighbours);
- the authored tree the layer belongs to: for a layer inside the `scenes/` folder of the nearest
  enclosing directory holding a `plan.toml` (allo_usd.usd.compose: OUT/plan.toml beside
  OUT/scenes/, OUT/sky/, OUT/poses/, OUT/stages/, OUT/hazards/), those authored folders, and nothing else
  of OUT. A `plan.toml` in some ancestor of an unrelated layer (~/plan.toml over
  ~/Downloads/x.usda) makes no root: that would open ~ to it. A tree one of whose own folders
  (those, and schema/) is a symbolic link grants nothing: its layers are refused, exactly as
  `--tree` refuses such a tree (linked_folders), since `hazards -> /` would open every file;
- the directories named in the environment variable `ALLO_ASSET_ROOTS` (os.pathsep-separated).
  The dispatcher sets it to the directories of the layers it renders and the plan's output
  directory, so worker processes inherit the same rule;
- the trees a user names (`allo-usd render/inspect/diff LAYER --tree OUT`, `trees_granted`): for
  a layer of one's own outside a tree that sublayers a tree's scene layer. Each must be an
  authored tree (`OUT/plan.toml` or `OUT/stages/base.usda`), and grants what a tree grants its
  own scene layers: its authored folders, each of which must lie inside OUT after symbolic
  links are resolved, and nothing else of OUT (not OUT/private/). They reach the process's
  `ALLO_ASSET_ROOTS`, so render workers inherit them.

Paths are compared after resolving symbolic links, so a link inside a root that points outside
it is rejected too.

A package (.usdz, `allo-usd pack`) opened as the scene is one file whose contents are its own:
every layer and asset of its stage must lie inside that package (`PKG[entry]`), whatever the
roots say; the package file itself must lie inside the roots.

allo_usd.usd.dependencies applies these roots (and the file-type and size
rules) to every file before USD opens it; `check_stage` checks the composed stage again after.
Blender never auto-runs scripts (`blender.build.reset`), so a layer can only ever bring data,
never code.
"""

from __future__ import annotations

import os
import stat
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from allo_usd.core.errors import LayerError
from allo_usd.core.files import folder_realpath, memo_realpath
from allo_usd.core.paths import STAGES
from allo_usd.usd.tree import (BASE_STAGE_FILE, GRANTED_DIRS, LAYER_FOLDER_DIRS, POSE_DIR, SCENE_DIR, SCHEMA_DIR,
                               SKY_DIR, STAGE_DIR, TREE_PLAN, tree_base_stage)

LAYER_FILE_SUFFIXES = (".usda", ".usdc", ".usd")   # a layer's names (allo_usd.usd.dependencies.LAYER_EXTENSIONS)

ENV_ROOTS = "ALLO_ASSET_ROOTS"


def _tree_folders(tree: Path) -> tuple[Path, ...]:
    """The authored folders of a tree (OUT/scenes, sky, poses, stages, hazards): all a tree grants."""
    return tuple(tree / d for d in GRANTED_DIRS)


def linked_folders(tree: str | Path) -> list[tuple[Path, Path]]:
    """(folder, target) of each of a tree's own folders that is a symbolic link (to anywhere): the
    folders it grants (_tree_folders) and schema/, which `author` writes and compares. `tree` is a
    real path. A tree with one is granted nothing, whether the user names it (`--tree`, tree_roots)
    or a layer lies in it (allowed_roots): a `hazards -> /` link would otherwise open every file."""
    tree = Path(tree)
    found = []
    for folder in (*_tree_folders(tree), tree / SCHEMA_DIR):
        target = Path(os.path.realpath(folder))
        if target != folder:
            found.append((folder, target))
    return found


def is_authored_tree(path: str | Path) -> bool:
    """A folder `allo-usd author` wrote: it holds plan.toml or stages/base.usda (regular files)."""
    path = Path(path)
    return (path / TREE_PLAN).is_file() or tree_base_stage(path).is_file()


def is_layer_folder(path: str | Path) -> bool:
    """A tree of the demo's shape (`allo-usd demo`'s OUT/layers, allo_usd.run.demo): its scene layers
    lie at its top, beside sky/, poses/, stages/base.usda and schema/, with no plan.toml and no
    scenes/ folder."""
    path = Path(path)
    return tree_base_stage(path).is_file() and not (path / TREE_PLAN).is_file() and not (path / SCENE_DIR).is_dir()


def _top_layers(tree: Path) -> tuple[Path, ...]:
    """The layer files at the top of a demo-shaped tree (regular files, not symbolic links): its scene
    layers, each granted by itself, so that nothing else at its top (a private/ folder) is."""
    found = []
    for entry in sorted(os.scandir(tree), key=lambda e: e.name):
        if entry.name.lower().endswith(LAYER_FILE_SUFFIXES) and entry.is_file(follow_symlinks=False):
            found.append(tree / entry.name)
    return tuple(found)


def tree_grants(tree: Path) -> tuple[Path, ...]:
    """What a tree grants its own scene layers: an authored tree its authored folders
    (_tree_folders); a demo-shaped tree (is_layer_folder) its top-level scene layers and its
    sky/, poses/, stages/ and schema/."""
    if is_layer_folder(tree):
        return (*_top_layers(tree), *(tree / d for d in LAYER_FOLDER_DIRS))
    return _tree_folders(tree)


def _grant_text(tree: Path) -> str:
    if is_layer_folder(tree):
        return (f"its scene layers (the layer files at its top), {', '.join(d + '/' for d in LAYER_FOLDER_DIRS)}")
    return ", ".join(d + "/" for d in GRANTED_DIRS)


def tree_roots(tree: str | Path, option: str = "--tree") -> tuple[Path, ...]:
    """The roots that naming `tree` grants (its authored folders, real paths), or a LayerError
    when `tree` is not an authored tree or one of its folders links outside it."""
    real = Path(os.path.realpath(tree))
    if not real.is_dir():
        raise LayerError(f"{option} {tree} is not a directory; pass the folder `allo-usd author` wrote (OUT, which "
                         f"holds {TREE_PLAN}, {SCENE_DIR}/, {SKY_DIR}/, {POSE_DIR}/ and {STAGE_DIR}/)")
    if not is_authored_tree(real):
        raise LayerError(f"{option} {tree} is not an authored tree (it holds neither {TREE_PLAN} nor "
                         f"{STAGE_DIR}/{BASE_STAGE_FILE}); pass the folder `allo-usd author` wrote (OUT, not a "
                         f"folder inside it) or the demo's OUT/layers, or add the directory your layer needs to "
                         f"{ENV_ROOTS}")
    for folder, target in linked_folders(real):
        raise LayerError(f"{option} {tree}: {folder} is a symbolic link to {target}; a tree grants only its own "
                         f"folders: replace the link with the folder's files, or add {target} to {ENV_ROOTS}")
    return tree_grants(real)


@contextmanager
def trees_granted(trees, option: str = "--tree"):
    """For the block, also allow the authored folders of each tree in `trees` (tree_roots), in this
    process and in the render workers it starts (they inherit ALLO_ASSET_ROOTS). Every tree is
    checked before anything is granted."""
    roots = [str(r) for t in trees for r in tree_roots(t, option)]
    if not roots:
        yield
        return
    prior = os.environ.get(ENV_ROOTS)
    os.environ[ENV_ROOTS] = os.pathsep.join([*roots, *([prior] if prior else [])])
    try:
        yield
    finally:
        if prior is None:
            os.environ.pop(ENV_ROOTS, None)
        else:
            os.environ[ENV_ROOTS] = prior


def _tree_of(path: str | Path) -> Path | None:
    """The authored tree whose authored folders hold `path` (after realpath), if any."""
    real = Path(os.path.realpath(path))
    for d in real.parents:
        if is_authored_tree(d) and any(f == real or f in real.parents for f in tree_grants(d)):
            return d
    return None


def in_tree_folder(path: str | Path) -> bool:
    """Does `path` lie in one of an authored tree's own folders (scenes/, sky/, poses/, stages/,
    hazards/, schema/): a file the project wrote there?"""
    real = Path(os.path.realpath(path))
    return any(is_authored_tree(d.parent) for d in real.parents
               if d.name in (*GRANTED_DIRS, SCHEMA_DIR) and d.parent != d)


def _named_trees(roots) -> list[Path]:
    """The trees among `roots` a layer was granted (by `--tree`, or as its own tree): every tree
    grants its stages/, so a granted stages/ other than the package's names its tree."""
    package = Path(os.path.realpath(STAGES))
    return [r.parent for r in roots if r.name == STAGE_DIR and r != package and is_authored_tree(r.parent)]


def _plan_root(layer_path: Path) -> Path | None:
    """The top of the authored tree whose `scenes/` folder holds the layer, if any."""
    real = Path(os.path.realpath(layer_path))
    for d in real.parents:
        if (d / TREE_PLAN).is_file() and (d / SCENE_DIR) in real.parents:
            return d
    return None


_ROOTS_CACHE: ContextVar[dict | None] = ContextVar("allo_roots_cache", default=None)


@contextmanager
def roots_cached(cache: dict | None = None):
    """For the block, in this thread only, allowed_roots answers from `cache` (if None: the
    enclosing block's, else a new one; pass the same dict to blocks of one decision to share it),
    and so do real_path's folders and check_root: computed once per
    (layer folder, extra roots, ALLO_ASSET_ROOTS, working directory) instead of ~20 realpath calls a
    layer. For a decision over many layers of one tree (the dispatcher's scan and resume check: the
    paper plan's 51,409 layers lie in a few folders). A tree folder turned into a symbolic link
    during the block is still refused where it matters: a render worker (another process or
    thread) checks its layer afresh. A layer that is itself a symbolic link is never cached (its
    tree is its target's)."""
    if cache is None:   # a block inside another joins it: one decision, one cache
        cache = _ROOTS_CACHE.get()
    token = _ROOTS_CACHE.set({} if cache is None else cache)
    try:
        yield
    finally:
        _ROOTS_CACHE.reset(token)


def _roots_key(layer_path: str | Path, extra) -> tuple | None:
    try:
        if stat.S_ISLNK(os.lstat(layer_path).st_mode):
            return None
    except OSError:
        return None
    return (os.getcwd(), os.path.dirname(os.fspath(layer_path)) or ".", tuple(map(str, extra)),
            os.environ.get(ENV_ROOTS, ""))


def allowed_roots(layer_path: str | Path, extra: tuple[str | Path, ...] = ()) -> tuple[Path, ...]:
    cache = _ROOTS_CACHE.get()
    key = _roots_key(layer_path, extra) if cache is not None else None
    if key is not None and key in cache:
        return cache[key]
    roots = [STAGES, Path(layer_path).parent, *extra]
    plan_root = _plan_root(Path(layer_path))
    if plan_root is not None:  # a plan's output tree (open_tree writes plan.toml at its top): its authored folders
        for folder, target in linked_folders(plan_root):   # refused as `--tree` refuses them (tree_roots)
            raise LayerError(f"{layer_path}: its authored tree {plan_root} has {folder.name}/ as a symbolic link to "
                             f"{target}, and a tree's layers may read only the tree's own folders; fix: replace the "
                             "link with the folder's files")
        roots += _tree_folders(plan_root)
    roots += [Path(p) for p in os.environ.get(ENV_ROOTS, "").split(os.pathsep) if p]
    out = []
    for r in roots:
        real = Path(os.path.realpath(r))
        if real not in out:
            out.append(real)
    out = tuple(out)
    if key is not None:
        cache[key] = out
    return out


def decision_cache() -> dict | None:
    """The cache of the roots_cached block this thread is in, or None outside one."""
    return _ROOTS_CACHE.get()


def real_path(path: str | Path) -> str:
    """os.path.realpath(path); inside a roots_cached block, a path that is not itself a symbolic
    link resolves as its folder (resolved once per block) joined with its name: one lstat instead
    of one per component (a 51,409-layer resume check resolves each layer and its inputs several
    times). A link, or a path whose lstat fails, resolves in full. A folder turned into a link
    during the block is seen as it was; a render worker checks its layer afresh."""
    return memo_realpath(path, _ROOTS_CACHE.get())


def real_folder(folder: str) -> str:
    """os.path.realpath of a folder, once per roots_cached block (real_path's folders)."""
    return folder_realpath(os.path.abspath(folder), _ROOTS_CACHE.get())


def inside(path: str, roots: tuple[Path, ...]) -> bool:
    """Does the real path of `path` lie in (or equal) one of `roots` (real paths)? Compared as
    strings: a root's path and a separator prefix the path of everything below it."""
    return inside_real(real_path(path), roots)


def inside_real(real: str, roots: tuple[Path, ...]) -> bool:
    """inside() for a path already resolved (os.path.realpath, real_path)."""
    for r in roots:
        top = str(r)
        if real == top or real.startswith(top if top.endswith(os.sep) else top + os.sep):
            return True
    return False


SHOWN_ROOTS = 2  # roots a refusal names; the rest are counted (a tree grants five folders, and each is a long path)


def roots_text(roots, shown: int = SHOWN_ROOTS) -> str:
    """The first `shown` of `roots`, then how many more: a refusal stays one readable line."""
    roots = [str(r) for r in roots]
    more = len(roots) - shown
    return ", ".join(roots[:shown]) + (f" and {more} more" if more > 0 else "")


def reject(what: str, path: str, layer_path, roots) -> None:
    """The one line for a file outside the roots: the file, the rule (its first roots) and the fix
    that fits where the file lies (an authored tree not named, a tree folder not granted, no tree)."""
    tree = _tree_of(path)
    real = Path(os.path.realpath(path))
    named = _named_trees(roots)
    holder = next((t for t in named if t in real.parents), None)
    if tree is not None:
        fix = (f"it belongs to the authored tree {tree}: name that tree with `--tree {tree}`, or add its folder to "
               f"{ENV_ROOTS}")
    elif holder is not None:   # inside a tree that was granted, but not in what a tree grants
        fix = (f"the tree {holder} grants only {_grant_text(holder)}, not {real.relative_to(holder).parts[0]}: move "
               f"the file into one of those, or add its folder to {ENV_ROOTS}")
    elif named:
        fix = (f"no tree granted ({roots_text(named, 1)}) holds it: move the file into a granted tree, or add its "
               f"folder to {ENV_ROOTS}")
    else:
        fix = (f"move the file under one of them, name its authored tree with `--tree OUT`, or add its folder to "
               f"{ENV_ROOTS}")
    raise LayerError(f"{layer_path}: {what} {path} resolves outside the allowed roots ({roots_text(roots)}); {fix}")


def in_package(path: str, package: str) -> bool:
    """`path` is the package (real path `package`) or an entry of it (`PKG[entry]`, not nested)."""
    from pxr import Ar

    if not Ar.IsPackageRelativePath(path):
        return os.path.realpath(path) == package
    outer, inner = Ar.SplitPackageRelativePathOuter(path)
    return os.path.realpath(outer) == package and not Ar.IsPackageRelativePath(inner)


def reject_outside_package(what: str, path: str, layer_path) -> None:
    raise LayerError(f"{layer_path}: {what} {path} lies outside the package; a package (.usdz) may use only the "
                     "files it holds: pack the scene with `allo-usd pack LAYER --out SCENE.usdz`, which takes in "
                     "every file the scene reads")


def check_stage(stage, layer_path: str | Path, extra: tuple[str | Path, ...] = ()) -> None:
    """Raise LayerError if any layer in the stack or any asset-valued attribute leaves the roots
    (for a package, the package)."""
    from pxr import Sdf, Usd

    roots = allowed_roots(layer_path, extra)
    package = os.path.realpath(layer_path) if str(layer_path).lower().endswith(".usdz") else None

    def outside(path: str) -> bool:
        return not in_package(path, package) if package else not inside(path, roots)

    def refuse(what: str, path: str) -> None:
        if package:
            reject_outside_package(what, path, layer_path)
        reject(what, path, layer_path, roots)

    for layer in stage.GetUsedLayers():
        if layer.anonymous:
            continue
        real = layer.realPath
        if real and outside(real):
            refuse("layer", real)
    asset_types = (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray)
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        for attr in prim.GetAttributes():
            if attr.GetTypeName() not in asset_types or not attr.HasAuthoredValue():
                continue
            value = attr.Get()
            for asset in (value if attr.GetTypeName() == Sdf.ValueTypeNames.AssetArray else [value]):
                if asset is None:
                    continue
                resolved = asset.resolvedPath
                if resolved and outside(resolved):
                    refuse(f"asset {attr.GetPath()} =", resolved)
                elif not resolved and asset.path and os.path.isabs(asset.path) and outside(asset.path):
                    refuse(f"asset {attr.GetPath()} =", asset.path)
