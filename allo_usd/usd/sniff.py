"""Cheap looks at a layer file before anything opens it for real: is it a scene layer (text
.usda, or a binary crate .usdc/.usd), what a render of it costs (pixels x samples), which passes
it orders (`layer_outputs`, for resume checks), and pxr loaded once with Ctrl-C held back (pxr's
module loader swallows a KeyboardInterrupt that lands while it imports its C++ modules, and
leaves pxr half-loaded: allo_usd.core.interrupts)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

from allo_usd.core.files import read_head
from allo_usd.core.interrupts import interrupt_held
from allo_usd.usd.layer_head import HEAD_BYTES, layer_metadata
from allo_usd.usd import attributes as A
from allo_usd.usd import layout
from allo_usd.plan.settings import DEFAULT_PASSES

LAYER_SUFFIXES = (".usda", ".usdc", ".usd")
CRATE_MAGIC = b"PXR-USDC"    # the first bytes of a binary (crate) layer
TEXT_MAGIC = b"#usda"
PXR_MODULES = ("Tf", "Gf", "Vt", "Sdf", "Plug", "Kind", "Usd", "UsdGeom", "UsdLux", "UsdRender", "UsdSemantics",
               "UsdShade", "UsdUtils")


def refusal(path: Path) -> str | None:
    """Why `path` must not be opened at all, or None when it may be read: the dependency walk's
    rule for a scene layer (allo_usd.usd.dependencies.check_root: inside its roots after realpath,
    so /etc/passwd linked in as x.usda is never read, not even its first bytes; a regular file, as
    a FIFO would block and a device never ends; within the layer size bound; a layer extension).
    Checked with os.stat and realpath only."""
    from allo_usd.core.errors import LayerError
    from allo_usd.usd.dependencies import check_root

    try:
        check_root(path)
    except LayerError as exc:
        return str(exc)
    return None


# The layer-metadata block every layer `allo-usd author` and the demo write for a scene starts with
# (Sdf's text export): customLayerData holding only allo, whose entries are one-line strings and
# numbers, sceneId among them. A head that starts so is a scene layer with no USD parse (~1 ms a layer,
# most of a 51,409-scene resume check's budget); any other shape, or a second customLayerData in the
# head, takes the parse below.
_ALLO_ENTRY = rb'            [a-z0-9]+ \w+ = (?:"[^"\\\n]*"|-?[0-9][0-9.e+-]*)\n'
_AUTHORED_HEAD = re.compile(rb'#usda 1\.0\n\(\n    customLayerData = \{\n        dictionary allo = \{\n'
                            rb'(?:' + _ALLO_ENTRY + rb')*            string sceneId = "[^"\\\n]*"\n'
                            rb'(?:' + _ALLO_ENTRY + rb')*        \}\n    \}\n')


MAX_OVER_DEPTH = 8   # how many layers of one's own may stand over a scene layer, each sublayering the next


def is_scene_layer(path: Path, head: bytes | None = None, _top: Path | None = None, _depth: int = 0) -> bool | None:
    """The one rule for what `render DIR` renders: a scene layer is a layer whose own layer metadata
    holds customLayerData.allo.sceneId, as every layer `allo-usd author` and the demo write for a
    scene does, and no sky, pose, stage, asset or schema layer does; or a layer of one's own over
    one: a layer whose subLayers reach a scene layer (directly, or through at most MAX_OVER_DEPTH
    layers of one's own), whatever its customLayerData holds. Its scene is named by its file stem,
    as every render output is (two layers of one name in one run are refused). A sublayer the
    layer may not read (outside its allowed roots, not a regular file) keeps the layer, so that the
    render says what is wrong with it. For a text layer only the
    layer-metadata block (the parenthesised block after `#usda 1.0`, before any prim) counts: a
    `string allo:sceneId` property further down (the schema's generatedSchema.usda, a sky layer's
    record) does not make a scene. A binary crate's customLayerData is read by Sdf. A file that is
    not even USD, or whose metadata does not parse, is kept, so the reader reports it instead of
    hiding it. None for a path that is not a regular file (a FIFO, a device): it is never opened for
    reading, and only the first 16 KiB of a regular file are read ."""
    if head is None:
        head = None if refusal(path) else read_head(path, HEAD_BYTES)
    if head is None:
        return None
    if head.startswith(TEXT_MAGIC):
        if _AUTHORED_HEAD.match(head) and head.count(b"customLayerData") == 1:
            return True
        block = layer_metadata(head.decode("utf-8", errors="replace"))
        if block is None:  # the metadata does not end within the head: its look decides
            return re.search(rb"\bsceneId\s*=", head) is not None
        if "sceneId" not in block and "subLayers" not in block:
            return False
        load_pxr()
        from pxr import Sdf, Tf

        try:
            layer = Sdf.Layer.CreateAnonymous(".usda")
            if not layer.ImportFromString(f"#usda 1.0\n{block}\n"):
                return True  # broken metadata: the reader says what is wrong
        except Tf.ErrorException:
            return True
        allo = layer.customLayerData.get("allo")
        if isinstance(allo, dict) and "sceneId" in allo:
            return True
        return _over_scene(path, list(layer.subLayerPaths), _top or path, _depth)
    if head.startswith(CRATE_MAGIC):
        load_pxr()
        from pxr import Sdf, Tf

        try:
            layer = Sdf.Layer.FindOrOpen(str(path))
        except Tf.ErrorException:
            return True  # a broken crate: let the reader say what is wrong
        if not layer:
            return False
        return "sceneId" in dict(layer.customLayerData.get("allo", {})) or \
            _over_scene(path, list(layer.subLayerPaths), _top or path, _depth)
    return True


def _over_scene(path: Path, subs: list[str], top: Path, depth: int) -> bool:
    """Does one of `subs` (the subLayers of `path`, as written) reach a scene layer (is_scene_layer)?
    Read with the allowed roots of `top`, the layer the scan found: a sublayer it may not read keeps
    it (True: its render names the rule); a path USD resolves otherwise (a variable expression, a
    search path, a package) is not followed."""
    import os

    from allo_usd.usd.safety import allowed_roots, inside

    if depth >= MAX_OVER_DEPTH:
        return False
    for raw in subs:
        if raw.startswith("`") or "[" in raw or not raw.strip():
            continue
        sub = Path(os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(path)), raw)))
        if not inside(str(sub), allowed_roots(top)) or refusal(sub):
            return True
        found = is_scene_layer(sub, None, top, depth + 1)
        if found is None or found:
            return True
    return False


def render_cost(path: Path) -> tuple[int, int] | None:
    """(pixels, samples) the scene layer itself orders on its render settings, read from the layer
    alone (no sublayer opened), or None when it does not say (or cannot be read)."""
    if refusal(path):
        return None
    load_pxr()
    from pxr import Sdf, Tf

    try:
        layer = Sdf.Layer.FindOrOpen(str(path))
    except Tf.ErrorException:
        return None
    spec = layer.GetPrimAtPath(layout.RENDER_SETTINGS) if layer else None
    if not spec:
        return None
    res, samples = spec.attributes.get("resolution"), spec.attributes.get(A.RENDER_SAMPLES.name)
    try:
        w, h = (int(v) for v in res.default)
        return w * h, int(samples.default)
    except (AttributeError, TypeError, ValueError):
        return None


def layer_outputs(layer: Path) -> tuple[str, ...]:
    """The passes a scene layer orders (its own override of the product, else the base's default
    passes), read from the layer file alone: cheap enough for resume checks."""
    from pxr import Sdf, Tf

    from allo_usd.usd.read import VAR_PASSES

    if refusal(layer):
        return DEFAULT_PASSES   # never opened (the walk's rule): read_scene will say what is wrong with it
    try:
        sdf = Sdf.Layer.FindOrOpen(str(layer))
    except Tf.ErrorException:
        return DEFAULT_PASSES  # unreadable: read_scene will say what is wrong with it
    rel = sdf.GetRelationshipAtPath(f"{layout.IMAGE_PRODUCT}.orderedVars") if sdf else None
    if not rel or not rel.targetPathList.explicitItems:
        return DEFAULT_PASSES
    return tuple(VAR_PASSES.get(t.name, t.name) for t in rel.targetPathList.explicitItems)


_LOADED = False


def load_pxr() -> None:
    """Import the pxr modules this package uses, once, with Ctrl-C held back until they are in: a
    KeyboardInterrupt raised while pxr's loader imports a C++ module's Python wrappers is caught
    and printed as a warning by that loader (the command would run on, with pxr half-loaded);
    allo_usd.core.interrupts.interrupt_held delivers it after the imports."""
    global _LOADED
    if _LOADED:
        return
    with interrupt_held():
        for name in PXR_MODULES:
            importlib.import_module(f"pxr.{name}")
    _LOADED = True
