"""Scene-layer authoring: layer specs, composed values, determinism, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

from allo_usd import __version__
from allo_usd.author.scene import write_scene_layer
from allo_usd.errors import AlloError, LayerError
from allo_usd.spec import CameraSpec, SunSpec

from conftest import make_spec


def test_layer_holds_only_scene_opinions(tiny_base, tmp_path):
    path = write_scene_layer(make_spec(anomaly=True), tmp_path / "s.usda", tiny_base)
    layer = Sdf.Layer.FindOrOpen(str(path))
    assert layer.subLayerPaths[0].endswith("base.usda") and not layer.subLayerPaths[0].startswith("/")
    assert layer.defaultPrim == "World"
    assert layer.customLayerData["allo"]["seed"] == 7
    assert layer.customLayerData["allo"]["packageVersion"] == __version__
    # Station geometry is never copied into the scene layer.
    assert layer.GetPrimAtPath("/World/Station") is None
    assert layer.GetPrimAtPath("/World/Camera").specifier == Sdf.SpecifierOver
    assert layer.GetPrimAtPath("/World/Anomaly").specifier == Sdf.SpecifierDef
    assert path.stat().st_size < 4096


def test_composed_values(tiny_base, tmp_path):
    spec = make_spec(anomaly=True)
    stage = Usd.Stage.Open(str(write_scene_layer(spec, tmp_path / "s.usda", tiny_base)))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    cam = stage.GetPrimAtPath("/World/Camera")
    m = np.array(UsdGeom.Xformable(cam).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    np.testing.assert_allclose(m[:3, 3], spec.camera.position)
    np.testing.assert_allclose(m[:3, :3], spec.camera.rotation, atol=1e-12)
    world = stage.GetPrimAtPath("/World")
    assert world.GetAttribute("allo:seed").Get() == 7
    assert world.GetAttribute("allo:variant").Get() == "anomaly"
    assert stage.GetPrimAtPath("/Render/Settings").GetAttribute("resolution").Get() == (64, 36)
    anomaly = stage.GetPrimAtPath("/World/Anomaly")
    assert anomaly.GetVariantSets().GetVariantSelection("variant") == "blue"
    assert stage.GetPrimAtPath("/World/Anomaly/Geom/Body").IsA(UsdGeom.Mesh)
    sun = stage.GetPrimAtPath("/World/Sky/SunLight")
    sm = np.array(UsdGeom.Xformable(sun).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    np.testing.assert_allclose(sm[:3, 2], spec.sun.direction, atol=1e-12)


def test_same_spec_same_bytes(tiny_base, tmp_path):
    a = write_scene_layer(make_spec(anomaly=True), tmp_path / "a" / "s.usda", tiny_base)
    b = write_scene_layer(make_spec(anomaly=True), tmp_path / "b" / "s.usda", tiny_base)
    assert a.read_bytes() == b.read_bytes()
    c = write_scene_layer(make_spec(anomaly=True, seed=8), tmp_path / "c" / "s.usda", tiny_base)
    assert c.read_bytes() != a.read_bytes()


@pytest.mark.parametrize("bad", [
    {"camera": CameraSpec((np.nan, 0.0, 0.0), np.eye(3))},
    {"sun": SunSpec((0.0, 0.0, np.inf), 1361.0, 1361.0, 0.533, 1.5e11)},
    {"split": "validation"},
])
def test_bad_spec_writes_nothing(tiny_base, tmp_path, bad):
    target = tmp_path / "bad.usda"
    with pytest.raises(AlloError):
        write_scene_layer(make_spec(**bad), target, tiny_base)
    assert list(tmp_path.iterdir()) == []


def test_missing_base_stage_is_named(tmp_path):
    with pytest.raises(LayerError, match="base stage"):
        write_scene_layer(make_spec(), tmp_path / "s.usda", tmp_path / "nope.usda")


def test_unknown_anomaly_asset(tiny_base, tmp_path):
    from allo_usd.spec import AnomalySpec

    from dataclasses import replace

    spec = replace(make_spec(), anomaly=AnomalySpec("NoSuchThing", "x", (1.0, 1.0, 1.0), np.eye(3)))
    with pytest.raises(LayerError, match="NoSuchThing"):
        write_scene_layer(spec, tmp_path / "s.usda", tiny_base)
    assert not (tmp_path / "s.usda").exists()
