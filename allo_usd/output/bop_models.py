"""The BOP dataset's object models and test targets (bop/CATEGORY/), so the BOP toolkit's pose errors
(bop_toolkit_lib.pose_error: mssd, mspd, vsd, add, adi) and its scripts (scripts/eval_calc_errors.py,
calc_gt_info.py) run on the dataset as on one of BOP's:

    bop/CATEGORY/models/obj_NNNNNN.ply       one per obj_id of models.json: triangles, vertex normals, mm
    bop/CATEGORY/models/models_info.json     per obj_id: diameter, min_x/y/z, size_x/y/z, symmetries
    bop/CATEGORY/models_eval/...             the same files (the toolkit's model_type "eval" reads these)
    bop/CATEGORY/test_targets_bop19.json     [{im_id, inst_count, obj_id, scene_id}] of the test split

Models (dataset_params.get_model_params: model_tpath models[_TYPE]/obj_{obj_id:06d}.ply): the anomaly
asset with its variant selected (allo_usd.usd.model_mesh), in the model frame the poses use (the asset
file's default prim: x_cam_mm = R @ (x_model_mm) + t where model_scale is 1, as for every anomaly this
project authors; the toolkit knows no model_scale), in millimetres as float32, binary little-endian PLY
with the property names bop_toolkit_lib.inout.load_ply reads (float x y z nx ny nz, face list uchar int
vertex_indices). Vertex normals: the area-weighted sum of the incident faces' normals (BOP's are
angle-weighted; the toolkit uses them for shading only). No colour: the assets' colours are materials.
`models_eval` holds the same bytes: BOP's eval models are resampled copies, ours are already the meshes
the renders show.

models_info.json (scripts/calc_model_info.py): min_x/y/z and size_x/y/z are misc.calc_3d_bbox of the PLY's
vertices as load_ply reads them (float32 widened to float64), `diameter` misc.calc_pts_diameter's (the
largest distance between two vertices), computed with the toolkit's arithmetic, so it is its value to
the bit. Symmetries as misc.get_symmetry_transformations reads them: `symmetries_discrete` (row-major 4x4,
t in mm) and `symmetries_continuous` ({axis, offset}). BOP (the BOP Challenge 2019's MSSD, Hodan et al.,
ECCVW 2020, section 2.2) takes a model's global symmetries S as those that leave the model's surface
where it was (a Hausdorff distance between the model and the model moved by S below a small threshold).
Ours are decided geometrically: S is a symmetry when every vertex and each of 2,000 seeded, area-uniform
samples of the surface, moved by S and by S's inverse, lies within SYMMETRY_TOLERANCE (1 %) of the
diameter of the model's surface (exact point-to-triangle distances, trimesh.proximity). Candidates are
rotations about the centre of the model's box: the 23 rotations of the cube's group (axis, face-diagonal
and body-diagonal turns) and n-fold turns (n = 3..8, 12) about the x, y and z axes; an axis is continuous
when turns by 13, 29, 61 and 97 degrees all pass (then its discrete turns are left out, as
get_symmetry_transformations composes the two). Which of the 16 assets get which: docs/formats/coco_bop.md.

test_targets_bop19.json (scripts/enumerate_test_targets.py): per test image and obj_id, the number of its
objects with visib_fract >= MIN_VISIB_FRACT (0.1, the script's), as inout.save_json writes a list.

Re-runs: a PLY is rewritten only when its bytes change (the asset changed: the bytes are built from it
every run), atomically; what is slow to derive from a PLY (diameter, symmetries) is kept in the dataset's
cache keyed by the PLY's sha256 (allo_usd.output.annotation_files: a derivation, checked as read).
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np

from allo_usd.core import fixedmath as fm

MODELS, MODELS_EVAL, MODELS_INFO = "models", "models_eval", "models_info.json"
TARGETS = "test_targets_bop19.json"
MIN_VISIB_FRACT = 0.1        # scripts/enumerate_test_targets.py's min_visib_fract
SYMMETRY_TOLERANCE = 0.01    # of the diameter: how far a symmetry may move the surface
SYMMETRY_SAMPLES = 2000
SYMMETRY_SEED = 20190726     # the samples are the same every run
CONTINUOUS_TEST_DEG = (13.0, 29.0, 61.0, 97.0)


def ply_name(obj_id: int) -> str:
    return f"obj_{int(obj_id):06d}.ply"


# --- PLY ---------------------------------------------------------------------------------------

def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals: the area-weighted sum of the incident faces' normals ((0, 0, 1) if none)."""
    p = np.asarray(points, dtype=np.float64)
    fn = fm.cross(p[triangles[:, 1]] - p[triangles[:, 0]], p[triangles[:, 2]] - p[triangles[:, 0]])
    vn = np.zeros_like(p)
    for k in range(3):
        np.add.at(vn, triangles[:, k], fn)
    norm = fm.norm(vn, axis=1, keepdims=True)
    return np.where(norm > 0, vn / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))


def ply_bytes(points_m: np.ndarray, triangles: np.ndarray) -> bytes:
    """The binary PLY of a model in metres: vertices in mm (float32), normals, triangles."""
    mm = (np.asarray(points_m, dtype=np.float64) * 1000.0).astype("<f4")
    normals = vertex_normals(mm.astype(np.float64), triangles).astype("<f4")
    header = ("ply\nformat binary_little_endian 1.0\ncomment allo-usd BOP model, millimetres\n"
              f"element vertex {len(mm)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\n"
              f"element face {len(triangles)}\nproperty list uchar int vertex_indices\nend_header\n")
    vertices = np.concatenate([mm, normals], axis=1).astype("<f4")
    faces = np.zeros(len(triangles), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, triangles
    return header.encode("ascii") + vertices.tobytes() + faces.tobytes()


def ply_points(data: bytes) -> np.ndarray:
    """The vertices of a PLY written by ply_bytes, as load_ply gives them (float64)."""
    head, _, body = data.partition(b"end_header\n")
    n = int(next(line.split()[-1] for line in head.decode("ascii").splitlines() if line.startswith("element vertex")))
    return np.frombuffer(body, dtype="<f4", count=n * 6).reshape(n, 6)[:, :3].astype(np.float64)


def ply_triangles(data: bytes) -> np.ndarray:
    head, _, body = data.partition(b"end_header\n")
    lines = head.decode("ascii").splitlines()
    n = int(next(line.split()[-1] for line in lines if line.startswith("element vertex")))
    m = int(next(line.split()[-1] for line in lines if line.startswith("element face")))
    faces = np.frombuffer(body, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=m, offset=n * 24)
    return faces["i"].astype(np.int64)


# --- models_info -------------------------------------------------------------------------------

def diameter(pts: np.ndarray, block: int = 256) -> float:
    """misc.calc_pts_diameter: the largest distance between two of `pts`, in its arithmetic (the
    difference, squares summed x + y then + z, the largest, math.sqrt), so its value to the bit."""
    pts = np.asarray(pts, dtype=np.float64)
    best = -1.0
    for i in range(0, len(pts), block):
        d = pts[i:i + block, None, :] - pts[None, :, :]
        sq = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
        sq = sq + d[..., 2] * d[..., 2]
        best = max(best, float(sq.max()))
    return math.sqrt(best) if best >= 0 else -1.0


def box_info(pts: np.ndarray) -> dict:
    """misc.calc_3d_bbox's min_x/y/z and size_x/y/z."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return {"min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]), "size_z": float(hi[2] - lo[2])}


def _axis_turn(axis: int, angle_deg: float) -> np.ndarray:
    c, s = fm.cos(fm.radians(angle_deg)), fm.sin(fm.radians(angle_deg))
    r = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _cube_group() -> list[np.ndarray]:
    """The 24 proper rotations that map the axes to the axes (signed permutation matrices, det +1)."""
    from itertools import permutations, product

    out = []
    for perm in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            for row, (col, sign) in enumerate(zip(perm, signs)):
                r[row, col] = sign
            inversions = sum(perm[i] > perm[j] for i in range(3) for j in range(i + 1, 3))
            if (-1.0 if inversions % 2 else 1.0) * signs[0] * signs[1] * signs[2] == 1.0:   # det +1: a rotation
                out.append(r)
    return out


def _candidates() -> list[np.ndarray]:
    seen, out = [], []
    turns = [_axis_turn(a, 360.0 * k / n) for a in range(3) for n in (3, 4, 5, 6, 7, 8, 12) for k in range(1, n)]
    for r in _cube_group() + turns:
        if np.allclose(r, np.eye(3), atol=1e-12) or any(np.allclose(r, q, atol=1e-9) for q in seen):
            continue
        seen.append(r)
        out.append(r)
    return out


def _samples(points: np.ndarray, triangles: np.ndarray, count: int = SYMMETRY_SAMPLES) -> np.ndarray:
    rng = np.random.default_rng(SYMMETRY_SEED + count)
    a, b, c = (points[triangles[:, k]] for k in range(3))
    area = fm.norm(fm.cross(b - a, c - a), axis=1)
    if area.sum() <= 0:
        return points
    tri = rng.choice(len(triangles), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    return a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])


def symmetries(points_mm: np.ndarray, triangles: np.ndarray, diam: float) -> dict:
    """{"symmetries_discrete": [...], "symmetries_continuous": [...]} (keys only where found): the
    rotations about the box centre that keep the surface within SYMMETRY_TOLERANCE * diam (module doc)."""
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(points_mm, triangles, process=False)
    centre = (points_mm.min(axis=0) + points_mm.max(axis=0)) / 2.0
    samples = np.concatenate([points_mm, _samples(points_mm, triangles)])   # every vertex, and the surface
    coarse = np.random.default_rng(SYMMETRY_SEED).choice(len(samples), size=min(300, len(samples)), replace=False)
    dense = cKDTree(_samples(points_mm, triangles, 100 * SYMMETRY_SAMPLES))
    tol = SYMMETRY_TOLERANCE * diam
    spacing = 2.0 * float(dense.query(samples)[0].max())   # the coarse test's own resolution, with room

    def moved(r):
        return fm.apply(r, samples - centre) + centre

    def keeps(r) -> bool:
        for q in (r, r.T):
            pts = moved(q)
            if float(dense.query(pts[coarse])[0].max()) > tol + spacing:   # a cheap rejection first
                return False
            near = dense.query(pts)[0]   # a sample of the surface is on it: an upper bound of the distance
            far = pts[near > tol]
            if len(far) and float(trimesh.proximity.closest_point(mesh, far)[1].max()) > tol:
                return False
        return True

    continuous = [a for a in range(3) if all(keeps(_axis_turn(a, d)) for d in CONTINUOUS_TEST_DEG)]
    discrete = []
    for r in _candidates():
        about = [a for a in continuous if np.allclose(r[:, a], np.eye(3)[a], atol=1e-9)]
        if about or not keeps(r):
            continue
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, centre - fm.apply(r, centre[None, :])[0]
        discrete.append([float(v) for v in m.ravel()])
    out = {}
    if discrete:
        out["symmetries_discrete"] = discrete
    if continuous:
        out["symmetries_continuous"] = [{"axis": [float(v) for v in np.eye(3)[a]], "offset": centre.tolist()}
                                        for a in continuous]
    return out


def model_info(data: bytes) -> dict:
    """models_info.json's entry of a PLY written by ply_bytes."""
    pts = ply_points(data)
    diam = diameter(pts)
    return {**box_info(pts), "diameter": diam, **symmetries(pts, ply_triangles(data), diam)}


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def info_problem(info) -> bool:
    """Whether a cached models_info entry is not one (types, finite numbers, well-formed symmetries)."""
    keys = {"min_x", "min_y", "min_z", "size_x", "size_y", "size_z", "diameter"}
    if not isinstance(info, dict) or not keys <= set(info) <= keys | {"symmetries_discrete", "symmetries_continuous"}:
        return True
    if not all(isinstance(info[k], float) and math.isfinite(info[k]) for k in keys) or info["diameter"] <= 0:
        return True
    disc, cont = info.get("symmetries_discrete", []), info.get("symmetries_continuous", [])
    if not (isinstance(disc, list) and isinstance(cont, list)):
        return True
    for m in disc:
        if not (isinstance(m, list) and len(m) == 16 and all(isinstance(v, float) and math.isfinite(v) for v in m)):
            return True
        r = np.reshape(m, (4, 4))[:3, :3]
        if not np.allclose(fm.matmul(r, r.T), np.eye(3), atol=1e-9):
            return True
    return not all(isinstance(c, dict) and set(c) == {"axis", "offset"} and isinstance(c["axis"], list)
                   and isinstance(c["offset"], list) and len(c["axis"]) == len(c["offset"]) == 3
                   and all(isinstance(v, float) and math.isfinite(v) for v in c["axis"] + c["offset"]) for c in cont)


# --- test targets --------------------------------------------------------------------------------

def test_targets(chunks: dict) -> list[dict]:
    """enumerate_test_targets's list from {scene_id: (scene_gt, scene_gt_info)} of the test split."""
    targets = []
    for scene_id in sorted(chunks):
        gt, info = chunks[scene_id]
        for im_id in sorted(gt, key=int):
            counts: dict[int, int] = {}
            for g, i in zip(gt[im_id], info.get(im_id, [])):
                if isinstance(i.get("visib_fract"), float) and i["visib_fract"] >= MIN_VISIB_FRACT:
                    counts[g["obj_id"]] = counts.get(g["obj_id"], 0) + 1
            targets += [{"im_id": int(im_id), "inst_count": n, "obj_id": o, "scene_id": int(scene_id)}
                        for o, n in counts.items()]
    return targets


def dumps_list(items: list) -> str:
    """inout.save_json's text of a list: one element a line."""
    return "[\n" + ",\n".join(f"  {json.dumps(e, sort_keys=True)}" for e in items) + ("\n" if items else "") + "]"
