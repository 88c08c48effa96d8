"""The dispatcher's index of finished renders, OUT/manifest.jsonl: one JSON line per scene, appended
as workers finish, so that a resume of a 51,409-scene run decides what is done without opening the
render records.

The render record NAME.json beside the outputs is the record (allo_usd.output.identity.done_record);
a row is an index the dispatcher keeps up with it: the scene's identity, each output's checksum and
the stat it was taken at (the quick check, is_verified), and a copy of what the check needs of the
record (record_fields). A scene another entry point rendered gets its row from its record
(index_row). is_done is the one rule of "done" for every entry point, with or without an index.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import stat
from pathlib import Path

from allo_usd.core.errors import DiskFullError
from allo_usd.core.files import DISK_FULL_ERRNOS, atomic_path, relpath, temp_name_re
from allo_usd.output.checksums import _SHA256, file_sha256, hashed  # noqa: F401 - _SHA256: the cache its checks fill
from allo_usd.output.identity import current_identity, done_record
from allo_usd.output.identity import record_json as _meta   # the JSON check_row reads when a row carries no copy
from allo_usd.output.record import RenderRecord
from allo_usd.output.render_outputs import PASS_FILES, layer_stem, output_paths
from allo_usd.usd.sniff import refusal

MANIFEST = "manifest.jsonl"
WORKDIR = ".allo-tmp"  # Blender's render files, one directory per worker pid


def stat_record(st: os.stat_result) -> dict[str, int]:
    """What the quick check compares (is_verified): a rewrite changes the size or the mtime, a
    replacement (os.replace of a new file) the inode. Not ctime: restoring an mtime by hand, or a
    hard link made elsewhere, changes it without changing a byte."""
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "ino": st.st_ino}


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
    return resume_check(layer, out_dir, manifest.get(layer_stem(layer)), verify)[0]


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
    if isinstance(row, dict) and (row.get("identity"), row.get("layer_sha256")) == (meta.identity, meta.layer_sha256):
        return False, None
    return True, index_row(layer, out_dir, meta)


def manifest_row(layer: Path, out_dir: Path, meta: RenderRecord) -> dict:
    """The manifest row of a scene whose render record is `meta`: what is_verified checks (identity,
    each output's checksum and the stat it was taken at, the JSON's included) and what a reader of
    the index wants to see. The checksums come from file_sha256's per-process cache, so the outputs
    render_layer has just hashed for `outputs_sha256` are not read again."""
    files, stats = {}, {}
    for p in output_paths(layer, out_dir).values():
        files[p.name], st = hashed(p)
        if st is not None:
            stats[p.name] = stat_record(st)
    return {"scene": Path(layer).stem, "layer": str(Path(layer).resolve()), "layer_sha256": meta.layer_sha256,
            "identity": meta.identity,  # what the render read and the versions
            **record_fields(meta),  # what check_row needs of the JSON, so that a resume does not read it
            "scene_id": (meta.scene or {}).get("provenance", {}).get("sceneId", Path(layer).stem),
            "files": files, "stat": stats,  # the quick check's evidence (is_verified)
            "render_seconds": meta.render_seconds,
            "device": {k: (meta.device or {}).get(k) for k in ("used", "backend", "gpus", "cpu_model")},
            "layer_relative": relpath(Path(layer), Path(out_dir))}


ROW_RECORD = "record"  # a row's copy of what check_row needs of the render's JSON (record_fields)


def record_fields(meta: RenderRecord) -> dict:
    """{ROW_RECORD: ...} of a render record `meta`: the paths of its inputs (the keys of its "inputs";
    their checksums are recomputed from the files, never trusted), the passes its layer orders and
    the passes it was rendered with (and, for a render to a target, the target and its layer's). A row carries them so that the resume check need not open
    51,409 JSONs: they are the JSON's own as long as the JSON passes the row's check (it is one of
    the row's files, with its checksum and stat), so trusting them is trusting the JSON."""
    inputs = meta.inputs
    targets = {k: getattr(meta, k) for k in ("target", "layer_target") if getattr(meta, k) is not None}
    return {ROW_RECORD: {"inputs": sorted(inputs) if isinstance(inputs, dict) else None,
                         "layer_passes": meta.layer_passes, "passes": meta.passes, **targets}}


def _row_record(row: dict) -> RenderRecord | None:
    """The record's fields a row carries (record_fields), as a record for check_row; None when the row
    has none (written before rows carried them) or they are malformed: the JSON is read then."""
    rec = row.get(ROW_RECORD)
    if not isinstance(rec, dict) or not isinstance(rec.get("inputs"), list):
        return None
    return RenderRecord(identity=row.get("identity"), inputs=rec["inputs"], layer_passes=rec.get("layer_passes"),
                        passes=rec.get("passes"), target=rec.get("target"), layer_target=rec.get("layer_target"))


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
        row = rows.get(layer_stem(layer))
        carried = _row_record(row) if isinstance(row, dict) else None
        if carried is None:
            continue
        here = real_folder(os.path.dirname(os.path.abspath(layer)))
        named.update((here, rel) for rel in carried.inputs if isinstance(rel, str) and "/" in rel.removeprefix("./"))
    paths = sorted({os.path.normpath(os.path.join(here, rel)) for here, rel in named})
    in_threads(file_sha256, paths)
    return len(paths)


def index_row(layer: Path, out_dir: Path, meta: RenderRecord) -> dict:
    """The manifest row of a scene whose render record `meta` is verified (done_record), for a scene
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
    stem = layer_stem(layer)
    # the JSON's fields: the row's copy (record_fields), else the JSON itself; trusted below only if the
    # JSON's stat (or checksum) is the row's
    carried = _row_record(row)
    meta = carried if carried is not None else RenderRecord.of(_meta(os.path.join(out_dir, f"{stem}.json")))
    passes = meta.layer_passes
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
    if meta.passes != meta.layer_passes or meta.target != meta.layer_target:
        return None  # a `--passes` or `--target-psnr` override's render (indexed by render_layer): not the layer's own
    if meta.identity != row["identity"] or current_identity(layer, meta.inputs, meta.target) != row["identity"]:
        return None
    if now == recorded and carried is not None:
        return row
    return {**row, "stat": now, **(record_fields(meta) if carried is None else {})}


# ---------------------------------------------------------------- manifest.jsonl

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
