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
Value clips are refused: no ALLO layer uses them and the walk does not follow them. So is a
path into a package (.usdz) named by a layer outside it.

**A package as the scene** (`allo-usd pack`, allo_usd.usd.pack). A .usdz given as the scene layer
is one file whose contents are its own: the package itself must pass the rules above (roots,
regular file, at most MAX_PACKAGE_BYTES) and hold entries USD can read in place (stored, not
encrypted, the first one a layer); then every path its layers name must resolve inside that same
package (`PKG[entry]`, an entry it holds, within the layer or asset size bound; a layer entry
with a layer extension). A path outside the package, into another package, or into a package
inside it is refused. The walk then lists the package file alone: its bytes are every input.
Blender reads textures from files only: the reader reads a packaged one through a copy
(`unpacked_file`) in a private temporary directory, removed when the process exits.

A refused file is named with the rule it breaks, never with its content.

**A user's USD hazard** (allo_usd.usd.hazard: a plan's `[[anomalies.assets]] file = "x.usda"`,
`allo-usd asset import x.usda`) is walked by `walk_hazard` with the same rules before USD opens
it; only its roots differ (`hazard_roots`): the folder that holds the hazard file, and
ALLO_ASSET_ROOTS, never the project's stages/ or a tree. A refusal says so and how to fix it.
The layers it found (`Walk.layer_files`) are the hazard's inputs, checksummed in its record.

The walk returns the files it read, root first (depth first, each file once): the inputs of a
render, whose checksums make its identity (allo_usd.output.identity.render_identity). A layer's
own list of what it names is cached per process by (real path, mtime_ns, size, inode), so the
shared sky, pose and base layers of a tree are opened once per process, not once per scene; the
roots, sizes and file types are checked again on every walk.

What it cannot see: a file swapped between the check and USD's read (the walk narrows that
window, it does not close it), and what a custom ArResolver would resolve differently.
"""

from __future__ import annotations

import atexit
import hashlib
import os
import re
import shutil
import tempfile
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

from allo_usd.core.errors import LayerError
from allo_usd.core.files import file_problem, write_bytes_atomic
from allo_usd.usd.safety import allowed_roots, decision_cache, inside, inside_real, real_path, reject

MAX_LAYER_BYTES = 256 << 20   # a scene layer is < 4 KB; the base stage's largest .usdc is a few MB
MAX_ASSET_BYTES = 256 << 20   # a texture; the shipped ones are < 1 MB
LAYER_EXTENSIONS = (".usda", ".usdc", ".usd")
PACKAGE_EXTENSION = ".usdz"   # a scene packed into one file (allo_usd.usd.pack)
MAX_PACKAGE_BYTES = 1 << 30   # a packed scene: its layers, assets and textures (the demo's: about 5.5 MB)
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
    for this walk (keep them alive across Usd.Stage.Open and USD parses none of them twice).
    `kinds`: each file's kind (LAYER or ASSET), by real path."""
    files: list[str] = field(default_factory=list)
    layers: list = field(default_factory=list)
    kinds: dict = field(default_factory=dict)

    def layer_files(self) -> list[str]:
        """The files the composition reads as layers (root first): what a stage is made of."""
        return [f for f in self.files if self.kinds.get(f) == LAYER]


@dataclass(frozen=True)
class _Rules:
    """Who is walked and how a refusal reads: `root` names the root file in messages, `refuse`
    raises for a path outside the roots (what, path, layer_path, roots), `reopen` is the fix of
    a file USD cannot parse (None: decided by the file, unreadable())."""
    root: str = "scene layer"
    refuse: object = reject
    reopen: str | None = None


REAUTHOR = "re-author it with `allo-usd author` or restore it from the plan"
_POSITION = re.compile(r"(?P<file>\S+):(?P<line>\d+):(?P<col>\d+): (?P<what>.*)", re.S)


def project_layer(path: str) -> bool:
    """Is `path` a layer the project authored: a scene layer (its layer metadata holds
    customLayerData.allo.sceneId, read from its first bytes as text, so a layer that does not
    parse is judged too) or a layer in an authored tree's own folders (scenes/, sky/, poses/,
    stages/, ...)? Those are restored by authoring again; a hand-written layer is fixed by hand."""
    from allo_usd.core.files import read_head
    from allo_usd.usd.safety import in_tree_folder
    from allo_usd.usd.layer_head import HEAD_BYTES, layer_metadata

    head = read_head(Path(path), HEAD_BYTES) or b""
    text = head.decode("utf-8", errors="replace")
    block = layer_metadata(text) if text.startswith("#usda") else None
    return re.search(r"\bsceneId\s*=", text if block is None else block) is not None or in_tree_folder(path)


def unreadable(identifier: str, layer_path, exc, fix: str | None = None) -> str:
    """The one line for a layer USD cannot read (`exc`, a Tf error): where (file, line and column
    for a syntax error), what USD says, and the fix: `fix` if given, else re-authoring for a layer
    the project wrote (project_layer) and "fix the layer's syntax" for one of one's own."""
    what = tf_message(exc)
    where = _used_by(identifier, layer_path)
    own = fix is None and not project_layer(identifier)
    fix = fix or (REAUTHOR if not own else "fix the layer's syntax")
    found = _POSITION.fullmatch(what)
    if own and found:
        return f"{where}: USD cannot parse line {found['line']} ({what}); {fix}"
    if own:
        return f"{where} is not a readable USD layer ({what}); {fix} (a .usda text or .usdc layer USD can open)"
    return f"{where} is not a readable USD layer ({what}); {fix}"


_SCENE = _Rules()


_NAMED: OrderedDict[tuple, tuple[_Named, ...]] = OrderedDict()
_ENTRIES: OrderedDict[tuple, dict] = OrderedDict()


def is_package(path: str | Path) -> bool:
    """A package (.usdz) by its name, which is how USD picks the file format."""
    return os.path.splitext(str(path))[1].lower() == PACKAGE_EXTENSION


@dataclass(frozen=True)
class Package:
    """The package a walk started from: its real path and its entries {name: uncompressed size}."""
    real: str
    entries: dict


def _package(real: str, layer_path) -> Package:
    """The package at `real` (already checked as a bounded regular file inside the roots), with
    the entries USD would read from it; a LayerError when USD could not read it in place."""
    from pxr import Sdf, Tf

    key = stat_key(real)
    entries = _ENTRIES.get(key)
    if entries is None:
        fix = "pack the scene again with `allo-usd pack LAYER --out SCENE.usdz`"
        if key[2] == 0:
            raise LayerError(f"{layer_path} is an empty file (0 bytes), not a USD package; {fix}")
        try:  # USD raises for a file it cannot map (an empty one), and returns nothing for one that is not a zip
            zf = Sdf.ZipFile.Open(real)
        except Tf.ErrorException:
            zf = None
        names = list(zf.GetFileNames()) if zf else []
        if not names:
            raise LayerError(f"{layer_path} is not a readable USD package (no zip entries USD can list); {fix}")
        entries = {}
        for name in names:
            info = zf.GetFileInfo(name)
            if info.compressionMethod != 0 or info.encrypted:
                raise LayerError(f"{layer_path}: entry {name} of the package is compressed or encrypted, which USD "
                                 f"cannot read in place (a .usdz stores its files as they are); {fix}")
            entries[name] = info.uncompressedSize
        if os.path.splitext(names[0])[1].lower() not in LAYER_EXTENSIONS:
            raise LayerError(f"{layer_path}: the first entry of the package, {names[0]}, is not a USD layer (the "
                             f"first entry is the scene layer); {fix}")
        _ENTRIES[key] = entries
        while len(_ENTRIES) > 64:
            _ENTRIES.popitem(last=False)
    return Package(real, entries)


def _check_packaged(kind: str, what: str, path: str, layer_path, package: Package) -> str:
    """The key (`REAL.usdz[entry]`) of a path a packaged layer names if it may be read: an entry
    of the package itself, within its size bound; else a LayerError naming the rule."""
    from pxr import Ar

    fix = ("a package (.usdz) may use only the files it holds: pack the scene with `allo-usd pack LAYER --out "
           "SCENE.usdz`, which takes in every file the scene reads")
    if not Ar.IsPackageRelativePath(path):
        raise LayerError(f"{layer_path}: {what} {path} lies outside the package; {fix}")
    outer, inner = Ar.SplitPackageRelativePathOuter(path)
    if os.path.realpath(outer) != package.real:
        raise LayerError(f"{layer_path}: {what} {path} lies in another package, outside this one; {fix}")
    if Ar.IsPackageRelativePath(inner):
        raise LayerError(f"{layer_path}: {what} {path} lies in a package inside the package, which allo-usd does "
                         f"not follow; {fix}")
    size = package.entries.get(inner)
    if size is None:
        raise LayerError(f"{layer_path}: {what} {path} is not an entry of the package; {fix}")
    limit = MAX_LAYER_BYTES if kind == LAYER else MAX_ASSET_BYTES
    if size > limit:
        raise LayerError(f"{layer_path}: {what} {path} holds {size:,} bytes, over the {limit >> 20:,} MiB allowed; a "
                         "layer may only use bounded files: fix the layer")
    if kind == LAYER and os.path.splitext(inner)[1].lower() not in LAYER_EXTENSIONS:
        raise LayerError(f"{layer_path}: {what} {path} is not a USD layer (its name must end in "
                         f"{', '.join(LAYER_EXTENSIONS)}); point the layer at a USD file")
    return f"{package.real}[{inner}]"


def stat_key(real: str) -> tuple:
    """What identifies a file's bytes without reading them: (real path, mtime_ns, size, inode)."""
    st = os.stat(real)
    return real, st.st_mtime_ns, st.st_size, st.st_ino


def _check(kind: str, what: str, path: str, layer_path, roots, package_root: bool = False,
           refuse=reject) -> str:
    """The real path of `path` if it may be read as a `kind`; else a LayerError naming the rule.
    `package_root`: `path` is the scene itself and may be a package (.usdz)."""
    real = real_path(path)
    if not inside_real(real, roots):
        refuse(what, path, layer_path, roots)
    packaged = package_root and is_package(path)
    problem = file_problem(real, MAX_PACKAGE_BYTES if packaged else MAX_LAYER_BYTES if kind == LAYER
                           else MAX_ASSET_BYTES)
    if problem:
        raise LayerError(f"{layer_path}: {what} {path} {problem}; a layer may only use bounded regular files: fix the "
                         "layer (restore the file, point it at another, or remove the path)")
    if kind == LAYER and not packaged and os.path.splitext(path)[1].lower() not in LAYER_EXTENSIONS:
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


def _open(identifier: str, layer_path, fix: str | None = _SCENE.reopen):
    from pxr import Sdf, Tf

    try:
        layer = Sdf.Layer.FindOrOpen(identifier)
    except Tf.ErrorException as exc:
        raise LayerError(unreadable(identifier, layer_path, exc, fix)) from None
    if layer is None:
        fix = fix or (REAUTHOR if project_layer(identifier) else "fix the layer (USD cannot open it as a layer)")
        raise LayerError(f"{_used_by(identifier, layer_path)} could not be opened as a USD layer; {fix}")
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


def _named(layer, layer_path, packaged: bool = False) -> tuple[_Named, ...]:
    """Every file `layer` names, in order: sublayers, then references and payloads, then assets.
    `packaged`: the layer lies in the package being walked, whose paths are package-relative."""
    from pxr import Sdf

    def named(kind: str, what: str, raw: str) -> _Named:
        if raw.startswith("`"):  # a variable expression: the stage would evaluate it, the walk cannot check it
            raise LayerError(f"{layer_path}: {what} {raw} in {layer.identifier} is a variable expression, which "
                             "allo-usd does not follow (its value is only known to the stage that opens it); write "
                             "the path itself")
        identifier = layer.ComputeAbsolutePath(raw)
        if not packaged and "[" in identifier and identifier.endswith("]"):
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


def _cached_named(key: tuple, identifier: str, layer_path, opened: list, packaged: bool = False,
                  fix: str | None = _SCENE.reopen) -> tuple[_Named, ...]:
    hit = _NAMED.get(key)
    if hit is not None:
        _NAMED.move_to_end(key)
        return hit
    layer = _open(identifier, layer_path, fix)
    opened.append(layer)
    found = _named(layer, layer_path, packaged)
    _NAMED[key] = found
    while len(_NAMED) > CACHE_SIZE:
        _NAMED.popitem(last=False)
    return found


def check_root(layer_path: str | Path, extra: tuple[str | Path, ...] = ()) -> str:
    """The real path of a scene layer that may be opened (its roots, a regular file, its size, a
    layer extension, or a package: .usdz), without opening it; else a LayerError naming the rule.
    Inside a roots_cached block (one decision over many layers: the dispatcher's scan, then its
    resume check) a layer's answer is given once per block."""
    cache = decision_cache()
    key = ("check_root", os.path.abspath(layer_path), tuple(map(str, extra)))
    if cache is not None and key in cache:
        real, problem = cache[key]
        if problem is not None:
            raise LayerError(problem)
        return real
    try:
        real = _check(LAYER, "scene layer", key[1], layer_path, allowed_roots(layer_path, extra), package_root=True)
    except LayerError as exc:
        if cache is not None:
            cache[key] = (None, str(exc))
        raise
    if cache is not None:
        cache[key] = (real, None)
    return real


def walk(layer_path: str | Path, extra: tuple[str | Path, ...] = ()) -> Walk:
    """Check every file the composition of `layer_path` reads, before USD opens it (see the module
    doc); raise LayerError for the first refused one. A file USD cannot resolve is skipped (the
    stage's composition errors report it), unless its path is absolute and outside the roots.
    A package (.usdz) is walked inside itself: its files are the package alone."""
    layer_path = Path(layer_path)
    return _walk(layer_path, allowed_roots(layer_path, extra), _SCENE)


def hazard_roots(hazard_path: str | Path) -> tuple[Path, ...]:
    """Where a user's USD hazard may reach: the folder that holds it (as named, and after symbolic
    links, if the file itself is a link), and the directories of ALLO_ASSET_ROOTS (a user's own
    grant). Never the project's stages/ or an authored tree: a hazard is the user's own file."""
    from allo_usd.usd.safety import ENV_ROOTS

    given = os.path.abspath(hazard_path)
    roots = [os.path.dirname(given), os.path.dirname(os.path.realpath(given))]
    roots += [p for p in os.environ.get(ENV_ROOTS, "").split(os.pathsep) if p]
    out: list[Path] = []
    for r in roots:
        real = Path(os.path.realpath(r))
        if real not in out:
            out.append(real)
    return tuple(out)


def _refuse_for_hazard(what: str, path: str, hazard_path, roots) -> None:
    from allo_usd.usd.safety import ENV_ROOTS, roots_text

    raise LayerError(f"{hazard_path}: {what} {path} resolves outside the hazard's folder "
                     f"({roots_text(roots)}); move the file beside the hazard (a hazard may use only the "
                     f"files in its own folder and below), or add its directory to {ENV_ROOTS}")


_HAZARD = _Rules("hazard", _refuse_for_hazard, "re-export the hazard from its tool or restore the file")


def walk_hazard(hazard_path: str | Path) -> Walk:
    """`walk` for a user's USD hazard (allo_usd.usd.hazard): the same rules (regular files by stat,
    size bounds, layer extensions, no variable expressions, no value clips, a package only
    itself), with the hazard's own roots (`hazard_roots`), checked before USD opens any file."""
    hazard_path = Path(hazard_path)
    return _walk(hazard_path, hazard_roots(hazard_path), _HAZARD)


def _walk(layer_path: Path, roots: tuple[Path, ...], rules: _Rules) -> Walk:
    """The walk itself (see `walk`), from `layer_path` within `roots`, refusing as `rules` say."""
    from pxr import Ar

    resolver = Ar.GetResolver()
    result, seen = Walk(), set()
    root = os.path.abspath(layer_path)
    package = None
    if is_package(root):
        real = _check(LAYER, rules.root, root, layer_path, roots, package_root=True, refuse=rules.refuse)
        package = _package(real, layer_path)
        result.files.append(real)
        result.kinds[real] = LAYER
    stack = [(LAYER, rules.root, root)]  # depth first, without a recursive closure
    while stack:  # (a closure calling itself is a reference cycle: it would keep the opened layers alive)
        kind, what, path = stack.pop()
        if package is None:
            real = key = _check(kind, what, path, layer_path, roots, refuse=rules.refuse)
        else:
            real = key = package.real if path == root else _check_packaged(kind, what, path, layer_path, package)
        if key in seen:
            continue
        seen.add(key)
        if package is None:
            result.files.append(real)
            result.kinds[real] = kind
        if kind != LAYER:
            continue
        children = []
        cache_key = stat_key(real) if package is None else (*stat_key(package.real), key)
        for n in _cached_named(cache_key, path, layer_path, result.layers, package is not None, rules.reopen):
            resolved = str(resolver.Resolve(n.identifier))
            if resolved:
                children.append((n.kind, n.what, resolved))
            elif package is not None and os.path.isabs(n.identifier) and not Ar.IsPackageRelativePath(n.identifier):
                _check_packaged(n.kind, n.what, n.identifier, layer_path, package)  # outside: refused
            elif os.path.isabs(n.identifier) and not inside(n.identifier, roots):
                rules.refuse(n.what, n.identifier, layer_path, roots)
        stack += reversed(children)
    return result


_UNPACKED: tuple[int, Path] | None = None  # (pid, directory) of this process's copies


def _unpack_dir() -> Path:
    global _UNPACKED
    if _UNPACKED is None or _UNPACKED[0] != os.getpid():
        path = Path(tempfile.mkdtemp(prefix="allo-usdz-"))
        atexit.register(shutil.rmtree, path, True)
        _UNPACKED = (os.getpid(), path)
    return _UNPACKED[1]


def unpacked_file(resolved: str, where: str = "") -> str:
    """The entry `PKG.usdz[entry]` (a path USD resolved) as a file of its own, for a reader that
    reads files only (Blender's image loader): a copy under this process's private temporary
    directory, named by its SHA-256 and keeping the entry's file name. The entry must be stored in
    place and at most MAX_ASSET_BYTES (the walk checked both; checked again here)."""
    from pxr import Ar, Sdf, Tf

    outer, inner = Ar.SplitPackageRelativePathOuter(resolved)
    try:
        zf = Sdf.ZipFile.Open(outer) if outer else None
    except Tf.ErrorException:  # emptied since the walk read it
        zf = None
    info = zf.GetFileInfo(inner) if zf else None
    at = f" ({where})" if where else ""
    if info is None or Ar.IsPackageRelativePath(inner):
        raise LayerError(f"{resolved}{at} is not an entry of its package; pack the scene again with `allo-usd pack`")
    if info.compressionMethod != 0 or info.encrypted or info.uncompressedSize > MAX_ASSET_BYTES:
        raise LayerError(f"{resolved}{at} is compressed, encrypted or over {MAX_ASSET_BYTES >> 20} MiB; pack the "
                         "scene again with `allo-usd pack`")
    data = bytes(zf.GetFile(inner))
    name = Path(inner).name
    if name in ("", ".", "..") or "\0" in name:
        name = "entry"
    dest = _unpack_dir() / hashlib.sha256(data).hexdigest() / name
    if not dest.is_file():
        write_bytes_atomic(dest, data)
    return str(dest)


__all__ = ["walk", "walk_hazard", "unreadable", "project_layer", "hazard_roots", "check_root", "Walk", "stat_key", "tf_message", "is_package",
           "unpacked_file", "MAX_LAYER_BYTES", "MAX_ASSET_BYTES", "MAX_PACKAGE_BYTES", "LAYER_EXTENSIONS", "PACKAGE_EXTENSION"]
