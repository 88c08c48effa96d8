"""Render passes chosen in the plan and per run (README, Passes): the layer's UsdRender product orders
one var per pass, rendering writes exactly those files, depth is metres along the view axis, normals
are unit length, the instance mask's ids follow the JSON's table and reproduce the class mask, and
every render's JSON counts station and body pixels."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import OpenEXR
import pytest
from PIL import Image
from typer.testing import CliRunner

from allo_usd.core.errors import AlloError, PlanError
from allo_usd.plan.settings import DEFAULT_PASSES, PASSES
from allo_usd.run.job import render_layer
from allo_usd.usd import layout
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

pytestmark = pytest.mark.render

GEOMETRY = ("depth", "normal", "instance", "mask")


def _exr(path) -> dict:
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {k: np.asarray(v.pixels) for k, v in f.channels().items()}


def _written(out) -> set[str]:
    return {p.name for p in out.iterdir() if p.is_file() and not p.name.startswith(".")}  # not the run lock


@pytest.fixture(scope="module")
def geometry(tiny_base, tmp_path_factory):
    """One anomalous scene rendered with every pass (its layer orders them all)."""
    tmp = tmp_path_factory.mktemp("passes")
    spec = make_spec(anomaly=True)
    spec = replace(spec, render=replace(spec.render, passes=PASSES))
    layer = write_scene_layer(spec, tmp / "allpasses.usda", tiny_base)
    out = tmp / "out"
    return layer, render_layer(layer, out), out


def test_plan_passes_reach_the_layers_usd_render_product(tiny_base, tmp_path):
    from pxr import Usd, UsdRender

    from allo_usd.plan.model import Quality
    from allo_usd.plan.settings import RenderSpec
    from allo_usd.usd.read import read_scene
    from allo_usd.usd.sniff import layer_outputs

    q = Quality(passes=["instance", "depth", "normal"])  # any order: recorded in PASSES order
    assert q.passes == ["depth", "normal", "instance"]
    assert Quality().passes == list(DEFAULT_PASSES)
    spec = make_spec()
    spec = replace(spec, render=RenderSpec(spec.render.resolution, exposure=spec.render.exposure,
                                           passes=tuple(q.passes)))
    layer = write_scene_layer(spec, tmp_path / "geo.usda", tiny_base)
    stage = Usd.Stage.Open(str(layer))
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings"))
    product = UsdRender.Product(stage.GetPrimAtPath(settings.GetProductsRel().GetForwardedTargets()[0]))
    sources = [UsdRender.Var(stage.GetPrimAtPath(p)).GetSourceNameAttr().Get()
               for p in product.GetOrderedVarsRel().GetForwardedTargets()]
    assert sources == ["depth", "normal", "primId"]   # Hydra's AOV names
    assert layer_outputs(layer) == ("depth", "normal", "instance") == read_scene(layer).render.outputs
    # the default layer orders the base product's vars and says nothing itself
    plain = write_scene_layer(make_spec(), tmp_path / "plain.usda", tiny_base)
    assert layer_outputs(plain) == DEFAULT_PASSES == read_scene(plain).render.outputs
    assert "orderedVars" not in plain.read_text()


def test_bad_pass_names_are_refused_naming_the_valid_ones(tmp_path):
    from allo_usd.cli import app
    from allo_usd.plan.io import load_plan

    plan = tmp_path / "p.toml"
    plan.write_text('name = "x"\n[quality]\npasses = ["rgb", "albedo"]\n')
    with pytest.raises(PlanError, match="albedo.*rgb, exr, mask, depth, normal, instance"):
        load_plan(plan)
    plan.write_text('name = "x"\n[quality]\npasses = []\n')
    with pytest.raises(PlanError, match="no render pass"):
        load_plan(plan)
    layer = tmp_path / "l.usda"
    layer.write_text("#usda 1.0\n")
    result = CliRunner().invoke(app, ["render", str(layer), "--out", str(tmp_path / "o"), "--passes", "rgb,zdepth"])
    assert isinstance(result.exception, AlloError)   # cli.main prints it as one line, exit 2
    assert "zdepth" in str(result.exception) and "rgb, exr, mask, depth, normal, instance" in str(result.exception)
    with pytest.raises(AlloError, match="directory"):
        from allo_usd.cli import _render
        from allo_usd.run.options import RunOptions
        _render(tmp_path, tmp_path / "o", RunOptions.from_cli(passes="mask"))


def test_rendering_writes_exactly_the_layers_passes(geometry):
    layer, meta, out = geometry
    stem = layer.stem
    assert _written(out) == {f"{stem}{s}" for s in (".png", ".exr", "_mask.png", "_depth.exr", "_normal.exr",
                                                     "_instance.png", "_amodal.png", ".json")}
    assert meta["passes"] == meta["layer_passes"] == list(PASSES)


def test_depth_is_metres_along_the_view_axis(geometry):
    """Unproject every pixel of the station's truss by its depth along the camera's -Z axis: the points
    lie on the truss box's surface (a ray-length depth would put them off it by metres at the edges)."""
    from allo_usd.usd.read import read_scene

    layer, meta, out = geometry
    desc = read_scene(layer)
    z = _exr(out / meta["files"]["depth"])["Z"]
    ids = np.asarray(Image.open(out / meta["files"]["instance"]))
    truss = next(int(i) for i, p in meta["instances"].items() if p.endswith("/Truss"))
    mesh = next(m for m in desc.meshes if m.path == meta["instances"][str(truss)])
    h, w = z.shape
    cam = desc.camera
    f_px = cam.focal_length_mm / cam.sensor_width_mm * w
    v, u = np.nonzero(ids == truss)
    assert len(u) > 20
    d = z[v, u].astype(np.float64)
    local = np.stack([(u + 0.5 - w / 2) / f_px * d, -(v + 0.5 - h / 2) / f_px * d, -d, np.ones_like(d)])
    world = cam.matrix @ local
    obj = np.linalg.inv(mesh.matrix) @ world
    half = (mesh.points.max(axis=0) - mesh.points.min(axis=0)) / 2
    centre = (mesh.points.max(axis=0) + mesh.points.min(axis=0)) / 2
    # distance outside/inside the box surface, in metres
    q = np.abs(obj[:3].T - centre) - half
    off = np.where(q.max(axis=1) > 0, np.linalg.norm(np.maximum(q, 0), axis=1), -q.max(axis=1))
    assert np.median(off) < 0.05 and np.percentile(off, 90) < 0.25, (np.median(off), off.max())
    assert 5.0 < np.median(d) < 40.0


def test_normals_are_unit_length_world_space(geometry):
    layer, meta, out = geometry
    n = _exr(out / meta["files"]["normal"])
    normal = np.stack([n["X"], n["Y"], n["Z"]], axis=-1)
    assert normal.dtype == np.float32
    ids = np.asarray(Image.open(out / meta["files"]["instance"]))
    length = np.linalg.norm(normal, axis=-1)
    # interior pixels (the same object, or background, all round) hold a unit vector, or 0 on the background
    interior = np.ones_like(ids, dtype=bool)
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, -1), (1, -1), (-1, 1)):
        interior &= np.roll(ids, (dv, du), axis=(0, 1)) == ids
    assert np.all(length[interior & (ids == 0)] == 0)
    inner = length[interior & (ids > 0)]
    assert len(inner) > 20
    assert np.median(np.abs(inner - 1)) < 1e-3 and np.percentile(np.abs(inner - 1), 75) < 1e-2, np.sort(inner)


def test_instance_ids_map_to_the_prim_table_and_reproduce_the_class_mask(geometry):
    from allo_usd.usd.read import read_scene

    layer, meta, out = geometry
    desc = read_scene(layer)
    ids = np.asarray(Image.open(out / meta["files"]["instance"]))
    mask = np.asarray(Image.open(out / meta["files"]["mask"]))
    assert ids.dtype == np.uint16
    table = meta["instances"]
    # one object per station or body mesh, one for the whole anomaly (all its meshes)
    objects = sorted({layout.ANOMALY if m.path.startswith(layout.ANOMALY + "/") else m.path for m in desc.meshes})
    assert [table[str(i)] for i in range(1, len(table) + 1)] == objects
    assert sum(m.path.startswith(layout.ANOMALY + "/") for m in desc.meshes) >= 1 and layout.ANOMALY in objects
    classes = {m.path: m.class_id for m in desc.meshes} | {layout.ANOMALY: 2}
    lut = np.array([0] + [classes[table[str(i)]] for i in range(1, len(table) + 1)], dtype=np.uint8)
    assert set(np.unique(ids)) <= set(range(len(table) + 1)) and len(np.unique(ids)) >= 3
    np.testing.assert_array_equal(lut[ids], mask)
    assert (mask == 2).any() and any("/Anomaly" in table[str(i)] for i in np.unique(ids) if i)
    anomaly_id = next(int(i) for i, p in table.items() if p == layout.ANOMALY)
    np.testing.assert_array_equal(ids == anomaly_id, mask == 2)  # the hazard is one id, whatever its meshes


def test_station_and_body_pixels_add_up_to_class_1(geometry, tiny_base, tmp_path):
    layer, meta, out = geometry
    mask = np.asarray(Image.open(out / meta["files"]["mask"]))
    bodies = meta["bodies"]
    assert set(bodies) == {"sun", "earth", "moon"}
    station = meta["station_fraction"] * mask.size
    assert abs(station - round(station)) < 1e-6 and round(station) > 0
    assert round(station) + sum(b["pixels"] for b in bodies.values()) == np.count_nonzero(mask == 1)
    # a view of the Moon: its pixels are counted (the default passes count too: no instance file needed)
    spec = make_spec(scene_id="moon")
    from allo_usd.core.geometry import look_at
    from allo_usd.scene.spec import CameraSpec
    from tests.support.helpers import CAM_POS

    spec = replace(spec, camera=CameraSpec(tuple(CAM_POS), look_at(CAM_POS, [0.0, 0.0, -7.0e6])))
    m = render_layer(write_scene_layer(spec, tmp_path / "moon.usda", tiny_base), tmp_path / "o")
    assert "instance" not in m["files"] and "instances" not in m
    moon_mask = np.asarray(Image.open(tmp_path / "o" / m["files"]["mask"]))
    assert m["bodies"]["moon"]["pixels"] > 100
    total = m["station_fraction"] * moon_mask.size + sum(b["pixels"] for b in m["bodies"].values())
    assert round(total) == np.count_nonzero(moon_mask == 1)


def test_mask_only_plan_writes_only_the_mask(tiny_base, tmp_path, geometry):
    spec = make_spec(anomaly=True)
    layer = write_scene_layer(replace(spec, render=replace(spec.render, passes=("mask",))), tmp_path / "m.usda",
                              tiny_base)
    meta = render_layer(layer, tmp_path / "out")
    assert _written(tmp_path / "out") == {"m_mask.png", "m.json"}
    assert meta["passes"] == ["mask"]
    _, full, out = geometry   # the same scene at full samples: the class mask is the same bytes' pixels
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "out" / "m_mask.png")),
                                  np.asarray(Image.open(out / full["files"]["mask"])))


def test_passes_override_per_run_is_written_and_recorded(tiny_base, tmp_path):
    from allo_usd.cli import app

    layer = write_scene_layer(make_spec(anomaly=True), tmp_path / "s.usda", tiny_base)
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["render", str(layer), "--out", str(out), "--passes", "rgb, mask,depth"])
    assert result.exit_code == 0, result.output
    assert _written(out) == {"s.png", "s_mask.png", "s_depth.exr", "s.json"}
    meta = json.loads((out / "s.json").read_text())
    assert meta["passes"] == ["rgb", "mask", "depth"] and meta["layer_passes"] == list(DEFAULT_PASSES)
    # a plain run afterwards renders the layer's own passes (the override's render is not taken as done)
    meta = render_layer(layer, out)
    assert meta["passes"] == list(DEFAULT_PASSES) and (out / "s.exr").is_file()
    assert render_layer(layer, out)["render_seconds"] == meta["render_seconds"]   # now done: skipped


def test_a_plans_passes_are_authored_into_its_layers(tmp_path):
    """quality.passes reaches every authored scene layer (what `render PLAN --passes` overrides)."""
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.plan.model import Anomalies, Dates, Plan, Poses, Quality
    from allo_usd.run.author import author_plan
    from allo_usd.usd.sniff import layer_outputs

    plan = Plan(name="passes", dates=Dates(days=1), poses=Poses(train=[1], test=[41]), anomalies=Anomalies(assets=[]),
                quality=Quality(resolution=(64, 36), samples=4, passes=["instance", "mask"]),
                base_stage=str(BASE_STAGE))
    layers = author_plan(plan, tmp_path / "tree", progress=False)
    assert layers and {layer_outputs(p) for p in layers} == {("mask", "instance")}
