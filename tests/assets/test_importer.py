"""Tests for allo_usd.assets.importer: glTF/OBJ/STL -> Asset in metres, Z up."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from allo_usd.assets.importer import (DEFAULT_MATERIAL, ISS_2016_ROTATION, UP_AXIS_ROTATIONS, guess_unit,
                                      import_mesh, import_mesh_report)
from allo_usd.core.errors import AssetError, DegenerateMeshError, ImportOptionError
from allo_usd.assets.mesh import MeshPart, validate_part

ISS_GLB = Path(__file__).resolve().parents[2].parent / "shared/assets/ISS_2016.glb"
needs_iss = pytest.mark.skipif(
    not ISS_GLB.is_file(),
    reason=f"NASA ISS_2016.glb not found at {ISS_GLB} (it is not in the repository; "
           f"place it in ../shared/assets/ to run the real-model import tests)")


def signed_volume(part: MeshPart) -> float:
    t = part.points[part.triangles()]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def extent(asset) -> np.ndarray:
    lo, hi = asset.bounds()
    return hi - lo


def check_asset(asset) -> None:
    names = [p.name for p in asset.parts]
    assert len(set(names)) == len(names)
    mats = {m.name for m in asset.materials}
    for p in asset.parts:
        assert p.name.isidentifier() and p.name.isascii()
        assert p.material in mats
        validate_part(p)
        assert (p.face_counts == 3).all()
        # no unused vertices
        assert len(np.unique(p.face_indices)) == len(p.points)
    for m in asset.materials:
        assert m.name.isidentifier()
        assert all(0.0 <= c <= 1.0 for c in m.base_color)
        assert 0.0 <= m.metallic <= 1.0 and 0.0 <= m.roughness <= 1.0


# ----------------------------------------------------------------------------- ISS_2016.glb

@pytest.fixture(scope="module")
def iss_default():
    return import_mesh_report(ISS_GLB)


@pytest.fixture(scope="module")
def iss_station():
    return import_mesh_report(ISS_GLB, rotation=ISS_2016_ROTATION, max_texture_size=256)


@needs_iss
def test_iss_units_extent_triangles(iss_default):
    r = iss_default
    assert r.unit == "in" and r.scale == pytest.approx(0.0254)
    assert "inches" in r.unit_reason
    assert r.format == "gltf" and r.source_up_axis == "y"
    np.testing.assert_allclose(r.source_extent, [3162.2, 4267.9, 1005.0], rtol=1e-3)
    ext = extent(r.asset)
    np.testing.assert_allclose(sorted(ext), sorted([80.0, 108.0, 26.0]), rtol=0.05)
    # default glTF Y-up conversion: the 108 m truss (file +Y) ends up along Z
    assert np.argmax(ext) == 2
    assert 29000 <= r.triangles <= 30000
    assert r.triangles + r.dropped_triangles == 30000
    assert sum(len(p.face_counts) for p in r.asset.parts) == r.triangles


@needs_iss
def test_iss_parts_materials_textures(iss_default):
    a = iss_default.asset
    check_asset(a)
    assert len(a.materials) >= 1 and len(a.parts) >= 1
    assert a.name == "ISS_2016"
    textured = [m for m in a.materials if m.base_color_texture]
    assert textured, "ISS_2016 has a base colour texture"
    for m in textured:
        tex = a.textures[m.base_color_texture]
        assert tex.dtype == np.uint8 and tex.ndim == 3 and tex.shape[2] == 3
        assert max(tex.shape[:2]) <= 1024
    part = a.parts[0]
    assert part.uv is not None and part.uv.shape == (len(part.face_indices), 2)
    assert part.smooth  # the file carries vertex normals
    # recentred
    lo, hi = a.bounds()
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)


@needs_iss
def test_iss_station_orientation(iss_station):
    r = iss_station
    a = r.asset
    ext = extent(a)
    # +X flight direction ~80 m, truss along Y ~108 m, Z up ~26 m
    np.testing.assert_allclose(ext, [80.3, 108.4, 25.5], rtol=0.02)
    # the whole map is 180 degrees about X from the file's axes (file is X fwd, Y stbd, Z nadir)
    np.testing.assert_array_equal(r.rotation, np.diag([1.0, -1.0, -1.0]))
    p = a.parts[0].points
    truss = p[(np.abs(p[:, 1]) > 30) & (p[:, 0] > 1) & (p[:, 0] < 6)]
    aft = p[(np.abs(p[:, 1]) < 2) & (p[:, 0] < -10)]
    fwd = p[(np.abs(p[:, 1]) < 2) & (p[:, 0] > 6)]
    # the truss sits on the zenith side of the pressurised modules
    assert np.median(truss[:, 2]) > np.median(aft[:, 2]) + 2.0
    # the Russian segment (Zvezda, Progress) trails: the module stack reaches further aft
    assert -aft[:, 0].min() > fwd[:, 0].max() + 10.0
    # Kibo (port side of Harmony) is on +Y, Columbus (shorter) on -Y
    side = p[(p[:, 0] > 10) & (p[:, 0] < 20) & (np.abs(p[:, 2] - np.median(aft[:, 2])) < 3) & (np.abs(p[:, 1]) > 3)]
    assert side[:, 1].max() > -side[:, 1].min() + 5.0
    tex = next(iter(a.textures.values()))
    assert max(tex.shape[:2]) <= 256


@needs_iss
def test_iss_up_axis_minus_z_equals_station_rotation(iss_station):
    r = import_mesh_report(ISS_GLB, up_axis="-z", max_texture_size=8)
    np.testing.assert_array_equal(r.asset.parts[0].points, iss_station.asset.parts[0].points)


# ----------------------------------------------------------------------------- OBJ / STL

def write_box(path: Path, extents) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    box.export(path)
    return box


def test_obj_cube_in_cm_y_up(tmp_path):
    f = tmp_path / "box.obj"
    write_box(f, (10.0, 20.0, 30.0))
    r = import_mesh_report(f, units="cm")
    assert r.unit == "cm" and r.scale == 0.01 and r.source_up_axis == "y"
    # OBJ is Y up: file (x, y, z) -> (x, -z, y)
    np.testing.assert_allclose(extent(r.asset), [0.1, 0.3, 0.2], rtol=1e-12)
    assert r.triangles == 12
    check_asset(r.asset)
    assert signed_volume(r.asset.parts[0]) == pytest.approx(0.1 * 0.2 * 0.3, rel=1e-9)
    r_z = import_mesh_report(f, units="cm", up_axis="z")
    np.testing.assert_allclose(extent(r_z.asset), [0.1, 0.2, 0.3], rtol=1e-12)


def test_stl_in_mm_is_z_up_with_default_material(tmp_path):
    f = tmp_path / "part.stl"
    write_box(f, (100.0, 200.0, 300.0))
    r = import_mesh_report(f, units="mm")
    assert r.source_up_axis == "z"
    np.testing.assert_allclose(extent(r.asset), [0.1, 0.2, 0.3], rtol=1e-12)
    a = r.asset
    check_asset(a)
    assert [m.name for m in a.materials] == [DEFAULT_MATERIAL.name]
    assert a.materials[0].metallic == 1.0
    assert a.parts[0].uv is None and a.parts[0].smooth is False
    assert a.textures == {}
    assert signed_volume(a.parts[0]) == pytest.approx(0.006, rel=1e-9)


@pytest.mark.parametrize("size, unit, expected", [
    ((5.0, 3.0, 1.0), "m", 5.0),
    ((2000.0, 1000.0, 500.0), "in", 2000.0 * 0.0254),
])
def test_stl_auto_units(tmp_path, size, unit, expected):
    f = tmp_path / "auto.stl"
    write_box(f, size)
    r = import_mesh_report(f)
    assert r.unit == unit
    assert extent(r.asset).max() == pytest.approx(expected, rel=1e-9)


def test_auto_units_refuses_to_guess_huge(tmp_path):
    f = tmp_path / "huge.stl"
    write_box(f, (50000.0, 10.0, 10.0))
    with pytest.raises(AssetError, match="huge.stl.*units="):
        import_mesh(f)
    assert extent(import_mesh(f, units="mm")).max() == pytest.approx(50.0)


def test_guess_unit_bounds():
    assert guess_unit(0.01) == ("m", 1.0)
    assert guess_unit(1000.0) == ("m", 1.0)
    assert guess_unit(1000.5) == ("in", 0.0254)
    assert guess_unit(20000.0) == ("in", 0.0254)
    with pytest.raises(ImportOptionError):
        guess_unit(20001.0)


def test_up_axis_rotations_are_exact_proper_rotations():
    for axis, m in UP_AXIS_ROTATIONS.items():
        assert set(np.unique(m)) <= {-1.0, 0.0, 1.0}
        np.testing.assert_array_equal(m @ m.T, np.eye(3))
        assert np.linalg.det(m) == pytest.approx(1.0)
        v = np.zeros(3)
        v["xyz".index(axis[-1])] = -1.0 if axis.startswith("-") else 1.0
        np.testing.assert_array_equal(m @ v, [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(ISS_2016_ROTATION @ UP_AXIS_ROTATIONS["y"], np.diag([1.0, -1.0, -1.0]))


def test_obj_with_mtl_materials_uv_and_texture(tmp_path):
    img = np.zeros((32, 64, 4), dtype=np.uint8)
    img[..., 0] = 200
    img[..., 3] = 255
    Image.fromarray(img, "RGBA").save(tmp_path / "paint.png")
    (tmp_path / "two.mtl").write_text(
        "newmtl red paint\nKd 1.0 0.0 0.0\nNs 100\nmap_Kd paint.png\n"
        "newmtl 2grey\nKd 0.5 0.5 0.5\n")
    (tmp_path / "two.obj").write_text(
        "mtllib two.mtl\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 9 9 9\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "usemtl red paint\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
        "usemtl 2grey\nf 1/1 2/2 5/3\n")
    r = import_mesh_report(tmp_path / "two.obj", units="m", max_texture_size=16, recenter=False)
    a = r.asset
    check_asset(a)
    by_name = {m.name: m for m in a.materials}
    assert set(by_name) == {"red_paint", "m_2grey"}
    assert {p.name for p in a.parts} == {"red_paint", "m_2grey"}
    red, grey = by_name["red_paint"], by_name["m_2grey"]
    assert red.base_color == pytest.approx((1.0, 0.0, 0.0))
    assert grey.base_color == pytest.approx((0.21404,) * 3, abs=2e-3)  # sRGB 0.5 -> linear
    assert red.metallic == 0.0 and grey.metallic == 0.0
    assert red.roughness == pytest.approx(np.sqrt(2 / 102))
    assert red.base_color_texture and grey.base_color_texture is None
    tex = a.textures[red.base_color_texture]
    assert tex.shape == (8, 16, 3) and tex.dtype == np.uint8
    assert abs(int(tex[..., 0].mean()) - 200) <= 2
    parts = {p.name: p for p in a.parts}
    assert len(parts["red_paint"].face_counts) == 2
    assert parts["red_paint"].uv.shape == (6, 2)
    assert parts["red_paint"].smooth is False  # no vn in the file
    # unused vertex 6 (9, 9, 9) is gone
    assert all(p.points.max() <= 1.0 for p in a.parts)
    assert r.triangles == 3 and r.dropped_triangles == 0


def test_gltf_pbr_material_texture_and_y_up(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    tex = Image.fromarray(np.full((40, 80, 3), (10, 120, 240), dtype=np.uint8))
    mat = trimesh.visual.material.PBRMaterial(
        name="hull.white", baseColorFactor=[0.2, 0.4, 0.6, 1.0], metallicFactor=0.7,
        roughnessFactor=0.3, baseColorTexture=tex)
    box.visual = trimesh.visual.TextureVisuals(uv=(box.vertices[:, :2] + 1.0) / 2.0, material=mat)
    f = tmp_path / "hull.glb"
    box.export(f)
    r = import_mesh_report(f, max_texture_size=32, name="3 hull")
    a = r.asset
    check_asset(a)
    assert r.unit == "m" and r.source_up_axis == "y"
    np.testing.assert_allclose(extent(a), [1.0, 3.0, 2.0], rtol=1e-6)
    assert a.name == "a_3_hull"
    (m,) = a.materials
    assert m.name == "hull_white"
    assert m.base_color == pytest.approx((0.2, 0.4, 0.6), abs=3e-3)  # linear, kept as is
    assert m.metallic == pytest.approx(0.7) and m.roughness == pytest.approx(0.3)
    t = a.textures[m.base_color_texture]
    assert t.shape == (16, 32, 3)
    assert a.parts[0].uv is not None


def test_gltf_text_with_buffers_and_obj_normals(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=2.0)
    sphere.export(tmp_path / "ball.gltf")  # JSON + external .bin buffers, no material
    r = import_mesh_report(tmp_path / "ball.gltf")
    assert r.triangles == 320 and r.unit == "m"
    assert [m.name for m in r.asset.materials] == [DEFAULT_MATERIAL.name]
    np.testing.assert_allclose(extent(r.asset), [4.0, 4.0, 4.0], rtol=0.1)
    sphere.export(tmp_path / "ball.obj", include_normals=True)
    part = import_mesh(tmp_path / "ball.obj").parts[0]
    assert part.smooth is True  # the OBJ carries vn
    assert len(part.points) == len(sphere.vertices)


def test_gltf_mirrored_instance_keeps_outward_winding(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="a", geom_name="box")
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirror[0, 3] = 5.0
    scene.add_geometry(box, node_name="b", geom_name="box", transform=mirror)
    f = tmp_path / "pair.glb"
    scene.export(f)
    r = import_mesh_report(f, up_axis="z")
    (part,) = r.asset.parts
    assert r.triangles == 24
    assert signed_volume(part) == pytest.approx(2.0, rel=1e-9)
    np.testing.assert_allclose(extent(r.asset), [6.0, 1.0, 1.0], rtol=1e-9)


def test_recenter_false_and_transform(tmp_path):
    f = tmp_path / "off.stl"
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    box.apply_translation([100.0, 0.0, 0.0])
    box.export(f)
    r = import_mesh_report(f, recenter=False, units="cm")
    np.testing.assert_array_equal(r.offset, 0.0)
    lo, hi = r.asset.bounds()
    np.testing.assert_allclose(lo, [0.99, -0.01, -0.01], atol=1e-12)
    r2 = import_mesh_report(f, units="cm")
    np.testing.assert_allclose(r2.offset, [-1.0, 0.0, 0.0], atol=1e-12)
    pts = box.vertices
    mapped = pts @ r2.transform[:3, :3].T + r2.transform[:3, 3]
    np.testing.assert_allclose(np.sort(mapped, axis=0),
                               np.sort(np.unique(r2.asset.parts[0].points, axis=0), axis=0), atol=1e-12)


def test_rotation_parameter(tmp_path):
    f = tmp_path / "rot.stl"
    write_box(f, (1.0, 2.0, 3.0))
    rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(extent(import_mesh(f, rotation=rz)), [2.0, 1.0, 3.0], rtol=1e-12)
    with pytest.raises(ImportOptionError, match="proper rotation"):
        import_mesh(f, rotation=np.diag([2.0, 1.0, 1.0]))
    with pytest.raises(ImportOptionError, match="proper rotation"):
        import_mesh(f, rotation=np.diag([-1.0, 1.0, 1.0]))
    with pytest.raises(ImportOptionError, match="3x3"):
        import_mesh(f, rotation=np.eye(4))


def test_bad_options(tmp_path):
    f = tmp_path / "opt.stl"
    write_box(f, (1.0, 1.0, 1.0))
    with pytest.raises(ImportOptionError, match="units"):
        import_mesh(f, units="furlong")
    with pytest.raises(ImportOptionError, match="up_axis"):
        import_mesh(f, up_axis="w")
    with pytest.raises(ImportOptionError, match="max_texture_size"):
        import_mesh(f, max_texture_size=0)


# ----------------------------------------------------------------------------- errors

def test_missing_file(tmp_path):
    f = tmp_path / "nope.glb"
    with pytest.raises(AssetError, match="not found") as e:
        import_mesh(f)
    assert str(f) in str(e.value)
    assert isinstance(e.value, FileNotFoundError)


def test_unsupported_extension(tmp_path):
    f = tmp_path / "model.fbx"
    f.write_bytes(b"\0" * 64)
    with pytest.raises(AssetError) as e:
        import_mesh(f)
    msg = str(e.value)
    assert str(f) in msg and ".fbx" in msg
    for ext in (".glb", ".gltf", ".obj", ".stl"):
        assert ext in msg


@pytest.mark.parametrize("fname, data", [
    ("garbage.glb", bytes(range(256)) * 8),
    ("garbage.gltf", b"{this is not json"),
    ("garbage.stl", bytes(range(256)) * 8),
    ("garbage.obj", b"hello\nthis is not an obj file\n"),
    ("empty.obj", b""),
])
def test_unreadable_file(tmp_path, fname, data):
    f = tmp_path / fname
    f.write_bytes(data)
    with pytest.raises(AssetError) as e:
        import_mesh(f)
    assert str(f) in str(e.value)


def test_all_degenerate_mesh(tmp_path):
    f = tmp_path / "flat.obj"
    f.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\nf 1 2 4\n")
    with pytest.raises(DegenerateMeshError) as e:
        import_mesh(f)
    assert str(f) in str(e.value)


def test_degenerate_triangles_and_unused_vertices_dropped(tmp_path):
    f = tmp_path / "some.obj"
    f.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nv 7 7 7\nf 1 2 3\nf 1 2 4\n")
    r = import_mesh_report(f, up_axis="z", recenter=False)
    (part,) = r.asset.parts
    assert r.triangles == 1 and r.dropped_triangles == 1
    assert len(part.points) == 3
    np.testing.assert_array_equal(np.sort(part.points, axis=0), [[0, 0, 0], [0, 0, 0], [1, 1, 0]])
