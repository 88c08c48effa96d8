"""The procedural station: determinism, scale, budget, materials, and camera fixture points."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from allo_usd.assets.station import (ARM_BASE, TRUSS_HALF_LENGTH, build_station, station_fixture_points,
                                     station_triangles)


@pytest.fixture(scope="module")
def station():
    return build_station(articulated=False)   # flat at rest (the articulated one: tests/scene/test_tracking.py)


def _area(part) -> float:
    t = part.triangles()
    p = part.points
    return float(0.5 * np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), axis=1).sum())


def _parts(station, prefix: str):
    return [p for p in station.parts if p.name.startswith(prefix)]


@pytest.mark.slow
def test_name_and_basic_shape(station):
    assert station.name == "Station"
    lo, hi = station.bounds()
    assert np.isfinite(lo).all() and np.isfinite(hi).all()
    # roughly centred: the origin lies inside the bounds and the span is station-sized
    assert (lo < 0).all() and (hi > 0).all()
    assert 100.0 < hi[1] - lo[1] < 130.0


@pytest.mark.slow
def test_deterministic(station):
    again = build_station(articulated=False)
    assert [p.name for p in again.parts] == [p.name for p in station.parts]
    assert again.materials == station.materials
    for a, b in zip(station.parts, again.parts):
        assert a.material == b.material and a.smooth == b.smooth
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.face_counts, b.face_counts)
        np.testing.assert_array_equal(a.face_indices, b.face_indices)
        np.testing.assert_array_equal(a.uv, b.uv)
    assert station.textures.keys() == again.textures.keys()
    for k in station.textures:
        np.testing.assert_array_equal(station.textures[k], again.textures[k])


def test_budget(station):
    tris = sum(len(p.triangles()) for p in station.parts)
    assert tris <= 150_000
    assert len(station.parts) <= 60
    names = [p.name for p in station.parts]
    assert len(set(names)) == len(names)
    assert all(n.isidentifier() for n in names)


def test_truss_extent_and_lattice(station):
    names = {f"truss_{s}{i}" for s in "SP" for i in "013456"}
    segments = [p for p in station.parts if p.name in names]
    assert len(segments) >= 10
    lo = np.min([p.points.min(axis=0) for p in segments], axis=0)
    hi = np.max([p.points.max(axis=0) for p in segments], axis=0)
    assert 100.0 <= hi[1] - lo[1] <= 120.0
    assert hi[1] == pytest.approx(TRUSS_HALF_LENGTH, abs=0.5)
    # a lattice, not a solid bar: rays straight through the S1 segment mostly miss its members
    s1 = next(p for p in segments if p.name == "truss_S1")
    mesh = trimesh.Trimesh(s1.points, s1.triangles(), process=False)
    b0, b1 = s1.bounds()
    ys, zs = np.meshgrid(np.linspace(b0[1] + 0.3, b1[1] - 0.3, 40), np.linspace(b0[2] + 0.3, b1[2] - 0.3, 12))
    origins = np.stack([np.full(ys.size, b0[0] - 1.0), ys.ravel(), zs.ravel()], 1)
    hits = mesh.ray.intersects_any(origins, np.tile([1.0, 0.0, 0.0], (len(origins), 1)))
    assert 0.05 < hits.mean() < 0.6


def _albedo(station, name: str) -> np.ndarray:
    """Mean linear colour a material renders with: texture (sRGB) x base_color, as the author does."""
    m = next(m for m in station.materials if m.name == name)
    colour = np.asarray(m.base_color, dtype=np.float64)
    if m.base_color_texture:
        c = station.textures[m.base_color_texture].astype(np.float64) / 255.0
        lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
        colour = colour * lin.reshape(-1, 3).mean(axis=0)
    return colour


def test_materials(station):
    mats = {m.name: m for m in station.materials}
    assert len(mats) >= 4
    for m in mats.values():
        assert all(0.0 <= c <= 1.0 for c in m.base_color)
        assert 0.0 <= m.metallic <= 1.0 and 0.0 <= m.roughness <= 1.0
    mli = mats["mli_gold"]
    assert mli.metallic >= 0.5 and mli.roughness >= 0.3 and mli.base_color_texture
    gold = _albedo(station, "mli_gold")
    assert gold[0] > gold[1] > gold[2]
    solar = mats["solar_cells"]
    assert solar.base_color_texture and solar.roughness <= 0.3
    cells = _albedo(station, "solar_cells")
    assert cells[2] > cells[0] and cells.max() < 0.15          # dark blue
    rad = mats["radiator"]
    assert rad.roughness >= 0.5 and rad.metallic == 0.0
    assert _albedo(station, "radiator").min() > 0.6             # white
    metal = mats["bare_metal"]
    assert metal.metallic >= 0.9 and 0.25 <= metal.roughness <= 0.45


def test_all_materials_used(station):
    used = {p.material for p in station.parts}
    assert used == {m.name for m in station.materials}


def test_textures(station):
    for key, tex in station.textures.items():
        assert tex.dtype == np.uint8 and tex.ndim == 3 and tex.shape[2] == 3, key
        assert tex.shape[0] >= 256 and tex.shape[1] >= 256
        assert tex.std() > 2.0, f"texture {key} is flat"
    cells = station.textures["solar_cells"].astype(float)
    assert cells.shape == (512, 512, 3)
    assert cells[..., 2].mean() > cells[..., 0].mean()       # blue cells
    # a 512 x 512 tile: the cell grid repeats with a period that divides the tile
    col = cells[..., 2].mean(axis=0)
    assert np.argsort(col)[-1] % 64 in (0, 62, 63)
    textured = {m.name for m in station.materials if m.base_color_texture}
    for p in station.parts:
        if p.material in textured:
            assert p.uv is not None, p.name
            assert np.isfinite(p.uv).all()


def test_solar_wings(station):
    wings = [p for p in _parts(station, "solar_wing_") if p.material == "solar_cells"]
    assert len(wings) == 8
    for w in wings:
        area = _area(w)                                     # two blankets, one side each
        assert 250.0 < area < 400.0, (w.name, area)
        lo, hi = w.bounds()
        assert np.linalg.norm(hi - lo) > 30.0                # a ~35 m wing
        centre = (lo + hi) / 2
        assert abs(centre[1]) > 30.0                         # on the outboard truss
    total = sum(_area(w) for w in wings)
    assert 2000.0 < total < 3500.0
    # double-sided: backs cover the blankets (solar_back sits just behind every front)
    backs = sum(_area(p) for p in station.parts if p.material == "solar_back")
    solar_all = sum(_area(p) for p in station.parts if p.material == "solar_cells")
    assert backs == pytest.approx(solar_all, rel=0.02)
    # blanket UVs are in cells, so a tiling texture repeats many times over a blanket
    assert np.ptp(wings[0].uv[:, 1]) > 20.0


def test_radiators_and_modules(station):
    rad = [p for p in station.parts if p.material == "radiator"]
    assert sum(_area(p) for p in rad) > 300.0
    modules = [p for p in _parts(station, "module_") if p.material == "module_skin"]
    assert len(modules) >= 10
    lab = next(p for p in station.parts if p.name == "module_destiny")
    lo, hi = lab.bounds()
    assert 5.0 <= hi[0] - lo[0] <= 15.0
    assert 4.0 <= hi[1] - lo[1] <= 4.6


def test_solids_face_outward(station):
    """Closed parts wind counter-clockwise from outside: their signed volume is positive."""
    for p in station.parts:
        if p.material in ("solar_cells", "solar_back"):
            continue   # open sheets; their double-sidedness is checked above
        v = p.points - p.points.mean(axis=0)
        t = p.triangles()
        vol = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6.0
        assert vol > 0.0, p.name


@pytest.mark.slow
def test_station_triangles(station):
    pts, tris = station_triangles()
    assert pts.shape[1] == 3 and tris.shape[1] == 3
    assert tris.min() >= 0 and tris.max() < len(pts)
    assert len(tris) == sum(len(p.triangles()) for p in station.parts)
    p2, t2 = station.triangle_soup()
    np.testing.assert_array_equal(pts, p2)
    np.testing.assert_array_equal(tris, t2)
    pts[:] = 0.0                                     # callers get copies
    assert np.abs(station_triangles()[0]).max() > 1.0


@pytest.mark.slow
def test_fixture_points(station):
    fx = station_fixture_points()
    assert fx.ndim == 2 and fx.shape[1] == 3 and fx.shape[0] >= 20
    assert np.isfinite(fx).all()
    np.testing.assert_array_equal(fx, station_fixture_points())
    pts, tris = station_triangles()
    mesh = trimesh.Trimesh(pts, tris, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, fx)
    assert (dist >= 0.3).all() and (dist <= 5.0).all(), dist
    lo, hi = station.bounds()
    assert ((fx > lo) & (fx < hi)).all()
    # some of them are around the robotic-arm base
    assert (np.linalg.norm(fx - ARM_BASE, axis=1) < 3.0).sum() >= 3
