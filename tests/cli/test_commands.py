"""The command line, and a base stage built around NASA's real ISS model, rendered."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from allo_usd.cli import app
from allo_usd.core.paths import ROOT

from tests.support.validation import validation_errors

ISS = ROOT.parent / "shared" / "assets" / "ISS_2016.glb"
needs_iss = pytest.mark.skipif(not ISS.is_file(), reason=f"NASA ISS_2016.glb not found at {ISS} (not in the repo)")


@pytest.mark.slow
def test_cli_sky_writes_a_year(tmp_path):
    result = CliRunner().invoke(app, ["sky", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader((tmp_path / "sky_2030.csv").open()))
    assert len(rows) == 365
    assert (tmp_path / "sky_2030.png").stat().st_size > 10_000


@pytest.mark.process
def test_cli_render_reports_a_missing_layer(tmp_path):
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "allo_usd.cli", "render", str(tmp_path / "nope.usda"),
                           "--out", str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "does not exist" in proc.stderr and "Traceback" not in proc.stderr


@needs_iss
def test_cli_asset_import_of_the_iss(tmp_path):
    result = CliRunner().invoke(app, ["asset", "import", str(ISS), "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    usda = next(tmp_path.glob("*.usda"))
    assert validation_errors(usda) == []
    assert "unit in" in result.output


@needs_iss
@pytest.mark.render
def test_base_stage_from_the_real_iss_renders(tmp_path):
    from scripts import make_base_stage

    base = make_base_stage.build(tmp_path / "stages", str(ISS), "in", "-z")  # the file breaks glTF's +Y up: say so
    assert validation_errors(base) == []

    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.run.job import render_layer
    from allo_usd.usd.stage_geometry import read_triangles
    from allo_usd.core.constants import EXPOSURE
    from allo_usd.scene.resolve import resolve_scene
    from allo_usd.usd.stage_geometry import scene_inputs
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.plan.settings import RenderSpec

    pts, _ = read_triangles(base, "/World/Station")
    extent = np.sort(pts.max(axis=0) - pts.min(axis=0))
    np.testing.assert_allclose(extent, np.sort([80.3, 108.4, 25.5]), rtol=0.05)  # inches became metres
    world = scene_inputs(base, compute_sky(default_epochs(2030, 10)), "2030-01-01T00:00:00Z")
    scene = resolve_scene(world, scene_id="iss", day=1, pose=5, plan_seed=1,
                          render=RenderSpec((64, 36), samples=4, exposure=EXPOSURE, denoise=False))
    meta = render_layer(write_scene_layer(scene, tmp_path / "iss.usda", base), tmp_path / "out")
    assert meta["class_pixels"]["station_and_bodies"] > 0


@needs_iss
@pytest.mark.render
def test_plan_station_option_uses_the_imported_model(tmp_path):
    """A plan naming a model file gets its own base stage; a scene of it renders on its own."""
    from allo_usd.run.author import author_plan
    from allo_usd.run.job import render_layer
    from allo_usd.plan.model import Anomalies, Dates, Plan, Poses, Quality, Station

    plan = Plan(name="iss", dates=Dates(days=1), poses=Poses(train=[3], test=[41]),
                anomalies=Anomalies(assets=[]), quality=Quality(resolution=(64, 36), samples=2),
                station=Station(source=str(ISS), units="in", up_axis="-z"))
    layers = author_plan(plan, tmp_path / "plan", progress=False)
    assert layers and (tmp_path / "plan" / "stages" / "base.usda").is_file()
    from allo_usd.usd.read import open_stage

    stage = open_stage(layers[0])  # keep the stage alive while its layers are read
    used = [str(layer.identifier) for layer in stage.GetUsedLayers()]
    assert any(p.endswith("plan/stages/base.usda") for p in used), used
    assert not any(p.endswith("/stages/station/Station.usda") and "/plan/" not in p for p in used)
    meta = render_layer(layers[0], tmp_path / "renders")  # single layer: the plan root is allowed
    assert meta["class_pixels"]["station_and_bodies"] > 0


@pytest.mark.render
def test_cli_render_save_blend_keeps_what_blender_got(tiny_base, tmp_path):
    """`allo-usd render LAYER --save-blend FILE` saves the Blender scene the layer built, which a
    fresh Blender opens with the camera and the station in it; the render itself is unchanged."""
    import json
    import subprocess
    import sys

    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    layer = write_scene_layer(make_spec(anomaly=True, samples=2), tmp_path / "layers" / "s.usda", tiny_base)
    cli = [sys.executable, "-m", "allo_usd.cli", "render", str(layer)]
    assert subprocess.run(cli + ["--out", str(tmp_path / "plain")], capture_output=True).returncode == 0
    blend = tmp_path / "debug" / "s.blend"
    r = subprocess.run(cli + ["--out", str(tmp_path / "out"), "--save-blend", str(blend)], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    assert f"saved as {blend}" in r.stdout
    head = blend.read_bytes()[:8]
    assert head.startswith(b"BLENDER") or head.startswith(b"\x28\xb5\x2f\xfd"), head  # plain or zstd
    assert blend.stat().st_size > 50_000
    for name in ("s.png", "s.exr", "s_mask.png"):  # saving the scene does not change the render
        assert (tmp_path / "out" / name).read_bytes() == (tmp_path / "plain" / name).read_bytes(), name

    probe = ("import bpy, json, sys; bpy.ops.wm.open_mainfile(filepath=sys.argv[1]); "
             "s = bpy.context.scene; print(json.dumps({'camera': s.camera.name if s.camera else None, "
             "'objects': sorted(o.name for o in s.objects), 'engine': s.render.engine, "
             "'size': [s.render.resolution_x, s.render.resolution_y]}))")
    r = subprocess.run([sys.executable, "-c", probe, str(blend)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["camera"] == "/World/Camera" and got["engine"] == "CYCLES" and got["size"] == [64, 36]
    assert [o for o in got["objects"] if o.startswith("/World/Station/")], got["objects"]
    assert [o for o in got["objects"] if "/Anomaly" in o], got["objects"]

    r = subprocess.run([sys.executable, "-m", "allo_usd.cli", "render", str(tmp_path / "layers"), "--out",
                        str(tmp_path / "many"), "--save-blend", str(blend)], capture_output=True, text=True)
    assert r.returncode == 2 and "single .usda layer" in r.stderr, r.stderr


@pytest.mark.process
def test_cli_render_save_blend_refuses_paths_blender_cannot_write(tiny_base, tmp_path):
    """A directory or an unwritable place for --save-blend is a clear error (exit 2), not a traceback."""
    import subprocess
    import sys

    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    layer = write_scene_layer(make_spec(samples=1), tmp_path / "layers" / "s.usda", tiny_base)
    (tmp_path / "adir").mkdir()
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    for target, words in ((tmp_path / "adir", "is a directory"), (blocker / "x.blend", "could not save")):
        r = subprocess.run([sys.executable, "-m", "allo_usd.cli", "render", str(layer), "--out", str(tmp_path / "o"),
                            "--save-blend", str(target)], capture_output=True, text=True)
        assert r.returncode == 2 and words in r.stderr and "fix:" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert not (tmp_path / "o" / "s.png").exists()  # refused before anything was rendered
