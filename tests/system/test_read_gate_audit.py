"""Every file the package reads goes through the one read gate (allo_usd.core.files: read_user_bytes,
read_user_text, read_user_json, read_head, read_whole_small, read_own_record, file_problem before a
library opens the file), or is listed below with the reason it is safe. An AST scan of allo_usd/ (nothing
imported) finds each call that opens or reads a file by name (open, Path.open/read_text/read_bytes,
os.open for reading, np.load, json.load, Image.open, trimesh.load, pandas' read_csv, USD's Stage.Open
and Layer.FindOrOpen, zipfile, ...) and fails on one that is neither allowed here nor gone from here:
a new read of a user's path must be routed through the gate, or allowed with its reason.

A site is `module:function:callee` (the call's enclosing function, dotted with its class; the callee
as written), counted: a second read in an allowed function is a new site too."""

from __future__ import annotations

import ast
from collections import Counter
from pathlib import Path

import allo_usd

from tests.support.source_audit import ScopedSites

PACKAGE = Path(allo_usd.__file__).parent

# Attribute names that open or read a file given by name, whatever they are called on.
READ_ATTRS = {"open", "Open", "FindOrOpen", "OpenAsAnonymous", "read_text", "read_bytes", "imread", "read_csv",
              "read_table", "fromfile", "memmap", "loadtxt", "genfromtxt", "ZipFile", "InputFile", "TarFile"}
# `load` reads a file only on these receivers (json.load takes an open file: the open is the site too)
LOAD_RECEIVERS = {"np", "numpy", "json", "pickle", "tomllib", "yaml", "trimesh", "torch", "bpy.data.images"}
# receivers named as written (a module or class); any other receiver is a path object: the callee is the method
MODULES = {"os", "io", "np", "numpy", "json", "pickle", "tomllib", "yaml", "trimesh", "torch", "bpy", "Image", "pd",
           "pandas", "Usd", "Sdf", "zipfile", "gzip", "tarfile", "imageio", "cv2", "OpenEXR"}
WRITE_FLAGS = ("O_CREAT", "O_WRONLY", "O_TMPFILE")   # os.open for writing (a new file or an append)

GATE = "the read gate itself (core.files)"
OWN_OUTPUT = "a file this code has just written or owns in its output (never a user's input)"
# module:function:callee -> (count, why it is safe)
ALLOWED: dict[str, tuple[int, str]] = {
    # the gate: non-blocking opens, checked as regular files that are no pseudo-files, bounded reads
    "core/files.py:sha256_file:os.open": (1, GATE + ": opened non-blocking, refused unless a regular file on disk"),
    "core/files.py:_yields_bytes:os.open": (1, GATE + ": the one-byte probe of a size-0 regular file"),
    "core/files.py:_bounded_read:os.open": (1, GATE),
    "core/files.py:read_head:os.open": (1, GATE),
    "core/files.py:read_whole_small:os.open": (1, GATE),
    "core/files.py:_open_temp_beside:os.open": (1, "creates a new temporary (O_CREAT | O_EXCL): a write"),
    "core/files.py:_open_unnamed_beside:os.open": (1, "creates an unnamed file (O_TMPFILE): a write"),
    "core/files.py:_link_unnamed:os.open": (1, "the root folder's descriptor, for linkat: nothing is read"),
    # fixed system paths chosen by the code, not by a user
    "blender/device.py:cpu_model:open": (1, "/proc/cpuinfo, a fixed path the code names (device detection)"),
    "blender/device.py:cpu_flags:open": (1, "/proc/cpuinfo, a fixed path the code names (device detection)"),
    "sky/ephemeris.py:load_de421:load": (1, "skyfield's loader of the package's own de421.bsp"),
    # libraries that open a file the gate has already checked
    "assets/importer.py:_load_scene:trimesh.load": (1, "the model file passed the gate in _check_path "
                                                       "(file_problem: regular, bounded, no pseudo-file)"),
    "blender/build.py:load_texture:bpy.data.images.load": (1, "the texture passed the gate in the reader "
                                                              "(reader_bounds.check_texture_file)"),
    "usd/reader_bounds.py:check_texture_file:open": (1, "file_problem just before: reads 16 bytes at each end"),
    "usd/read.py:open_stage:Usd.Stage.Open": (1, "every layer and asset the stage names passed the gate in the "
                                                 "dependency walk (usd.dependencies) first"),
    "usd/schema.py:extends_copy:Sdf.Layer.FindOrOpen": (1, "the package's own generatedSchema.usda (schema.PLUGIN); "
                                                           "the tree's copy it is compared with is read through "
                                                           "read_user_text"),
    "usd/dependencies.py:_open:Sdf.Layer.FindOrOpen": (1, "the dependency walk's own open, after its gate check "
                                                          "(_check: file_problem on the real path)"),
    "usd/dependencies.py:_package:Sdf.ZipFile.Open": (1, "a package the walk checked (_check, MAX_PACKAGE_BYTES)"),
    "usd/dependencies.py:unpacked_file:Sdf.ZipFile.Open": (1, "a package the walk checked"),
    "usd/hazard.py:read_usd_hazard:Usd.Stage.Open": (1, "every file of the hazard's composition passed the "
                                                        "dependency walk (usd_hazard_walk) just before"),
    "usd/model_mesh.py:read_model:Usd.Stage.Open": (1, "every file of the model's composition passed the "
                                                      "dependency walk (dependencies.walk) just before"),
    "usd/sniff.py:is_scene_layer:Sdf.Layer.FindOrOpen": (1, "after refusal() (dependencies.check_root: the gate's "
                                                            "rule and the roots) and read_head"),
    "usd/sniff.py:render_cost:Sdf.Layer.FindOrOpen": (1, "after refusal() (dependencies.check_root)"),
    "usd/sniff.py:layer_outputs:Sdf.Layer.FindOrOpen": (1, "after refusal() (dependencies.check_root)"),
    "plan/io.py:_parse:yaml.load": (1, "parses text, not a path: the plan's text read by load_plan through "
                                       "read_user_text"),
    # files this code wrote, in its own output
    "usd/asset.py:write_geometry:Usd.Stage.Open": (1, OWN_OUTPUT + ": the layer just written"),
    "usd/asset.py:write_interface:Usd.Stage.Open": (1, OWN_OUTPUT + ": the layer just written"),
    "usd/base_stage.py:write_base_stage:Usd.Stage.Open": (1, OWN_OUTPUT + ": the stage just written"),
    "usd/pack.py:_check_metadata:Sdf.Layer.FindOrOpen": (1, OWN_OUTPUT + ": the package's layers just written"),
    "usd/pack.py:fix_timestamps:zipfile.ZipFile": (1, OWN_OUTPUT + ": the package just written"),
    "usd/pack.py:fix_timestamps:open": (1, OWN_OUTPUT + ": the package just written"),
    "run/ledgers.py:read_skipped:open": (1, OWN_OUTPUT + ": the tree's skipped.csv"),
    "run/ledgers.py:read_reserves:open": (1, OWN_OUTPUT + ": the tree's reserves.csv"),
    "run/ledgers.py:read_counts:open": (1, OWN_OUTPUT + ": the tree's counts.csv"),
    "run/render_index.py:_manifest_rows:read_text": (1, OWN_OUTPUT + ": the render folder's manifest.jsonl"),
    "output/contact.py:read_pixels:Image.open": (1, "images named by source_file (a plain name whose real path "
                                                    "lies in the render folder: no link out, no pseudo-file) or "
                                                    "written by the dataset itself"),
    # the dataset's own reads: its renders' images (source_file: confined to the render folder) and its outputs
    "output/annotation_files.py:compute_record:Image.open": (1, OWN_OUTPUT + ": the mask the dataset filed (allo_mask)"),
    "output/dataset.py:_write_csv:read_bytes": (1, OWN_OUTPUT + ": compared (a regular file of the new size) before a "
                                                "rewrite"),
    "output/dataset.py:write_manifest:pd.read_csv": (1, OWN_OUTPUT + ": the manifest.csv it has just written"),
    "output/dataset.py:image_size:Image.open": (1, "images named by source_file (a plain name whose real path lies in "
                                                  "the render folder) or written by the dataset itself"),
}


def _callee(call: ast.Call) -> str | None:
    """The callee as written if `call` opens or reads a file by name, else None."""
    fn = call.func
    if isinstance(fn, ast.Name):
        return fn.id if fn.id in ("open", "load") and (fn.id == "open" or call.args) else None
    if not isinstance(fn, ast.Attribute):
        return None
    text = ast.unparse(fn)
    receiver = ast.unparse(fn.value)
    if fn.attr == "load":
        return text if receiver in LOAD_RECEIVERS else None
    if fn.attr not in READ_ATTRS:
        return None
    if text == "os.open":
        flags = ast.unparse(call.args[1]) if len(call.args) > 1 else ""
        return None if any(f in flags for f in WRITE_FLAGS) else text
    if receiver.split(".")[0] not in MODULES:   # a path object: Path.open(mode), .read_text(), ...
        return _mode_read(call, 0, fn.attr) if fn.attr == "open" else fn.attr
    return text


def _mode_read(call: ast.Call, at: int, text: str) -> str | None:
    """`text` unless the call's mode (positional `at` or mode=) is a literal that only writes."""
    mode = next((k.value for k in call.keywords if k.arg == "mode"), call.args[at] if len(call.args) > at else None)
    if isinstance(mode, ast.Constant) and isinstance(mode.value, str) and "r" not in mode.value \
            and "+" not in mode.value:
        return None
    return text


def read_sites() -> Counter:
    """Counter of module:function:callee over every read call in the package."""
    sites: Counter = Counter()
    for path in sorted(PACKAGE.rglob("*.py")):
        module = path.relative_to(PACKAGE).as_posix()

        class Visitor(ScopedSites):
            def visit_Call(self, node):
                callee = _callee(node)
                if callee == "open":
                    callee = _mode_read(node, 1, callee)
                if callee is not None:
                    self.add(callee)
                self.generic_visit(node)

        Visitor(module, sites).visit(ast.parse(path.read_text(encoding="utf-8")))
    return sites


def test_every_read_of_a_file_goes_through_the_gate_or_is_allowed_with_its_reason():
    found = read_sites()
    allowed = Counter({k: n for k, (n, _) in ALLOWED.items()})
    new = found - allowed
    gone = allowed - found
    assert not new, ("reads outside the read gate (route them through allo_usd.core.files.read_user_bytes/"
                     "read_user_text/read_user_json/read_head/file_problem, or add them to ALLOWED with the "
                     "reason they are safe):\n  " + "\n  ".join(f"{k} (x{n})" for k, n in sorted(new.items())))
    assert not gone, ("ALLOWED lists reads that are no longer there (remove them):\n  "
                      + "\n  ".join(sorted(gone)))


def test_every_allowed_read_says_why():
    assert all(n >= 1 and len(why) > 20 for n, why in ALLOWED.values())


def test_the_scan_sees_a_new_read_of_a_user_path(tmp_path, monkeypatch):
    """The audit's own check: a module that reads a path with open(), Path.read_text() or np.load is found;
    one that writes with open(..., "w") or creates with os.open(O_CREAT) is not."""
    import allo_usd

    pkg = tmp_path / "allo_usd"
    (pkg / "core").mkdir(parents=True)
    (pkg / "core" / "leak.py").write_text(
        "import os\nimport numpy as np\n\n\ndef leak(p):\n    with open(p) as f:\n        f.read()\n"
        "    p.read_text()\n    np.load(p)\n    open(p, 'w').close()\n    os.open(p, os.O_WRONLY | os.O_CREAT)\n")
    monkeypatch.setattr(allo_usd, "__file__", str(pkg / "__init__.py"))
    monkeypatch.setattr(__import__(__name__, fromlist=["PACKAGE"]), "PACKAGE", pkg)
    assert read_sites() == Counter({"core/leak.py:leak:open": 1, "core/leak.py:leak:read_text": 1,
                                    "core/leak.py:leak:np.load": 1})
