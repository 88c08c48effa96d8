"""inspect/diff read scenes from the USD alone: identity, seed and anomaly, and composed differences."""

from __future__ import annotations

import json
import os
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.cli import app
from allo_usd.usd.inspect import PRIM, STACK, describe, diff, format_description, format_diff
from allo_usd.scene.spec import CameraSpec

from tests.support.helpers import CAM_POS, EXPOSURE, make_spec


@pytest.fixture
def anomalous(tiny_base, tmp_path):
    spec = make_spec(anomaly=True, seed=99, epoch="2030-03-05T00:00:00Z", day=63, pose=41, split="test",
                     seed_path="2030/63/41/Crate/blue", scene_id="d063_p41_crate")
    spec = replace(spec, anomaly=replace(spec.anomaly, depth_index=3, depth_offset=-1.0, predicted_area_fraction=0.02))
    return spec, write_scene_layer(spec, tmp_path / "a.usda", tiny_base)


def test_describe_reads_the_scene_from_the_layer_alone(anomalous, tiny_base):
    spec, layer = anomalous
    d = describe(layer)
    assert (d["scene_id"], d["epoch"], d["day"], d["pose"], d["split"], d["variant"]) == \
        ("d063_p41_crate", "2030-03-05T00:00:00Z", 63, 41, "test", "anomaly")
    assert d["seed"] == 99 and d["seed_path"] == "2030/63/41/Crate/blue" and d["package_version"] == "0.1.0"
    an = d["anomaly"]
    assert (an["asset"], an["variant"], an["variant_selection"], an["depth_index"]) == ("Crate", "blue", "blue", 3)
    assert an["depth_offset"] == -1.0 and an["predicted_area_fraction"] == pytest.approx(0.02)
    np.testing.assert_allclose(an["position"], spec.anomaly.position)
    np.testing.assert_allclose(d["camera"]["position"], CAM_POS)
    np.testing.assert_allclose(d["camera"]["forward"], -CAM_POS / np.linalg.norm(CAM_POS), atol=1e-9)
    np.testing.assert_allclose(d["sun"]["direction"], spec.sun.direction, atol=1e-7)
    assert d["sun"]["eclipse_state"] == "lit" and d["sun"]["irradiance"] == pytest.approx(1361.0)
    r = d["render"]
    assert r["resolution"] == (64, 36) and r["samples"] == 4 and r["seed"] == 1
    assert r["exposure"] == pytest.approx(EXPOSURE, rel=1e-6)
    assert d["effects"]["inspectionLight"] is True
    rel = os.path.relpath(tiny_base, layer.parent)
    assert d["layer_stack"]["sublayers"] == [rel if rel.startswith(".") else f"./{rel}"]
    assert len(d["layer_stack"]["layers"]) == 2
    json.dumps(d)  # plain values only
    text = format_description(d)
    assert "Crate/blue" in text and "d063_p41_crate" in text


def test_describe_a_normal_scene_has_no_anomaly(tiny_base, tmp_path):
    d = describe(write_scene_layer(make_spec(), tmp_path / "n.usda", tiny_base))
    assert d["anomaly"] is None and d["variant"] == "normal" and d["seed"] == 7


def test_diff_of_identical_scenes_is_empty(anomalous, tiny_base, tmp_path):
    spec, layer = anomalous
    twin = write_scene_layer(spec, tmp_path / "twin" / "a.usda", tiny_base)  # other file, same opinions
    assert diff(layer, layer) == []
    assert diff(layer, twin) == [] and diff(layer, twin, full=True) == []
    assert format_diff([]) == "no differences"


def test_diff_finds_a_camera_change(tiny_base, tmp_path):
    spec = make_spec()
    moved = replace(spec, camera=CameraSpec(tuple(CAM_POS + [1.0, 0, 0]), spec.camera.rotation))
    a = write_scene_layer(spec, tmp_path / "a.usda", tiny_base)
    b = write_scene_layer(moved, tmp_path / "b.usda", tiny_base)
    rows = diff(a, b)
    assert [(p, k) for p, k, _, _ in rows] == [("/World/Camera", "xformOp:translate")]
    _, _, x, y = rows[0]
    assert y[0] - x[0] == pytest.approx(1.0)
    assert rows == diff(a, b, full=True)


def test_diff_finds_a_variant_change_and_what_it_brings(anomalous, tiny_base, tmp_path):
    spec, a = anomalous
    red = replace(spec, anomaly=replace(spec.anomaly, variant="red"))
    b = write_scene_layer(red, tmp_path / "b.usda", tiny_base)
    rows = diff(a, b)
    keys = {(p, k): (x, y) for p, k, x, y in rows}
    assert keys[("/World/Anomaly", "variant:variant")] == ("blue", "red")
    assert keys[("/World/Anomaly", "allo:anomaly:assetVariant")] == ("blue", "red")
    colour = [(x, y) for (p, k), (x, y) in keys.items() if p.startswith("/World/Anomaly/") and k == "inputs:diffuseColor"]
    assert colour and colour[0][0][2] > colour[0][0][0] and colour[0][1][0] > colour[0][1][2]
    assert rows == diff(a, b, full=True)  # the fast path misses nothing


def test_diff_reports_a_prim_present_in_one_scene_only(anomalous, tiny_base, tmp_path):
    _, a = anomalous
    b = write_scene_layer(make_spec(), tmp_path / "b.usda", tiny_base)
    rows = diff(a, b)
    assert ("/World/Anomaly", PRIM, "Xform", "<absent>") in rows
    assert rows == diff(a, b, full=True)


def _day_layer(path, base, intensity: float):
    """A day layer between scene and base: it sets what no scene layer sets (the inspection light)."""
    from pxr import Sdf

    path.parent.mkdir(parents=True, exist_ok=True)
    layer = Sdf.Layer.CreateNew(str(path))
    layer.subLayerPaths.append(os.path.relpath(base, path.parent))
    prim = Sdf.CreatePrimInLayer(layer, "/World/Camera/InspectionLight")
    prim.specifier = Sdf.SpecifierOver
    attr = Sdf.AttributeSpec(prim, "inputs:intensity", Sdf.ValueTypeNames.Float)
    attr.default = intensity
    layer.Save()
    return path


def test_diff_finds_a_difference_inside_same_named_day_layers(tiny_base, tmp_path):
    # Both scenes sublayer ./day.usda over the same base, so their layer stacks read the same;
    # only the day layers' content differs. The fast path must still find it.
    layers = []
    for name, intensity in (("a", 100.0), ("b", 250.0)):
        day = _day_layer(tmp_path / name / "day.usda", tiny_base, intensity)
        layers.append(write_scene_layer(make_spec(), tmp_path / name / "scene.usda", day))
    assert describe(layers[0])["layer_stack"]["sublayers"] == ["./day.usda"]
    rows = diff(*layers)
    assert rows == [("/World/Camera/InspectionLight", "inputs:intensity", 100.0, 250.0)]
    assert rows == diff(*layers, full=True)


def test_diff_reports_a_changed_layer_stack(tiny_base, tmp_path):
    day = _day_layer(tmp_path / "day.usda", tiny_base, 100.0)
    a = write_scene_layer(make_spec(), tmp_path / "a.usda", tiny_base)
    b = write_scene_layer(make_spec(), tmp_path / "b.usda", day)
    rows = diff(a, b)
    assert rows[0][:2] == ("/", STACK) and "./day.usda" in rows[0][3]
    assert ("/World/Camera/InspectionLight", "inputs:intensity", 20000.0, 100.0) in rows


def test_cli_inspect_and_diff(anomalous, tiny_base, tmp_path):
    _, a = anomalous
    runner = CliRunner()
    result = runner.invoke(app, ["inspect", str(a), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["anomaly"]["asset"] == "Crate"
    assert "Crate/blue" in runner.invoke(app, ["inspect", str(a)]).output
    same = runner.invoke(app, ["diff", str(a), str(a)])
    assert same.exit_code == 0 and "no differences" in same.output
    b = write_scene_layer(make_spec(), tmp_path / "b.usda", tiny_base)
    differ = runner.invoke(app, ["diff", str(a), str(b)])
    assert differ.exit_code == 1 and "/World/Anomaly" in differ.output


def test_describe_shows_the_sensor_only_when_noise_is_on(tiny_base, tmp_path):
    from dataclasses import replace

    from allo_usd.plan.settings import EffectsSpec

    quiet = describe(write_scene_layer(make_spec(), tmp_path / "quiet.usda", tiny_base))
    assert quiet["sensor"] is None and "sensor " not in format_description(quiet)
    noisy_spec = replace(make_spec(), effects=EffectsSpec(sensor_noise=True))
    noisy = describe(write_scene_layer(noisy_spec, tmp_path / "noisy.usda", tiny_base))
    assert noisy["sensor"]["fullWell"] == noisy_spec.effects.sensor.full_well_e
    assert noisy["sensor"]["seed"] == noisy_spec.effects.sensor.seed
    assert "fullWell=" in format_description(noisy)
