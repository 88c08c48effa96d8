"""The committed base stage is exactly what the generator makes, and has what scenes need."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdLux, UsdRender, UsdSemantics

from allo_usd import schema
from allo_usd.paths import BASE_STAGE, ROOT, STAGES
from allo_usd.read import read_rig


def _generator():
    spec = importlib.util.spec_from_file_location("make_base_stage", ROOT / "scripts" / "make_base_stage.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_committed_stage_matches_generator(tmp_path):
    _generator().build(tmp_path)
    made = {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    committed = {p.relative_to(STAGES): p.read_bytes() for p in STAGES.rglob("*") if p.is_file()}
    assert sorted(made) == sorted(committed)
    differ = [str(k) for k in made if made[k] != committed[k]]
    assert differ == [], f"regenerate with scripts/make_base_stage.py: {differ}"


def test_base_stage_contents():
    schema.register()
    stage = Usd.Stage.Open(str(BASE_STAGE))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    world = stage.GetDefaultPrim()
    assert world.GetName() == "World" and Usd.ModelAPI(world).GetKind() == "assembly"
    assert stage.GetPrimAtPath("/World/Sky/SunLight").IsA(UsdLux.DistantLight)
    spot = stage.GetPrimAtPath("/World/Camera/InspectionLight")
    assert spot.IsA(UsdLux.SphereLight) and spot.HasAPI(UsdLux.ShapingAPI)
    assert stage.GetPrimAtPath("/Render/Settings").IsA(UsdRender.Settings)
    labels = {}
    for name in ("/World/Station", "/World/Sky/Moon", "/World/Sky/Earth", "/World/Sky/Sun"):
        prim = stage.GetPrimAtPath(name)
        labels[name] = list(UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get())
    assert labels["/World/Station"] == ["station"] and labels["/World/Sky/Moon"] == ["celestial_body"]
    materials = [p for p in Usd.PrimRange(stage.GetPrimAtPath("/World/Station")) if p.GetTypeName() == "Material"]
    assert len(materials) >= 4
    # Heavy geometry lives in crate, interfaces in text.
    assert (STAGES / "station" / "Station_geom.usdc").stat().st_size > 1_000_000
    assert (STAGES / "station" / "Station.usda").stat().st_size < 2_000


def test_rig_has_50_disjoint_poses():
    poses = read_rig(BASE_STAGE)
    assert [p.index for p in poses] == list(range(1, 51))
    train = [p for p in poses if p.split == "train"]
    test = [p for p in poses if p.split == "test"]
    assert [p.index for p in train] == list(range(1, 41)) and [p.index for p in test] == list(range(41, 51))
    tr = np.array([p.position for p in train])
    te = np.array([p.position for p in test])
    # Test viewpoints are not training viewpoints: every test camera is away from every train camera.
    assert np.linalg.norm(tr[:, None] - te[None], axis=2).min() > 1.0
    for p in poses:
        np.testing.assert_allclose(p.rotation @ p.rotation.T, np.eye(3), atol=1e-9)


def test_station_and_anomaly_assets_exist():
    from allo_usd.assets.anomalies import ANOMALY_VARIANTS

    assert len(ANOMALY_VARIANTS) == 16
    for name, variants in ANOMALY_VARIANTS.items():
        stage = Usd.Stage.Open(str(STAGES / "anomalies" / f"{name}.usda"))
        prim = stage.GetDefaultPrim()
        assert list(prim.GetVariantSets().GetVariantSet("variant").GetVariantNames()) == sorted(variants) or \
            set(prim.GetVariantSets().GetVariantSet("variant").GetVariantNames()) == set(variants)
        assert list(UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get()) == ["anomaly"]
