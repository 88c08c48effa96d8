"""The BOP toolkit's computations (github.com/thodan/bop_toolkit, not a package), written here from its
definitions, to run on a dataset's bop/CATEGORY/ as the toolkit would:

- load_ply: bop_toolkit_lib/inout.py load_ply (header properties by name; binary little-endian or ascii)
- calc_pts_diameter: bop_toolkit_lib/misc.py calc_pts_diameter, its loop as written
- calc_3d_bbox, calc_2d_bbox: misc.py
- render_depth: what renderer.render_object(...)["depth"] gives: the z (mm) of the nearest PLY triangle
  through each pixel centre (an embree ray cast of the triangles, trimesh), 0 where none
- calc_gt_info: scripts/calc_gt_info.py (the 3W x 3H canvas, cx + W, cy + H; visibility
  visibility.estimate_visib_mask_gt in "bop19" mode, delta 15 mm; depth_im_to_dist_im_fast)
- mssd, mspd, vsd, get_symmetry_transformations: pose_error.py and misc.py
- dataset layout: dataset_params.py get_split_params / get_model_params paths (classic BOP format)
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np

FORMATS = {"float": ("f", 4), "double": ("d", 8), "int": ("i", 4), "uint": ("I", 4), "uchar": ("B", 1)}


def load_ply(path) -> dict:
    with open(path, "rb") as f:
        props, face_props, section, binary, n_pts, n_faces = [], [], None, False, 0, 0
        while True:
            line = f.readline().decode("utf8").rstrip("\n").rstrip("\r")
            if line.startswith("element vertex"):
                n_pts, section = int(line.split()[-1]), "v"
            elif line.startswith("element face"):
                n_faces, section = int(line.split()[-1]), "f"
            elif line.startswith("element"):
                section = None
            elif line.startswith("property list") and section == "f":
                e = line.split()
                face_props = [("n", e[2])] + [(f"i{k}", e[3]) for k in range(3)]
            elif line.startswith("property") and section == "v":
                props.append((line.split()[-1], line.split()[-2]))
            elif line.startswith("format"):
                binary = "binary" in line
            elif line.startswith("end_header"):
                break
        names = [p[0] for p in props]
        pts = np.zeros((n_pts, len(props)), np.float64)
        for i in range(n_pts):
            if binary:
                pts[i] = [struct.unpack(FORMATS[t][0], f.read(FORMATS[t][1]))[0] for _, t in props]
            else:
                pts[i] = [float(v) for v in f.readline().split()]
        faces = np.zeros((n_faces, 3), np.float64)
        for i in range(n_faces):
            vals = [struct.unpack(FORMATS[t][0], f.read(FORMATS[t][1]))[0] for _, t in face_props] if binary \
                else [int(v) for v in f.readline().split()]
            if vals[0] != 3:
                raise ValueError("Only triangular faces are supported.")
            faces[i] = vals[1:4]
    model = {"pts": pts[:, [names.index(k) for k in "xyz"]], "faces": faces}
    if {"nx", "ny", "nz"} <= set(names):
        model["normals"] = pts[:, [names.index(k) for k in ("nx", "ny", "nz")]]
    return model


def calc_pts_diameter(pts) -> float:
    diameter = -1.0
    for pt_id in range(pts.shape[0]):
        pt_dup = np.tile(np.array([pts[pt_id, :]]), [pts.shape[0] - pt_id, 1])
        pts_diff = pt_dup - pts[pt_id:, :]
        max_dist = math.sqrt((pts_diff * pts_diff).sum(axis=1).max())
        if max_dist > diameter:
            diameter = max_dist
    return diameter


def calc_3d_bbox(pts) -> list:
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return [lo[0], lo[1], lo[2], hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]]


def calc_2d_bbox(xs, ys) -> list:
    return [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]


def render_depth(model: dict, R, t, fx, fy, cx, cy, width: int, height: int) -> np.ndarray:
    """renderer.render_object's depth: z in mm of the nearest triangle through each pixel centre."""
    import trimesh

    cam = model["pts"] @ np.asarray(R).T + np.asarray(t).reshape(1, 3)
    mesh = trimesh.Trimesh(cam, model["faces"].astype(np.int64), process=False)
    v, u = np.mgrid[0:height, 0:width]
    dirs = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(u.size)], axis=1)
    locs, rays, _ = mesh.ray.intersects_location(np.zeros_like(dirs), dirs, multiple_hits=False)
    depth = np.zeros(width * height)
    depth[rays] = locs[:, 2]
    return depth.reshape(height, width)


def depth_im_to_dist_im_fast(depth_im, K) -> np.ndarray:
    h, w = depth_im.shape
    xs = (np.arange(w) - K[0, 2]) / K[0, 0]
    ys = (np.arange(h) - K[1, 2]) / K[1, 1]
    return np.sqrt(xs[None, :] ** 2 * depth_im ** 2 + ys[:, None] ** 2 * depth_im ** 2 + depth_im ** 2)


def estimate_visib_mask_gt(d_test, d_model, delta) -> np.ndarray:
    d_diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    return np.logical_and(np.logical_or(d_diff <= delta, d_test == 0), d_model > 0)


def calc_gt_info(depth_mm, K, gt: dict, model: dict, delta: float = 15.0) -> dict:
    """scripts/calc_gt_info.py's entry of one ground-truth pose (depth_mm: the test depth in mm)."""
    height, width = depth_mm.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    large = render_depth(model, gt["cam_R_m2c"], gt["cam_t_m2c"], fx, fy, cx + width, cy + height,
                         3 * width, 3 * height)
    depth_gt = large[height:2 * height, width:2 * width]
    dist_gt, dist_im = depth_im_to_dist_im_fast(depth_gt, K), depth_im_to_dist_im_fast(depth_mm, K)
    visib_gt = estimate_visib_mask_gt(dist_im, dist_gt, delta)
    px_count_all = int(np.sum(large > 0))
    px_count_visib = int(visib_gt.sum())
    bbox = bbox_visib = [-1, -1, -1, -1]
    if px_count_visib > 0:
        ys, xs = (large > 0).nonzero()
        bbox = [int(e) for e in calc_2d_bbox(xs - width, ys - height)]
        ys, xs = visib_gt.nonzero()
        bbox_visib = [int(e) for e in calc_2d_bbox(xs, ys)]
    return {"px_count_all": px_count_all, "px_count_valid": int(np.sum(dist_im[dist_gt > 0] > 0)),
            "px_count_visib": px_count_visib, "visib_fract": px_count_visib / px_count_all if px_count_all else 0.0,
            "bbox_obj": bbox, "bbox_visib": bbox_visib, "mask_visib": visib_gt, "mask_all": large > 0}


def transform_pts_Rt(pts, R, t):
    return (R.dot(pts.T) + t.reshape((3, 1))).T


def project_pts(pts, K, R, t):
    P = K.dot(np.hstack((R, t.reshape(3, 1))))
    pts_h = np.hstack((pts, np.ones((pts.shape[0], 1))))
    im = P.dot(pts_h.T)
    im /= im[2, :]
    return im[:2, :].T


def rotation_matrix(angle, direction):
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    c, s = math.cos(angle), math.sin(angle)
    return c * np.eye(3) + s * np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]]) \
        + (1 - c) * np.outer(d, d)


def get_symmetry_transformations(model_info: dict, max_sym_disc_step: float) -> list:
    trans_disc = [{"R": np.eye(3), "t": np.zeros((3, 1))}]
    for sym in model_info.get("symmetries_discrete", []):
        m = np.reshape(sym, (4, 4))
        trans_disc.append({"R": m[:3, :3], "t": m[:3, 3].reshape((3, 1))})
    trans_cont = []
    for sym in model_info.get("symmetries_continuous", []):
        offset = np.array(sym["offset"]).reshape((3, 1))
        steps = int(np.ceil(np.pi / max_sym_disc_step))
        for i in range(steps):
            R = rotation_matrix(i * 2.0 * np.pi / steps, sym["axis"])
            trans_cont.append({"R": R, "t": -R.dot(offset) + offset})
    if not trans_cont:
        return trans_disc
    return [{"R": c["R"].dot(d["R"]), "t": c["R"].dot(d["t"]) + c["t"]} for d in trans_disc for c in trans_cont]


def mssd(R_est, t_est, R_gt, t_gt, pts, syms) -> float:
    pts_est = transform_pts_Rt(pts, R_est, t_est)
    return min(np.linalg.norm(pts_est - transform_pts_Rt(pts, R_gt.dot(s["R"]), R_gt.dot(s["t"]) + t_gt.reshape(3, 1)),
                              axis=1).max() for s in syms)


def mspd(R_est, t_est, R_gt, t_gt, K, pts, syms) -> float:
    proj_est = project_pts(pts, K, R_est, t_est)
    return min(np.linalg.norm(proj_est - project_pts(pts, K, R_gt.dot(s["R"]), (R_gt.dot(s["t"]) + t_gt.reshape(3, 1))),
                              axis=1).max() for s in syms)


def vsd(R_est, t_est, R_gt, t_gt, depth_test, K, delta, taus, diameter, model) -> list:
    """pose_error.vsd, normalized by the diameter, "step" cost, the depth rendered by render_depth."""
    h, w = depth_test.shape
    args = (K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h)
    dist_test = depth_im_to_dist_im_fast(depth_test, K)
    dist_gt = depth_im_to_dist_im_fast(render_depth(model, R_gt, t_gt, *args), K)
    dist_est = depth_im_to_dist_im_fast(render_depth(model, R_est, t_est, *args), K)
    visib_gt = estimate_visib_mask_gt(dist_test, dist_gt, delta)
    visib_est = np.logical_and(np.logical_or(dist_est - dist_test <= delta, dist_test == 0), dist_est > 0)
    visib_est = np.logical_or(visib_est, np.logical_and(visib_gt, dist_est > 0))
    inter, union = np.logical_and(visib_gt, visib_est), np.logical_or(visib_gt, visib_est)
    if union.sum() == 0:
        return [1.0] * len(taus)
    dists = np.abs(dist_gt[inter] - dist_est[inter]) / diameter
    comp = union.sum() - inter.sum()
    return [(np.sum(dists >= tau) + comp) / float(union.sum()) for tau in taus]


def split_paths(datasets_path: Path, name: str, split: str, scene_id: int) -> dict:
    """get_split_params' classic-format templates (split_type None), for one scene."""
    scene = Path(datasets_path) / name / split / f"{scene_id:06d}"
    return {"scene_camera": scene / "scene_camera.json", "scene_gt": scene / "scene_gt.json",
            "scene_gt_info": scene / "scene_gt_info.json", "rgb": scene / "rgb" / "{im_id:06d}.png",
            "depth": scene / "depth" / "{im_id:06d}.png", "mask": scene / "mask" / "{im_id:06d}_{gt_id:06d}.png",
            "mask_visib": scene / "mask_visib" / "{im_id:06d}_{gt_id:06d}.png"}


def load_json(path, keys_to_int=False):
    with open(path) as f:
        if keys_to_int:
            return json.load(f, object_hook=lambda x: {int(k) if k.lstrip("-").isdigit() else k: v
                                                        for k, v in x.items()})
        return json.load(f)
