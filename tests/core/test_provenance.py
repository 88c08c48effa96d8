"""The versions that computed the bytes: every render's JSON records `libraries`, every
authored tree a `versions.json` (allo_usd.core.provenance); none of it enters a USD layer."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest

from allo_usd.core import provenance
from allo_usd.core.paths import BASE_STAGE, ROOT
from allo_usd.core.provenance import LIBRARIES, TREE_VERSIONS, library_versions, record_tree_versions
from allo_usd.output.identity import render_identity, render_versions


def one_scene_plan():
    from allo_usd.plan.model import Anomalies, Dates, Plan, Poses, Quality

    return Plan(name="versions", dates=Dates(days=1), poses=Poses(train=[1], test=[]), anomalies=Anomalies(assets=[]),
                quality=Quality(resolution=(64, 36), samples=2), base_stage=str(BASE_STAGE))


def runs(tree) -> list[dict]:
    return json.loads((tree / TREE_VERSIONS).read_text())["runs"]


@pytest.mark.process
def test_versions_come_from_metadata_without_importing_bpy():
    code = ("import json, sys; from allo_usd.core.provenance import library_versions; "
            "v = library_versions(); assert 'bpy' not in sys.modules, 'bpy imported'; print(json.dumps(v))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    versions = json.loads(r.stdout)
    assert list(versions) == [*LIBRARIES, "lock_sha256"]
    assert versions["numpy"] == np.__version__ and versions["bpy"] and versions["usd-core"]
    assert all(versions[n] for n in LIBRARIES), {n: v for n, v in versions.items() if not v}  # all installed here
    lock = ROOT / "requirements.lock"
    assert versions["lock_sha256"] == hashlib.sha256(lock.read_bytes()).hexdigest()
    assert versions == library_versions()


def test_an_installed_wheel_names_no_lock(monkeypatch):
    """A wheel carries its data inside the package (core.paths.DATA is the package): no checkout, no lock."""
    from allo_usd.core import paths

    assert provenance.lock_path() == ROOT / "requirements.lock"
    monkeypatch.setattr(paths, "DATA", paths.PACKAGE)
    assert provenance.lock_path() is None


def test_the_render_identity_covers_numpy():
    """numpy draws the sensor noise (Generator streams may change between numpy releases) and encodes
    sRGB: a render made with another numpy is not done (allo_usd.output.identity)."""
    versions = render_versions()
    assert versions["numpy"] == np.__version__
    inputs = {"./s.usda": "0" * 64}
    assert render_identity(inputs) == render_identity(inputs, versions)
    assert render_identity(inputs, {**versions, "numpy": "2.0.0"}) != render_identity(inputs)


@pytest.mark.render
def test_a_render_json_records_the_libraries(rendered):
    layer, meta, out = rendered["normal"]
    on_disk = json.loads((out / f"{layer.stem}.json").read_text())
    for record in (meta, on_disk):
        assert record["libraries"] == library_versions()
        assert record["libraries"]["numpy"] == np.__version__
        assert record["versions"]["numpy"] == np.__version__
    assert "numpy" not in layer.read_text() and np.__version__ not in layer.read_text()


@pytest.mark.slow
def test_an_authored_tree_records_each_runs_versions(tmp_path, monkeypatch):
    from allo_usd.run.author import author_plan
    from allo_usd.usd.tree import TREE_ENTRIES

    tree = tmp_path / "tree"
    [layer] = author_plan(one_scene_plan(), tree, progress=False)
    assert runs(tree) == [library_versions()]
    lock = library_versions()["lock_sha256"]
    for usda in tree.rglob("*.usd*"):   # never inside a layer: layers stay byte-identical across versions
        text = usda.read_bytes()
        assert f'"{np.__version__}"'.encode() not in text and (lock is None or lock.encode() not in text), usda
    record = (tree / TREE_VERSIONS).read_bytes()

    author_plan(one_scene_plan(), tree, progress=False)          # a resume with the same versions
    assert (tree / TREE_VERSIONS).read_bytes() == record

    other = {**library_versions(), "numpy": "1.26.0"}
    monkeypatch.setattr(provenance, "library_versions", lambda: dict(other))
    layer_bytes = layer.read_bytes()
    assert author_plan(one_scene_plan(), tree, progress=False) == [layer]   # not refused
    assert layer.read_bytes() == layer_bytes
    assert [r["numpy"] for r in runs(tree)] == [np.__version__, "1.26.0"]

    assert TREE_VERSIONS in TREE_ENTRIES
    monkeypatch.undo()
    author_plan(one_scene_plan(), tree, progress=False, replace=True)   # --replace starts the record anew
    assert runs(tree) == [library_versions()]


def test_an_unreadable_record_is_replaced_not_refused(tmp_path):
    for bad in ("{not json", "[]", '{"runs": 3}'):
        (tmp_path / TREE_VERSIONS).write_text(bad)
        record_tree_versions(tmp_path)
        assert runs(tmp_path) == [library_versions()]
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]   # written atomically, no temporary


def test_the_demo_tree_records_its_versions(tmp_path, monkeypatch):
    """The demo authors a tree in OUT/layers: its versions.json is written before any scene (stopped here
    before anything is resolved or rendered)."""
    from allo_usd.run import demo

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop

    monkeypatch.setattr(demo, "scene_inputs", stop)
    monkeypatch.setattr("allo_usd.sky.model.compute_sky", lambda *a, **k: None)
    with pytest.raises(Stop):
        demo.run_demo(tmp_path / "demo", progress=False)
    assert runs(tmp_path / "demo" / "layers") == [library_versions()]
