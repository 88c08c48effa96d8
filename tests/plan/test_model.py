"""Dataset plans (counts, validation, files, schema) and authoring a tiny plan by composition."""

from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import replace
from pathlib import Path

import pytest
from pxr import Sdf, Usd

from allo_usd.core.errors import PlanError
from allo_usd.core.paths import BASE_STAGE, SCHEMAS
from allo_usd.plan.model import AnomalyChoice, Anomalies, Counts, Dates, Plan, Poses, Quality, paper_plan
from allo_usd.plan.enumeration import anomaly_quotas, enumerate_scenes, reserve_cap, reserve_group
from allo_usd.plan.io import load_plan, make_plan, save_plan, schema_text

from tests.support.plans import plain_usd_report, tiny_plan
from tests.support.validation import validation_errors


@pytest.mark.slow
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

@pytest.fixture(scope="module")
def authored(tmp_path_factory):
    from allo_usd.run.author import author_plan

    out = tmp_path_factory.mktemp("tiny")
    paths = author_plan(tiny_plan(), out, progress=False)
    return out, paths


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def _csv(path: Path) -> list[dict]:
    import csv

    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _sublayers(path: Path) -> list[str]:
    layer = Sdf.Layer.FindOrOpen(str(path))  # held while the list proxy is read
    return list(layer.subLayerPaths)


@pytest.mark.slow
def test_tiny_plan_layout_and_sizes(authored):
    out, paths = authored
    keys = enumerate_scenes(tiny_plan())
    assert len(keys) == 4 + 2 + 10
    main_skipped = [r for r in _csv(out / "skipped.csv") if not r["reserve"]]
    planned = [p for p in paths if "_r" not in p.stem]
    assert len(planned) + len(main_skipped) == len(keys)   # nothing silently dropped
    assert len(paths) == len(keys)   # and every skipped depth topped up
    assert sorted(p.name for p in (out / "sky").iterdir()) == ["d000.usda", "d001.usda"]
    reserve_groups = len(_csv(out / "reserves.csv"))
    assert len(list((out / "poses").rglob("*.usda"))) <= 4 + 2 + 2 + reserve_groups   # depths share a pose layer
    for p in paths:
        assert p.stat().st_size <= 4096, p  # a scene layer's own file is at most 4 KB
        layer = Sdf.Layer.FindOrOpen(str(p))
        subs = list(layer.subLayerPaths)
        assert subs[0].startswith("../../../poses/s2030/") and subs[1].startswith("../../../sky/d00"), subs
        assert subs[2] == "../../../stages/base.usda", subs  # the tree's own copy, never the repo's
        camera = layer.GetPrimAtPath("/World/Camera")  # only the image's exposure (UsdGeom.Camera), not the pose
        assert camera is None or set(camera.attributes.keys()) == {"exposure"}
        assert layer.GetPrimAtPath("/World/Sky") is None
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


@pytest.mark.slow
def test_every_layer_validates(authored):
    out, _ = authored
    authored_layers = sorted(p for d in ("sky", "poses", "scenes") for p in (out / d).rglob("*.usda"))
    assert len(authored_layers) == 2 + 8 + len(list((out / "scenes").rglob("*.usda")))
    for p in authored_layers:  # (stages/ is the base stage's byte copy, checked in test_tiny_plan_layout...)
        layer = Sdf.Layer.FindOrOpen(str(p))
        assert layer.defaultPrim == "World"
        assert layer.pseudoRoot.GetInfo("upAxis") == "Z" and layer.pseudoRoot.GetInfo("metersPerUnit") == 1.0
        assert validation_errors(p) == [], p


@pytest.mark.slow
def test_reauthoring_is_byte_identical_and_resumes(authored, tmp_path_factory):
    from allo_usd.run.author import author_plan

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


@pytest.mark.slow
def test_composed_values_equal_resolve_scene(authored, tmp_path):
    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.core.constants import EXPOSURE
    from allo_usd.scene.resolve import resolve_scene
    from allo_usd.usd.stage_geometry import scene_inputs
    from allo_usd.plan.settings import preset_spec
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit

    out, paths = authored
    plan = tiny_plan()
    world = scene_inputs(BASE_STAGE, compute_sky(plan.dates.epochs(), Orbit()), "2030-01-01T00:00:00Z")
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

@pytest.mark.process
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
    from allo_usd.usd.read import read_scene
    from allo_usd.usd.safety import ENV_ROOTS

    monkeypatch.delenv(ENV_ROOTS, raising=False)  # allo_usd.usd.safety allows the plan tree by itself
    assert read_scene(layers[-1]).meta["sceneId"] == paths[-1].stem


@pytest.mark.slow
def test_an_existing_tree_stage_that_differs_is_refused(authored, tmp_path):
    import shutil

    from allo_usd.run.author import author_plan
    from allo_usd.core.errors import LayerError

    out, _ = authored
    other = tmp_path / "other"
    shutil.copytree(out, other)
    victim = next((other / "stages" / "anomalies").glob("*.usda"))
    victim.write_text(victim.read_text() + "\n")
    with pytest.raises(LayerError, match="not a copy of .*files differ"):
        author_plan(tiny_plan(), other, progress=False)


def test_plan_refuses_a_resolution_no_layer_could_render():
    """Plans, authoring and the reader share one size bound (allo_usd.scene.spec.MAX_SIDE_PX / MAX_PIXELS)."""
    from allo_usd.usd.scene_layer import validate_spec
    from allo_usd.core.errors import LayerError
    from allo_usd.core.limits import MAX_SIDE_PX
    from allo_usd.plan.settings import RenderSpec

    from tests.support.helpers import make_spec

    with pytest.raises(PlanError, match=r"quality.resolution.*per side"):
        make_plan({"name": "x", "quality": {"resolution": [MAX_SIDE_PX + 1, 36]}})
    spec = make_spec()
    with pytest.raises(LayerError, match="per side"):
        validate_spec(replace(spec, render=RenderSpec(resolution=(MAX_SIDE_PX, MAX_SIDE_PX))))


# ---------------------------------------------------------------------------------------------
# Top-up: skipped depths filled from reserve groups of the same (seed, asset, variant)

SCENE_ID = re.compile(r"^s(\d+)_d(\d+)_p(\d+)_(.+)-(.+?)(?:_r(\d+))?_z(\d)$")


def topup_plan(asset: str = "wrench", resolution=(64, 36), days: int = 3, **anomalies) -> Plan:
    """The wrench at 64x36 over 3 days: about half of its depths fail (under 0.1% of the image far
    away, against the camera near it), so the top-up really runs, and it takes a second."""
    return Plan(name="topup", dates=Dates(days=days), poses=Poses(train=[1], test=[41, 42]),
                anomalies=Anomalies(assets=[AnomalyChoice(id=asset)], **anomalies),
                counts=Counts(normal_train=2, normal_test=2),
                quality=Quality(resolution=resolution, samples=4), base_stage=str(BASE_STAGE))


@pytest.fixture(scope="module")
def topped_up(tmp_path_factory):
    from allo_usd.run.author import author

    out = tmp_path_factory.mktemp("topup")
    return out, author(topup_plan(), out, progress=False, workers=1)


def _anomalous_on_disk(out: Path) -> Counter:
    found = Counter()
    for p in (out / "scenes" / "test" / "anomaly").glob("*.usda"):
        m = SCENE_ID.match(p.stem)
        found[(int(m[1]), m[4], m[5])] += 1
    return found


def test_reserve_groups_are_seeded_apart_from_the_plan():
    plan = topup_plan()
    g = reserve_group(plan, 2030, "wrench", "chrome", 1)
    assert [k.depth_index for k in g] == plan.anomalies.depths and {k.reserve for k in g} == {1}
    assert all(k.scene_id.endswith(f"_wrench-chrome_r1_z{k.depth_index}") for k in g)
    assert {k.sample_id for k in g} == {f"s2030_d{g[0].day:03d}_p{g[0].pose}_wrench-chrome_r1"}  # its own pose layer
    assert reserve_group(topup_plan(), 2030, "wrench", "chrome", 1) == g                    # deterministic
    # Each seed's (day, test pose) pairs, in a seeded order, before any repeats.
    pairs = [reserve_group(plan, 2030, "wrench", "chrome", k)[0] for k in range(1, 8)]
    assert sorted((k.day, k.pose) for k in pairs[:6]) == [(d, p) for d in range(3) for p in (41, 42)]
    assert (pairs[6].day, pairs[6].pose) == (pairs[0].day, pairs[0].pose) and pairs[6].scene_id != pairs[0].scene_id
    # The reserve stream leaves the planned scenes alone: the plan enumerates the same with or without it.
    assert enumerate_scenes(topup_plan(reserve_groups_per_slot=0)) == enumerate_scenes(plan)
    assert reserve_cap(plan, 7) == 21 and reserve_cap(topup_plan(reserve_groups_per_slot=0), 7) == 0
    with pytest.raises(PlanError, match="reserve_groups_per_slot"):
        make_plan({"name": "x", "anomalies": {"reserve_groups_per_slot": -1}})


@pytest.mark.slow
def test_topup_meets_every_quota_exactly(topped_up):
    out, done = topped_up
    plan = topup_plan()
    keys = enumerate_scenes(plan)
    quotas = anomaly_quotas(keys)
    skipped = {r["scene_id"]: r for r in _csv(out / "skipped.csv")}
    lost = Counter((k.seed, k.asset, k.variant) for k in keys if k.scene_id in skipped)
    assert sum(lost.values()) >= 6 and len(lost) == 2          # the plan really skips depths of both variants
    assert _anomalous_on_disk(out) == quotas                    # ... and each (seed, asset, variant) meets its quota
    assert sorted(done.paths) == sorted((out / "scenes").rglob("*.usda")) and done.short == {}
    assert len(done.paths) == len(keys)

    groups = _csv(out / "reserves.csv")
    partial = 0
    for sav, n in lost.items():
        mine = [g for g in groups if (int(g["seed"]), g["asset"], g["variant"]) == sav]
        assert [int(g["reserve"]) for g in mine] == list(range(1, len(mine) + 1))      # strictly in order
        assert sum(len(g["authored"].split()) for g in mine) == n
        for i, g in enumerate(mine):
            k = int(g["reserve"])
            keys_k = reserve_group(plan, *sav, k)
            assert (keys_k[0].day, keys_k[0].pose) == (int(g["day"]), int(g["pose"]))
            ok, bad = set(map(int, g["authored"].split())), set(map(int, g["skipped"].split()))
            used = sorted(ok | bad)
            assert used == plan.anomalies.depths[:len(used)]           # depths used in depth order
            if i < len(mine) - 1:
                assert len(used) == len(plan.anomalies.depths)           # every earlier group used in full
            else:
                assert max(ok) == used[-1]                              # the last one stops at the last image needed
                partial += len(used) < len(plan.anomalies.depths)
            for key in keys_k:
                layer = out / "scenes" / "test" / "anomaly" / f"{key.scene_id}.usda"
                assert layer.is_file() == (key.depth_index in ok), key
                row = skipped.get(key.scene_id)
                assert (row is not None) == (key.depth_index in bad), key   # unused depths: neither authored nor listed
                if row is not None:
                    assert row["reserve"] == str(k)
                    assert "was skipped" in row["reason"] or "no initial placement" in row["reason"]
            if ok:
                pose_layer = out / "poses" / "s2030" / f"{keys_k[0].sample_id.split('_', 1)[1]}.usda"
                pose = Sdf.Layer.FindOrOpen(str(pose_layer))
                assert pose.customLayerData["allo"]["seedPath"].endswith(f"/r{k}")   # a camera draw of its own
    assert partial >= 1   # some last group really had depths left over

    counts = {(r["split"], r["kind"], r["asset"]): r for r in _csv(out / "counts.csv")}
    n_lost, n_groups = str(sum(lost.values())), str(len(groups))
    assert counts["train", "normal", ""] == {"split": "train", "kind": "normal", "asset": "", "planned": "2",
                                            "authored": "2", "skipped": "0", "reserve_groups": "0",
                                            "from_reserve": "0", "short": "0"}
    for asset in ("", "wrench"):
        r = counts["test", "anomaly", asset]
        assert (r["planned"], r["authored"], r["skipped"], r["from_reserve"], r["reserve_groups"], r["short"]) == \
            ("30", "30", n_lost, n_lost, n_groups, "0")


@pytest.mark.slow
def test_limit_tops_up_the_scenes_within_it(tmp_path):
    from allo_usd.run.author import author

    plan = topup_plan()
    keys = enumerate_scenes(plan)[:4 + 12]   # 4 normal scenes, then 2 placements and 2 depths of a third
    done = author(plan, tmp_path, limit=len(keys), progress=False)
    assert _anomalous_on_disk(tmp_path) == anomaly_quotas(keys) and done.short == {}
    assert {r["asset"]: r["planned"] for r in _csv(tmp_path / "counts.csv") if r["kind"] == "anomaly"} == \
        {"": "12", "wrench": "12"}


@pytest.mark.slow
def test_topup_cap_is_honoured_and_reported(topped_up, tmp_path):
    from typer.testing import CliRunner

    from allo_usd.run.author import author
    from allo_usd.run.ledgers import summary_lines
    from allo_usd.cli import app

    # Off: the planned scenes are the same bytes as with the top-up, and every skipped depth is short.
    out, _ = topped_up
    off = author(topup_plan(reserve_groups_per_slot=0), tmp_path / "off", progress=False)
    lost = sum(1 for r in _csv(out / "skipped.csv") if not r["reserve"])
    assert off.short == {"wrench": lost} and _csv(tmp_path / "off" / "reserves.csv") == []
    planned = _files(tmp_path / "off")
    assert planned and all(_files(out)[f] == b for f, b in planned.items()
                           if f.startswith(("scenes", "poses", "sky")))
    # ... and the command says so plainly and succeeds: with the top-up off, skips are expected.
    path = save_plan(topup_plan(reserve_groups_per_slot=0), tmp_path / "off.toml")
    result = CliRunner().invoke(app, ["author", str(path), "--out", str(tmp_path / "off"), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "SHORT" not in result.output and "the plan turns the top-up off" in result.output

    # The bolt cluster at 8x4 pixels almost never covers a pixel centre: its reserves run out.
    plan = topup_plan("bolt_cluster", (8, 4), days=2, reserve_groups_per_slot=1)
    path = save_plan(plan, tmp_path / "bolts.toml")
    result = CliRunner().invoke(app, ["author", str(path), "--out", str(tmp_path / "bolts"), "--no-progress"])
    assert result.exit_code == 1, result.output
    counts = _csv(tmp_path / "bolts" / "counts.csv")
    row = next(r for r in counts if r["asset"] == "bolt_cluster")
    assert int(row["short"]) > 0 and int(row["authored"]) == int(row["planned"]) - int(row["short"])
    assert f"test/anomaly: {row['authored']} of {row['planned']} planned authored" in result.output
    assert f"SHORT: bolt_cluster: {row['authored']} of {row['planned']} ({row['short']} missing" in result.output
    assert summary_lines(counts)[-1].startswith("SHORT: bolt_cluster")
    keys = enumerate_scenes(plan)
    skipped = {r["scene_id"] for r in _csv(tmp_path / "bolts" / "skipped.csv")}
    groups = Counter((int(g["seed"]), g["asset"], g["variant"]) for g in _csv(tmp_path / "bolts" / "reserves.csv"))
    on_disk = _anomalous_on_disk(tmp_path / "bolts")
    for sav, quota in anomaly_quotas(keys).items():
        n_lost = sum(1 for k in keys if (k.seed, k.asset, k.variant) == sav and k.scene_id in skipped)
        assert groups[sav] <= reserve_cap(plan, n_lost)                   # never more reserve groups than the cap
        if on_disk[sav] < quota:
            assert groups[sav] == reserve_cap(plan, n_lost)               # short only once the cap is reached


def _interrupt_at(monkeypatch, n: int, reserve: bool):
    """Ctrl-C in the parent at the n-th sample it writes (reserve groups, or planned ones), halfway
    through the sample: its first scene is written, the rest are not."""
    import allo_usd.run.samples as authoring

    real, calls = authoring.write_sample, []

    def write_sample(ctx, keys, resolved):
        if bool(keys[0].reserve) == reserve and keys[0].kind == "anomaly":
            calls.append(keys[0].scene_id)
            if len(calls) == n:
                real(ctx, keys[:1], resolved)
                raise KeyboardInterrupt
        return real(ctx, keys, resolved)

    monkeypatch.setattr(authoring, "write_sample", write_sample)


@pytest.mark.slow
def test_topup_is_the_same_for_any_workers_and_after_interruptions(topped_up, tmp_path, monkeypatch):
    from allo_usd.run.author import AuthoringInterrupted, author

    out, _ = topped_up
    want = _files(out)
    assert author(topup_plan(), tmp_path / "two", progress=False, workers=2).short == {}
    assert _files(tmp_path / "two") == want

    for n, reserve in ((2, False), (3, True), (5, True)):    # Ctrl-C while placing, and while topping up
        tree = tmp_path / f"cut{n}{reserve}"
        with monkeypatch.context() as m:
            _interrupt_at(m, n, reserve)
            with pytest.raises(AuthoringInterrupted):
                author(topup_plan(), tree, progress=False, workers=1)
        assert not (tree / "counts.csv").exists() and _files(tree) != want
        if reserve:
            assert 0 < len(_csv(tree / "reserves.csv")) < len(_csv(out / "reserves.csv"))
        author(topup_plan(), tree, progress=False, workers=1)
        assert _files(tree) == want, (n, reserve)

    # Killed without a trace (SIGKILL): no records at all, and some reserve layers gone.
    import shutil

    tree = tmp_path / "killed"
    shutil.copytree(out, tree)
    for name in ("skipped.csv", "reserves.csv", "counts.csv"):
        (tree / name).unlink()
    for p in sorted((tree / "scenes" / "test" / "anomaly").glob("*_r*.usda"))[::2]:
        p.unlink()
    author(topup_plan(), tree, progress=False, workers=1)
    assert _files(tree) == want

    # Interrupted in the parent of a 2-worker pool while it writes reserve groups, resumed with 2.
    tree = tmp_path / "pool"
    with monkeypatch.context() as m:
        _interrupt_at(m, 2, True)
        with pytest.raises(AuthoringInterrupted):
            author(topup_plan(), tree, progress=False, workers=2)
    author(topup_plan(), tree, progress=False, workers=2)
    assert _files(tree) == want


@pytest.mark.slow
def test_a_tree_built_from_one_model_refuses_another(tmp_path):
    """A model-built stages/ records its source; a plan naming another model is refused, not
    silently authored over the old station (the procedural station's mesh stands in for a model)."""
    import shutil

    import trimesh

    from allo_usd.assets.station import build_station
    from allo_usd.run.author_tree import with_tree_stage
    from allo_usd.usd.tree import STATION_MARKER
    from allo_usd.plan.model import Station

    pts, tris = build_station().triangle_soup()
    a, b = tmp_path / "a.stl", tmp_path / "b.stl"
    trimesh.Trimesh(pts, tris, process=False).export(a)
    shutil.copy(a, b)
    with open(b, "ab") as f:
        f.write(b"\0")  # another file: another sha256
    out = tmp_path / "tree"
    plan = tiny_plan().model_copy(update={"station": Station(source=str(a), units="m")})
    with_tree_stage(plan, out)
    recorded = json.loads((out / "stages" / STATION_MARKER).read_text())
    assert recorded["source"] == "a.stl" and len(recorded["sha256"]) == 64 and recorded["units"] == "m"
    before = (out / "stages" / "base.usda").read_bytes()
    with_tree_stage(plan, out)  # the same model: reused as it is
    with pytest.raises(PlanError, match=r"was built from .*a\.stl.*new output directory"):
        with_tree_stage(plan.model_copy(update={"station": Station(source=str(b), units="m")}), out)
    assert (out / "stages" / "base.usda").read_bytes() == before
