"""An imported model's orientation and units come from its format or from explicit options
(`asset import --up-axis/--units`, a plan's [station]), never from its file name."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from allo_usd.cli import app
from allo_usd.core.errors import PlanError
from allo_usd.plan.io import make_plan
from allo_usd.usd.build_stage import station_and_fixtures

ISS = Path(__file__).resolve().parents[2].parent / "shared/assets/ISS_2016.glb"
needs_iss = pytest.mark.skipif(not ISS.is_file(), reason=f"NASA ISS_2016.glb not found at {ISS} (not in the repo; "
                                                        "place it in ../shared/assets/)")


def bounds(asset) -> np.ndarray:
    return np.array(asset.bounds())


def test_a_model_named_like_nasas_is_not_turned_by_its_name(tmp_path):
    """A 4 x 8 x 2 m glTF box: glTF is +Y up, so its 8 m side is up (Z), whatever the file is called."""
    box = trimesh.creation.box(extents=(4.0, 8.0, 2.0))
    named, plain = tmp_path / "ISS_2016.glb", tmp_path / "box.glb"
    box.export(named)
    shutil.copy(named, plain)
    got = [bounds(station_and_fixtures(str(p))[0]) for p in (named, plain)]
    np.testing.assert_array_equal(got[0], got[1])
    np.testing.assert_allclose(got[0][1] - got[0][0], [4.0, 2.0, 8.0])
    z_up = bounds(station_and_fixtures(str(plain), up_axis="Z")[0])
    np.testing.assert_allclose(z_up[1] - z_up[0], [4.0, 8.0, 2.0])


@needs_iss
def test_a_renamed_copy_of_the_iss_imports_with_the_same_orientation(tmp_path):
    copy = tmp_path / "station_copy.glb"
    shutil.copy(ISS, copy)
    original, renamed = (station_and_fixtures(str(p))[0] for p in (ISS, copy))
    np.testing.assert_array_equal(bounds(original), bounds(renamed))
    # given explicitly, its up axis gives the station frame: 80 m flight direction, 108 m truss along Y, 26 m up
    for path in (ISS, copy):
        station = station_and_fixtures(str(path), units="in", up_axis="-z")[0]
        lo, hi = bounds(station)
        np.testing.assert_allclose(hi - lo, [80.3, 108.4, 25.5], rtol=0.02)


def _usd_extent(usda: Path) -> np.ndarray:
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(usda))
    box = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default"]).ComputeWorldBound(stage.GetDefaultPrim())
    r = box.ComputeAlignedRange()
    return np.array(r.GetMax()) - np.array(r.GetMin())


def test_asset_import_takes_up_axis_and_units(tmp_path):
    obj = tmp_path / "part.obj"
    trimesh.creation.box(extents=(10.0, 20.0, 30.0)).export(obj)
    runner = CliRunner()
    r = runner.invoke(app, ["asset", "import", str(obj), "--out", str(tmp_path / "y"), "--units", "cm"])
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(_usd_extent(tmp_path / "y" / "part.usda"), [0.1, 0.3, 0.2], rtol=1e-6)  # OBJ: Y up
    r = runner.invoke(app, ["asset", "import", str(obj), "--out", str(tmp_path / "z"), "--units", "cm",
                            "--up-axis", "Z"])
    assert r.exit_code == 0, r.output
    assert "up axis z" in r.output
    np.testing.assert_allclose(_usd_extent(tmp_path / "z" / "part.usda"), [0.1, 0.2, 0.3], rtol=1e-6)
    r = runner.invoke(app, ["asset", "import", str(obj), "--out", str(tmp_path / "w"), "--up-axis", "w"])
    assert r.exit_code != 0 and "up_axis" in str(r.exception or r.output)


def test_the_plans_station_takes_up_axis_and_units():
    plan = make_plan({"name": "x", "station": {"source": "models/iss.glb", "up_axis": "-Z", "units": "in"}})
    assert (plan.station.up_axis, plan.station.units) == ("-z", "in")
    assert make_plan({"name": "x"}).station.up_axis == "auto"
    with pytest.raises(PlanError, match=r"station\.up_axis.*fix:"):
        make_plan({"name": "x", "station": {"source": "iss.glb", "up_axis": "sideways"}})
    with pytest.raises(PlanError, match=r"station\.source.*\.glb"):   # the importer reads no USD
        make_plan({"name": "x", "station": {"source": "iss.usda"}})


@needs_iss
@pytest.mark.slow
def test_the_plans_up_axis_reaches_the_trees_base_stage(tmp_path):
    from allo_usd.run.author_tree import with_tree_stage
    from allo_usd.usd.tree import STATION_MARKER
    from allo_usd.usd.stage_geometry import read_triangles

    plan = make_plan({"name": "iss", "dates": {"days": 1}, "poses": {"train": [1], "test": []},
                      "station": {"source": str(ISS), "units": "in", "up_axis": "-z"}})
    base = Path(with_tree_stage(plan, tmp_path).base_stage)
    pts, _ = read_triangles(base, "/World/Station")
    np.testing.assert_allclose(pts.max(axis=0) - pts.min(axis=0), [80.3, 108.4, 25.5], rtol=0.02)
    recorded = json.loads((base.parent / STATION_MARKER).read_text())
    assert (recorded["units"], recorded["up_axis"]) == ("in", "-z")
