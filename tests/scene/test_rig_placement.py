"""Camera perturbation and anomaly placement: statistics, hard cases, agreement with a render."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from allo_usd.assets.primitives import box
from allo_usd.scene.spec import CameraPose
from allo_usd.core.labels import ANOMALY, STATION
from allo_usd.core.errors import DegenerateMeshError, PlacementError
from allo_usd.core.geometry import look_at
from allo_usd.assets.mesh import MeshPart
from allo_usd.scene.placement import DEPTH_OFFSETS, check, place, visible_fraction
from allo_usd.scene.raycast import RayScene, class_image
from allo_usd.scene.rig import ANGLE_SIGMA_RAD, POSITION_SIGMA_M, perturb

from tests.support.helpers import tiny_station


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

def test_pixel_rays_equal_the_matrix_form_bit_for_bit():
    """pixel_rays computes each direction component as its own array; the bits equal R @ (x, y, -1)
    normalised per ray, as written out here."""
    from allo_usd.core.geometry import camera_intrinsics
    from allo_usd.scene.placement import random_rotation
    from allo_usd.scene.raycast import pixel_rays

    rng = np.random.default_rng(11)
    for w, h in ((1920, 1080), (480, 270), (64, 36)):
        k = camera_intrinsics(w, h)
        for _ in range(10):
            rot, idx = random_rotation(rng), np.sort(rng.choice(w * h, min(w * h, 3000), replace=False))
            u, v = (idx % w) + 0.5, (idx // w) + 0.5
            x, y = (u - k[0, 2]) / k[0, 0], -(v - k[1, 2]) / k[1, 1]
            want = x[:, None] * rot[:, 0] + y[:, None] * rot[:, 1] - rot[:, 2]
            want /= np.sqrt(want[:, 0] * want[:, 0] + want[:, 1] * want[:, 1] + want[:, 2] * want[:, 2])[:, None]
            o, d = pixel_rays(np.ones(3), rot, w, h, idx)
            assert np.array_equal(d.view(np.uint64), want.view(np.uint64)) and np.array_equal(o[-1], np.ones(3))


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
