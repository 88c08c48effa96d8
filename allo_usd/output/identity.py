"""A render's identity and the rule of "done": one rule for `allo-usd render LAYER`, render_layer,
the dispatcher's resume and the demo, so they never disagree about what to skip.

A render's identity is the SHA-256 of a canonical JSON of its inputs and of the versions that
affect pixels: every file its composition read (allo_usd.usd.dependencies.walk: each layer of the
stack, the referenced assets, the textures), as {path relative to the layer's directory: sha256},
and allo-usd's, bpy's, usd-core's and numpy's versions (read from package metadata: the parent never
imports bpy; numpy draws the sensor noise, whose Generator streams a numpy release may change, and
encodes sRGB). Other libraries (image encoders, the plan's numerics) are recorded in the record's
"libraries" (allo_usd.core.provenance), not in the identity: a new version of one does not re-render
finished scenes.

The render record NAME.json (allo_usd.output.record), written last beside its outputs, records
"identity", "inputs", "versions" and "outputs_sha256" (each output's checksum), and it is the
record: a scene is done for every entry point when its JSON verifies (done_record), whichever
rendered it; the dispatcher's index (allo_usd.run.render_index) keeps up with it. A scene is done
only while the identity recomputed from the recorded inputs' current bytes matches: the recorded
inputs are the complete list of what the render read, so if none of their bytes changed, a new walk
would read the same files. Checksums come from allo_usd.output.checksums' per-process cache.

It lives in the output layer beside the record it reads; the render job (`run/`) uses it from above.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path

from allo_usd.core.errors import LayerError
from allo_usd.core.files import MAX_RECORD_BYTES, InputRefused, read_user_json, relpath
from allo_usd.core.version import __version__
from allo_usd.output.checksums import file_sha256
from allo_usd.output.record import RenderRecord
from allo_usd.output.render_outputs import output_paths, stem_problem
from allo_usd.usd.sniff import refusal


@functools.cache
def render_versions() -> dict[str, str]:
    """The package versions that affect pixels (from package metadata: importing bpy is not needed):
    allo-usd, the renderer (bpy), what a layer composes to (usd-core) and numpy (sensor noise, sRGB)."""
    from allo_usd.core.provenance import installed_version

    def installed(name: str) -> str:
        return installed_version(name) or "not installed"

    return {"allo_usd": __version__, "bpy": installed("bpy"), "usd-core": installed("usd-core"),
            "numpy": installed("numpy")}


def render_identity(inputs: dict[str, str], versions: dict[str, str] | None = None, target=None) -> str:
    """SHA-256 of the canonical JSON of a render's inputs ({relative path: sha256}) and versions, and of
    its `target` (render_target: the target mode it rendered to) when it has one: a render without a
    target keeps the identity it had before the target mode, and a changed target re-renders."""
    record = {"inputs": inputs, "versions": render_versions() if versions is None else versions}
    if target:
        record["target"] = target
    return hashlib.sha256(json.dumps(record, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def render_target(render) -> dict | None:
    """The target mode a render's settings (a RenderDesc) ask for, as its record and identity hold it:
    {"target_psnr": dB, "time_limit": seconds}, or None for fixed samples."""
    if not render.target_psnr > 0:
        return None
    return {"target_psnr": float(render.target_psnr), "time_limit": float(render.time_limit)}


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


def current_identity(layer: Path, inputs, target=None) -> str | None:
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
    return render_identity(now, target=target)


def record_json(path: Path) -> dict:
    """A render record NAME.json as parsed, read through the read gate (core.files.read_user_json: a
    FIFO or /dev/zero named NAME.json is never opened, a huge or deeply nested one never parsed), or
    {} when it cannot be used: the scene then counts as not done and renders again."""
    try:
        meta = read_user_json(path, MAX_RECORD_BYTES, "render record")
    except InputRefused:
        return {}
    return meta if isinstance(meta, dict) else {}


def done_record(layer: Path, out_dir: Path, strict: bool = False) -> RenderRecord | None:
    """The render record of `layer` in `out_dir` when it records a finished render of the layer's
    current bytes, else None. The JSON (written last, beside its outputs) is the source of truth:

    - it names the layer's current bytes (`layer_sha256`) and was not rendered with other passes
      than its layer orders (`passes` == `layer_passes`: a `--passes` override is never done), nor to
      another target (`target` == `layer_target`: likewise a `--target-psnr` override);
    - every output the layer orders exists, with the checksum the JSON records (`outputs_sha256`);
    - the identity recomputed from the current bytes of the inputs it records (and its `target`) is
      its `identity`.

    A JSON without `outputs_sha256` (written before JSONs carried them) is accepted on the
    outputs' presence alone unless `strict` (the dispatcher: it re-renders such a scene unless
    its manifest row checksums the outputs, is_done)."""
    if refusal(layer):
        return None
    problem = stem_problem(Path(layer))
    if problem:
        raise LayerError(problem)
    meta = RenderRecord.of(record_json(Path(out_dir) / f"{Path(layer).stem}.json"))
    identity = meta.identity
    if not identity or not isinstance(identity, str):
        return None
    # the layer's bytes first: the layer is read for its output names only when it holds what was rendered
    if meta.layer_sha256 != file_sha256(layer):
        return None
    if meta.passes != meta.layer_passes:
        return None  # rendered with other passes than the layer orders (render_layer(passes=...))
    if meta.target != meta.layer_target:
        return None  # rendered to another target than the layer's (`render --target-psnr`)
    paths = output_paths(layer, out_dir)
    if not all(p.is_file() for p in paths.values()):
        return None
    sums = meta.outputs_sha256
    if isinstance(sums, dict) and sums:
        names = {p.name for k, p in paths.items() if k != "meta"}
        if set(sums) != names or not all(file_sha256(Path(out_dir) / n) == sums[n] for n in names):
            return None
    elif strict:
        return None
    return meta if current_identity(layer, meta.inputs, meta.target) == identity else None


def outputs_sha256(paths: dict[str, Path]) -> dict[str, str]:
    """{file name: sha256} of a render's outputs (output_paths without the JSON): what the JSON records."""
    return {p.name: file_sha256(p) for k, p in paths.items() if k != "meta"}

