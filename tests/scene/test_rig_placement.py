"""Camera perturbation and anomaly placement: statistics, hard cases, agreement with a render."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from allo_usd.assets.primitives import box
from allo_usd.core import fixedmath as fm
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.scene.spec import CameraPose
from allo_usd.core.labels import ANOMALY, STATION
from allo_usd.core.errors import DegenerateMeshError, PlacementError
from allo_usd.core.geometry import box_corners, camera_intrinsics, look_at, quat_to_matrix
from allo_usd.assets.mesh import MeshPart
from allo_usd.scene import placement, rig
from allo_usd.scene.placement import DEPTH_OFFSETS, check, place, visible_fraction
from allo_usd.scene.raycast import RayScene, class_image, pixel_ray_columns, pixel_rays
from allo_usd.scene.rig import ANGLE_SIGMA_RAD, POSITION_SIGMA_M, perturb

from tests.support.helpers import tiny_station
from tests.support.soups import blob, numpy_path, station_scene


def _scene_of(*boxes):
    return RayScene([(b.points, b.triangles(), STATION) for b in boxes])


CUBE = box("c", (0.4, 0.4, 0.4), "m")


@pytest.mark.slow
def test_perturbation_has_the_paper_statistics():
    pose = CameraPose(1, "train", np.zeros(3), np.eye(3))
    rng = np.random.default_rng(1)
    draws = [perturb(pose, rng) for _ in range(4000)]
    dpos = np.array([d[2] for d in draws])
    dang = np.array([d[3] for d in draws])
    assert np.allclose(dpos.std(axis=0), POSITION_SIGMA_M, rtol=0.05)
    assert np.allclose(dang.std(axis=0), ANGLE_SIGMA_RAD, rtol=0.05)
    for pos, rot, dp, _, attempts in draws[:50]:
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        assert attempts == 1


def test_camera_inside_the_bounding_box_but_in_free_space_is_fine():
    # Two slabs 10 m apart: the camera between them is inside the station's bounding box, not inside it.
    a = box("a", (10, 10, 1), "m").transformed(np.diag([1, 1, 1, 1.0]) + np.eye(4) * 0 + _t(0, 0, -5))
    b = box("b", (10, 10, 1), "m").transformed(_t(0, 0, 5))
    scene = _scene_of(a, b)
    pose = CameraPose(1, "train", np.zeros(3), np.eye(3))
    pos, _, _, _, attempts = perturb(pose, np.random.default_rng(0), scene)
    assert abs(pos[2]) < 4.5 and attempts >= 1


def test_camera_inside_solid_structure_is_resampled_then_refused():
    big = box("big", (40, 40, 40), "m")
    pose = CameraPose(7, "train", np.zeros(3), np.eye(3))
    with pytest.raises(PlacementError, match="pose 7.*30 attempts"):
        perturb(pose, np.random.default_rng(0), _scene_of(big), max_attempts=30)
    small = box("small", (1.5, 1.5, 1.5), "m")
    pos, _, _, _, attempts = perturb(pose, np.random.default_rng(0), _scene_of(small))
    assert attempts >= 1 and np.abs(pos).max() > 0.75 + 0.3 - 1e-9


def _t(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def test_anomaly_behind_the_camera_is_rejected():
    station = _scene_of(box("wall", (20, 20, 1), "m").transformed(_t(0, 0, -20)))
    cam = np.array([0.0, 0.0, 0.0])
    ok, frac, why = check(station, CUBE.points, CUBE.triangles(), np.array([0, 0, 3.0]), np.eye(3),
                          cam, np.eye(3), 160, 90)
    assert not ok and "behind" in why


def test_anomaly_grazing_the_frame_edge_counts_only_visible_pixels():
    station = _scene_of(box("wall", (200, 200, 1), "m").transformed(_t(0, 0, -30)))
    cam, rot = np.zeros(3), np.eye(3)
    w, h = 320, 180
    half_fov = np.arctan(18 / 25)
    depth = 3.0
    x_edge = depth * np.tan(half_fov)
    centred = np.array([0.0, 0.0, -depth])
    grazing = np.array([x_edge, 0.0, -depth])  # centre on the right edge: about half is in frame
    anomaly_at = lambda p: RayScene([(CUBE.points + p, CUBE.triangles(), ANOMALY)])
    f_centre = visible_fraction(station, anomaly_at(centred), cam, rot, w, h)
    f_edge = visible_fraction(station, anomaly_at(grazing), cam, rot, w, h)
    assert 0.3 < f_edge / f_centre < 0.8  # about half the cube, plus the side face perspective shows
    # Same answer as a full owner image over station + anomaly.
    both = RayScene([(box("wall", (200, 200, 1), "m").transformed(_t(0, 0, -30)).points,
                   box("wall", (200, 200, 1), "m").triangles(), STATION), (CUBE.points + grazing, CUBE.triangles(), ANOMALY)])
    assert f_edge == pytest.approx((class_image(both, cam, rot, w, h) == ANOMALY).mean())


def test_anomaly_overlapping_the_station_is_rejected():
    station = _scene_of(box("wall", (20, 20, 1), "m").transformed(_t(0, 0, -5)))
    ok, _, why = check(station, CUBE.points, CUBE.triangles(), np.array([0, 0, -4.7]), np.eye(3),
                       np.zeros(3), np.eye(3), 160, 90)
    assert not ok and "intersects" in why


def test_degenerate_meshes_give_a_clear_error():
    with pytest.raises(DegenerateMeshError, match="zero"):
        MeshPart("flat", np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), [3], [0, 1, 2], "m")
    with pytest.raises(DegenerateMeshError, match="NaN"):
        MeshPart("nan", np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0.0]]), [3], [0, 1, 2], "m")
    with pytest.raises(DegenerateMeshError, match="out of range"):
        MeshPart("idx", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), [3], [0, 1, 5], "m")


def test_impossible_placement_is_bounded_and_clear():
    # The camera faces a wall 0.8 m away: nothing fits between them.
    station = _scene_of(box("wall", (50, 50, 0.2), "m").transformed(_t(0, 0, -0.9)))
    with pytest.raises(PlacementError, match="20 attempts"):
        place(station, CUBE.points, CUBE.triangles(), np.zeros(3), np.eye(3), np.random.default_rng(0),
              160, 90, max_attempts=20)


def test_five_depths_along_the_view_ray_and_determinism():
    st = tiny_station()
    pts, tris = st.triangle_soup()
    station = RayScene([(pts, tris, STATION)])
    cam = np.array([15.0, 8.0, 5.0])
    rot = look_at(cam, [0, 0, 0])
    runs = [place(station, CUBE.points, CUBE.triangles(), cam, rot, np.random.default_rng(3), 160, 90)
            for _ in range(2)]
    a, b = runs
    assert [p.depth_offset for p in a] == list(DEPTH_OFFSETS)
    assert all(np.array_equal(x.position, y.position) for x, y in zip(a, b) if x.position is not None)
    first = a[0].position
    for p in a[1:]:
        if p.position is None:
            assert p.skipped_reason
            continue
        step = p.position - first
        ray = (first - cam) / np.linalg.norm(first - cam)
        assert np.linalg.norm(np.cross(step, ray)) < 1e-9
        assert np.dot(step, ray) == pytest.approx(p.depth_offset)
        assert p.area_fraction >= 0.001


@pytest.mark.render
def test_predicted_area_matches_the_rendered_mask(tiny_base, tmp_path):
    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.blender.render import render_scene
    from allo_usd.usd.read import read_scene
    from allo_usd.usd.stage_geometry import read_triangles
    from allo_usd.scene.spec import AnomalySpec, CameraSpec

    from tests.support.helpers import make_spec

    st_pts, st_tris = read_triangles(tiny_base, "/World/Station")
    station = RayScene([(st_pts, st_tris, STATION)])
    a_pts, a_tris = read_triangles(tiny_base.parent / "anomalies" / "Crate.usda", "/Crate", "blue")
    cam = np.array([15.0, 8.0, 5.0])
    rot = look_at(cam, [0, 0, 0])
    w, h = 192, 108
    placement = place(station, a_pts, a_tris, cam, rot, np.random.default_rng(11), w, h)[0]
    spec = replace(make_spec(resolution=(w, h), samples=1),
                   camera=CameraSpec(tuple(cam), rot),
                   anomaly=AnomalySpec("Crate", "blue", tuple(placement.position), placement.rotation))
    result = render_scene(read_scene(write_scene_layer(spec, tmp_path / "s.usda", tiny_base)))
    rendered = int((result.mask == 2).sum())
    predicted = placement.area_fraction * w * h
    assert abs(rendered - predicted) <= max(0.02 * predicted, 50), (rendered, predicted)


def _random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    from allo_usd.core.geometry import quat_to_matrix
    return quat_to_matrix(q)


@pytest.mark.slow
def test_object_frame_casting_equals_world_frame_casting():
    """The anomaly's BVH is built once in its own frame and the rays are moved into it; on random
    poses and cameras this gives the same visible fraction as a BVH of the posed object."""
    from allo_usd.scene.placement import anomaly_scene
    from allo_usd.scene.raycast import pixel_rays

    rng = np.random.default_rng(7)
    st = tiny_station()
    pts, tris = st.triangle_soup()
    station = RayScene([(pts, tris, STATION)])
    obj = box("o", (0.6, 0.3, 0.2), "m")
    local = anomaly_scene(obj.points, obj.triangles())
    w, h = 160, 90
    compared = 0
    for _ in range(40):
        cam = rng.uniform(-1, 1, 3) * np.array([15.0, 15.0, 8.0])
        rot = look_at(cam, rng.uniform(-2, 2, 3))
        o, d = pixel_rays(cam, rot, w, h)
        pos = cam + d[rng.integers(len(d))] * rng.uniform(1.5, 10.0)
        r = _random_rotation(rng)
        world = RayScene([(obj.points @ r.T + pos, obj.triangles(), ANOMALY)])
        sphere = (pos, np.linalg.norm(obj.points, axis=1).max())
        f_world = visible_fraction(station, world, cam, rot, w, h, (o, d))
        f_local = visible_fraction(station, local, cam, rot, w, h, None, sphere, (pos, r))
        assert abs(f_world - f_local) * w * h <= 1, (f_world, f_local)   # one grazing pixel at most
        compared += f_world > 0
    assert compared >= 10


def test_pixel_ray_subsets_and_sphere_culling_are_exact():
    from allo_usd.scene.placement import sphere_pixels
    from allo_usd.scene.raycast import pixel_rays

    rng = np.random.default_rng(3)
    w, h = 96, 54
    for _ in range(30):
        cam, rot = rng.normal(size=3), _random_rotation(rng)
        o, d = pixel_rays(cam, rot, w, h)
        idx = rng.choice(w * h, 50, replace=False)
        assert np.array_equal(pixel_rays(cam, rot, w, h, idx)[1], d[idx])
        centre, radius = cam - rot[:, 2] * rng.uniform(1, 6) + rng.normal(size=3), rng.uniform(0.05, 0.8)
        v = centre - cam
        t = d @ v
        inside = np.flatnonzero((v @ v - t * t <= radius ** 2) & (t >= -radius))
        box_idx = sphere_pixels(cam, rot, w, h, centre, radius)
        if box_idx is not None:
            assert set(inside) <= set(box_idx.tolist())


def test_raycaster_matches_trimesh():
    """`RayScene` calls embree directly; it hits what trimesh's RayMeshIntersector hits, at the same
    distances to the last few ulps (trimesh sums its dot products with BLAS, whose rounding depends on
    the CPU; RayScene sums them in a fixed order, core.fixedmath)."""
    import trimesh

    st = tiny_station()
    pts, tris = st.triangle_soup()
    scene = RayScene([(pts, tris, STATION)])
    ref = trimesh.ray.ray_pyembree.RayMeshIntersector(trimesh.Trimesh(pts, tris, process=False))
    rng = np.random.default_rng(5)
    o = rng.uniform(-20, 20, (2000, 3))
    d = rng.normal(size=(2000, 3))
    owner, dist = scene.first_hit(o, d)
    locs, ray_idx, _ = ref.intersects_location(o, d, multiple_hits=False)
    want = np.full(len(o), np.inf)
    want[ray_idx] = np.linalg.norm(locs - o[ray_idx], axis=1)
    assert np.array_equal(np.isfinite(dist), np.isfinite(want)) and np.array_equal(owner > 0, np.isfinite(want))
    hit = np.isfinite(want)
    assert hit.sum() > 100 and np.allclose(dist[hit], want[hit], rtol=1e-12, atol=0.0)
    _, multi, _ = ref.intersects_location(o[:200], d[:200], multiple_hits=True)
    assert np.array_equal(np.bincount(scene.hits(o[:200], d[:200]), minlength=200), np.bincount(multi, minlength=200))


# ---------------------------------------------------------------------------------- camera rig

def test_view_quality_rejects_a_wall_and_an_empty_view_and_accepts_structure_in_range():
    from allo_usd.scene.rig import view_quality

    cam, rot = np.zeros(3), np.eye(3)                       # looks down -Z
    wall = view_quality(_scene_of(box("w", (40, 40, 0.2), "m").transformed(_t(0, 0, -1.5))), cam, rot)
    assert not wall.ok and wall.coverage == 1.0 and wall.near == 1.0 and wall.centre_m < 5
    empty = view_quality(_scene_of(box("b", (2, 2, 2), "m").transformed(_t(0, 0, 30))), cam, rot)
    assert not empty.ok and empty.coverage == 0.0 and empty.centre_m == np.inf
    # A 12 x 6 m block 15 m away fills the middle of the frame with structure in range.
    block = view_quality(_scene_of(box("b", (12, 6, 2), "m").transformed(_t(0, 0, -16))), cam, rot)
    assert block.ok and 14 < block.centre_m < 16 and 0.2 < block.coverage < 0.9 and block.in_range == 1.0


def test_base_poses_refuse_too_few_candidates_clearly():
    from allo_usd.scene.rig import base_poses

    st = tiny_station()
    pts, tris = st.triangle_soup()
    ring = np.array([[15 * np.cos(a), 15 * np.sin(a), 3.0] for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)])
    with pytest.raises(PlacementError, match="50 are needed"):
        base_poses(ring, pts, tris)


def _iss_model():
    """NASA's ISS model beside the repository (../shared/assets), or beside a worktree's parent."""
    from allo_usd.core.paths import ROOT

    found = [d / "shared" / "assets" / "ISS_2016.glb" for d in (ROOT.parent, ROOT.parent.parent)]
    return next((p for p in found if p.is_file()), found[0])


ISS = _iss_model()


@pytest.mark.slow
@pytest.mark.skipif(not ISS.is_file(), reason=f"NASA ISS_2016.glb not found at {ISS} (not in the repo)")
def test_rig_around_the_imported_iss():
    """The same rule picks 50 poses around NASA's model (inches, imported through trimesh)."""
    from allo_usd.usd.build_stage import station_and_fixtures
    from allo_usd.scene.rig import (MIN_SPACING_M, TEST_NEIGHBOUR_M, TEST_SEPARATION_M, TEST_TURN_DEG, base_poses,
                                    view_quality)

    station, candidates, _ = station_and_fixtures(str(ISS), units="in", up_axis="-z")  # its axes break glTF's
    pts, tris = station.triangle_soup()
    poses = base_poses(candidates, pts, tris)
    assert [p.split for p in poses] == ["train"] * 40 + ["test"] * 10
    pos = np.array([p.position for p in poses])
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=2) + np.eye(50) * 1e9
    assert gap.min() >= MIN_SPACING_M and gap[:40, 40:].min() >= TEST_SEPARATION_M
    ahead = np.array([-p.rotation[:, 2] for p in poses])
    turn = np.degrees(np.arccos(np.clip(ahead[:40] @ ahead[40:].T, -1, 1)))
    assert turn[gap[:40, 40:] < TEST_NEIGHBOUR_M].min() >= TEST_TURN_DEG
    scene = RayScene([(pts, tris, STATION)])
    assert all(view_quality(scene, p.position, p.rotation).ok for p in poses)


# ---------------------------------------------------------------------------------- placement

def _far_station():
    """A 6 m block 14 m down -Z with empty space around it: most of the frame is sky."""
    return box("block", (6, 6, 6), "m").transformed(_t(0, 0, -17))


@pytest.mark.slow
def test_placed_objects_stay_near_station_structure():
    """Every accepted depth has station geometry within NEAR_STRUCTURE_M of the object's centre
    (exact closest-point distance), and sits in front of the structure its ray meets, even when
    most of the frame shows empty space."""
    import trimesh

    from allo_usd.scene.placement import NEAR_STRUCTURE_M

    assert NEAR_STRUCTURE_M == 5.0
    block = _far_station()
    station = _scene_of(block)
    mesh = trimesh.Trimesh(block.points, block.triangles(), process=False)
    cam, rot = np.zeros(3), np.eye(3)
    obj = box("o", (0.8, 0.6, 0.5), "m")
    placed = 0
    for seed in range(12):
        for p in place(station, obj.points, obj.triangles(), cam, rot, np.random.default_rng(seed), 320, 180):
            if p.position is None:
                continue
            placed += 1
            _, dist, _ = trimesh.proximity.closest_point(mesh, p.position[None])
            assert dist[0] <= 5.0, (seed, p)          # the stated distance (NEAR_STRUCTURE_M)
            ray = p.position / np.linalg.norm(p.position)
            _, hit = station.first_hit(cam[None], ray[None])
            assert np.linalg.norm(p.position) < hit[0]
    assert placed >= 50


@pytest.mark.slow
def test_a_group_is_redrawn_until_all_five_depths_pass():
    """A 40 cm cube in front of the tiny station: every group places all five depths, each
    checked again here at the full resolution."""
    st = tiny_station()
    pts, tris = st.triangle_soup()
    station = RayScene([(pts, tris, STATION)])
    cam = np.array([15.0, 8.0, 5.0])
    rot = look_at(cam, [0, 0, 0])
    redrawn = 0
    for seed in range(10):
        group = place(station, CUBE.points, CUBE.triangles(), cam, rot, np.random.default_rng(seed), 320, 180)
        assert all(p.position is not None and not p.skipped_reason for p in group), group
        assert len({p.attempts for p in group}) == 1
        redrawn += group[0].attempts > 1
        for p in group:
            ok, frac, _ = check(station, CUBE.points, CUBE.triangles(), p.position, p.rotation, cam, rot, 320, 180)
            assert ok and frac == p.area_fraction
    assert redrawn >= 1       # the first draw does not always work: the redraw is what fills the group


def test_an_object_too_small_for_five_depths_falls_back_with_reasons():
    """A 4 cm cube covers 0.1% of the image only within ~1.5 m of the camera, so no draw fits five
    depths 4 m apart: the search stops after PARTIAL_ATTEMPTS draws and keeps the best group, whose
    failing depths carry their reason."""
    from allo_usd.scene.placement import PARTIAL_ATTEMPTS

    tiny = box("t", (0.04, 0.04, 0.04), "m")
    station = _scene_of(box("wall", (30, 30, 1), "m").transformed(_t(0, 0, -4)))
    group = place(station, tiny.points, tiny.triangles(), np.zeros(3), np.eye(3), np.random.default_rng(2), 320, 180)
    assert group[0].position is not None and group[0].area_fraction >= 0.001
    assert {p.attempts for p in group} == {PARTIAL_ATTEMPTS}
    skipped = [p for p in group if p.position is None]
    assert 1 <= len(skipped) <= 3
    assert all(("under 0.1%" in p.skipped_reason or "camera" in p.skipped_reason) for p in skipped), skipped


@pytest.mark.slow
def test_screened_placements_hold_at_the_render_resolution():
    """Candidates are screened at 480 px wide and confirmed at 1920x1080: every recorded fraction is
    the 1080p pixel-centre fraction (exactly, for objects under 8,000 px; within 1% above), and every
    accepted depth covers at least 0.1% of the 1080p image."""
    st = tiny_station()
    pts, tris = st.triangle_soup()
    station = RayScene([(pts, tris, STATION)])
    cam = np.array([15.0, 8.0, 5.0])
    rot = look_at(cam, [0, 0, 0])
    w, h = 1920, 1080
    obj = box("o", (0.5, 0.2, 0.1), "m")
    for seed in range(3):
        for p in place(station, obj.points, obj.triangles(), cam, rot, np.random.default_rng(seed), w, h):
            if p.position is None:
                continue
            ok, exact, _ = check(station, obj.points, obj.triangles(), p.position, p.rotation, cam, rot, w, h)
            assert ok and exact >= 0.001
            if exact * w * h < 8000:
                assert p.area_fraction == exact
            else:
                assert abs(p.area_fraction - exact) <= 0.01 * exact, (p.area_fraction, exact)


@pytest.mark.slow
def test_part_pixels_and_subgrid_cast_every_pixel_the_object_can_cover():
    """The part boxes' pixels that limit the rays cast never leave out a pixel whose centre ray meets
    the object, on the full grid or on a sub-grid, at every pose (a long thin object: its box is
    mostly empty), and none lies off the sub-grid or outside the image."""
    from allo_usd.scene.placement import _box_indices, _parts_pixels, anomaly_scene, random_rotation
    from allo_usd.scene.raycast import pixel_rays

    rng = np.random.default_rng(4)
    obj = box("thin", (1.2, 0.05, 0.03), "m")
    pts, tris = obj.points, obj.triangles()
    local = anomaly_scene(pts, tris)
    w, h = 320, 180
    checked = 0
    for _ in range(30):
        rot = random_rotation(rng)
        pos = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-0.8, 0.8), -rng.uniform(1.0, 4.0)])
        for stride in (1, 2, 3):
            every = _box_indices((0, w - 1, 0, h - 1), w, stride)
            o, d = pixel_rays(np.zeros(3), np.eye(3), w, h, every)
            owner, _ = local.first_hit((o - pos) @ rot, d @ rot)
            covered = set(every[owner > 0].tolist())
            cast = _parts_pixels(local, np.zeros(3), np.eye(3), w, h, (pos, rot), stride).index(w)
            assert covered <= set(cast.tolist()) <= set(every.tolist())
            assert len(set(cast.tolist())) == len(cast)
            checked += len(covered)
    assert checked > 1000
    behind = (np.array([0.0, 0.0, 0.2]), np.eye(3))                 # the object reaches behind the camera
    assert _parts_pixels(local, np.zeros(3), np.eye(3), w, h, behind) is None


def test_occlusion_query_agrees_with_first_hit():
    st = tiny_station()
    pts, tris = st.triangle_soup()
    scene = RayScene([(pts, tris, STATION)])
    rng = np.random.default_rng(8)
    o = rng.uniform(-20, 20, (3000, 3))
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, dist = scene.first_hit(o, d)
    tmax = rng.uniform(0.5, 40, len(o))
    clear = np.abs(dist - tmax) > 1e-4            # away from the float32 tie
    assert np.array_equal(scene.occluded(o, d, tmax)[clear], (dist < tmax)[clear])
    assert (dist < tmax).sum() > 100 and (dist >= tmax).sum() > 100


# ------------------------------------------------------------ speed-ups that change no decision

@pytest.mark.slow
def test_part_pixels_keep_every_pixel_and_the_count(monkeypatch):
    """The part boxes' pixels hold every pixel the object covers at any number of parts, and
    visible_fraction gives the same value (the same bits) with that cull, with fewer parts, or with
    none (the sphere and box-corner cull alone), with or without the station in front."""
    import allo_usd.scene.placement as P
    from allo_usd.assets.anomalies import build_anomaly
    from allo_usd.scene.raycast import pixel_rays

    rng = np.random.default_rng(12)
    st = tiny_station()
    pts_s, tris_s = st.triangle_soup()
    station = RayScene([(pts_s, tris_s, STATION)])
    part = build_anomaly("data_cable", "white").parts[0]            # a tube along a spline: a loose box
    pts = part.points - 0.5 * (part.points.min(axis=0) + part.points.max(axis=0))
    tris = part.triangles()
    local = P.anomaly_scene(pts, tris)
    r = np.linalg.norm(pts, axis=1).max()
    w, h = 320, 180
    fractions, covered_total = [], 0
    for _ in range(25):
        rot = P.random_rotation(rng)
        pos = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-0.8, 0.8), -rng.uniform(1.0, 5.0)])
        every = P._box_indices((0, w - 1, 0, h - 1), w)
        o, d = pixel_rays(np.zeros(3), np.eye(3), w, h, every)
        owner, _ = local.first_hit((o - pos) @ rot, d @ rot)
        covered = set(every[owner > 0].tolist())
        for levels in (P._PART_LEVELS, 3, 0):
            with monkeypatch.context() as m:
                m.setattr(P, "_PART_LEVELS", levels)
                assert covered <= set(P._parts_pixels(local, np.zeros(3), np.eye(3), w, h, (pos, rot)).index(w).tolist())
        covered_total += len(covered)
        cam = np.array([12.0, 6.0, 4.0])
        cam_rot = look_at(cam, [0, 0, 0])
        at = cam - cam_rot[:, 2] * rng.uniform(2.0, 9.0) + rng.normal(scale=0.5, size=3)
        for scene in (station, None):
            args = (scene, local, cam, cam_rot, w, h, None, (at, r), (at, rot), P.box_corners(pts), 1)
            got = []
            for levels in (P._PART_LEVELS, 2, 0):
                with monkeypatch.context() as m:
                    m.setattr(P, "_PART_LEVELS", levels)
                    got.append(visible_fraction(*args))
            assert got[0] == got[1] == got[2], got
            fractions.append(got[0])
    assert covered_total > 500 and sum(f > 0 for f in fractions) >= 10


def test_fallback_ranking_screens_less_and_ranks_as_screening_everything():
    """`_ranked` orders the fallback draws exactly as screening every depth of every draw would
    (most depths passing, then earliest attempt; initial depth required), on random tables."""
    from allo_usd.scene.placement import _ranked

    rng = np.random.default_rng(13)
    saved = 0
    for _ in range(300):
        attempts = sorted(rng.choice(100, rng.integers(1, 5), replace=False).tolist())
        table = {(a, i): bool(rng.random() < 0.6) for a in attempts for i in range(len(DEPTH_OFFSETS))}
        asked = []
        got = list(_ranked(attempts, lambda a, i: asked.append((a, i)) or table[a, i]))
        want = sorted((a for a in attempts if table[a, 0]),
                      key=lambda a: (-sum(table[a, i] for i in range(len(DEPTH_OFFSETS))), a))
        assert got == want and len(asked) == len(set(asked))
        saved += len(table) - len(asked)
    assert saved > 0


# ------------------------------------------------------------ placement's reference forms
# Each computation placement does by a shorter route gives exactly the bits of its plain form,
# written out below as a named reference implementation.

def _bits(a) -> bytes:
    """The array's dtype and bytes: equal only for the same dtype and the same bits."""
    a = np.asarray(a)
    return a.dtype.str.encode() + np.ascontiguousarray(a).tobytes()


def reference_posed_fraction(station, anomaly, cam_pos, cam_rot, width, height, idx, lens, pose, sphere, stride):
    """visible_fraction of a posed object for rays=None on (n, 3) arrays (pixel_rays, fm.matmul, first_hit
    on broadcast origins): the plain form the per-component count must equal bit for bit."""
    o, d = pixel_rays(cam_pos, cam_rot, width, height, idx, lens)
    if not len(o):
        return 0.0
    if sphere is not None:
        c, r = sphere
        v = c - o[0]
        t = fm.dot(d, v)
        miss = (fm.dot(v, v) - t * t > r * r) | (t < -r)
        keep = np.flatnonzero(~miss)
        if keep.size == 0:
            return 0.0
        o, d = o[keep], d[keep]
    position, rotation = np.asarray(pose[0], dtype=np.float64), np.asarray(pose[1], dtype=np.float64)
    origin = fm.matmul(np.asarray(cam_pos, dtype=np.float64)[None] - position, rotation)
    a_owner, a_dist = anomaly.first_hit(np.broadcast_to(origin, d.shape), fm.matmul(d, rotation))
    hit = a_owner > 0
    if not hit.any():
        return 0.0
    if station is None:
        return float(hit.sum() * stride * stride / (width * height))
    hidden = station.occluded(o[hit], d[hit], a_dist[hit])
    return float((~hidden).sum() * stride * stride / (width * height))


_posed_cases_seen: set = set()   # (without a station, fraction > 0) of each case of the test below


@pytest.mark.parametrize("seed", range(8))
def test_posed_fraction_is_the_n_by_3_count(seed):
    rng = np.random.default_rng(100 + seed)
    cam_pos = np.array([0.0, 0.0, 0.0])
    cam_rot = quat_to_matrix(rng.normal(size=4))
    position = -cam_rot[:, 2] * rng.uniform(3, 12) + rng.normal(size=3) * 0.5
    # the station partly between the camera and the object (some rays hidden, some not)
    anomaly, station = blob(200, seed), blob(60, seed + 50, 0.6 * position + cam_rot[:, 0] * 1.5)
    pose = (position, quat_to_matrix(rng.normal(size=4)))
    width, height, stride = 160, 90, int(rng.integers(1, 3))
    idx = placement._box_indices((0, width - 1, 0, height - 1), width, stride)
    for sphere in (None, (position, 3.0)):
        for st in (None, station):
            want = reference_posed_fraction(st, anomaly, cam_pos, cam_rot, width, height, idx, DEFAULT_CAMERA, pose,
                                            sphere, stride)
            got = placement._posed_fraction(st, anomaly, cam_pos, width, height, pose, stride, sphere,
                                            pixel_ray_columns(cam_rot, width, height, idx, DEFAULT_CAMERA))
            assert got.hex() == want.hex()
            _posed_cases_seen.add((st is None, got > 0.0))


def test_posed_fraction_cases_were_all_seen():
    """Both counts (silhouette alone, and behind the station) were exercised with something visible."""
    assert {(True, True), (False, True)} <= _posed_cases_seen, _posed_cases_seen


def reference_sphere_box(cam_pos, cam_rot, width, height, centre, radius, lens):
    """_sphere_box on numpy arrays (camera_intrinsics and fm.matmul): the plain form its Python-float
    route must equal exactly."""
    k = camera_intrinsics(width, height, lens)
    c = fm.matmul(np.asarray(centre, dtype=np.float64) - np.asarray(cam_pos, dtype=np.float64), np.asarray(cam_rot))
    depth = -c[2]
    if depth <= radius * 1.01:
        return None
    bounds = []
    for lateral in (c[0], c[1]):
        h = fm.hypot(lateral, depth)
        theta, beta = fm.arctan2(lateral, depth), fm.arcsin(min(1.0, radius / h))
        bounds.append((fm.tan(theta - beta), fm.tan(theta + beta)))
    (sx0, sx1), (sy0, sy1) = bounds
    return placement._bounds_to_pixels(width, height, sx0 * k[0, 0] + k[0, 2], sx1 * k[0, 0] + k[0, 2],
                                       k[1, 2] - sy1 * k[1, 1], k[1, 2] - sy0 * k[1, 1])


@pytest.mark.parametrize("lens", [DEFAULT_CAMERA, CameraModel(principal_point_offset_px=(13.25, -7.5))])
def test_sphere_box_is_its_matmul_form(lens):
    rng = np.random.default_rng(3)
    for _ in range(2000):
        cam = rng.normal(size=3) * 10
        rot = quat_to_matrix(rng.normal(size=4))
        centre = cam + rng.normal(size=3) * rng.uniform(0.5, 40)
        radius = float(rng.uniform(0.01, 5.0))
        w = int(rng.choice([480, 1920]))
        h = w * 9 // 16
        assert placement._sphere_box(cam, rot, w, h, centre, radius, lens) == \
            reference_sphere_box(cam, rot, w, h, centre, radius, lens)


def reference_rects_union(width, height, stride, u0, u1, v0, v1):
    """placement._rects_union with each axis on its own and every part in the loop: the plain form
    the stacked-axes union must equal bit for bit."""
    phase, m = stride // 2, placement.CULL_MARGIN_PX
    none = np.zeros(0, dtype=np.int64)
    if phase >= width or phase >= height:
        return none, none, none, none
    t0 = np.maximum(-((phase - np.ceil(u0 - (0.5 + m)).astype(np.int64)) // stride), 0)
    t1 = np.minimum((np.floor(u1 - (0.5 - m)).astype(np.int64) - phase) // stride, (width - 1 - phase) // stride)
    r0 = np.maximum(-((phase - np.ceil(v0 - (0.5 + m)).astype(np.int64)) // stride), 0)
    r1 = np.minimum((np.floor(v1 - (0.5 - m)).astype(np.int64) - phase) // stride, (height - 1 - phase) // stride)
    some = (t0 <= t1) & (r0 <= r1)
    if not some.any():
        return none, none, none, none
    c0, c1, w0, w1 = int(t0[some].min()), int(t1[some].max()), int(r0[some].min()), int(r1[some].max())
    covered = np.zeros((w1 - w0 + 1, c1 - c0 + 1), dtype=bool)
    for a, b, c, d in zip((r0 - w0).tolist(), (r1 - w0 + 1).tolist(), (t0 - c0).tolist(), (t1 - c0 + 1).tolist()):
        if a < b and c < d:
            covered[a:b, c:d] = True
    jj, ii = np.nonzero(covered)
    return phase + stride * np.arange(c0, c1 + 1), phase + stride * np.arange(w0, w1 + 1), ii, jj


@pytest.mark.slow
def test_rects_union_is_the_per_axis_form():
    rng = np.random.default_rng(4)
    cases = 0
    for k in range(3000):
        w, h, stride, parts = (int(rng.integers(1, 240)), int(rng.integers(1, 140)), int(rng.integers(1, 5)),
                               int(rng.integers(1, 70)))
        u0, v0 = rng.uniform(-40, w + 40, parts), rng.uniform(-40, h + 40, parts)
        u1, v1 = u0 + rng.uniform(-4, 50, parts), v0 + rng.uniform(-4, 50, parts)
        if k % 3 == 0:                                     # edges on and near pixel centres
            u0, v0 = np.round(u0) + 0.5 + rng.choice([0.0, 0.05, -0.05, 0.0500001], parts), np.round(v0) + 0.45
        got = placement._rects_union(w, h, stride, np.stack([u0, v0]), np.stack([u1, v1]))
        want = reference_rects_union(w, h, stride, u0, u1, v0, v1)
        assert all(g.dtype == np.int64 and _bits(g) == _bits(x) for g, x in zip(got, want)), (w, h, stride)
        cases += bool(len(want[2]))
    assert cases > 1500


@pytest.mark.parametrize("size", [(64, 36), (480, 270), (1920, 1080)])
@pytest.mark.slow
def test_part_cull_margin_keeps_every_pixel_the_object_covers(size):
    """CULL_MARGIN_PX (a twentieth of a pixel around each part box's image) never leaves out a pixel
    whose ray embree finds on the object: the paper's hazard objects (thin cables and rails, hollow
    hooks, boxy bags) from the camera clearance out to 40 m, on the full grid and on sub-grids. Every
    pixel in the object's bounding-sphere box is cast as the reference."""
    from allo_usd.assets.anomalies import ANOMALY_IDS, build_anomaly
    w, h = size
    rng = np.random.default_rng(w)
    covered_total = 0
    for name in ANOMALY_IDS:
        pts, tris = build_anomaly(name).triangle_soup()
        local = placement.anomaly_scene(pts, tris)
        radius = float(fm.norm(pts, axis=1).max())
        for _ in range(2 if w > 1000 else 4):
            cam_rot = quat_to_matrix(rng.normal(size=4))
            depth = radius + placement.CAMERA_CLEARANCE_M + rng.choice([0.0, rng.uniform(0.5, 4.0), 40.0])
            lateral = rng.uniform(-0.3, 0.3, 2) * depth
            pos = cam_rot @ np.array([lateral[0], lateral[1], -depth])
            pose = (pos, quat_to_matrix(rng.normal(size=4)))
            box = placement._sphere_box(np.zeros(3), cam_rot, w, h, pos, radius * 1.01)
            if box is None:
                continue
            for stride in (1, 2, 3):
                every = placement._box_indices(box, w, stride)
                if not every.size:
                    continue
                covered = []
                for part in np.array_split(every, -(-every.size // 100_000)):   # bounded memory at 1920x1080
                    o, d = pixel_rays(np.zeros(3), cam_rot, w, h, part)
                    owner, _ = local.first_hit(fm.matmul(o - pose[0], pose[1]), fm.matmul(d, pose[1]))
                    covered.append(part[owner > 0])
                covered = np.concatenate(covered)
                cells = placement._parts_pixels(local, np.zeros(3), cam_rot, w, h, pose, stride)
                cast = np.zeros(w * h, dtype=bool)
                cast[cells.index(w) if cells is not None else every] = True
                assert cast[covered].all(), (name, stride, int((~cast[covered]).sum()))
                covered_total += covered.size
    assert covered_total > 500


def test_the_extent_kept_on_the_bvh_follows_the_points():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(200, 3))
    tris = rng.integers(0, 200, size=(100, 3))
    scene = placement.anomaly_scene(pts, tris)
    radius, corners = placement._extent(scene, pts)
    assert radius == float(fm.norm(pts, axis=1).max()) and _bits(corners) == _bits(box_corners(pts))
    assert placement._extent(scene, pts)[1] is corners             # kept
    other = pts * 2.0
    radius2, corners2 = placement._extent(scene, other)           # other points: computed afresh
    assert radius2 == float(fm.norm(other, axis=1).max()) and _bits(corners2) == _bits(box_corners(other))


def test_a_placement_is_the_same_with_the_extent_kept():
    """Two groups of one asset on one BVH place as a fresh BVH each would."""
    station = station_scene()
    obj = (np.array([[-0.3, -0.2, -0.15], [0.3, -0.2, -0.15], [0.3, 0.2, -0.15], [-0.3, 0.2, -0.15],
                     [-0.3, -0.2, 0.15], [0.3, -0.2, 0.15], [0.3, 0.2, 0.15], [-0.3, 0.2, 0.15]]))
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6], [0, 4, 5], [0, 5, 1], [1, 5, 6], [1, 6, 2],
                      [2, 6, 7], [2, 7, 3], [3, 7, 4], [3, 4, 0]])
    cam_pos = np.array([15.0, 8.0, 5.0])
    look = -cam_pos / fm.norm(cam_pos)
    right = fm.cross(look, np.array([0.0, 0.0, 1.0]))
    right /= fm.norm(right)
    cam_rot = np.stack([right, fm.cross(right, look), -look], axis=1)
    shared = placement.anomaly_scene(obj, faces)
    for seed in (1, 2):
        got = placement.place(station, obj, faces, cam_pos, cam_rot, np.random.default_rng(seed), 160, 90,
                              check_width=None, anomaly=shared)
        want = placement.place(station, obj, faces, cam_pos, cam_rot, np.random.default_rng(seed), 160, 90,
                               check_width=None)
        assert [(p.depth_index, None if p.position is None else _bits(p.position), p.area_fraction) for p in got] == \
            [(p.depth_index, None if p.position is None else _bits(p.position), p.area_fraction) for p in want]
    assert shared.memo["extent"][0] is obj


def test_rig_clearance_and_line_of_sight_are_the_numpy_paths(monkeypatch):
    """too_close and the one-ray look along a candidate's line of sight, on the station, give the
    numpy path's answers and distances with the few-ray path on."""
    scene = station_scene()
    rng = np.random.default_rng(5)
    lo, hi = scene.vertices.min(axis=0) - 2.0, scene.vertices.max(axis=0) + 2.0
    points = lo + (hi - lo) * rng.random((300, 3))
    got = [rig.too_close(scene, p) for p in points]
    assert got == numpy_path(monkeypatch, lambda: [rig.too_close(scene, p) for p in points])
    assert 0 < sum(got) < len(got)
    rays = scene.vertices[rng.integers(len(scene.vertices), size=300)] - points + rng.normal(scale=0.5, size=(300, 3))
    rays /= fm.norm(rays, axis=1, keepdims=True)
    got = [scene.first_hit(p[None], r[None])[1][0] for p, r in zip(points, rays)]
    want = numpy_path(monkeypatch, lambda: [scene.first_hit(p[None], r[None])[1][0] for p, r in zip(points, rays)])
    assert _bits(got) == _bits(want) and np.isfinite(got).sum() > 50
