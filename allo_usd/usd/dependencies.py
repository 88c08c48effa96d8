"""Every file a scene layer's composition reads, checked before USD opens any of them.

`Usd.Stage.Open` reads every sublayer, reference and payload as it composes, so a check of the
composed stage (allo_usd.usd.safety.check_stage) comes too late: the file has been read, and a
parse error would quote it. `walk` goes first. From the root layer it checks each file before
anything opens it, then opens that one layer alone (`Sdf.Layer.FindOrOpen`, which composes
nothing) and goes on to the files it names:

- sublayers, references and payloads, including those inside variants
  (`GetCompositionAssetDependencies` covers every prim and variant spec);
- asset-valued attributes (textures), their defaults and time samples, in every spec of every
  layer, variants included.

Each path is anchored to the layer that names it (`Sdf.Layer.ComputeAbsolutePath`) and resolved
by USD's own resolver, as `Usd.Stage.Open` will. Each file must then
- resolve, after symbolic links, inside the allowed roots (allo_usd.usd.safety.allowed_roots);
- be a regular file (`os.stat` only: a FIFO, device or directory is never opened);
- hold at most MAX_LAYER_BYTES (a layer) or MAX_ASSET_BYTES (an asset): a sparse 2 GB
  sublayer once cost a worker 4.3 GB of memory;
- for a layer, end in a USD layer extension (.usda, .usdc, .usd).
Value clips and package (.usdz) paths are refused: no ALLO layer uses them and the walk does
not follow them. A refused file is named with the rule it breaks, never with its content.

The walk returns the files it read, root first (depth first, each file once): the inputs of a
render, whose checksums make its identity (allo_usd.run.manifest.render_identity). A layer's
own list of what it names is cached per process by (real path, mtime_ns, size, inode), so the
shared sky, pose and base layers of a tree are opened once per process, not once per scene; the
roots, sizes and file types are checked again on every walk.

What it cannot see: a file swapped between the check and USD's read (the walk narrows that
window, it does not close it), and what a custom ArResolver would resolve differently.
"""

from __future__ import annotations

import os
import re
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

from allo_usd.core.errors import LayerError
from allo_usd.core.files import file_problem
from allo_usd.usd.safety import allowed_roots, inside, reject

MAX_LAYER_BYTES = 256 << 20   # a scene layer is < 4 KB; the base stage's largest .usdc is a few MB
MAX_ASSET_BYTES = 256 << 20   # a texture; the shipped ones are < 1 MB
LAYER_EXTENSIONS = (".usda", ".usdc", ".usd")
CACHE_SIZE = 4096             # layers whose direct dependencies are remembered (LRU)

LAYER, ASSET = "layer", "asset"


@dataclass(frozen=True)
class _Named:
    """One file a layer names: its kind, what names it (for messages) and the identifier USD will
    resolve (anchored to the layer). Resolved on every walk, never cached: a file that appears
    later must be checked too."""
    kind: str
    what: str
    identifier: str


@dataclass
class Walk:
    """What `walk` found: the files read (real paths, root first) and the Sdf layers it opened
    for this walk (keep them alive across Usd.Stage.Open and USD parses none of them twice)."""
    files: list[str] = field(default_factory=list)
    layers: list = field(default_factory=list)


_NAMED: OrderedDict[tuple, tuple[_Named, ...]] = OrderedDict()


def stat_key(real: str) -> tuple:
    """What identifies a file's bytes without reading them: (real path, mtime_ns, size, inode)."""
    st = os.stat(real)
    return real, st.st_mtime_ns, st.st_size, st.st_ino


def _check(kind: str, what: str, path: str, layer_path, roots) -> str:
    """The real path of `path` if it may be read as a `kind`; else a LayerError naming the rule."""
    real = os.path.realpath(path)
    if not inside(real, roots):
        reject(what, path, layer_path, roots)
    problem = file_problem(real, MAX_LAYER_BYTES if kind == LAYER else MAX_ASSET_BYTES)
    if problem:
        raise LayerError(f"{layer_path}: {what} {path} {problem}; a layer may only use bounded regular files: fix the "
                         "layer (restore the file, point it at another, or remove the path)")
    if kind == LAYER and os.path.splitext(path)[1].lower() not in LAYER_EXTENSIONS:
        raise LayerError(f"{layer_path}: {what} {path} is not a USD layer (its name must end in "
                         f"{', '.join(LAYER_EXTENSIONS)}); point the layer at a USD file")
    return real


_TF_ENTRY = re.compile(r"Error in '[^']*' at line \d+ in file [^\n]*? : '(.*?)'\s*(?=\n\s*Error in |\Z)", re.S)
_FILE_LINE_COL = re.compile(r"\S+:\d+:\d+: ")
_NAMESPACE = re.compile(r"pxrInternal_v[0-9_]+?__pxrReserved__(?:::|_)")


def tf_message(exc) -> str:
    """The telling line of a Tf error, safe against bytes that are not UTF-8 (garbage layers).

    A Tf error lists its entries, each wrapped as "Error in 'FUNCTION' at line N in file
    SOURCE : 'MESSAGE'". A parse error's entry starts with USD's FILE:LINE:COL (the layer's own
    position); that one is kept, else the last entry. USD's C++ namespace is dropped."""
    try:
        text = str(exc)
    except UnicodeDecodeError:
        return "the file holds bytes that are not UTF-8"
    entries = [m.strip() for m in _TF_ENTRY.findall(text)]
    if entries:
        chosen = next((e for e in entries if _FILE_LINE_COL.match(e)), entries[-1])
    else:
        lines = text.strip().splitlines()
        chosen = lines[-1].strip() if lines else type(exc).__name__
    return _NAMESPACE.sub("", chosen)


def _used_by(identifier: str, layer_path) -> str:
    same = os.path.abspath(identifier) == os.path.abspath(layer_path)
    return identifier if same else f"{identifier} (used by {layer_path})"


def _open(identifier: str, layer_path):
    from pxr import Sdf, Tf

    try:
        layer = Sdf.Layer.FindOrOpen(identifier)
    except Tf.ErrorException as exc:
        raise LayerError(f"{_used_by(identifier, layer_path)} is not a readable USD layer ({tf_message(exc)}); "
                         "re-author it with `allo-usd author` or restore it from the plan") from None
    if layer is None:
        raise LayerError(f"{_used_by(identifier, layer_path)} could not be opened as a USD layer; re-author it")
    return layer


def _asset_values(spec) -> list:
    from pxr import Sdf

    values = [] if spec.default is None else [spec.default]
    layer, path = spec.layer, spec.path
    values += [layer.QueryTimeSample(path, t) for t in layer.ListTimeSamplesForPath(path)]
    out = []
    for v in values:
        out += list(v) if spec.typeName == Sdf.ValueTypeNames.AssetArray else [v]
    return [v.path for v in out if v is not None and v.path]


def _named(layer, layer_path) -> tuple[_Named, ...]:
    """Every file `layer` names, in order: sublayers, then references and payloads, then assets."""
    from pxr import Sdf

    def named(kind: str, what: str, raw: str) -> _Named:
        if raw.startswith("`"):  # a variable expression: the stage would evaluate it, the walk cannot check it
            raise LayerError(f"{layer_path}: {what} {raw} in {layer.identifier} is a variable expression, which "
                             "allo-usd does not follow (its value is only known to the stage that opens it); write "
                             "the path itself")
        identifier = layer.ComputeAbsolutePath(raw)
        if "[" in identifier and identifier.endswith("]"):
            raise LayerError(f"{layer_path}: {what} {raw} in {layer.identifier} is inside a package (.usdz); "
                             "unpack it and refer to the files themselves")
        return _Named(kind, what, identifier)

    subs = list(layer.subLayerPaths)
    out = [named(LAYER, "layer", p) for p in subs]
    out += [named(LAYER, "layer", p) for p in sorted(set(layer.GetCompositionAssetDependencies()) - set(subs))]
    asset_types = (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray)
    paths: list = []
    layer.Traverse(Sdf.Path.absoluteRootPath, paths.append)
    for p in reversed(paths):  # Traverse visits children first; reversed is parents first
        spec = layer.GetObjectAtPath(p)
        if isinstance(spec, Sdf.PrimSpec) and (spec.HasInfo("clips") or spec.HasInfo("clipSets")):
            raise LayerError(f"{layer_path}: {layer.identifier} authors value clips at {p}, which allo-usd does not "
                             "follow; bake the values into the layer")
        if isinstance(spec, Sdf.AttributeSpec) and spec.typeName in asset_types:
            out += [named(ASSET, f"asset {p} =", raw) for raw in _asset_values(spec)]
    return tuple(out)


def _cached_named(real: str, identifier: str, layer_path, opened: list) -> tuple[_Named, ...]:
    key = stat_key(real)
    hit = _NAMED.get(key)
    if hit is not None:
        _NAMED.move_to_end(key)
        return hit
    layer = _open(identifier, layer_path)
    opened.append(layer)
    found = _named(layer, layer_path)
    _NAMED[key] = found
    while len(_NAMED) > CACHE_SIZE:
        _NAMED.popitem(last=False)
    return found


def check_root(layer_path: str | Path, extra: tuple[str | Path, ...] = ()) -> str:
    """The real path of a scene layer that may be opened (its roots, a regular file, its size, a
    layer extension), without opening it; else a LayerError naming the rule."""
    return _check(LAYER, "scene layer", os.path.abspath(layer_path), layer_path, allowed_roots(layer_path, extra))


def walk(layer_path: str | Path, extra: tuple[str | Path, ...] = ()) -> Walk:
    """Check every file the composition of `layer_path` reads, before USD opens it (see the module
    doc); raise LayerError for the first refused one. A file USD cannot resolve is skipped (the
    stage's composition errors report it), unless its path is absolute and outside the roots."""
    from pxr import Ar

    resolver = Ar.GetResolver()
    layer_path = Path(layer_path)
    roots = allowed_roots(layer_path, extra)
    result, seen = Walk(), set()
    stack = [(LAYER, "scene layer", os.path.abspath(layer_path))]  # depth first, without a recursive closure
    while stack:  # (a closure calling itself is a reference cycle: it would keep the opened layers alive)
        kind, what, path = stack.pop()
        real = _check(kind, what, path, layer_path, roots)
        if real in seen:
            continue
        seen.add(real)
        result.files.append(real)
        if kind != LAYER:
            continue
        children = []
        for n in _cached_named(real, path, layer_path, result.layers):
            resolved = str(resolver.Resolve(n.identifier))
            if resolved:
                children.append((n.kind, n.what, resolved))
            elif os.path.isabs(n.identifier) and not inside(n.identifier, roots):
                reject(n.what, n.identifier, layer_path, roots)
        stack += reversed(children)
    return result


__all__ = ["walk", "check_root", "Walk", "stat_key", "tf_message", "MAX_LAYER_BYTES", "MAX_ASSET_BYTES",
           "LAYER_EXTENSIONS"]
