"""Camera perturbation and anomaly placement: statistics, hard cases, agreement with a render."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from allo_usd.assets.primitives import box
from allo_usd.author.base import CameraPose
from allo_usd.description import ANOMALY, STATION
from allo_usd.errors import DegenerateMeshError, PlacementError
from allo_usd.geometry import look_at
from allo_usd.mesh import MeshPart
from allo_usd.placement import DEPTH_OFFSETS, check, place, visible_fraction
from allo_usd.raycast import Scene, class_image
from allo_usd.rig import ANGLE_SIGMA_RAD, POSITION_SIGMA_M, perturb

from conftest import tiny_station


def _scene_of(*boxes):
    return Scene([(b.points, b.triangles(), STATION) for b in boxes])


CUBE = box("c", (0.4, 0.4, 0.4), "m")


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
    anomaly_at = lambda p: Scene([(CUBE.points + p, CUBE.triangles(), ANOMALY)])
    f_centre = visible_fraction(station, anomaly_at(centred), cam, rot, w, h)
    f_edge = visible_fraction(station, anomaly_at(grazing), cam, rot, w, h)
    assert 0.3 < f_edge / f_centre < 0.8  # about half the cube, plus the side face perspective shows
    # Same answer as a full owner image over station + anomaly.
    both = Scene([(box("wall", (200, 200, 1), "m").transformed(_t(0, 0, -30)).points,
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
    station = Scene([(pts, tris, STATION)])
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
    from allo_usd.author.scene import write_scene_layer
    from allo_usd.blender.render import render_scene
    from allo_usd.read import read_scene, read_triangles
    from allo_usd.spec import AnomalySpec, CameraSpec

    from conftest import make_spec

    st_pts, st_tris = read_triangles(tiny_base, "/World/Station")
    station = Scene([(st_pts, st_tris, STATION)])
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
    from allo_usd.geometry import quat_to_matrix
    return quat_to_matrix(q)


def test_object_frame_casting_equals_world_frame_casting():
    """The anomaly's BVH is built once in its own frame and the rays are moved into it; on random
    poses and cameras this gives the same visible fraction as a BVH of the posed object."""
    from allo_usd.placement import anomaly_scene
    from allo_usd.raycast import pixel_rays

    rng = np.random.default_rng(7)
    st = tiny_station()
    pts, tris = st.triangle_soup()
    station = Scene([(pts, tris, STATION)])
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
        world = Scene([(obj.points @ r.T + pos, obj.triangles(), ANOMALY)])
        sphere = (pos, np.linalg.norm(obj.points, axis=1).max())
        f_world = visible_fraction(station, world, cam, rot, w, h, (o, d))
        f_local = visible_fraction(station, local, cam, rot, w, h, None, sphere, (pos, r))
        assert abs(f_world - f_local) * w * h <= 1, (f_world, f_local)   # one grazing pixel at most
        compared += f_world > 0
    assert compared >= 10


def test_pixel_ray_subsets_and_sphere_culling_are_exact():
    from allo_usd.placement import sphere_pixels
    from allo_usd.raycast import pixel_rays

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
    """`Scene` calls embree directly; distances and owners equal trimesh's RayMeshIntersector."""
    import trimesh

    st = tiny_station()
    pts, tris = st.triangle_soup()
    scene = Scene([(pts, tris, STATION)])
    ref = trimesh.ray.ray_pyembree.RayMeshIntersector(trimesh.Trimesh(pts, tris, process=False))
    rng = np.random.default_rng(5)
    o = rng.uniform(-20, 20, (2000, 3))
    d = rng.normal(size=(2000, 3))
    owner, dist = scene.first_hit(o, d)
    locs, ray_idx, _ = ref.intersects_location(o, d, multiple_hits=False)
    want = np.full(len(o), np.inf)
    want[ray_idx] = np.linalg.norm(locs - o[ray_idx], axis=1)
    assert np.array_equal(dist, want) and np.array_equal(owner > 0, np.isfinite(want))
    _, multi, _ = ref.intersects_location(o[:200], d[:200], multiple_hits=True)
    assert np.array_equal(np.bincount(scene.hits(o[:200], d[:200]), minlength=200), np.bincount(multi, minlength=200))
