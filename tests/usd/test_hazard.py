"""Your own hazards: a plan's anomaly list names a mesh file next to the built-in ids; it is
converted into the tree (allo_usd.usd.hazard), placed, authored, rendered and recorded like a built-in one."""

from __future__ import annotations

import json
import os
import struct

import numpy as np
import pytest

from allo_usd.core.errors import PlanError
from allo_usd.plan.model import AnomalyChoice, Anomalies, Counts, Dates, Plan, Poses, Quality

BRACKET_MM = ((0, 0, 0), (900, 300, 60)), ((0, 0, 60), (120, 300, 400))   # an L bracket, 0.9 m x 0.3 m x 0.4 m


def box_triangles(lo, hi) -> np.ndarray:
    """(12, 3, 3) triangles of an axis-aligned box, wound outwards."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    c = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=float)
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    return np.array([[c[a], c[b], c[d]] for a, b, cc, d in quads for (b, d) in ((b, cc), (cc, d))])


def write_stl(path, boxes=BRACKET_MM) -> np.ndarray:
    """A binary STL written byte by byte (no library): the mesh a team brings. Returns its triangles."""
    tris = np.concatenate([box_triangles(lo, hi) for lo, hi in boxes])
    with open(path, "wb") as f:
        f.write(b"allo-usd test bracket".ljust(80, b" "))
        f.write(struct.pack("<I", len(tris)))
        for t in tris:
            n = np.cross(t[1] - t[0], t[2] - t[0])
            f.write(struct.pack("<12fH", *(n / np.linalg.norm(n)), *t.reshape(-1), 0))
    return tris


def hazard(path, **kw) -> AnomalyChoice:
    return AnomalyChoice(**{"id": "bracket", "file": str(path), "units": "mm", "up_axis": "z",
                            "colors": {"red": (0.8, 0.05, 0.05)}, **kw})


# ------------------------------------------------------------------------- the plan refuses what it must


@pytest.mark.parametrize("kw, words", [
    ({"id": "power_drill"}, "built-in anomaly"),
    ({"id": "Bracket"}, "lower case"),
    ({"id": "good"}, "not allowed"),
    ({"id": "a b"}, "not allowed"),
    ({"units": None}, "needs units"),
    ({"up_axis": None}, "needs up_axis"),
    ({"file": "bracket.ply"}, "not a model file"),
    ({"colors": {"default": (1, 0, 0)}}, "not allowed"),
    ({"colors": {"red": (1.5, 0, 0)}}, "not a linear RGB"),
    ({"colors": {"red": (float("nan"), 0, 0)}}, "not a linear RGB"),
    ({"variants": ["blue"]}, "variant 'blue' is not defined"),
    ({"variants": []}, "variants is empty; fix: list some of default, red"),
    ({"variants": ["red", "red"]}, "variant 'red' is listed twice"),
])
def test_plan_refuses_bad_hazards_naming_the_fix(tmp_path, kw, words):
    with pytest.raises(ValueError) as e:
        hazard(tmp_path / "bracket.stl", **kw)
    assert words in str(e.value) and "fix" in str(e.value)


def test_builtin_ids_take_no_file_options_and_unknown_ids_point_to_file():
    with pytest.raises(ValueError, match="takes no units"):
        AnomalyChoice(id="wrench", units="mm")
    with pytest.raises(ValueError, match="add `file"):
        AnomalyChoice(id="my_part")


def test_choices_and_round_trip_through_toml(tmp_path):
    from allo_usd.plan.io import load_plan, save_plan

    write_stl(tmp_path / "bracket.stl")
    h = hazard(tmp_path / "bracket.stl", colors={"red": (0.8, 0.05, 0.05), "blue": (0.05, 0.05, 0.8)})
    assert h.choices() == [("bracket", "default"), ("bracket", "red"), ("bracket", "blue")]
    plan = Plan(name="own", anomalies=Anomalies(assets=[AnomalyChoice(id="wrench"), h]))
    save_plan(plan, tmp_path / "plan.toml")
    assert load_plan(tmp_path / "plan.toml") == plan


# ------------------------------------------------------------------------- conversion


def test_mesh_conversion_uses_the_given_units_and_colours(tmp_path):
    from pxr import Sdf, Usd, UsdShade

    from allo_usd.usd.hazard import convert_hazard
    from allo_usd.usd.stage_geometry import read_triangles

    write_stl(tmp_path / "bracket.stl")
    path = convert_hazard(hazard(tmp_path / "bracket.stl"), tmp_path / "out")
    prov = dict(Sdf.Layer.FindOrOpen(str(path)).customLayerData["allo"]["hazard"])
    assert prov["source"] == "bracket.stl" and prov["unit"] == "mm" and prov["upAxis"] == "z"
    pts, tris = read_triangles(path, "/bracket", "default")
    assert len(tris) == 24
    np.testing.assert_allclose(pts.max(axis=0) - pts.min(axis=0), (0.9, 0.3, 0.4), atol=1e-6)
    np.testing.assert_allclose((pts.max(axis=0) + pts.min(axis=0)) / 2, 0, atol=1e-6)   # centred
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/bracket")
    assert prim.GetVariantSets().GetVariantSet("variant").GetVariantNames() == ["default", "red"]
    prim.GetVariantSets().SetSelection("variant", "red")
    shaders = [p for p in Usd.PrimRange(prim) if p.GetTypeName() == "Shader"]
    colours = {tuple(round(c, 4) for c in UsdShade.Shader(p).GetInput("diffuseColor").Get()) for p in shaders}
    assert colours == {(0.8, 0.05, 0.05)}


def _usd_box(path, meters_per_unit=0.01, up="Y", authored=True):
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

    stage = Usd.Stage.CreateNew(str(path))
    if authored:
        UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Part")
    stage.SetDefaultPrim(root.GetPrim())
    tris = box_triangles((0, 0, 0), (50, 20, 10))   # cm: 0.5 x 0.2 x 0.1 m, Y up -> 0.2 m becomes height
    mesh = UsdGeom.Mesh.Define(stage, "/Part/Body")
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in tris.reshape(-1, 3)])
    mesh.CreateFaceVertexCountsAttr([3] * len(tris))
    mesh.CreateFaceVertexIndicesAttr(list(range(3 * len(tris))))
    mat = UsdShade.Material.Define(stage, "/Part/Looks/Orange")
    shader = UsdShade.Shader.Define(stage, "/Part/Looks/Orange/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.9, 0.4, 0.05))
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    stage.Save()
    return path


def test_usd_hazard_takes_its_units_and_axis_from_the_file(tmp_path):
    from allo_usd.usd.hazard import load_hazard

    asset, info = load_hazard(_usd_box(tmp_path / "part.usda"), "part", None, None)
    lo, hi = asset.bounds()
    np.testing.assert_allclose(hi - lo, (0.5, 0.1, 0.2), atol=1e-6)   # Y up turned to Z up, cm to m
    assert info["unit"] == "cm" and info["upAxis"] == "y"
    assert asset.materials[0].base_color == pytest.approx((0.9, 0.4, 0.05), abs=1e-6)
    with pytest.raises(PlanError, match="declares metersPerUnit = 0.01, but the plan says units = 'm'"):
        load_hazard(tmp_path / "part.usda", "part", "m", None)
    with pytest.raises(PlanError, match="declares no metersPerUnit"):
        load_hazard(_usd_box(tmp_path / "bare.usda", authored=False), "part", None, None)


@pytest.mark.parametrize("content", [b"", b"solid x\nendsolid x\n", os.urandom(200),
                                     b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 1 1\n"
                                     b"vertex 2 2 2\nendloop\nendfacet\nendsolid x\n"])   # one degenerate triangle
def test_broken_mesh_files_are_plan_errors(tmp_path, content):
    from allo_usd.usd.hazard import load_hazard

    (tmp_path / "bad.stl").write_bytes(content)
    with pytest.raises(PlanError) as e:
        load_hazard(tmp_path / "bad.stl", "bad", "mm", "z")
    assert "bad" in str(e.value) and "fix" in str(e.value)


def test_a_unit_mistake_is_caught_by_size(tmp_path):
    from allo_usd.usd.hazard import load_hazard

    write_stl(tmp_path / "bracket.stl")
    with pytest.raises(PlanError, match=r"measures 900 m .* units 'm'.*fix: give the unit"):
        load_hazard(tmp_path / "bracket.stl", "bracket", "m", "z")


# ------------------------------------------------------------------------- authored, rendered, recorded


def _plan(stl) -> Plan:
    from allo_usd.core.paths import BASE_STAGE

    return Plan(name="own-hazard", dates=Dates(days=1), poses=Poses(train=[], test=[41]),
                anomalies=Anomalies(assets=[hazard(stl, variants=["red"])]),
                counts=Counts(normal_test=0, anomalous_test=5),
                quality=Quality(resolution=(64, 36), samples=4, preset="draft"), base_stage=str(BASE_STAGE))


@pytest.fixture(scope="module")
def authored(tmp_path_factory):
    from allo_usd.run.author import author_plan

    root = tmp_path_factory.mktemp("hazard")
    stl = root / "bracket.stl"
    write_stl(stl)
    layers = author_plan(_plan(stl), root / "tree", progress=False)
    return root, layers


@pytest.mark.slow
def test_the_tree_carries_the_converted_hazard_and_layers_reference_it(authored):
    from pxr import Sdf

    root, layers = authored
    tree = root / "tree"
    assert len(layers) == 5
    marker = json.loads((tree / "hazards" / "bracket" / "source.json").read_text())
    assert marker["source"] == "bracket.stl" and marker["units"] == "mm"
    for layer in layers:
        sdf = Sdf.Layer.FindOrOpen(str(layer))
        refs = sdf.GetPrimAtPath("/World/Anomaly").referenceList.GetAddedOrExplicitItems()
        assert [r.assetPath for r in refs] == ["../../../hazards/bracket/bracket.usda"]


def test_layers_pass_usd_validation_and_inspect_names_the_source(authored):
    from allo_usd.usd.inspect import describe, format_description

    from tests.support.validation import validation_errors

    _, layers = authored
    assert validation_errors(layers[0]) == []
    d = describe(layers[0])
    assert d["anomaly"]["asset"] == "bracket" and d["anomaly"]["variant"] == "red"
    assert d["anomaly"]["source"]["kind"] == "user" and d["anomaly"]["source"]["file"] == "bracket.stl"
    assert "from bracket.stl (your hazard" in format_description(d)


def test_same_plan_gives_byte_identical_hazards_and_layers_elsewhere(authored, tmp_path):
    from allo_usd.run.author import author_plan

    root, layers = authored
    again = author_plan(_plan(root / "bracket.stl"), tmp_path / "moved", progress=False)
    a, b = root / "tree" / "hazards", tmp_path / "moved" / "hazards"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    assert [p.read_bytes() for p in layers] == [p.read_bytes() for p in again]


@pytest.mark.slow
def test_an_edited_hazard_file_is_refused_on_resume(tmp_path):
    from allo_usd.run.author import author_plan

    stl = tmp_path / "bracket.stl"
    write_stl(stl)
    plan = _plan(stl).model_copy(update={"counts": Counts(normal_test=0, anomalous_test=1)})
    author_plan(plan, tmp_path / "tree", progress=False)
    author_plan(plan, tmp_path / "tree", progress=False)   # the same file: resumes
    write_stl(stl, boxes=BRACKET_MM[:1])                   # the file changed under the same name
    with pytest.raises(PlanError, match="changed since its scenes were authored"):
        author_plan(plan, tmp_path / "tree", progress=False)
    assert author_plan(plan, tmp_path / "tree", progress=False, replace=True)


@pytest.mark.render
def test_the_rendered_mask_covers_the_projected_mesh(authored, tmp_path):
    """The rendered anomaly class is the converted mesh where ray casting puts it: rays through every
    pixel centre of the recorded camera hit the hazard exactly where the mask says class 2."""
    from PIL import Image

    from allo_usd.run.job import render_layer
    from allo_usd.scene.raycast import RayScene
    from allo_usd.usd.stage_geometry import StageGeometry
    from pxr import Usd, UsdGeom

    root, layers = authored
    tree = root / "tree"
    sizes = []
    for layer in layers:
        stage = Usd.Stage.Open(str(layer))
        sizes.append(stage.GetPrimAtPath("/World/Anomaly").GetAttribute("allo:anomaly:predictedAreaFraction").Get())
    layer = layers[int(np.argmax(sizes))]
    meta = render_layer(layer, tmp_path / "renders")
    mask = np.asarray(Image.open(tmp_path / "renders" / meta["files"]["mask"]))
    assert (mask == 2).sum() >= 3

    stage = Usd.Stage.Open(str(layer))
    m = np.array(UsdGeom.Xformable(stage.GetPrimAtPath("/World/Anomaly")).ComputeLocalToWorldTransform(
        Usd.TimeCode.Default())).T
    geometry = StageGeometry(tree / "stages" / "base.usda", {"bracket": tree / "hazards" / "bracket" / "bracket.usda"})
    pts, tris = geometry.anomaly_triangles("bracket", "red")
    world = pts @ m[:3, :3].T + m[:3, 3]
    spts, stris = geometry.station_triangles()
    scene = RayScene([(spts, stris, 1), (world, tris, 2)])
    h, w = mask.shape
    camera = meta["annotations"]["camera"]       # the recorded K and pose (OpenCV pixel centres)
    k, cam = np.array(camera["K_px"]), np.array(camera["cam_to_world_usd"])
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d_cv = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u, dtype=float)], -1).reshape(-1, 3)
    d_usd = d_cv * (1, -1, -1)
    dirs = d_usd @ cam[:3, :3].T
    owner, _ = scene.first_hit(np.broadcast_to(cam[:3, 3], dirs.shape), dirs)
    ray2 = owner.reshape(h, w) == 2
    assert ray2.sum() >= 3
    assert (ray2 == (mask == 2)).all(), f"{int((ray2 != (mask == 2)).sum())} pixels disagree"


def test_asset_import_is_the_same_importer_for_usd_files(tmp_path):
    """`allo-usd asset import` reads a USD file through the importer a plan's hazards use."""
    from typer.testing import CliRunner

    from allo_usd.cli import app
    from allo_usd.usd.hazard import load_hazard
    from allo_usd.usd.stage_geometry import read_triangles

    src = _usd_box(tmp_path / "part.usda")
    r = CliRunner().invoke(app, ["asset", "import", str(src), "--out", str(tmp_path / "out"), "--label", "anomaly"])
    assert r.exit_code == 0, r.output
    assert "unit cm, up axis y" in r.output
    pts, _ = read_triangles(tmp_path / "out" / "part.usda", "/part")
    asset, _ = load_hazard(src, "part", None, None)
    np.testing.assert_allclose(np.ptp(pts, axis=0), np.ptp(asset.parts[0].points, axis=0), atol=1e-6)


@pytest.mark.parametrize("make, words", [(lambda p: None, "does not exist"), (lambda p: p.mkdir(), "is not a regular file \\(a directory")])
def test_a_missing_or_odd_hazard_file_is_named_before_anything_is_made(tmp_path, make, words):
    from allo_usd.run.author import author_plan

    make(tmp_path / "bracket.stl")
    with pytest.raises(PlanError, match=f"bracket.stl {words}.*; fix"):
        author_plan(_plan(tmp_path / "bracket.stl"), tmp_path / "tree", progress=False)
    assert not (tmp_path / "tree" / "scenes").exists() and not (tmp_path / "tree" / "hazards").exists()


def test_usd_instances_count_and_guides_do_not(tmp_path):
    """An instanced mesh is part of the hazard (instance proxies are read); a guide-purpose mesh is not."""
    from pxr import Gf, Usd, UsdGeom

    from allo_usd.usd.hazard import load_hazard

    stage = Usd.Stage.CreateNew(str(tmp_path / "pair.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    proto = UsdGeom.Xform.Define(stage, "/Proto")
    proto.GetPrim().SetSpecifier(__import__("pxr").Sdf.SpecifierClass)
    tris = box_triangles((0, 0, 0), (0.2, 0.2, 0.2))
    mesh = UsdGeom.Mesh.Define(stage, "/Proto/Body")
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in tris.reshape(-1, 3)])
    mesh.CreateFaceVertexCountsAttr([3] * len(tris))
    mesh.CreateFaceVertexIndicesAttr(list(range(3 * len(tris))))
    for name, x in (("A", 0.0), ("B", 1.0)):
        inst = UsdGeom.Xform.Define(stage, f"/Pair/{name}")
        inst.AddTranslateOp().Set(Gf.Vec3d(x, 0, 0))
        inst.GetPrim().GetInherits().AddInherit("/Proto")
        inst.GetPrim().SetInstanceable(True)
    guide = UsdGeom.Mesh.Define(stage, "/Pair/Guide")
    guide.CreatePointsAttr([Gf.Vec3f(*p) for p in box_triangles((0, 0, 0), (9, 9, 9)).reshape(-1, 3)])
    guide.CreateFaceVertexCountsAttr([3] * 12)
    guide.CreateFaceVertexIndicesAttr(list(range(36)))
    guide.CreatePurposeAttr(UsdGeom.Tokens.guide)
    stage.SetDefaultPrim(stage.GetPrimAtPath("/Pair"))
    stage.Save()
    asset, info = load_hazard(tmp_path / "pair.usda", "pair", None, None)
    lo, hi = asset.bounds()
    np.testing.assert_allclose(hi - lo, (1.2, 0.2, 0.2), atol=1e-6)   # both instances, not the 9 m guide
    assert info["triangles"] == 24


def test_too_many_colours_and_a_name_too_long_are_plan_errors(tmp_path):
    from allo_usd.run.author import author_plan

    with pytest.raises(ValueError, match="colour variants, above the 32"):
        hazard(tmp_path / "b.stl", colors={f"c{i}": (0.5, 0.5, 0.5) for i in range(33)})
    long = tmp_path / ("x" * 300 + ".stl")
    with pytest.raises(PlanError, match=r"cannot be read \(.+\); fix"):
        author_plan(_plan(long), tmp_path / "tree", progress=False)
