"""What a rendered scene leaves behind and when it counts as done: one rule for `allo-usd render
LAYER`, the dispatcher's resume and the demo, so they never disagree about what to skip.

**Output names.** A layer STEM writes STEM.png, STEM.exr, STEM_mask.png, STEM_depth.exr,
STEM_normal.exr, STEM_instance.png, STEM_amodal.png (those of its passes) and STEM.json. They are
collision-free by construction: a stem ending in a reserved suffix (`_mask`, `_depth`, `_normal`,
`_instance`, `_amodal`, in any case) is refused, and so are two stems of one run equal up to case (file
systems that ignore case). Then no name of one layer can be a name of another
(tests/test_render_identity.py checks every pair).

**Identity.** A render's identity is the SHA-256 of a canonical JSON of its inputs and of the
versions that affect pixels: every file its composition read (allo_usd.usd.dependencies.walk:
each layer of the stack, the referenced assets, the textures), as {path relative to the layer's
directory: sha256}, and allo-usd's, bpy's, usd-core's and numpy's versions (read from package
metadata: the parent never imports bpy; numpy draws the sensor noise, whose Generator streams a numpy
release may change, and encodes sRGB). Other libraries (image encoders, the plan's numerics) are
recorded in the JSON's "libraries" (allo_usd.core.provenance), not in the identity: a new version of
one does not re-render finished scenes. The render's JSON records "identity", "inputs", "versions" and
"outputs_sha256" (each output's checksum); the manifest row records "identity". The JSON, written last
beside its outputs, is the record: a scene is done for every entry point when its JSON verifies
(done_record), whichever rendered it; the manifest is an index the dispatcher keeps up with it
(index_row). A scene is done only while the identity recomputed from the
recorded inputs' current bytes matches: the recorded inputs are the complete list of what the
render read, so if none of their bytes changed, a new walk would read the same files. File
checksums are cached per process by (real path, mtime_ns, size, inode), so the shared sky, pose
and base files of a tree are hashed once per resume check, not once per scene.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import os
import shutil
import stat
from pathlib import Path

from allo_usd.core.version import __version__
from allo_usd.core.errors import DiskFullError, LayerError
from allo_usd.core.files import DISK_FULL_ERRNOS, atomic_path, relpath, sha256_file, temp_name_re
from allo_usd.usd.read import layer_outputs
from allo_usd.usd.sniff import refusal

MANIFEST = "manifest.jsonl"
WORKDIR = ".allo-tmp"  # Blender's render files, one directory per worker pid
RESERVED_SUFFIXES = ("_mask", "_depth", "_normal", "_instance", "_amodal")  # what output_paths appends to a stem
PASS_FILES = {"rgb": ".png", "exr": ".exr", "mask": "_mask.png", "depth": "_depth.exr", "normal": "_normal.exr",
              "instance": "_instance.png", "amodal": "_amodal.png"}  # pass -> what output_paths appends to a stem


def _stem(layer) -> str:
    """A layer's stem (Path.stem) without building a Path: a 51,409-layer run asks for it often."""
    if isinstance(layer, Path):
        return layer.stem
    name = os.path.basename(os.fspath(layer))
    i = name.rfind(".")
    return name[:i] if 0 < i < len(name) - 1 else name


def _stem_problem(layer: Path) -> str | None:
    low = _stem(layer).lower()
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
        problem = _stem_problem(layer)
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
    problem = _stem_problem(Path(layer))
    if problem:
        raise LayerError(problem)
    stem = Path(layer).stem
    out_dir = Path(out_dir)
    outputs = layer_outputs(layer) if outputs is None else outputs
    paths = {p: out_dir / f"{stem}{PASS_FILES[p]}" for p in PASS_FILES if p in outputs}
    paths["meta"] = out_dir / f"{stem}.json"
    return paths


# ---------------------------------------------------------------- identity

_SHA256: dict[tuple, str] = {}
_SHA256_BOUND = 1 << 20  # entries (~200 B each); a paper plan's resume needs ~100,000


def file_sha256(path: str | Path, fresh: bool = False) -> str | None:
    """SHA-256 of a regular file, cached per process by (path, mtime_ns, size, inode, device); None
    for a missing or non-regular file (never opened: a FIFO or a device would block or never end).
    One os.stat per call (it follows symbolic links: a link pointed elsewhere changes the inode).
    `fresh` reads the bytes even when the cache holds this stat (`render --verify`: a file edited
    in place with its mtime put back keeps its stat, not its bytes)."""
    return hashed(path, fresh)[0]


def hashed(path: str | Path, fresh: bool = False) -> tuple[str | None, os.stat_result | None]:
    """file_sha256 and the os.stat it was keyed by (None, None for a missing or non-regular file),
    so that a manifest row records the stat of exactly the bytes it checksums."""
    path = os.path.abspath(path)
    try:
        st = os.stat(path)
    except OSError:
        return None, None
    if not stat.S_ISREG(st.st_mode):
        return None, None
    digest = None if fresh else _SHA256.get(_cache_key(path, st))
    if digest is None:
        try:
            digest = sha256_file(Path(path))
        except OSError:
            return None, None
        remember_digest(path, st, digest)
    return digest, st


def _cache_key(path: str, st: os.stat_result) -> tuple:
    return path, st.st_mtime_ns, st.st_size, st.st_ino, st.st_dev


def remember_digest(path: str | Path, st: os.stat_result, digest: str) -> None:
    """Enter `digest`, the checksum of the file at `path` as it was at `st`, into file_sha256's
    cache (bounded: cleared when full)."""
    if len(_SHA256) >= _SHA256_BOUND:
        _SHA256.clear()
    _SHA256[_cache_key(os.path.abspath(path), st)] = digest


def remember_sha256(path: str | Path, st: os.stat_result, data: bytes) -> None:
    """remember_digest of `data`, the whole of the file at `path` as read at `st`
    (core.files.read_whole_small): the dispatcher's scan reads each scene layer once, to sniff it
    and to checksum it for the resume check."""
    remember_digest(path, st, hashlib.sha256(data).hexdigest())


def stat_record(st: os.stat_result) -> dict[str, int]:
    """What the quick check compares (is_verified): a rewrite changes the size or the mtime, a
    replacement (os.replace of a new file) the inode. Not ctime: restoring an mtime by hand, or a
    hard link made elsewhere, changes it without changing a byte."""
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "ino": st.st_ino}


@functools.cache
def render_versions() -> dict[str, str]:
    """The package versions that affect pixels (from package metadata: importing bpy is not needed):
    allo-usd, the renderer (bpy), what a layer composes to (usd-core) and numpy (sensor noise, sRGB)."""
    from allo_usd.core.provenance import installed_version

    def installed(name: str) -> str:
        return installed_version(name) or "not installed"

    return {"allo_usd": __version__, "bpy": installed("bpy"), "usd-core": installed("usd-core"),
            "numpy": installed("numpy")}


def render_identity(inputs: dict[str, str], versions: dict[str, str] | None = None) -> str:
    """SHA-256 of the canonical JSON of a render's inputs ({relative path: sha256}) and versions."""
    record = {"inputs": inputs, "versions": render_versions() if versions is None else versions}
    return hashlib.sha256(json.dumps(record, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def input_hashes(layer: Path, files) -> dict[str, str]:
    """{path relative to the layer's directory: sha256} of the files a render of `layer` reads
    (allo_usd.usd.dependencies.walk), checksummed before the render reads them: a file changed
    meanwhile is recorded with its old checksum, so the next run renders it again."""
    here = Path(layer).parent
    out = {}
    for f in files:
        digest = file_sha256(f)
        if digest is None:
            raise LayerError(f"{layer}: {f} vanished or stopped being a regular file while it was read; re-run")
        out[relpath(Path(f), here)] = digest
    return out


def current_identity(layer: Path, inputs) -> str | None:
    """The identity of a new render of `layer` whose recorded `inputs` still hold: recomputed from
    those files' current bytes. None if the record is unusable (not a mapping or a list of its
    paths, or not naming the layer itself) or an input is missing or not a regular file. Inside the
    dispatcher's decision block (safety.roots_cached) real paths are resolved per folder and each
    input file is checksummed once per block (a pose or stage layer many scenes share); a worker
    that renders a scene computes its identity afresh."""
    from allo_usd.usd.safety import decision_cache, real_folder, real_path

    if not isinstance(inputs, (dict, list)) or not inputs or not all(isinstance(r, str) for r in inputs):
        return None
    layer = os.path.abspath(layer)
    here = real_folder(os.path.dirname(layer))  # input_hashes wrote paths relative to it, links resolved
    memo = decision_cache()  # the dispatcher's decision: a file shared by many scenes is looked at once
    now, paths = {}, set()
    for rel in inputs:
        hit = memo.get(("input", here, rel)) if memo is not None else None
        if hit is None:
            path = os.path.normpath(os.path.join(here, rel))
            hit = (path, file_sha256(path))
            if hit[1] is None:
                return None
            if memo is not None:
                memo["input", here, rel] = hit
        path, now[rel] = hit
        paths.add(path)
    if real_path(layer) not in paths:
        return None
    return render_identity(now)


def _meta(path: Path) -> dict:
    """A render record NAME.json read through the read gate (core.files.read_user_json: a FIFO or
    /dev/zero named NAME.json is never opened, a huge or deeply nested one never parsed), or {}
    when it cannot be used: the scene then counts as not done and renders again."""
    from allo_usd.core.files import MAX_RECORD_BYTES, InputRefused, read_user_json

    try:
        meta = read_user_json(path, MAX_RECORD_BYTES, "render record")
    except InputRefused:
        return {}
    return meta if isinstance(meta, dict) else {}


def is_done(layer: Path, out_dir: Path, manifest: dict[str, dict] | None = None, verify: bool = False) -> bool:
    """True when `out_dir` holds every output of `layer` rendered from the current bytes of
    everything its composition read, with the current package versions (its identity): the one
    rule of "done" for `allo-usd render LAYER`, render_layer, the dispatcher's resume and the demo,
    whichever of them rendered the scene (done_record).

    `manifest` (scene name -> row, from load_manifest: a dispatch run) is an index, not the record:
    the dispatcher's rule applies (resume_check: the row's quick check, or every byte with `verify`;
    else the render's JSON). The JSON is required to checksum its outputs then (a record written
    before JSONs did is done only with a matching row, so the dispatcher never trusts outputs
    nothing checksummed)."""
    if refusal(layer):  # not safe to read for its output names (a FIFO or device would block the check)
        return False  # the render says what is wrong with it
    if manifest is None:
        return done_record(layer, out_dir) is not None
    return resume_check(layer, out_dir, manifest.get(_stem(layer)), verify)[0]


def resume_check(layer: Path, out_dir: Path, row: dict | None, verify: bool = False) -> tuple[bool, dict | None]:
    """The dispatcher's decision for one layer with its manifest row (None: no row): (done, a row to
    append to the manifest, or None).

    A row that verifies (check_row: quick, or every byte with `verify`) says done; the row to append
    then is its upgrade when the outputs' stat changed (an old row, a copied tree). Otherwise the
    render's JSON decides (done_record, strict), for a scene another entry point rendered or whose
    row was lost: the index catches up with an index_row. Not when the row indexes that very render
    (the same identity and layer bytes): its outputs just failed the row's check (truncated,
    rewritten, touched or replaced since), and the row's stat, not the JSON's checksums, is what a
    resume trusts, so the scene renders again."""
    kept = check_row(row, layer, out_dir, verify)
    if kept is not None:
        return True, (None if kept is row else kept)
    meta = done_record(layer, out_dir, strict=True)
    if meta is None:
        return False, None
    if isinstance(row, dict) and (row.get("identity"), row.get("layer_sha256")) == (meta["identity"],
                                                                                  meta.get("layer_sha256")):
        return False, None
    return True, index_row(layer, out_dir, meta)


def done_record(layer: Path, out_dir: Path, strict: bool = False) -> dict | None:
    """The render JSON of `layer` in `out_dir` when it records a finished render of the layer's
    current bytes, else None. The JSON (written last, beside its outputs) is the source of truth:

    - it names the layer's current bytes (`layer_sha256`) and was not rendered with other passes
      than its layer orders (`passes` == `layer_passes`: a `--passes` override is never done);
    - every output the layer orders exists, with the checksum the JSON records (`outputs_sha256`);
    - the identity recomputed from the current bytes of the inputs it records is its `identity`.

    A JSON without `outputs_sha256` (written before JSONs carried them) is accepted on the
    outputs' presence alone unless `strict` (the dispatcher: it re-renders such a scene unless
    its manifest row checksums the outputs, is_done)."""
    if refusal(layer):
        return None
    stem_problem = _stem_problem(Path(layer))
    if stem_problem:
        raise LayerError(stem_problem)
    meta = _meta(Path(out_dir) / f"{Path(layer).stem}.json")
    identity = meta.get("identity")
    if not identity or not isinstance(identity, str):
        return None
    # the layer's bytes first: the layer is read for its output names only when it holds what was rendered
    if meta.get("layer_sha256") != file_sha256(layer):
        return None
    if meta.get("passes", meta.get("layer_passes")) != meta.get("layer_passes"):
        return None  # rendered with other passes than the layer orders (render_layer(passes=...))
    paths = output_paths(layer, out_dir)
    if not all(p.is_file() for p in paths.values()):
        return None
    sums = meta.get("outputs_sha256")
    if isinstance(sums, dict) and sums:
        names = {p.name for k, p in paths.items() if k != "meta"}
        if set(sums) != names or not all(file_sha256(Path(out_dir) / n) == sums[n] for n in names):
            return None
    elif strict:
        return None
    return meta if current_identity(layer, meta.get("inputs")) == identity else None


def outputs_sha256(paths: dict[str, Path]) -> dict[str, str]:
    """{file name: sha256} of a render's outputs (output_paths without the JSON): what the JSON records."""
    return {p.name: file_sha256(p) for k, p in paths.items() if k != "meta"}


def manifest_row(layer: Path, out_dir: Path, meta: dict) -> dict:
    """The manifest row of a scene whose render JSON is `meta`: what is_verified checks (identity,
    each output's checksum and the stat it was taken at, the JSON's included) and what a reader of
    the index wants to see. The checksums come from file_sha256's per-process cache, so the outputs
    render_layer has just hashed for `outputs_sha256` are not read again."""
    files, stats = {}, {}
    for p in output_paths(layer, out_dir).values():
        files[p.name], st = hashed(p)
        if st is not None:
            stats[p.name] = stat_record(st)
    return {"scene": Path(layer).stem, "layer": str(Path(layer).resolve()), "layer_sha256": meta["layer_sha256"],
            "identity": meta["identity"],  # what the render read and the versions
            **record_fields(meta),  # what check_row needs of the JSON, so that a resume does not read it
            "scene_id": (meta.get("scene") or {}).get("provenance", {}).get("sceneId", Path(layer).stem),
            "files": files, "stat": stats,  # the quick check's evidence (is_verified)
            "render_seconds": meta.get("render_seconds"),
            "device": {k: (meta.get("device") or {}).get(k) for k in ("used", "backend", "gpus", "cpu_model")},
            "layer_relative": relpath(Path(layer), Path(out_dir))}


ROW_RECORD = "record"  # a row's copy of what check_row needs of the render's JSON (record_fields)


def record_fields(meta: dict) -> dict:
    """{ROW_RECORD: ...} of a render JSON `meta`: the paths of its inputs (the keys of its "inputs";
    their checksums are recomputed from the files, never trusted), the passes its layer orders and
    the passes it was rendered with. A row carries them so that the resume check need not open
    51,409 JSONs: they are the JSON's own as long as the JSON passes the row's check (it is one of
    the row's files, with its checksum and stat), so trusting them is trusting the JSON."""
    inputs = meta.get("inputs")
    return {ROW_RECORD: {"inputs": sorted(inputs) if isinstance(inputs, dict) else None,
                         "layer_passes": meta.get("layer_passes"),
                         "passes": meta.get("passes", meta.get("layer_passes"))}}


def _row_record(row: dict) -> dict | None:
    """The JSON's fields a row carries (record_fields), as a `meta` for check_row; None when the row
    has none (written before rows carried them) or they are malformed: the JSON is read then."""
    rec = row.get(ROW_RECORD)
    if not isinstance(rec, dict) or not isinstance(rec.get("inputs"), list):
        return None
    return {"identity": row.get("identity"), "inputs": rec["inputs"], "layer_passes": rec.get("layer_passes"),
            "passes": rec.get("passes")}


def prefetch(layers, rows: dict[str, dict]) -> int:
    """Checksum, several reads in flight (core.threads), every input file the manifest rows of
    `layers` carry (record_fields) outside the layer's own folder (the scene layer itself was read
    by the scan), into file_sha256's cache, before the dispatcher's decision looks at the scenes one
    by one: on a cold page cache the paper plan's ~37,000 pose layers are then read concurrently,
    not one disk round trip at a time. Only what the decision would checksum anyway (it still
    stats each file); returns how many files. Call it inside the decision's roots_cached block (its
    real paths). The outputs are not warmed so: 200,000 stats in threads cost more in GIL hand-offs
    than their disk latency (measured)."""
    from allo_usd.core.threads import in_threads
    from allo_usd.usd.safety import real_folder

    named: set[tuple[str, str]] = set()   # (folder, relative path): a shared file's name repeats 51,409 times
    for layer in layers:
        row = rows.get(_stem(layer))
        carried = _row_record(row) if isinstance(row, dict) else None
        if carried is None:
            continue
        here = real_folder(os.path.dirname(os.path.abspath(layer)))
        named.update((here, rel) for rel in carried["inputs"] if isinstance(rel, str) and "/" in rel.removeprefix("./"))
    paths = sorted({os.path.normpath(os.path.join(here, rel)) for here, rel in named})
    in_threads(file_sha256, paths)
    return len(paths)


def index_row(layer: Path, out_dir: Path, meta: dict) -> dict:
    """The manifest row of a scene whose render JSON `meta` is verified (done_record), for a scene
    another entry point rendered (render_layer, `allo-usd render LAYER`, the demo): the index
    catches up with the record instead of the scene rendering again."""
    return {**manifest_row(layer, out_dir, meta), "indexed_from": "json"}


def is_verified(row: dict | None, layer: Path, out_dir: Path, verify: bool = False) -> bool:
    """check_row found the row true (quick check of the outputs, or every byte with `verify`)."""
    return check_row(row, layer, out_dir, verify) is not None


def check_row(row: dict | None, layer: Path, out_dir: Path, verify: bool = False) -> dict | None:
    """The manifest row when it matches the current layer, every output and the identity recomputed
    from the inputs the (verified) metadata JSON records; else None. The returned row is a new one,
    with the outputs' current stat, when that differs from the recorded one (an old row without
    stat, a tree copied with its mtimes): the caller appends it, so the next run is quick again.

    The layer's bytes are compared first, by a checksum that opens regular files only: a layer is
    read for its output names only when it holds the bytes a worker rendered (and so checked). The
    inputs are always checked by checksum (per-process cache: a tree's shared files once a run).

    Outputs, the quick check (make, rsync, git's index): an output whose size, mtime_ns and inode
    are those the row recorded is trusted without being read; one whose size or mtime differs fails
    (re-rendered: truncated, rewritten, touched, replaced by a new file); one with only another
    inode (copied with its mtime kept, `cp -a`, `rsync -a`, a backup restored) is hashed and kept if
    its checksum is the row's. A row without stat (written before rows had it) is hashed. `verify`
    reads every output's bytes, ignoring stat and the checksum cache (`render --verify`: after a
    disk error, or a copy that did not keep mtimes)."""
    if not isinstance(row, dict) or not row.get("identity") or row.get("layer_sha256") != file_sha256(layer):
        return None
    files = row.get("files")
    if not isinstance(files, dict):
        return None
    stem = _stem(layer)
    # the JSON's fields: the row's copy (record_fields), else the JSON itself; trusted below only if the
    # JSON's stat (or checksum) is the row's
    carried = _row_record(row)
    meta = carried if carried is not None else _meta(os.path.join(out_dir, f"{stem}.json"))
    passes = meta.get("layer_passes")
    named = ({f"{stem}{PASS_FILES[p]}" for p in passes} | {f"{stem}.json"}
             if isinstance(passes, list) and all(isinstance(p, str) and p in PASS_FILES for p in passes) else None)
    # the outputs the layer orders: as its JSON names them (the layer's bytes are the rendered ones), else
    # read from the layer (an Sdf parse, ~2 ms: only when the two disagree)
    if set(files) != named and set(files) != {p.name for p in output_paths(layer, out_dir).values()}:
        return None
    recorded = row.get("stat") if isinstance(row.get("stat"), dict) else {}
    now = {}
    for name, digest in files.items():
        path, was = os.path.join(out_dir, name), recorded.get(name)   # a str: no Path built per output
        if verify or not isinstance(was, dict):
            got, st = hashed(path, fresh=verify)
            if got is None or got != digest:
                return None
        else:
            try:
                st = os.stat(path)
            except OSError:
                return None
            if not stat.S_ISREG(st.st_mode) or st.st_size != was.get("size") or st.st_mtime_ns != was.get("mtime_ns"):
                return None
            if st.st_ino != was.get("ino"):  # the same size and mtime in another file: its bytes decide
                got, st = hashed(path)
                if got is None or got != digest:
                    return None
        now[name] = stat_record(st)
    if meta.get("passes", meta.get("layer_passes")) != meta.get("layer_passes"):
        return None  # a `--passes` override's render (indexed by render_layer): not the layer's own outputs
    if meta.get("identity") != row["identity"] or current_identity(layer, meta.get("inputs")) != row["identity"]:
        return None
    if now == recorded and carried is not None:
        return row
    return {**row, "stat": now, **(record_fields(meta) if carried is None else {})}


# ---------------------------------------------------------------- manifest.jsonl

def read_jsonl(path: Path) -> list[dict]:
    rows = []
    if path.is_file():
        for line in path.read_text(errors="replace").splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line torn by a crash mid-append
            if isinstance(row, dict) and "scene" in row:
                rows.append(row)
    return rows


def load_manifest(out_dir: Path) -> dict[str, dict]:
    """Finished scenes by name (the last row of a scene wins; torn lines and rows without a scene
    name are skipped)."""
    path = Path(out_dir) / MANIFEST
    return _manifest_rows(path)[0] if path.is_file() else {}


def _manifest_rows(path: Path) -> tuple[dict[str, dict], bool]:
    """(finished scenes by name, whether the file holds anything but one whole line per scene: a torn
    or foreign line, a repeated scene, no final newline)."""
    rows: dict[str, dict] = {}
    text = path.read_text(errors="replace")
    lines = text.splitlines()
    messy = bool(text) and not text.endswith("\n")
    for line in lines:
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            messy = True
            continue
        if not isinstance(row, dict) or not isinstance(row.get("scene"), str):
            messy = True
            continue
        messy = messy or row["scene"] in rows
        rows[row["scene"]] = row
    return rows, messy


def append_jsonl(path: Path, row: dict) -> None:
    """One os.write of one line on an O_APPEND descriptor, then fsync: a crash loses at most the line.
    A line torn by an earlier crash is ended first, so it cannot swallow this one; a write cut
    short by a full disk is truncated away, so the file never ends in half a line."""
    append_rows(path, [row])


def append_rows(path: Path, rows: list[dict]) -> None:
    """append_jsonl for many rows in one write and one fsync (a resume that upgrades or indexes
    thousands of rows: one fsync each would cost minutes). A crash loses at most the last line."""
    if not rows:
        return
    data = "".join(json.dumps(row, sort_keys=True) + "\n" for row in rows).encode()
    fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        size = os.fstat(fd).st_size
        try:
            if size and os.pread(fd, 1, size - 1) != b"\n":
                data = b"\n" + data
            if os.write(fd, data) != len(data):
                raise OSError(errno.ENOSPC, "short write", str(path))
            os.fsync(fd)
        except OSError as exc:
            if exc.errno in DISK_FULL_ERRNOS:
                try:
                    os.ftruncate(fd, size)
                except OSError:
                    pass
                raise DiskFullError(f"no space left on the device while appending to {path}; free space and "
                                    "re-run") from exc
            raise
    finally:
        os.close(fd)


def compact_manifest(out_dir: Path) -> dict[str, dict]:
    """Rewrite the manifest with one row per scene (atomically), dropping torn lines and repeats,
    when it holds any (a clean 51,409-row manifest is read once, not rewritten); returns the
    finished scenes by name (load_manifest)."""
    path = Path(out_dir) / MANIFEST
    if not path.is_file():
        return {}
    rows, messy = _manifest_rows(path)
    if messy:
        text = "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows.values())
        with atomic_path(path) as tmp:
            tmp.write_text(text)
    return rows


def clean_stale(out_dir: Path, pid: int | None = None) -> int:
    """Remove temporaries left by killed writers (only those of writer `pid` when given: the
    others may belong to live workers); returns how many files beside the outputs went."""
    out_dir = Path(out_dir)
    pattern = temp_name_re(pid)
    n = 0
    if out_dir.is_dir():
        with os.scandir(out_dir) as entries:   # a paper-size folder holds ~260,000 names: no Path, no stat each
            stale = [e.path for e in entries if e.name.startswith(".") and pattern.match(e.name) and e.is_file()]
        for p in stale:
            Path(p).unlink(missing_ok=True)
            n += 1
    shutil.rmtree(out_dir / WORKDIR if pid is None else out_dir / WORKDIR / str(int(pid)), ignore_errors=True)
    return n
