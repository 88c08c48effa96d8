"""The shortcuts of issue 26 (round 4) give exactly the bits of the code they stand in for: the
surface-crossing walk (`RayScene.hits`, `RayScene.inside`) on Python floats is its former numpy
form, written out here as the oracle; pixel rays built per column and row (`subgrid_ray_columns`,
the cells placement's part-box cull returns) are `pixel_rays`; an occlusion query from one broadcast
camera position is the query from that position repeated."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core.geometry import quat_to_matrix
from allo_usd.scene import placement
from allo_usd.scene.raycast import (_PARITY_DIRS, _RAY_OFFSET_FACTOR, _RAY_OFFSET_FLOOR, RayScene, _unitize,
                                    pixel_ray_columns, pixel_rays, subgrid_ray_columns)
from tests.support.helpers import tiny_station


def _bits(a) -> bytes:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes()


def _old_crossings(scene: RayScene, origins, dirs, max_hits):
    """RayScene._crossings before round 4: numpy arrays throughout."""
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


def _old_inside(scene: RayScene, point) -> bool:
    n = len(_PARITY_DIRS)
    origins = np.repeat(np.asarray(point, dtype=np.float64)[None], n, 0)
    crossings = np.zeros(n, dtype=np.int64)
    done = np.ones(n, dtype=bool)
    for crossed, live in _old_crossings(scene, origins, _PARITY_DIRS, 100):
        crossings += np.bincount(crossed, minlength=n)
        done[:] = True
        done[live] = False
        odd = crossings % 2 == 1
        if int((done & odd).sum()) >= 4 or int((done & ~odd).sum()) > n - 4:
            break
    return int((crossings % 2 == 1).sum()) >= 4


def _station() -> RayScene:
    pts, tris = tiny_station().triangle_soup()
    return RayScene([(pts, tris, 1)])


def _shell() -> RayScene:
    """Random triangles, many nearly parallel to the axis rays, some sharing planes (re-hits)."""
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(400, 1, 3)) * 2.0
    pts = (centres + rng.normal(scale=0.4, size=(400, 3, 3))).reshape(-1, 3)
    pts[:60, 0] = np.round(pts[:60, 0])            # faces in the planes x = k: axis rays graze them
    return RayScene([(pts, np.arange(len(pts)).reshape(-1, 3), 1)])


@pytest.mark.parametrize("make", [_station, _shell])
def test_inside_is_the_numpy_walk(make):
    scene = make()
    rng = np.random.default_rng(7)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    points = [lo + (hi - lo) * rng.random(3) for _ in range(1500)]
    points += [scene.vertices[i] + rng.normal(scale=1e-3, size=3) for i in rng.integers(len(scene.vertices), size=300)]
    points += [np.array([-10.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0]), np.array([-10.0, 5.0, 0.5])]
    got = [scene.inside(p) for p in points]
    assert got == [_old_inside(scene, p) for p in points]
    assert sum(got) > 20 and len(got) - sum(got) > 20         # points inside and outside


@pytest.mark.parametrize("make", [_station, _shell])
def test_hits_are_the_numpy_walk(make):
    scene = make()
    rng = np.random.default_rng(8)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    o = lo + (hi - lo) * rng.random((400, 3))                   # within the mesh's box: most rays cross it
    d = rng.normal(size=(400, 3))
    d[:50] = [1.0, 0.0, 0.0]                                  # along faces' planes
    want = [r for crossed, _ in _old_crossings(scene, o, d, 100) for r in crossed.tolist()]
    got = scene.hits(o, d)
    assert got.dtype == np.int64 and got.tolist() == want and len(want) > 50
    steps_old = [(c.tolist(), sorted(v.tolist())) for c, v in _old_crossings(scene, o, d, 3)]
    assert [(c, sorted(v)) for c, v in scene._crossings(o, d, 3)] == steps_old
    assert scene.hits(o[:0], d[:0]).size == 0


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_cells_rays_are_pixel_rays(stride):
    """The part-box cull's cells cast through subgrid_ray_columns give pixel_rays' bits for their
    row-major pixels, for any lens offset and sub-grid."""
    from allo_usd.core.camera_model import CameraModel

    rng = np.random.default_rng(20 + stride)
    scene = _shell()
    for lens in (placement.DEFAULT_CAMERA, CameraModel(principal_point_offset_px=(12.5, -7.0))):
        for _ in range(10):
            cam_rot = quat_to_matrix(rng.normal(size=4))
            pose = (-cam_rot[:, 2] * rng.uniform(6, 20) + rng.normal(size=3), quat_to_matrix(rng.normal(size=4)))
            cells = placement._parts_pixels(scene, np.zeros(3), cam_rot, 480, 270, pose, stride, lens)
            if cells is None:
                continue
            index = cells.index(480)
            assert index.size and np.all(np.diff(index) > 0)           # row-major, no repeats
            got = subgrid_ray_columns(cam_rot, 480, 270, *cells, lens)
            _, want = pixel_rays(np.zeros(3), cam_rot, 480, 270, index, lens)
            assert all(_bits(got[j]) == _bits(want[:, j]) for j in range(3))
            assert all(_bits(a) == _bits(b) for a, b in zip(got, pixel_ray_columns(cam_rot, 480, 270, index, lens)))


def test_pixel_ray_columns_of_the_whole_image_are_row_major():
    rot = quat_to_matrix(np.array([0.3, -0.2, 0.9, 0.1]))
    whole = pixel_ray_columns(rot, 64, 36)
    some = pixel_ray_columns(rot, 64, 36, np.array([0, 63, 64, 64 * 36 - 1]))
    assert all(_bits(w[[0, 63, 64, 64 * 36 - 1]]) == _bits(s) for w, s in zip(whole, some))
    assert whole[2][0] != whole[2][63] or whole[0][0] != whole[0][63]


def test_occlusion_from_one_broadcast_point_is_the_repeated_point():
    scene = _station()
    rng = np.random.default_rng(9)
    cam = np.array([12.0, 6.0, 4.0])
    d = rng.normal(size=(3000, 3))
    d = d / fm.norm(d, axis=1, keepdims=True)
    tmax = rng.uniform(1, 40, len(d))
    broadcast = scene.occluded(np.broadcast_to(cam, d.shape), d, tmax)
    assert np.array_equal(broadcast, scene.occluded(np.repeat(cam[None], len(d), 0), d, tmax))
    assert 100 < broadcast.sum() < len(d) - 100


@pytest.mark.parametrize("size", [(64, 36), (480, 270), (1920, 1080)])
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


def test_double_fast_layout_is_tf_layout_and_sdfs():
    """_double's repr shortcut (1e-4 <= |x| < 1e15) writes what the digit layout it skips writes, and
    what Sdf writes, at the range's edges, whole numbers and random values of every magnitude; and
    _float's memo gives each value's own text (not a zero's sign for another zero)."""
    from pxr import Sdf

    from allo_usd.usd import usda_writer as S

    def layout(x: float) -> str:
        if x == 0.0:
            return "-0" if str(x)[0] == "-" else "0"
        mantissa, _, e = repr(abs(x)).partition("e")
        digits, exp = S._digits(mantissa, int(e) if e else 0)
        return ("-" if x < 0 else "") + S._shortest(digits, exp)

    rng = np.random.default_rng(30)
    edges = [1e-4, np.nextafter(1e-4, 0), 1e15, np.nextafter(1e15, 0), 1e14, 123.0, -123.0, 0.5, 2.0 ** 53 + 2,
             100000000000000.5, 5e-324, -0.0, 0.0]
    values = [float(v) for v in [*edges, *(rng.normal(size=20000) * 10.0 ** rng.integers(-8, 18, 20000)),
                                 *range(-300, 300)]]
    assert [S._double(v) for v in values] == [layout(v) for v in values]
    layer = Sdf.Layer.CreateAnonymous(".usda")
    spec = Sdf.CreatePrimInLayer(layer, "/P")
    sample = values[:400]
    for i, v in enumerate(sample):
        Sdf.AttributeSpec(spec, f"a{i}", Sdf.ValueTypeNames.Double).default = v
    written = {}
    for line in layer.ExportToString().splitlines():
        if line.strip().startswith("double a"):
            name, _, text = line.strip()[len("double "):].partition(" = ")
            written[int(name[1:])] = text
    assert [written[i] for i in range(len(sample))] == [S._double(v) for v in sample]
    for v in (0.1, -0.1, 0.0, -0.0, 1e-50, -1e-50, 0.1):
        assert S._float(v) == S._float_text(v)
    assert (S._float(0.0), S._float(-0.0)) == ("0", "-0")


def test_inside_by_folder_is_commonpaths_rule():
    """write_composed_scene's tree check, decided per folder (and kept per run), answers as
    os.path.commonpath([top, target]) == top for the tree itself, paths below it, siblings that
    share a prefix and the file system's root."""
    import os

    from allo_usd.usd.compose import TreeLinks, _inside, _uncached

    tops = ["/", "/a", "/a/b", "/a/bc", "/x/y/z"]
    paths = ["/", "/a", "/a/b", "/a/b/c", "/a/bc", "/a/bc/d", "/a/b/c/d/e.usda", "/ab", "/a/b.usda", "/x/y",
             "/x/y/z", "/x/y/z/w", "/x/y/zz/w"]
    links = TreeLinks()
    for top in tops:
        for p in paths:
            want = os.path.commonpath([top, p]) == top
            assert _inside(top, p, _uncached) == want and _inside(top, p, links.once) == want, (top, p)


def test_a_scene_layer_naming_a_file_outside_its_tree_is_refused_with_or_without_a_run(tmp_path):
    """The tree check still refuses a base stage outside the tree (a run's TreeLinks keeps answers,
    not refusals), writes nothing, and accepts the same layer once the stage is the tree's own copy."""
    from allo_usd.core.errors import LayerError
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.usd.compose import TreeLinks, copy_base_stage, write_composed_scene, write_pose_layer
    from tests.support.helpers import make_spec

    spec = make_spec()
    tree = tmp_path / "tree"
    pose = write_pose_layer(tree / "poses" / "p.usda", pose=1, camera=spec.camera, seed=1, seed_path="t",
                            sample_id="s1_d000_p01")
    sky = tree / "sky" / "d000.usda"
    sky.parent.mkdir(parents=True)
    sky.write_text("#usda 1.0\n")
    links = TreeLinks()
    for run in (None, links, links):
        with pytest.raises(LayerError, match="outside its tree"):
            write_composed_scene(spec, tree / "scenes" / "a.usda", pose_layer=pose, sky_layer=sky,
                                 base_stage=BASE_STAGE, root=tree, links=run)
    assert not (tree / "scenes" / "a.usda").exists()
    own = copy_base_stage(BASE_STAGE, tree)
    layer = write_composed_scene(spec, tree / "scenes" / "a.usda", pose_layer=pose, sky_layer=sky, base_stage=own,
                                 root=tree, links=links)
    assert "@../stages/base.usda@" in layer.read_text()
