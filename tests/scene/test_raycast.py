"""allo_usd.scene.raycast gives exactly the bits of the plain numpy forms it computes by other
routes: a fan cast from one point is first_hit from that point repeated; every way of making pixel
rays (pixel_rays, pixel_ray_columns, subgrid_ray_columns over the cells placement's part-box cull
returns) is R @ (x, y, -1) normalised, as written out here; a few rays' hits on Python floats are
the numpy path's; the surface-crossing walk behind `hits` and `inside` is the numpy walk written out
here; and the helpers (_unitize, intrinsic_rows, part_boxes, hits_from, occluded) are their plain
forms. Each plain form is a named reference implementation (reference_*) in this file."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.geometry import box_corners, camera_intrinsics, quat_to_matrix
from allo_usd.scene import placement, raycast, rig
from allo_usd.scene.raycast import (_PARITY_DIRS, _RAY_OFFSET_FACTOR, _RAY_OFFSET_FLOOR, RayFan, RayScene,
                                    _unitize, intrinsic_rows, pixel_ray_columns, pixel_rays, subgrid_ray_columns)

from tests.support.soups import blob, numpy_path, station_scene


def _bits(a) -> bytes:
    """The array's dtype and bytes: equal only for the same dtype and the same bits."""
    a = np.asarray(a)
    return a.dtype.str.encode() + np.ascontiguousarray(a).tobytes()


def _bits64(a) -> bytes:
    """The bytes of the values as float64 (lists, float32 and float64 arrays compared by value bits)."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes()


# --------------------------------------------------------------- first_hit_fan is first_hit

def _fan_casts(case: str, seed: int):
    """(scene, [(origin, directions, fans of those directions)]) for one case of the fan test."""
    rng = np.random.default_rng(seed)
    if case == "columns":        # one origin, up to 3000 rays towards the blob, some of zero length
        scene = blob(seed=seed)
        origin = rng.normal(size=3) * 5
        n = int(rng.integers(1, 3000))
        dirs = -origin + rng.normal(size=(n, 3)) * 1.5
        dirs[: n // 20] = 0.0                           # zero directions take the masked path
        return scene, [(origin, dirs, [RayFan(dirs[:, 0].copy(), dirs[:, 1].copy(), dirs[:, 2].copy())])]
    if case == "rows":           # one fan of up to 300 rays cast from five points, made of rows and of columns
        scene = blob(seed=seed, spread=(0.5, 3.0))
        dirs = rng.normal(size=(int(rng.integers(1, 300)), 3))
        if seed % 2:
            dirs[0] = 0.0                               # a direction without a length
        fan = RayFan.of_rows(dirs)
        casts = []
        for _ in range(5):
            p = rng.normal(size=3) * rng.uniform(0.1, 4.0)
            casts.append((p, dirs, [fan, RayFan(*(np.ascontiguousarray(dirs[:, j]) for j in range(3)))]))
        return scene, casts
    # the fans placement and the rig build once at import (their clearance probes)
    scene = blob(seed=seed, spread=(0.5, 3.0))
    p = np.array([0.3, -0.2, 0.1])
    return scene, [(p, placement._SPHERE_DIRS, [placement._SPHERE_FAN]), (p, rig._CLEARANCE_DIRS, [rig._CLEARANCE_FAN])]


@pytest.mark.parametrize("case, seed", [("columns", s) for s in range(6)] + [("rows", s) for s in range(6)]
                         + [("module fans", 9)])
def test_first_hit_fan_is_first_hit_from_the_repeated_origin(case, seed):
    """first_hit_fan(p, fan) gives the bits of first_hit on p repeated (and on p broadcast) for each
    ray: fans of component arrays and of rows, directions of zero length, a fan cast from several
    points, and placement's and the rig's module fans."""
    scene, casts = _fan_casts(case, seed)
    for origin, dirs, fans in casts:
        want = scene.first_hit(np.repeat(np.asarray(origin)[None], len(dirs), 0), dirs)
        broadcast = scene.first_hit(np.broadcast_to(origin, (len(dirs), 3)), dirs)
        assert all(_bits(w) == _bits(b) for w, b in zip(want, broadcast))
        for fan in fans:
            got = scene.first_hit_fan(origin, fan)
            assert all(_bits(w) == _bits(g) for w, g in zip(want, got))
        assert (want[0] > 0).any()


def test_first_hit_fan_no_rays():
    owner, dist = blob().first_hit_fan(np.zeros(3), RayFan(np.zeros(0), np.zeros(0), np.zeros(0)))
    assert owner.shape == dist.shape == (0,)


def _blob_parts(seed: int, owners=(2,)) -> RayScene:
    """Random triangles around the origin (some nearly edge-on to any ray), one part per owner id."""
    rng = np.random.default_rng(seed)
    parts = []
    for oid in owners:
        centres = rng.normal(size=(300, 1, 3))
        pts = (centres + rng.normal(scale=0.3, size=(300, 3, 3))).reshape(-1, 3)
        parts.append((pts, np.arange(len(pts)).reshape(-1, 3), oid))
    return RayScene(parts)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hits_from_is_first_hit_fans_hits(seed):
    rng = np.random.default_rng(seed)
    scene = _blob_parts(seed, owners=(0, 1, 2))                 # owner 0 hits count as none
    for _ in range(20):
        origin = rng.normal(size=3) * 6.0
        dirs = rng.normal(size=(2000, 3)) * rng.uniform(0.1, 3.0)
        fan = RayFan.of_rows(dirs)
        owner, dist = scene.first_hit_fan(origin, fan)
        want = np.flatnonzero(owner > 0)
        rays, got = scene.hits_from(origin, fan)
        assert np.array_equal(rays, want) and _bits64(got) == _bits64(dist[want])
        rays2, none = scene.hits_from(origin, fan, distances=False)
        assert np.array_equal(rays2, want) and none is None
    rays, dist = scene.hits_from(np.full(3, 100.0), RayFan.of_rows(np.array([[1.0, 0.0, 0.0]])))
    assert rays.size == 0 and dist.size == 0


def test_occlusion_from_one_broadcast_point_is_the_repeated_point():
    scene = station_scene()
    rng = np.random.default_rng(9)
    cam = np.array([12.0, 6.0, 4.0])
    d = rng.normal(size=(3000, 3))
    d = d / fm.norm(d, axis=1, keepdims=True)
    tmax = rng.uniform(1, 40, len(d))
    broadcast = scene.occluded(np.broadcast_to(cam, d.shape), d, tmax)
    assert np.array_equal(broadcast, scene.occluded(np.repeat(cam[None], len(d), 0), d, tmax))
    assert 100 < broadcast.sum() < len(d) - 100


# --------------------------------------------------------------- a few rays on Python floats

def _soup(seed: int) -> RayScene:
    """Random triangles with degenerate ones, and faces in the planes x = k that axis rays graze."""
    rng = np.random.default_rng(seed)
    pts = (rng.normal(size=(300, 1, 3)) * 2.0 + rng.normal(scale=0.5, size=(300, 3, 3))).reshape(-1, 3)
    pts[:60, 0] = np.round(pts[:60, 0])
    pts[60:90] = pts[60]
    owner_a, owner_b = np.arange(450).reshape(-1, 3), np.arange(450, 900).reshape(-1, 3)
    return RayScene([(pts[:450], owner_a, 1), (pts[450:], owner_b - 450, 2)])


@pytest.mark.parametrize("make", [station_scene, lambda: _soup(1), lambda: _soup(2)])
def test_few_rays_are_the_numpy_hits(make, monkeypatch):
    """Up to `_FEW` rays, first_hit and first_hit_fan work on Python floats (`RayScene._few_hits`);
    the hits and distances are the numpy path's, grazing hits and zero directions included."""
    scene = make()
    rng = np.random.default_rng(11)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    dropped = hits = 0
    for k in range(400):
        n = int(rng.integers(1, raycast._FEW + 1))
        o = lo + (hi - lo) * rng.random((n, 3))
        d = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 1e3])
        if k % 5 == 0:                                     # towards a face's centre along its plane: grazing hits
            tri = scene.vertices[scene.faces[rng.integers(len(scene.faces), size=n)]]
            normal = fm.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            centre = tri.mean(axis=1)
            o = centre + 2.0 * (centre - tri[:, 0]) + normal * 1e-9
            d = (centre - o) - normal * rng.choice([0.0, 1e-7, 1e-6])
        if k % 7 == 0:
            d[-1] = 0.0                                    # a direction without a length
        got = scene.first_hit(o, d)
        want = numpy_path(monkeypatch, lambda: scene.first_hit(o, d))
        assert [_bits(a) for a in got] == [_bits(a) for a in want]
        fan = RayFan.of_rows(d)
        assert fan.rows is not None
        got_fan = scene.first_hit_fan(o[0], fan)
        want_fan = numpy_path(monkeypatch, lambda: scene.first_hit_fan(o[0], RayFan.of_rows(d)))
        assert [_bits(a) for a in got_fan] == [_bits(a) for a in want_fan]
        embree = scene._run(o, raycast._unitize(d)[0])
        hits += int((want[0] > 0).sum())
        dropped += int(((embree != -1) & (want[0] == 0)).sum())
    assert hits > 500 and dropped > 0                     # both kinds of hit were exercised


def test_a_fan_past_few_rays_takes_the_numpy_path():
    assert RayFan.of_rows(np.eye(3)[np.arange(raycast._FEW + 1) % 3]).rows is None
    assert rig._CLEARANCE_FAN.rows is not None and placement._SPHERE_FAN.rows is None


# --------------------------------------------------------------- the surface-crossing walk

def reference_crossings(scene: RayScene, origins, dirs, max_hits):
    """RayScene._crossings in numpy arrays throughout: the plain form the walk on Python floats must
    equal step for step."""
    o = np.array(origins, dtype=np.float64)
    d = _unitize(np.asarray(dirs, dtype=np.float64))[0]
    base = max(_RAY_OFFSET_FLOOR, scene.scale * _RAY_OFFSET_FACTOR)
    offsets = d * base
    last = np.full(len(o), -1, dtype=np.int64)
    live = np.arange(len(o))
    for _ in range(max_hits):
        prim = scene._run(o[live], d[live])
        hit = prim != -1
        if not hit.any():
            break
        rays, tri = live[hit], prim[hit].astype(np.int64)
        dupe = last[rays] == tri
        last[rays] = tri
        ok_rays, ok_tri, dupe_rays = rays[~dupe], tri[~dupe], rays[dupe]
        valid, t = scene._plane_distance(ok_tri, o[ok_rays], d[ok_rays])
        ok_rays = ok_rays[valid]
        o[ok_rays] = o[ok_rays] + d[ok_rays] * t[:, None] + offsets[ok_rays]
        offsets[ok_rays] = d[ok_rays] * base
        offsets[dupe_rays] *= 2.0
        o[dupe_rays] += offsets[dupe_rays]
        live = np.concatenate([ok_rays, dupe_rays])
        yield ok_rays, live


def reference_inside(scene: RayScene, point) -> bool:
    """RayScene.inside on reference_crossings: the parity vote in numpy arrays."""
    n = len(_PARITY_DIRS)
    origins = np.repeat(np.asarray(point, dtype=np.float64)[None], n, 0)
    crossings = np.zeros(n, dtype=np.int64)
    done = np.ones(n, dtype=bool)
    for crossed, live in reference_crossings(scene, origins, _PARITY_DIRS, 100):
        crossings += np.bincount(crossed, minlength=n)
        done[:] = True
        done[live] = False
        odd = crossings % 2 == 1
        if int((done & odd).sum()) >= 4 or int((done & ~odd).sum()) > n - 4:
            break
    return int((crossings % 2 == 1).sum()) >= 4


def _shell() -> RayScene:
    """Random triangles, many nearly parallel to the axis rays, some sharing planes (re-hits)."""
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(400, 1, 3)) * 2.0
    pts = (centres + rng.normal(scale=0.4, size=(400, 3, 3))).reshape(-1, 3)
    pts[:60, 0] = np.round(pts[:60, 0])            # faces in the planes x = k: axis rays graze them
    return RayScene([(pts, np.arange(len(pts)).reshape(-1, 3), 1)])


@pytest.mark.parametrize("make", [station_scene, _shell])
def test_inside_is_the_numpy_walk(make):
    scene = make()
    rng = np.random.default_rng(7)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    points = [lo + (hi - lo) * rng.random(3) for _ in range(1500)]
    points += [scene.vertices[i] + rng.normal(scale=1e-3, size=3) for i in rng.integers(len(scene.vertices), size=300)]
    points += [np.array([-10.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0]), np.array([-10.0, 5.0, 0.5])]
    got = [scene.inside(p) for p in points]
    assert got == [reference_inside(scene, p) for p in points]
    assert sum(got) > 20 and len(got) - sum(got) > 20         # points inside and outside


@pytest.mark.parametrize("make", [station_scene, _shell])
def test_hits_are_the_numpy_walk(make):
    scene = make()
    rng = np.random.default_rng(8)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    o = lo + (hi - lo) * rng.random((400, 3))                   # within the mesh's box: most rays cross it
    d = rng.normal(size=(400, 3))
    d[:50] = [1.0, 0.0, 0.0]                                  # along faces' planes
    want = [r for crossed, _ in reference_crossings(scene, o, d, 100) for r in crossed.tolist()]
    got = scene.hits(o, d)
    assert got.dtype == np.int64 and got.tolist() == want and len(want) > 50
    steps_reference = [(c.tolist(), sorted(v.tolist())) for c, v in reference_crossings(scene, o, d, 3)]
    assert [(c, sorted(v)) for c, v in scene._crossings(o, d, 3)] == steps_reference
    assert scene.hits(o[:0], d[:0]).size == 0


# --------------------------------------------------------------- pixel rays

def reference_pixel_directions(cam_rot, width, height, index, lens=DEFAULT_CAMERA) -> np.ndarray:
    """R @ (x, y, -1) normalised per ray, for the row-major pixels `index` (all when None), written
    out in (n, 3) numpy arrays: the matrix form every pixel-ray route must equal bit for bit."""
    k = camera_intrinsics(width, height, lens)
    idx = np.arange(width * height) if index is None else np.asarray(index)
    u, v = (idx % width) + 0.5, (idx // width) + 0.5
    x, y = (u - k[0, 2]) / k[0, 0], -(v - k[1, 2]) / k[1, 1]
    rot = np.asarray(cam_rot, dtype=np.float64)
    want = x[:, None] * rot[:, 0] + y[:, None] * rot[:, 1] - rot[:, 2]
    want /= np.sqrt(want[:, 0] * want[:, 0] + want[:, 1] * want[:, 1] + want[:, 2] * want[:, 2])[:, None]
    return want


def _pixel_ray_views(case: str, arg):
    """(camera position, rotation, width, height, index, lens, part-box cells or None) for a case of
    the pixel-ray test."""
    if case == "samples":        # random sorted pixels of three image sizes, the default lens
        w, h = arg
        rng = np.random.default_rng(11)
        k = 0
        while k < 10:
            rot, idx = placement.random_rotation(rng), np.sort(rng.choice(w * h, min(w * h, 3000), replace=False))
            yield np.ones(3), rot, w, h, idx, DEFAULT_CAMERA, None
            k += 1
    elif case == "lens":         # the whole image and 3000 of its pixels, through a lens
        rng = np.random.default_rng(2626)
        rot = quat_to_matrix(rng.normal(size=4))
        idx = rng.choice(480 * 270, 3000, replace=False)
        for index in (None, np.sort(idx)):
            yield np.array([1.0, 2.0, 3.0]), rot, 480, 270, index, arg, None
    else:                        # the cells of placement's part-box cull on a sub-grid of stride `arg`
        rng = np.random.default_rng(20 + arg)
        scene = _shell()
        for lens in (placement.DEFAULT_CAMERA, CameraModel(principal_point_offset_px=(12.5, -7.0))):
            for _ in range(10):
                cam_rot = quat_to_matrix(rng.normal(size=4))
                pose = (-cam_rot[:, 2] * rng.uniform(6, 20) + rng.normal(size=3), quat_to_matrix(rng.normal(size=4)))
                cells = placement._parts_pixels(scene, np.zeros(3), cam_rot, 480, 270, pose, arg, lens)
                if cells is None:
                    continue
                yield np.zeros(3), cam_rot, 480, 270, cells.index(480), lens, cells


@pytest.mark.parametrize("case, arg", [("samples", (1920, 1080)), ("samples", (480, 270)), ("samples", (64, 36)),
                                       ("lens", DEFAULT_CAMERA),
                                       ("lens", CameraModel(principal_point_offset_px=(12.5, -7.0))),
                                       ("cells", 1), ("cells", 2), ("cells", 3)])
def test_pixel_rays_are_the_matrix_form(case, arg):
    """pixel_rays, pixel_ray_columns and (over the part-box cull's cells, for any lens offset and
    sub-grid) subgrid_ray_columns compute each direction component as its own array; every one gives
    the bits of R @ (x, y, -1) normalised per ray, for any pixels, lens and image size."""
    views = 0
    for cam, rot, w, h, index, lens, cells in _pixel_ray_views(case, arg):
        o, d = pixel_rays(cam, rot, w, h, index, lens)
        assert np.array_equal(d.view(np.uint64), reference_pixel_directions(rot, w, h, index, lens).view(np.uint64))
        assert np.array_equal(o[-1], cam)
        cols = pixel_ray_columns(rot, w, h, index, lens)
        assert all(_bits(d[:, j]) == _bits(cols[j]) for j in range(3))
        if cells is not None:
            assert index.size and np.all(np.diff(index) > 0)           # row-major, no repeats
            got = subgrid_ray_columns(rot, w, h, *cells, lens)
            assert all(_bits64(got[j]) == _bits64(d[:, j]) for j in range(3))
            assert all(_bits64(a) == _bits64(b) for a, b in zip(got, cols))
        views += 1
    assert views


def test_pixel_ray_columns_of_the_whole_image_are_row_major():
    rot = quat_to_matrix(np.array([0.3, -0.2, 0.9, 0.1]))
    whole = pixel_ray_columns(rot, 64, 36)
    some = pixel_ray_columns(rot, 64, 36, np.array([0, 63, 64, 64 * 36 - 1]))
    assert all(_bits64(w[[0, 63, 64, 64 * 36 - 1]]) == _bits64(s) for w, s in zip(whole, some))
    assert whole[2][0] != whole[2][63] or whole[0][0] != whole[0][63]


def test_intrinsic_rows_are_camera_intrinsics():
    for lens in (DEFAULT_CAMERA, CameraModel(principal_point_offset_px=(3.5, 1.25)).scaled(0.25)):
        for w, h in ((480, 270), (1920, 1080), (641, 479)):
            assert _bits(np.array(intrinsic_rows(w, h, lens))) == _bits(camera_intrinsics(w, h, lens))


# --------------------------------------------------------------- helpers

def reference_unitize(v: np.ndarray) -> np.ndarray:
    """_unitize's masked form (zero-length rows left as they are): the plain numpy form its
    all-nonzero path must equal bit for bit."""
    length = fm.norm(v, axis=-1)
    ok = length > raycast._ZERO
    inv = np.where(ok, 1.0 / np.where(ok, length, 1.0), 1.0)
    return v * inv[:, None]


def test_unitize_of_nonzero_rows_is_the_masked_form():
    rng = np.random.default_rng(2626)
    v = rng.normal(size=(5000, 3)) * 10.0 ** rng.uniform(-6, 6, (5000, 1))
    got, ok = raycast._unitize(v)
    assert ok.all()
    assert _bits(got) == _bits(reference_unitize(v))


def reference_part_boxes(scene: RayScene, levels: int) -> np.ndarray:
    """RayScene.part_boxes with np.unique: the faces split in halves along the longest extent of
    their centroids, `levels` times, and each group's box of its distinct vertices."""
    cent = scene.vertices[scene.faces].mean(axis=1)
    groups = [np.arange(len(scene.faces))]
    for _ in range(levels):
        split = []
        for g in groups:
            c = cent[g]
            order = np.argsort(c[:, int(np.argmax(np.ptp(c, axis=0)))], kind="stable")
            split += [g[order[:len(g) // 2]], g[order[len(g) // 2:]]]
        groups = split
    return np.array([box_corners(scene.vertices[np.unique(scene.faces[g])]) for g in groups]).reshape(-1, 8, 3)


def test_part_boxes_are_the_boxes_of_each_groups_distinct_vertices():
    scene = blob(n_tris=700, seed=4, spread=(0.5, 3.0))
    assert _bits(scene.part_boxes(5)) == _bits(reference_part_boxes(scene, 5))
