"""The committed base stage is exactly what the generator makes, and has what scenes need."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdLux, UsdRender, UsdSemantics

from allo_usd.usd import schema
from allo_usd.core.paths import BASE_STAGE, ROOT, STAGES
from allo_usd.usd.stage_geometry import read_rig


@pytest.mark.slow
def test_committed_stage_matches_generator(tmp_path):
    """The script, run as users run it (with the machine's own BLAS kernel and SIMD features: the
    maths that reaches a file is CPU-independent, allo_usd.core.fixedmath), rebuilds the committed
    files byte for byte."""
    subprocess.run([sys.executable, "-m", "scripts.make_base_stage", "--out", str(tmp_path)],
                   check=True, capture_output=True, cwd=ROOT)
    made = {p.relative_to(tmp_path): p for p in tmp_path.rglob("*") if p.is_file()}
    committed = {p.relative_to(STAGES): p for p in STAGES.rglob("*") if p.is_file()}
    assert sorted(made) == sorted(committed)
    differ = [str(k) for k in made if made[k].read_bytes() != committed[k].read_bytes()]
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
    from allo_usd.scene.rig import MIN_SPACING_M, TEST_NEIGHBOUR_M, TEST_SEPARATION_M, TEST_TURN_DEG

    poses = read_rig(BASE_STAGE)
    assert [p.index for p in poses] == list(range(1, 51))
    train = [p for p in poses if p.split == "train"]
    test = [p for p in poses if p.split == "test"]
    assert [p.index for p in train] == list(range(1, 41)) and [p.index for p in test] == list(range(41, 51))
    pos = np.array([p.position for p in poses])
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=2) + np.eye(50) * 1e9
    # 50 distinct camera positions, a few metres apart.
    assert gap.min() >= MIN_SPACING_M - 1e-9, gap.min()
    # Test viewpoints are not training viewpoints: every test camera stands TEST_SEPARATION_M (8 m) from
    # every training camera, so after the N(0, 1 m) perturbation they still stand in different places.
    assert gap[:40, 40:].min() >= TEST_SEPARATION_M - 1e-9, gap[:40, 40:].min()
    # ... and a training camera within 16 m of a test camera looks at least 30 degrees away from it.
    ahead = np.array([-p.rotation[:, 2] for p in poses])
    turn = np.degrees(np.arccos(np.clip(ahead[:40] @ ahead[40:].T, -1, 1)))
    near = gap[:40, 40:] < TEST_NEIGHBOUR_M
    assert near.any() and turn[near].min() >= TEST_TURN_DEG, turn[near].min()
    for p in poses:
        np.testing.assert_allclose(p.rotation @ p.rotation.T, np.eye(3), atol=1e-9)


@pytest.mark.slow
def test_every_base_pose_looks_at_structure_5_to_40_m_away():
    """Each committed pose's view, ray cast on a 32x18 grid: the optical axis hits structure 5-40 m
    away, most structure in frame is 5-40 m away, and it neither leaves the frame empty nor fills it."""
    from allo_usd.scene.raycast import RayScene
    from allo_usd.usd.stage_geometry import read_triangles
    from allo_usd.scene.rig import COVERAGE_RANGE, MAX_NEAR, MIN_IN_RANGE, view_quality

    pts, tris = read_triangles(BASE_STAGE, "/World/Station")
    station = RayScene([(pts, tris, 1)])
    for p in read_rig(BASE_STAGE):
        q = view_quality(station, p.position, p.rotation)
        assert 5.0 <= q.centre_m <= 40.0, (p.index, q)
        assert COVERAGE_RANGE[0] <= q.coverage <= COVERAGE_RANGE[1], (p.index, q)
        assert q.in_range >= MIN_IN_RANGE and q.near <= MAX_NEAR, (p.index, q)


def test_station_and_anomaly_assets_exist():
    from allo_usd.assets.anomalies import ANOMALY_VARIANTS

    assert len(ANOMALY_VARIANTS) == 16
    for name, variants in ANOMALY_VARIANTS.items():
        stage = Usd.Stage.Open(str(STAGES / "anomalies" / f"{name}.usda"))
        prim = stage.GetDefaultPrim()
        assert list(prim.GetVariantSets().GetVariantSet("variant").GetVariantNames()) == sorted(variants) or \
            set(prim.GetVariantSets().GetVariantSet("variant").GetVariantNames()) == set(variants)
        assert list(UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get()) == ["anomaly"]


def test_sun_lamps_and_disc_have_one_colour():
    """The Sun's colour is SUN_COLOR everywhere it shows: every sun lamp (the station's and the bodies')
    authors it, no sky layer overrides it, and the Sun's sphere adds none (it emits nothing and is cut out),
    so the disc the station's lamp draws has the lamps' colour."""
    from pxr import UsdShade

    from allo_usd.core.constants import SUN_COLOR

    schema.register()
    stage = Usd.Stage.Open(str(BASE_STAGE))
    lamps = [UsdLux.DistantLight(p) for p in stage.TraverseAll() if p.IsA(UsdLux.DistantLight)]
    assert len(lamps) == 3
    for lamp in lamps:
        assert tuple(lamp.GetColorAttr().Get()) == SUN_COLOR, lamp.GetPath()
        assert lamp.GetColorAttr().IsAuthored() and not lamp.GetEnableColorTemperatureAttr().Get()
    golden = Path(__file__).resolve().parents[1] / "support" / "golden"
    for layer in sorted(golden.rglob("*.usda")):
        assert "inputs:color" not in layer.read_text(), f"{layer} overrides a lamp's colour"
    sun = Usd.Stage.Open(str(STAGES / "bodies" / "Sun.usda"))
    shaders = [UsdShade.Shader(p) for p in sun.Traverse() if p.IsA(UsdShade.Shader)]
    assert [s.GetIdAttr().Get() for s in shaders] == ["UsdPreviewSurface"]
    surface = shaders[0]
    assert surface.GetInput("opacity").Get() == 0.0 and surface.GetInput("opacityThreshold").Get() > 0.0
    emissive = surface.GetInput("emissiveColor")
    assert emissive is None or not emissive or tuple(emissive.Get()) == (0.0, 0.0, 0.0)
