"""The 16 procedural anomaly assets (and the primitives they are built from). Fast; no bpy."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from allo_usd.assets.anomalies import ANOMALY_IDS, ANOMALY_TRIANGLE_BUDGET, ANOMALY_VARIANTS, build_anomaly
from allo_usd.assets.primitives import (extrude_polygon, lathe, ring_prism, smooth_path, superellipsoid, sweep,
                                        triangulate_polygon)
from allo_usd.core.errors import AlloError, UnknownAnomalyError
from allo_usd.assets.mesh import Asset

ALL = [(name, v) for name, variants in ANOMALY_VARIANTS.items() for v in variants]


@pytest.fixture(scope="module")
def assets() -> dict[tuple[str, str], Asset]:
    return {key: build_anomaly(*key) for key in ALL}


def _vector_area(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, float]:
    c = np.cross(points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]]) / 2
    return c.sum(axis=0), float(np.linalg.norm(c, axis=1).sum())


def _signed_volume(points: np.ndarray, tris: np.ndarray) -> float:
    p = points - points.mean(axis=0)
    return float(np.einsum("ij,ij->i", p[tris[:, 0]], np.cross(p[tris[:, 1]], p[tris[:, 2]])).sum() / 6)


# --- the catalogue ---------------------------------------------------------------------------

def test_exactly_sixteen_ids_with_two_or_more_variants():
    assert len(ANOMALY_VARIANTS) == 16
    assert tuple(ANOMALY_VARIANTS) == ANOMALY_IDS
    for name, variants in ANOMALY_VARIANTS.items():
        assert name.isidentifier() and name == name.lower(), name
        assert len(variants) >= 2, name
        assert len(set(variants)) == len(variants), name
        assert all(v.isidentifier() for v in variants), name


def test_catalogue_covers_the_paper_hazard_kinds():
    ids = set(ANOMALY_IDS)
    assert sum("mli" in i for i in ids) == 3            # thermal blankets
    assert sum("cable" in i for i in ids) == 3          # loose cables
    for tool in ("power_drill", "eva_glove", "wrench", "hammer", "bolt_cluster", "tether_hook",
                 "handrail", "crew_bag", "experiment_box", "camera_unit"):
        assert tool in ids


# --- every build ------------------------------------------------------------------------------

@pytest.mark.parametrize("key", ALL, ids=[f"{n}-{v}" for n, v in ALL])
@pytest.mark.slow
def test_builds_sized_centred_and_within_budget(assets, key):
    asset = assets[key]
    assert asset.name == key[0]
    lo, hi = asset.bounds()
    extent = hi - lo
    assert 0.05 <= extent.max() <= 2.0, extent
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-6)
    pts, tris = asset.triangle_soup()
    assert len(tris) <= ANOMALY_TRIANGLE_BUDGET
    assert _vector_area(pts, tris)[1] > 0


@pytest.mark.parametrize("key", ALL, ids=[f"{n}-{v}" for n, v in ALL])
def test_names_materials_and_faces(assets, key):
    asset = assets[key]
    part_names = [p.name for p in asset.parts]
    mat_names = [m.name for m in asset.materials]
    assert len(set(part_names)) == len(part_names)
    assert len(set(mat_names)) == len(mat_names)
    assert all(n.isidentifier() for n in part_names + mat_names)
    assert {p.material for p in asset.parts} == set(mat_names)   # no unused materials
    for m in asset.materials:
        assert all(0.0 <= c <= 1.0 for c in m.base_color)
        assert 0.0 <= m.metallic <= 1.0 and 0.0 <= m.roughness <= 1.0
    for p in asset.parts:
        assert p.points.dtype == np.float64 and np.isfinite(p.points).all()
        tris = p.triangles()
        vec, area = _vector_area(p.points, tris)
        assert area > 0
        if np.linalg.norm(vec) < 1e-3 * area:   # a closed part: its faces must point outwards
            assert _signed_volume(p.points, tris) > 0, p.name
    # Closed solids and double-sided sheets leave no net oriented area: nothing one-sided.
    pts, tris = asset.triangle_soup()
    vec, area = _vector_area(pts, tris)
    assert np.linalg.norm(vec) < 0.01 * area


def test_most_assets_have_several_materials(assets):
    multi = sum(len(assets[(n, ANOMALY_VARIANTS[n][0])].materials) >= 2 for n in ANOMALY_IDS)
    assert multi == 16


def test_sheets_are_double_sided(assets):
    for name in ("mli_blanket", "mli_torn_sheet", "mli_strip"):
        asset = assets[(name, ANOMALY_VARIANTS[name][0])]
        sheets = [p for p in asset.parts if p.name.startswith(("blanket_", "strip_", "inner_layer"))]
        assert sheets
        vecs = [_vector_area(p.points, p.triangles()) for p in sheets]
        net = np.sum([v for v, _ in vecs], axis=0)
        total = sum(a for _, a in vecs)
        assert np.linalg.norm(net) < 0.01 * total, name


def _fingerprint(asset: Asset):
    return ([(p.name, p.points.tobytes(), p.face_indices.tobytes(), p.material) for p in asset.parts],
            asset.materials)


@pytest.mark.parametrize("name", ANOMALY_IDS)
def test_variants_differ_from_the_default(assets, name):
    default = _fingerprint(assets[(name, ANOMALY_VARIANTS[name][0])])
    for v in ANOMALY_VARIANTS[name][1:]:
        assert _fingerprint(assets[(name, v)]) != default, v


@pytest.mark.parametrize("name", ANOMALY_IDS)
def test_deterministic(assets, name):
    for v in ANOMALY_VARIANTS[name]:
        again = build_anomaly(name, v)
        first = assets[(name, v)]
        assert again.materials == first.materials
        assert len(again.parts) == len(first.parts)
        for a, b in zip(first.parts, again.parts):
            assert a.name == b.name and a.material == b.material and a.smooth == b.smooth
            np.testing.assert_array_equal(a.points, b.points)
            np.testing.assert_array_equal(a.face_counts, b.face_counts)
            np.testing.assert_array_equal(a.face_indices, b.face_indices)


@pytest.mark.slow
def test_default_variant_is_the_first(assets):
    for name in ANOMALY_IDS:
        assert _fingerprint(build_anomaly(name)) == _fingerprint(assets[(name, ANOMALY_VARIANTS[name][0])])


@pytest.mark.slow
def test_ids_are_distinct_shapes(assets):
    extents = {n: tuple(np.round(np.sort(np.ptp(build_anomaly(n).bounds(), axis=0)), 4)) for n in ANOMALY_IDS}
    assert len(set(extents.values())) == 16


# --- errors -------------------------------------------------------------------------------------

def test_unknown_name_lists_the_valid_ids():
    with pytest.raises(UnknownAnomalyError) as err:
        build_anomaly("space_toaster")
    msg = str(err.value)
    assert "space_toaster" in msg
    for name in ANOMALY_IDS:
        assert name in msg
    assert isinstance(err.value, ValueError) and isinstance(err.value, AlloError)


def test_unknown_variant_lists_the_valid_variants():
    with pytest.raises(UnknownAnomalyError) as err:
        build_anomaly("hammer", "sledge")
    msg = str(err.value)
    assert "sledge" in msg and "claw" in msg and "mallet" in msg


@settings(max_examples=40, deadline=None)
@given(st.text(max_size=20).filter(lambda s: s not in ANOMALY_VARIANTS))
@pytest.mark.slow
def test_any_other_name_raises(name):
    with pytest.raises(UnknownAnomalyError):
        build_anomaly(name)


# --- the primitives added for these builders ----------------------------------------------------

def _volume(part) -> float:
    return _signed_volume(part.points, part.triangles())


def test_lathe_volumes_match_solids_of_revolution():
    cyl = lathe("c", [(0, 0), (1, 0), (1, 2), (0, 2)], "m", 256)
    assert _volume(cyl) == pytest.approx(2 * np.pi, rel=1e-3)
    washer = lathe("w", [(1, 0), (2, 0), (2, 1), (1, 1)], "m", 256, closed=True)
    assert _volume(washer) == pytest.approx(3 * np.pi, rel=1e-3)
    # hard corners get their own vertices: 4 runs of 2 rings on the washer
    assert len(washer.points) == 4 * 2 * 256


def test_extrusions_and_rings_are_outward_whatever_the_winding():
    ell = [(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)]
    assert _volume(extrude_polygon("a", ell, 1.0, "m")) == pytest.approx(3.0)
    assert _volume(extrude_polygon("b", ell[::-1], 1.0, "m")) == pytest.approx(3.0)
    t = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    hexa = np.column_stack([np.cos(t), np.sin(t)])
    assert _volume(ring_prism("r", 2 * hexa, hexa[::-1], 1.0, "m")) == pytest.approx(3 * 1.5 * np.sqrt(3))


def test_triangulate_concave_polygon_keeps_area():
    rng = np.random.default_rng(0)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 40))
    r = rng.uniform(0.3, 1.0, 40)
    poly = np.column_stack([r * np.cos(ang), r * np.sin(ang)])   # star-shaped, very concave
    tris = triangulate_polygon(poly)
    assert tris.shape == (38, 3)
    a = poly[tris]
    areas = 0.5 * ((a[:, 1, 0] - a[:, 0, 0]) * (a[:, 2, 1] - a[:, 0, 1])
                   - (a[:, 1, 1] - a[:, 0, 1]) * (a[:, 2, 0] - a[:, 0, 0]))
    shoelace = 0.5 * np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    assert (areas > -1e-12).all()
    assert areas.sum() == pytest.approx(shoelace)


def test_sweep_profiles_and_closed_loops():
    path = np.column_stack([np.zeros(40), np.zeros(40), np.linspace(0, 1, 40)])
    assert _volume(sweep("s", path, 0.1, "m", 256)) == pytest.approx(np.pi * 0.01, rel=1e-3)
    assert _volume(sweep("e", path, 0.1, "m", 256, aspect=2.0)) == pytest.approx(2 * np.pi * 0.01, rel=1e-3)
    ang = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    loop = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    torus = sweep("t", loop, 0.1, "m", 64, closed=True)
    assert _volume(torus) == pytest.approx(2 * np.pi ** 2 * 0.01, rel=1e-2)
    tapered = sweep("tip", path, np.linspace(0.1, 0.0, 40), "m", 32)  # closes itself at r=0
    assert _volume(tapered) > 0


def test_superellipsoid_spans_its_size_and_smooth_path_hits_its_ends():
    s = superellipsoid("b", (0.4, 0.2, 0.1), "m", 0.3)
    np.testing.assert_allclose(np.ptp(s.points, axis=0), (0.4, 0.2, 0.1))
    ctrl = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 1.0]])
    p = smooth_path(ctrl, 50)
    np.testing.assert_allclose(p[0], ctrl[0], atol=1e-12)
    np.testing.assert_allclose(p[-1], ctrl[-1], atol=1e-12)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert step.max() / step.min() < 1.05
