"""Dataset plans (counts, validation, files, schema) and authoring a tiny plan by composition."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import replace
from pathlib import Path

import pytest
from pxr import Sdf, Usd

from allo_usd.errors import PlanError
from allo_usd.paths import BASE_STAGE, SCHEMAS
from allo_usd.plan import (AnomalyChoice, Anomalies, Dates, Plan, Poses, Quality, enumerate_scenes, load_plan,
                           make_plan, paper_plan, save_plan, schema_text)

from test_validation import validation_errors


def test_paper_plan_matches_table_ii():
    plan = paper_plan()
    keys = enumerate_scenes(plan)
    counts = Counter((k.split, k.kind) for k in keys)
    assert counts == {("train", "normal"): 29_085, ("test", "normal"): 7_300, ("test", "anomaly"): 15_024}
    assert len(keys) == 51_409 and len({k.scene_id for k in keys}) == 51_409
    assert {k.pose for k in keys if k.split == "train"} == set(range(1, 41))
    assert {k.pose for k in keys if k.split == "test"} == set(range(41, 51))
    assert {k.day for k in keys} == set(range(365)) and plan.seeds == [2030, 2031]
    assert plan.dates.epochs()[-1].isoformat() == "2030-12-31T00:00:00+00:00"
    assert len({k.asset for k in keys if k.asset}) == 16
    assert enumerate_scenes(paper_plan()) == keys  # deterministic


def test_poses_disjoint_and_named():
    with pytest.raises(PlanError, match=r"poses\.test.*|poses: .*both train and test"):
        make_plan({"name": "x", "poses": {"train": [1, 2, 3], "test": [3, 41]}})
    with pytest.raises(PlanError, match=r"poses.train.*outside 1..50"):
        make_plan({"name": "x", "poses": {"train": [0, 51]}})


@pytest.mark.parametrize("data, field", [
    ({"dates": {"start": "2060-01-01"}}, "dates"),
    ({"anomalies": {"assets": ["no_such_thing"]}}, "anomalies.assets.0"),
    ({"quality": {"resolution": [0, 1080]}}, "quality.resolution"),
    ({"counts": {"normal_test": 10**6}}, "counts.normal_test"),
    ({"colour": "red"}, "colour"),
])
def test_validation_names_field_and_fix(data, field):
    with pytest.raises(PlanError) as err:
        make_plan({"name": "x", **data})
    line = next(line for line in str(err.value).splitlines() if line.startswith(f"{field}: ") or field in line)
    assert "fix:" in line, str(err.value)


@pytest.mark.parametrize("suffix", [".toml", ".yaml"])
def test_file_round_trip(tmp_path, suffix):
    plan = paper_plan()
    path = save_plan(plan, tmp_path / f"plan{suffix}")
    assert load_plan(path) == plan
    with pytest.raises(PlanError, match="toml, .yaml"):
        save_plan(plan, tmp_path / "plan.json")


def test_committed_json_schema_is_current():
    assert (SCHEMAS / "plan.schema.json").read_text() == schema_text()
    assert json.loads(schema_text())["title"] == "Plan"


# ---------------------------------------------------------------------------------------------
# Authoring a tiny plan

def tiny_plan() -> Plan:
    return Plan(name="tiny", dates=Dates(days=2), poses=Poses(train=[1, 2], test=[41]),
                anomalies=Anomalies(assets=[AnomalyChoice(id="power_drill")], depths=[0, 1, 2, 3, 4]),
                quality=Quality(resolution=(64, 36), samples=4), base_stage=str(BASE_STAGE))


@pytest.fixture(scope="module")
def authored(tmp_path_factory):
    from allo_usd.authoring import author_plan

    out = tmp_path_factory.mktemp("tiny")
    paths = author_plan(tiny_plan(), out, progress=False)
    return out, paths


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def _sublayers(path: Path) -> list[str]:
    layer = Sdf.Layer.FindOrOpen(str(path))  # held while the list proxy is read
    return list(layer.subLayerPaths)


def test_tiny_plan_layout_and_sizes(authored):
    out, paths = authored
    keys = enumerate_scenes(tiny_plan())
    assert len(keys) == 4 + 2 + 10
    skipped = (out / "skipped.csv").read_text().splitlines()[1:]
    assert len(paths) + len(skipped) == len(keys)   # nothing silently dropped
    assert sorted(p.name for p in (out / "sky").iterdir()) == ["d000.usda", "d001.usda"]
    assert len(list((out / "poses").rglob("*.usda"))) == 4 + 2 + 2   # the depths share a pose layer
    for p in paths:
        assert p.stat().st_size <= 4096, p  # issue 6: a scene layer's own file is at most 4 KB
        layer = Sdf.Layer.FindOrOpen(str(p))
        subs = list(layer.subLayerPaths)
        assert subs[0].startswith("../../../poses/s2030/") and subs[1].startswith("../../../sky/d00"), subs
        assert subs[2] == "../../../stages/base.usda", subs  # the tree's own copy, never the repo's
        assert layer.GetPrimAtPath("/World/Camera") is None and layer.GetPrimAtPath("/World/Sky") is None
        anomaly = layer.GetPrimAtPath("/World/Anomaly")
        if anomaly is not None:
            ref, = anomaly.referenceList.prependedItems
            assert ref.assetPath == "../../../stages/anomalies/power_drill.usda"
    stages = sorted(p.relative_to(BASE_STAGE.parent) for p in BASE_STAGE.parent.rglob("*") if p.is_file())
    assert sorted(p.relative_to(out / "stages") for p in (out / "stages").rglob("*") if p.is_file()) == stages
    assert all((out / "stages" / f).read_bytes() == (BASE_STAGE.parent / f).read_bytes() for f in stages)
    anomalous = [p for p in paths if "_z" in p.name]
    by_sample = Counter(_sublayers(p)[0] for p in anomalous)
    assert len(by_sample) <= 2 and sum(by_sample.values()) == len(anomalous)  # depths share a pose layer
    assert max(by_sample.values(), default=0) >= 2


def test_every_layer_validates(authored):
    out, _ = authored
    authored_layers = sorted(p for d in ("sky", "poses", "scenes") for p in (out / d).rglob("*.usda"))
    assert len(authored_layers) == 2 + 8 + len(list((out / "scenes").rglob("*.usda")))
    for p in authored_layers:  # (stages/ is the base stage's byte copy, checked in test_tiny_plan_layout...)
        layer = Sdf.Layer.FindOrOpen(str(p))
        assert layer.defaultPrim == "World"
        assert layer.pseudoRoot.GetInfo("upAxis") == "Z" and layer.pseudoRoot.GetInfo("metersPerUnit") == 1.0
        assert validation_errors(p) == [], p


def test_reauthoring_is_byte_identical_and_resumes(authored, tmp_path_factory):
    from allo_usd.authoring import author_plan

    out, paths = authored
    again = tmp_path_factory.mktemp("tiny") / "deeper" / "still" / "deeper"  # other place, other depth
    author_plan(tiny_plan(), again, progress=False)
    assert _files(again) == _files(out)
    victim = paths[0]
    mtimes = {p: p.stat().st_mtime_ns for p in paths[1:]}
    victim.unlink()
    resumed = author_plan(tiny_plan(), out, progress=False)
    assert victim.is_file() and resumed == paths
    assert all(p.stat().st_mtime_ns == t for p, t in mtimes.items())


def test_composed_values_equal_resolve_scene(authored, tmp_path):
    from allo_usd.author.scene import write_scene_layer
    from allo_usd.scenes import EXPOSURE, World, resolve_scene
    from allo_usd.presets import preset_spec
    from allo_usd.sky import Orbit, compute_sky

    out, paths = authored
    plan = tiny_plan()
    world = World(BASE_STAGE, compute_sky(plan.dates.epochs(), Orbit()), "2030-01-01T00:00:00Z")
    render = preset_spec("preview", (64, 36), EXPOSURE, samples=4)  # what tiny_plan's quality resolves to
    keys = {k.scene_id: k for k in enumerate_scenes(plan)}
    checked = 0
    for path in [paths[0], paths[-1]]:
        k = keys[path.stem]
        spec = resolve_scene(world, scene_id=k.scene_id, day=k.day, pose=k.pose, plan_seed=k.seed, render=render,
                             anomaly=None if k.asset is None else (k.asset, k.variant), depth_index=k.depth_index)
        mono = write_scene_layer(spec, tmp_path / f"{k.scene_id}.usda", BASE_STAGE)
        composed, reference = Usd.Stage.Open(str(path)), Usd.Stage.Open(str(mono))
        mono_layer = Sdf.Layer.FindOrOpen(str(mono))
        for prim_spec in [mono_layer.GetPrimAtPath(p) for p in ("/World", "/World/Camera", "/World/Sky/SunLight",
                          "/World/Sky/Sun", "/World/Sky/Moon", "/World/Anomaly", "/Render/Settings")]:
            if prim_spec is None:
                continue
            for name in prim_spec.attributes.keys():
                got = composed.GetPrimAtPath(prim_spec.path).GetAttribute(name).Get()
                want = reference.GetPrimAtPath(prim_spec.path).GetAttribute(name).Get()
                assert got == want, (path.name, prim_spec.path, name)
                checked += 1
    assert checked > 40


# ---------------------------------------------------------------------------------------------
# A self-contained tree: moved, it opens with plain usd-core

PLAIN_USD = r"""
import json, os, sys
from pxr import Usd, UsdValidation
root = os.path.realpath(sys.argv[1])
validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
report = {"validators": len(validators), "layers": {}}
for path in sys.argv[2:]:
    stage = Usd.Stage.Open(path)
    used = [layer.realPath for layer in stage.GetUsedLayers() if not layer.anonymous]
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    report["layers"][path] = {
        "composition_errors": [str(e) for e in stage.GetCompositionErrors()],
        "outside": [u for u in used if os.path.commonpath([root, os.path.realpath(u)]) != root],
        "used": len(used),
        "anomaly_loaded": (len(stage.GetPrimAtPath("/World/Anomaly").GetAllChildren()) > 0
                           if stage.GetPrimAtPath("/World/Anomaly") else None),
        "validation_errors": [f"{e.GetName()}: {e.GetMessage()}" for e in errors
                              if e.GetType() == UsdValidation.ValidationErrorType.Error]}
report["allo_usd_imported"] = any(m.startswith("allo_usd") for m in sys.modules)
print(json.dumps(report))
"""


def plain_usd_report(root: Path, layers: list[Path]) -> dict:
    """Open each layer with usd-core alone, in a fresh process: no allo_usd import, no plugin path
    or asset-root variables, run from an unrelated directory. Returns what it found."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k in ("PATH", "HOME", "LANG", "TMPDIR")}
    proc = subprocess.run([sys.executable, "-c", PLAIN_USD, str(root), *map(str, layers)], env=env,
                          cwd=Path(root).anchor, capture_output=True, text=True, check=True)
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["validators"] > 10 and report["allo_usd_imported"] is False
    return report


def test_a_moved_tree_opens_with_plain_usd(authored, tmp_path, monkeypatch):
    import shutil

    out, paths = authored
    moved = tmp_path / "a" / "b" / "moved"  # another place and depth; "outside" proves nothing leaks back
    shutil.copytree(out, moved)
    layers = [moved / p.relative_to(out) for p in paths]
    report = plain_usd_report(moved, layers)
    for path, r in report["layers"].items():
        assert r["composition_errors"] == [] and r["outside"] == [], (path, r)
        assert r["used"] >= 4 and r["validation_errors"] == [], (path, r)
        assert r["anomaly_loaded"] in (None, True), (path, r)  # the reference reached the copied asset
    assert any(r["anomaly_loaded"] for r in report["layers"].values())
    from allo_usd.read import read_scene
    from allo_usd.safety import ENV_ROOTS

    monkeypatch.delenv(ENV_ROOTS, raising=False)  # allo_usd.safety allows the plan tree by itself
    assert read_scene(layers[-1]).meta["sceneId"] == paths[-1].stem


def test_an_existing_tree_stage_that_differs_is_refused(authored, tmp_path):
    import shutil

    from allo_usd.authoring import author_plan
    from allo_usd.errors import LayerError

    out, _ = authored
    other = tmp_path / "other"
    shutil.copytree(out, other)
    victim = next((other / "stages" / "anomalies").glob("*.usda"))
    victim.write_text(victim.read_text() + "\n")
    with pytest.raises(LayerError, match="not a copy of .*files differ"):
        author_plan(tiny_plan(), other, progress=False)


def test_plan_refuses_a_resolution_no_layer_could_render():
    """Plans, authoring and the reader share one size bound (allo_usd.spec.MAX_SIDE_PX / MAX_PIXELS)."""
    from allo_usd.author.scene import validate_spec
    from allo_usd.errors import LayerError
    from allo_usd.spec import MAX_SIDE_PX, RenderSpec

    from conftest import make_spec

    with pytest.raises(PlanError, match=r"quality.resolution.*per side"):
        make_plan({"name": "x", "quality": {"resolution": [MAX_SIDE_PX + 1, 36]}})
    spec = make_spec()
    with pytest.raises(LayerError, match="per side"):
        validate_spec(replace(spec, render=RenderSpec(resolution=(MAX_SIDE_PX, MAX_SIDE_PX))))
