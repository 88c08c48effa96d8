"""The render record NAME.json, one definition: what `render_layer` writes beside a render's files
(last, so its presence marks a finished scene) and what every reader of it gets back.

It lives in the output layer, not in `run/` where the renders happen: the dataset
(allo_usd.output.dataset) and its annotation files read records, and a layer may import only its own
and lower layers (tests/system/test_import_graph.py); the render job (`run/`) builds it from above.

The JSON is `json.dumps(indent=2, sort_keys=True)` of `as_dict()` (allo_usd.output.writers.write_json),
so its bytes depend on the values only, not on the order of the fields here: finished renders stay
done. A field that is None is not written: `amodal_seconds` and `instances` exist only with their
passes (amodal, instance), and a record read from an older JSON lacks what that JSON lacked.

A record read back (`of`, `load`) is not trusted: its values are what the JSON holds, of whatever
type (JSON null and a missing key both read as None), and each reader checks what it relies on
(allo_usd.output.identity.done_record: the done rule; allo_usd.output.dataset.check_render: the
dataset's rules). The table of the fields is docs/render_record.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from allo_usd.core.files import MAX_RECORD_BYTES, read_user_json


@dataclass(frozen=True)
class RenderRecord:
    """One render's record: where it came from, its identity, what rendered it, its pixel counts and
    files, and the scene's annotations (the JSON's keys are these field names)."""

    layer: str | None = None               # the scene layer, absolute (the rendering machine's path)
    layer_relative: str | None = None      # the layer from the render folder: moves with the tree
    layer_sha256: str | None = None
    identity: str | None = None            # allo_usd.output.identity.render_identity of inputs and versions
    inputs: dict | None = None             # {path relative to the layer's folder: sha256} of what it read
    versions: dict | None = None           # the versions that affect pixels (in the identity)
    libraries: dict | None = None          # every library that computes values (core.provenance)
    package_version: str | None = None
    device: dict | None = None             # allo_usd.blender.device.record: asked, used, GPUs or CPU
    cycles_cpu: dict | None = None         # the CPU kernel Cycles used and the flags that pick it
    render_seconds: float | None = None
    amodal_seconds: float | None = None    # only with the amodal pass
    resolution: list | None = None         # [width, height]
    class_pixels: dict | None = None       # {"background", "station_and_bodies", "anomaly": pixels}
    anomaly_fraction: float | None = None
    station_fraction: float | None = None
    bodies: dict | None = None             # {"sun"|"earth"|"moon": {"pixels": n}}
    passes: list | None = None             # the passes written (a record without it: its layer's)
    layer_passes: list | None = None       # the passes its layer orders
    target: dict | None = None             # the target mode it rendered to (identity.render_target), in the identity
    layer_target: dict | None = None       # the target its layer orders (differs from `target` after an override)
    accuracy: dict | None = None           # the render's estimated accuracy (allo_usd.blender.render.RenderResult)
    instances: dict | None = None          # only with the instance pass: {"id": prim path}
    scene: dict | None = None              # allo_usd.usd.read_labels.read_meta of the layer
    effects: dict | None = None            # post-render effects applied (sensor noise)
    files: dict | None = None              # {pass or "meta": file name in the render folder}
    outputs_sha256: dict | None = None     # {file name: sha256} of every output but the JSON
    annotations: dict | None = None        # camera, anomaly, bodies in view (allo_usd.output.annotations)

    @classmethod
    def of(cls, meta: dict) -> "RenderRecord":
        """The record a parsed NAME.json holds; keys it does not know are dropped. A JSON without
        "passes" (written before a run could override them) rendered its layer's passes."""
        values = {f.name: meta.get(f.name) for f in dataclasses.fields(cls)}
        if "passes" not in meta:
            values["passes"] = meta.get("layer_passes")
        return cls(**values)

    @classmethod
    def from_json(cls, value) -> "RenderRecord | None":
        """The record a parsed JSON file holds, or None when it is no render record: not an object,
        or without the "scene" and "files" keys (a plan or a report beside the renders)."""
        if not isinstance(value, dict) or "scene" not in value or "files" not in value:
            return None
        return cls.of(value)

    @classmethod
    def load(cls, path: Path, roots=None) -> "RenderRecord | None":
        """from_json of the file at `path` read through the read gate (core.files.read_user_json: a
        FIFO or /dev/zero named NAME.json is never opened, a huge or deeply nested one never parsed:
        InputRefused). `roots`: folders the file must lie in."""
        return cls.from_json(read_user_json(path, MAX_RECORD_BYTES, "render record", roots=roots))

    @classmethod
    def given(cls, meta: "RenderRecord | dict") -> "RenderRecord":
        """`meta` as a record: a RenderRecord as it is, a parsed NAME.json object through `of` (for
        callers that hold the JSON: the annotation columns and records take either)."""
        return meta if isinstance(meta, RenderRecord) else cls.of(meta)

    def as_dict(self) -> dict:
        """The JSON's object: every field that is not None."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}

    def write(self, path: Path) -> Path:
        """NAME.json, atomically (allo_usd.output.writers.write_json). A record a render writes names
        every field but the OPTIONAL ones: a missing one is a programming error, never a file."""
        from allo_usd.output.writers import write_json

        missing = [f.name for f in dataclasses.fields(self) if getattr(self, f.name) is None and f.name not in OPTIONAL]
        if missing:
            raise ValueError(f"a render record without {', '.join(missing)} is not written ({path})")
        return write_json(path, self.as_dict())

    def json_text(self) -> str:
        """What `write` puts in NAME.json (allo_usd.output.writers.json_text)."""
        from allo_usd.output.writers import json_text

        return json_text(self.as_dict())


# written only with their passes (amodal, instance), with a target (target, layer_target) or an estimate (accuracy)
OPTIONAL = ("amodal_seconds", "instances", "target", "layer_target", "accuracy")
