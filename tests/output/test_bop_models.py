"""allo_usd.output.bop_models against the BOP toolkit's definitions (tests/support/bop_toolkit.py): the
PLY as load_ply reads it, calc_pts_diameter's diameter to the bit, calc_3d_bbox, and symmetries decided
geometrically (a box has its three half turns, a cylinder its axis, an asymmetric part none)."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.assets.mesh import fan_triangulate
from allo_usd.assets.primitives import box, cylinder
from allo_usd.output import bop_models as bm
from tests.support import bop_toolkit as bt


def tris(part):
    return part.points, fan_triangulate(part.face_counts, part.face_indices)


def test_the_ply_reads_back_in_millimetres_with_normals(tmp_path):
    pts, t = tris(box("B", (0.6, 0.4, 0.3), "m"))
    (tmp_path / "m.ply").write_bytes(bm.ply_bytes(pts, t))
    model = bt.load_ply(tmp_path / "m.ply")
    assert np.array_equal(model["pts"], (pts * 1000.0).astype(np.float32).astype(np.float64))
    assert np.array_equal(model["faces"], t) and np.allclose(np.linalg.norm(model["normals"], axis=1), 1, atol=1e-6)


def test_diameter_and_box_are_the_toolkits_to_the_bit():
    rng = np.random.default_rng(3)
    for n in (1, 2, 300, 1000):
        pts = rng.normal(size=(n, 3)).astype(np.float32).astype(np.float64) * 123.4
        assert bm.diameter(pts) == bt.calc_pts_diameter(pts)
        info = bm.box_info(pts)
        assert [info[k] for k in ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z")] == bt.calc_3d_bbox(pts)


@pytest.mark.slow   # ~15 s: a cylinder's candidates each checked against its surface
def test_symmetries_are_found_geometrically():
    pts, t = tris(box("B", (0.6, 0.4, 0.3), "m"))
    info = bm.model_info(bm.ply_bytes(pts, t))
    half_turns = sorted(np.reshape(m, (4, 4))[:3, :3].diagonal().tolist() for m in info["symmetries_discrete"])
    assert half_turns == [[-1, -1, 1], [-1, 1, -1], [1, -1, -1]] and "symmetries_continuous" not in info
    pts, t = tris(cylinder("C", 0.1, 0.5, "m", segments=24))
    info = bm.model_info(bm.ply_bytes(pts, t))
    axes = [c["axis"] for c in info["symmetries_continuous"]]
    assert len(axes) == 1 and len(info["symmetries_discrete"]) >= 1   # about its axis, and flipped end for end
    lopsided = np.concatenate([pts, pts[:4] + [0.3, 0.0, 0.0]])
    lop_t = np.concatenate([t, [[len(pts), len(pts) + 1, len(pts) + 2]]])
    info = bm.model_info(bm.ply_bytes(lopsided, lop_t))
    assert "symmetries_continuous" not in info and "symmetries_discrete" not in info


def test_symmetries_leave_mssd_of_the_symmetric_pose_zero():
    pts, t = tris(box("B", (0.6, 0.4, 0.3), "m"))
    data = bm.ply_bytes(pts, t)
    info, mm = bm.model_info(data), bm.ply_points(data)
    syms = bt.get_symmetry_transformations(info, 0.01)
    flip = np.diag([-1.0, -1.0, 1.0])
    t0 = np.array([[0.0], [0.0], [2000.0]])
    assert bt.mssd(flip, t0, np.eye(3), t0, mm, syms) < 1e-9


def test_test_targets_follow_enumerate_test_targets():
    chunks = {"000000": ({"3": [{"obj_id": 2}, {"obj_id": 2}, {"obj_id": 5}], "1": []},
                         {"3": [{"visib_fract": 0.5}, {"visib_fract": 0.1}, {"visib_fract": 0.05}], "1": []})}
    assert bm.test_targets(chunks) == [{"im_id": 3, "inst_count": 2, "obj_id": 2, "scene_id": 0}]
    assert bm.dumps_list(bm.test_targets(chunks)) == '[\n  {"im_id": 3, "inst_count": 2, "obj_id": 2, "scene_id": 0}\n]'
