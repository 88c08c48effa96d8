"""The render record NAME.json has one definition (allo_usd.output.record.RenderRecord): a record
writes byte for byte what its dict literal form writes (so finished renders stay done), a real
render's JSON loads to its own bytes, and docs/render_record.md lists exactly its fields."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from allo_usd.output.record import OPTIONAL, RenderRecord
from allo_usd.output.writers import json_text, write_json

DOC = Path(__file__).resolve().parents[2] / "docs" / "render_record.md"


def _values(amodal: bool, instance: bool) -> dict:
    """A render's values, as the render job computes them (numpy scalars included: write_json's default)."""
    import numpy as np

    counts = np.array([1000, 250, 46])
    paths = {"rgb": "s.png", "mask": "s_mask.png", **({"amodal": "s_amodal.png"} if amodal else {}),
             **({"instance": "s_instance.png"} if instance else {}), "meta": "s.json"}
    return {"inputs": {"s.usda": "a" * 64, "../sky/d.usda": "b" * 64}, "counts": counts, "paths": paths,
            "objects": ("/World/Station", "/World/Bodies/Sun"), "seconds": 12.34567, "amodal_seconds": 0.98765}


def _dict_form(v: dict, amodal: bool, instance: bool) -> dict:
    """The record as a dict literal, keys in the render job's order, the optional ones only with their passes."""
    counts = v["counts"]
    return {
        "layer": "/r/layers/s.usda", "layer_relative": "../layers/s.usda", "layer_sha256": "c" * 64,
        "identity": "d" * 64, "inputs": v["inputs"], "versions": {"allo_usd": "0.1.0", "bpy": "4.2.0"},
        "libraries": {"numpy": "2.0.0"}, "package_version": "0.1.0", "device": {"asked": "auto", "used": "cpu"},
        "cycles_cpu": {"kernel": "AVX2"}, "render_seconds": round(v["seconds"], 3),
        **({"amodal_seconds": round(v["amodal_seconds"], 3)} if amodal else {}),
        "resolution": list((64, 48)),
        "class_pixels": {"background": int(counts[0]), "station_and_bodies": int(counts[1]), "anomaly": int(counts[2])},
        "anomaly_fraction": float(counts[2] / counts.sum()),
        "station_fraction": 0.25, "bodies": {"sun": {"pixels": 3}, "earth": {"pixels": 0}, "moon": {"pixels": 9}},
        "passes": ["rgb", "mask"], "layer_passes": ["rgb", "mask"],
        **({"instances": {str(i): p for i, p in enumerate(v["objects"], start=1)}} if instance else {}),
        "scene": {"split": "test", "variant": "anomaly", "pose": (1, 2)}, "effects": {},
        "files": dict(v["paths"]), "outputs_sha256": {"s.png": "e" * 64},
        "annotations": {"camera": {"K_px": [[1.5, 0, 32], [0, 1.5, 24], [0, 0, 1]]}},
    }


def _record(v: dict, amodal: bool, instance: bool) -> RenderRecord:
    counts = v["counts"]
    return RenderRecord(
        layer="/r/layers/s.usda", layer_relative="../layers/s.usda", layer_sha256="c" * 64, identity="d" * 64,
        inputs=v["inputs"], versions={"allo_usd": "0.1.0", "bpy": "4.2.0"}, libraries={"numpy": "2.0.0"},
        package_version="0.1.0", device={"asked": "auto", "used": "cpu"}, cycles_cpu={"kernel": "AVX2"},
        render_seconds=round(v["seconds"], 3), amodal_seconds=round(v["amodal_seconds"], 3) if amodal else None,
        resolution=list((64, 48)),
        class_pixels={"background": int(counts[0]), "station_and_bodies": int(counts[1]), "anomaly": int(counts[2])},
        anomaly_fraction=float(counts[2] / counts.sum()), station_fraction=0.25,
        bodies={"sun": {"pixels": 3}, "earth": {"pixels": 0}, "moon": {"pixels": 9}},
        passes=["rgb", "mask"], layer_passes=["rgb", "mask"],
        instances={str(i): p for i, p in enumerate(v["objects"], start=1)} if instance else None,
        scene={"split": "test", "variant": "anomaly", "pose": (1, 2)}, effects={}, files=dict(v["paths"]),
        outputs_sha256={"s.png": "e" * 64}, annotations={"camera": {"K_px": [[1.5, 0, 32], [0, 1.5, 24], [0, 0, 1]]}})


@pytest.mark.parametrize("amodal", [False, True])
@pytest.mark.parametrize("instance", [False, True])
def test_a_record_writes_the_bytes_of_its_dict_form(tmp_path, amodal, instance):
    v = _values(amodal, instance)
    literal, rec = _dict_form(v, amodal, instance), _record(v, amodal, instance)
    assert rec.as_dict() == literal and list(rec.as_dict()) == list(literal)
    write_json(tmp_path / "literal.json", literal)
    rec.write(tmp_path / "new.json")
    assert (tmp_path / "new.json").read_bytes() == (tmp_path / "literal.json").read_bytes()
    assert rec.json_text() == (tmp_path / "literal.json").read_text()
    loaded = RenderRecord.load(tmp_path / "new.json")
    assert loaded.json_text() == (tmp_path / "literal.json").read_text()


@pytest.mark.render
def test_a_rendered_json_loads_to_its_own_bytes(rendered):
    """A real render's NAME.json: loaded and written again, the same bytes; render_layer's answer is its object."""
    for layer, meta, out in rendered.values():
        path = out / f"{layer.stem}.json"
        data = path.read_bytes()
        rec = RenderRecord.load(path)
        assert rec.json_text().encode() == data
        assert rec.as_dict() == json.loads(data)
        assert json_text(meta).encode() == data   # what render_layer returned (tuples where the JSON has lists)
        assert RenderRecord.of(json.loads(data)) == rec


def test_a_record_without_a_field_is_not_written(tmp_path):
    v = _values(False, False)
    rec = dataclasses.replace(_record(v, False, False), identity=None)
    with pytest.raises(ValueError, match="without identity"):
        rec.write(tmp_path / "s.json")
    assert not (tmp_path / "s.json").exists()


def test_a_loaded_record_is_what_the_json_holds():
    """Unknown keys are dropped, null and missing read alike, and a record from before "passes"
    rendered its layer's passes; a JSON that is not an object is no record."""
    rec = RenderRecord.of({"identity": "x", "layer_passes": ["rgb"], "extra": 1, "scene": None})
    assert rec.identity == "x" and rec.passes == ["rgb"] and rec.scene is None
    assert rec.as_dict() == {"identity": "x", "layer_passes": ["rgb"], "passes": ["rgb"]}
    assert RenderRecord.of({"passes": None, "layer_passes": ["rgb"]}).passes is None


def test_a_json_that_is_no_render_record_loads_as_none(tmp_path):
    """Not an object, or without "scene" and "files" (a plan or a report beside the renders); a null
    scene is still a record (its reader refuses it)."""
    for text in ("[1, 2]", '{"files": {}}', '{"scene": {}}'):
        (tmp_path / "s.json").write_text(text)
        assert RenderRecord.load(tmp_path / "s.json") is None, text
    (tmp_path / "s.json").write_text('{"scene": null, "files": {}}')
    assert RenderRecord.load(tmp_path / "s.json") == RenderRecord(files={})


def test_the_doc_lists_exactly_the_fields():
    """docs/render_record.md's table names every field of RenderRecord once, in its order, and no other."""
    rows = re.findall(r"^\| `([a-z_0-9]+)` \|", DOC.read_text(), flags=re.M)
    assert rows == [f.name for f in dataclasses.fields(RenderRecord)]
    text = DOC.read_text()
    assert all(f"`{name}`" in text for name in OPTIONAL)
