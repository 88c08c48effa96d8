"""Per-image camera and object annotations: the render JSON's `annotations` block and the manifest's
CAMERA/ANNOTATION columns, computed from the scene description, the class mask and the `amodal` pass's
mask when it ran (no pxr, no bpy). Without the pass, the anomaly's full silhouette is ray-cast here, in
the render worker: embreex loads once per process (~0.35 s) and the cast costs ~0.05 s at 640x360,
~0.3 s for a 30,000-pixel silhouette at 1920x1080, small beside the render.

Conventions (docs/formats/coco_bop.md repeats them; tests/output/test_annotations_camera.py and tests/output/test_annotations_pose.py
check each):
- Pixels: OpenCV's. u to the right, v down; the centre of the pixel in column c, row r is at
  (u, v) = (c, r), so the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5].
- `K_px` = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] as Blender renders the layer's camera: sensor fit
  horizontal, square pixels, so fx = fy = focal_length_mm / sensor_width_mm * W (the vertical
  aperture follows from the aspect ratio), and cx = (W - 1) / 2 + dx, cy = (H - 1) / 2 + dy, where
  (dx, dy) = (-horizontalApertureOffset, +verticalApertureOffset) / horizontalAperture x W is the
  principal point's offset from the image centre in pixels (core.camera_model; the builder renders
  the offsets as Blender's lens shift). The paper's camera has no offset.
- `cam_to_world_usd`: the camera prim's local-to-world 4x4 in the stage's frame (Z up, metres),
  camera looking down its -Z with +Y up and +X right (UsdGeom.Camera), as nested rows in the
  column-vector convention: p_world = M @ [x, y, z, 1], translation in the last column. (USD's
  GfMatrix4d multiplies row vectors, p' = p M: it is the transpose of this.)
- `world_to_cam_opencv`: world -> camera frame in OpenCV's axes (x right, y down, z forward,
  metres), column vectors: p_cam = M @ [X, Y, Z, 1]; then (u, v) = (fx x / z + cx, fy y / z + cy).
  It is diag(1, -1, -1, 1) @ inverse(cam_to_world_usd).
- Anomaly objects: one record per anomaly object (MeshDesc.object: the prim its anomaly label is
  applied on), its pixels its own id's in the object index pass (the class mask's anomaly pixels when
  the scene has one). Bounding box `bbox_xyxy_px`: [x_min, y_min, x_max, y_max] of the object's pixels in the
  mask, inclusive pixel indices (COCO's [x, y, w, h] is [x_min, y_min, x_max - x_min + 1,
  y_max - y_min + 1]); null when no anomaly pixel is visible. `pixels`: its visible pixel count.
- The anomaly's model frame is its prim's own (/World/Anomaly: the frame of the file it references,
  `model.path`, relative to the layer's folder; `model.model_id` is "ASSET/VARIANT"). Its meshes'
  points mapped into that frame are the model's vertices (metres) and their axis-aligned box is the
  model's box.
- `pose` (BOP's convention, model to camera in OpenCV's camera frame): x_cam_mm = R @ (S @ x_model_m *
  1000) + t, with `cam_R_m2c` R row-major (a proper rotation: det +1, orthonormal to 1e-9),
  `cam_t_m2c` t in millimetres, `model_scale` S's diagonal: the scale part of the prim's
  local-to-world (1, 1, 1 for every anomaly this project authors; split_rotation_scale).
- `center_px`: the projection of the model box's centre (which `center_cam_opencv_m` holds in the
  OpenCV camera frame, metres; `distance_m` its distance from the camera); null behind the camera.
  `mask_centroid_px`: the mean (u, v) of the visible anomaly pixels of the mask (null if none). They
  differ: the box centre ignores occlusion and shape, the centroid is where the visible pixels are.
- `bbox3d_cam_m`: the model box's 8 corners in the OpenCV camera frame (metres), corner 4 ix + 2 iy + iz
  takes x from (min, max)[ix], y from (min, max)[iy], z from (min, max)[iz] of the model frame's box;
  `bbox3d_px` their projections (null for a corner behind the camera).
- Amodal: `bbox_amodal_xyxy_px` (as bbox_xyxy_px) and `amodal_pixels` of the full silhouette, as if
  nothing hid the anomaly, inside the image. `visib_source` says where the silhouette comes from:
  "amodal_pass", the `amodal` pass's STEM_amodal.png (a render of the anomaly alone: exact,
  blender.amodal); else "raycast", the anomaly's triangles alone ray-cast through every pixel centre
  (scene.raycast, embree; the same pixel rule as the mask, so it agrees with the pass to a pixel or
  two on an edge), joined with the visible pixels so that visib_fract <= 1. `amodal_segmentation`:
  those pixels as COCO compressed RLE (as `segmentation`; null when none), so the dataset writes BOP's
  full-silhouette mask/ and px_count_valid for every anomaly object, pass or not.
- Truncation, as the BOP toolkit counts it (scripts/calc_gt_info.py renders the object on a canvas of
  3W x 3H with the principal point shifted by (W, H)): `amodal_pixels_canvas` and
  `bbox_amodal_canvas_xyxy_px` are the full silhouette's count and inclusive box on that canvas, pixel
  centres (u, v) at integers with u in [-W, 2W), v in [-H, 2H), the same pixel rule: the in-image
  pixels above, plus the ray cast of the canvas outside the image (only the projected vertices' box
  when every vertex is in front of the camera; the whole canvas otherwise: an object around the
  lens). The box is in image pixels and may start below 0 or end past W - 1, H - 1 (calc_gt_info's
  bbox_obj is misc.calc_2d_bbox of it, clip=False). `visib_fract` = pixels / amodal_pixels_canvas
  (0 when the silhouette misses the canvas): the toolkit's visib_fract, so a truncated anomaly's
  is below 1 though nothing hides it; the same value everywhere it is written (bop.gt_info).
  Cost at 1920x1080 (a 0.6 x 0.4 x 0.3 m box, one thread, a loaded 2-core machine): in the frame,
  nothing outside to cast (0.001 s); centred on the left edge, 0.007 s beside the in-image 0.009 s;
  around the lens (0.12 m ahead, vertices behind the camera), the whole canvas outside the image,
  16.6 million rays, 2.4 s beside the in-image 0.36 s (tests/output/test_annotations_canvas.py checks
  each case against an independent Moller-Trumbore of every canvas pixel).
- `in_view`: whether a body's disc (centre and angular radius asin(R / d) from its sphere's
  recorded translate and scale, seen from the camera) intersects the image's field of view,
  geometrically: occlusion by the station is ignored.
"""

from __future__ import annotations

import json
import math

import numpy as np

from allo_usd.core import fixedmath as fm
from allo_usd.core.labels import ANOMALY
from allo_usd.output.record import RenderRecord
from allo_usd.sky.model import BODIES
from allo_usd.usd.layout import ANOMALY as ANOMALY_PRIM, body_path

USD_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])   # camera axes: USD (x right, y up, -z forward) -> OpenCV


def intrinsics(width: int, height: int, focal_length_mm: float, sensor_width_mm: float,
               offset_mm: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """3x3 K in pixels, OpenCV pixel centres (module docstring), as Blender's horizontal sensor fit renders;
    `offset_mm`: the camera's (horizontalApertureOffset, verticalApertureOffset) in mm."""
    f = focal_length_mm / sensor_width_mm * width
    px_per_mm = width / sensor_width_mm
    dx, dy = -offset_mm[0] * px_per_mm, offset_mm[1] * px_per_mm
    return np.array([[f, 0.0, (width - 1) / 2.0 + dx], [0.0, f, (height - 1) / 2.0 + dy], [0.0, 0.0, 1.0]])


def world_to_cam_opencv(cam_to_world_usd: np.ndarray) -> np.ndarray:
    return fm.matmul(USD_TO_OPENCV, fm.inv4(cam_to_world_usd))   # fixed order, no BLAS or LAPACK: the same bits everywhere


def project(k: np.ndarray, world_to_cam: np.ndarray, points) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) pixel coordinates, (N,) depth z) of world points through K and an OpenCV pose."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cam = fm.apply(world_to_cam[:3, :3], p) + world_to_cam[:3, 3]
    uv = cam[:, :2] / cam[:, 2:3] * np.diag(k)[:2] + k[:2, 2]
    return uv, cam[:, 2]


def mask_bbox(mask: np.ndarray, class_id: int = ANOMALY) -> list[int] | None:
    """[x_min, y_min, x_max, y_max] (inclusive pixel indices) of a class in the mask, or None."""
    rows = np.flatnonzero((mask == class_id).any(axis=1))
    if not rows.size:
        return None
    cols = np.flatnonzero((mask == class_id).any(axis=0))
    return [int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1])]


def _world_points(mesh) -> np.ndarray:
    p = np.asarray(mesh.points, dtype=np.float64)
    return p @ mesh.matrix[:3, :3].T + mesh.matrix[:3, 3]


def disc_in_view(direction, angular_radius: float, half_x: float, half_y: float,
                 centre: tuple[float, float] = (0.0, 0.0)) -> bool:
    """Does a disc (centre direction in OpenCV camera axes, angular radius in radians) meet the
    view pyramid |x/z - cx| <= half_x, |y/z - cy| <= half_y, z > 0 ((cx, cy) = `centre`: the image
    centre's direction, off the axis with a principal point offset)? Exact: the angle from the
    centre to the pyramid (0 inside; else to the nearest face or edge ray) is below the radius."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / fm.norm(d)
    cx, cy = centre
    corners = np.array([[cx - half_x, cy - half_y, 1.0], [cx + half_x, cy - half_y, 1.0],
                        [cx + half_x, cy + half_y, 1.0], [cx - half_x, cy + half_y, 1.0]])
    corners /= fm.norm(corners, axis=1, keepdims=True)
    normals = np.cross(corners, np.roll(corners, -1, axis=0))     # inward: the optical axis is on their + side
    normals /= fm.norm(normals, axis=1, keepdims=True)
    if np.all(fm.dot(normals, d) >= 0.0):
        return True
    best = float(fm.arccos(np.clip(fm.dot(corners, d), -1.0, 1.0)).min())  # edge rays
    for i, n in enumerate(normals):
        nd = fm.dot(n, d)
        p = d - nd * n                                             # nearest direction on this face's plane
        a, b = _in_plane(corners[i], corners[(i + 1) % 4], p)
        if a >= 0.0 and b >= 0.0:                                  # within the face's wedge
            best = min(best, fm.arcsin(min(1.0, abs(nd))))
    return best < angular_radius


def _in_plane(e1: np.ndarray, e2: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    """(a, b) with p = a e1 + b e2 (p in the plane of e1 and e2, not parallel): the least-squares
    solution by the normal equations and Cramer's rule, in fixed order (no LAPACK)."""
    g11, g12, g22 = fm.dot(e1, e1), fm.dot(e1, e2), fm.dot(e2, e2)
    h1, h2 = fm.dot(e1, p), fm.dot(e2, p)
    det = g11 * g22 - g12 * g12
    return (h1 * g22 - g12 * h2) / det, (g11 * h2 - g12 * h1) / det


def camera_record(desc, width: int, height: int) -> dict:
    cam = desc.camera
    k = intrinsics(width, height, cam.focal_length_mm, cam.sensor_width_mm,
                   (cam.horizontal_offset_mm, cam.vertical_offset_mm))
    c2w = np.asarray(cam.matrix, dtype=np.float64)
    return {"width": int(width), "height": int(height), "K_px": k.tolist(),
            "focal_length_mm": float(cam.focal_length_mm), "sensor_width_mm": float(cam.sensor_width_mm),
            "sensor_height_mm": float(cam.sensor_height_mm), "clip_near_m": float(cam.clip[0]),
            "clip_far_m": float(cam.clip[1]), "cam_to_world_usd": c2w.tolist(),
            "world_to_cam_opencv": world_to_cam_opencv(c2w).tolist()}


def split_rotation_scale(a) -> tuple[np.ndarray, np.ndarray]:
    """(R, s) with a = R @ diag(s), R a proper rotation: a's columns divided by their lengths (exact for a
    rotation times a per-axis scale, which is what every transform this project authors is; a mirror
    gets a negative z scale). A sheared `a` (a non-uniform scale under a rotation further up) has no such
    split: then R is its polar rotation (the nearest rotation, from the SVD) and s = diag(R^T a), the
    best per-axis scale for it."""
    a = np.asarray(a, dtype=np.float64)
    s = fm.norm(a, axis=0)
    if fm.det3(a) < 0:
        s[2] = -s[2]
    r = a / s
    if np.abs(fm.matmul(r.T, r) - np.eye(3)).max() > 1e-9:
        u, _, vt = np.linalg.svd(a)   # a sheared transform only (none is authored here): LAPACK's bits
        if fm.det3(fm.matmul(u, vt)) < 0:
            u[:, 2] = -u[:, 2]
        r = fm.matmul(u, vt)
        s = np.diag(fm.matmul(r.T, a)).copy()
    return r, s


def _pixels(k: np.ndarray, cam: np.ndarray) -> list:
    """[u, v] of each camera-frame point through K, None for one at or behind the camera plane."""
    cam = np.asarray(cam, dtype=np.float64).reshape(-1, 3)
    return [[float(k[0, 0] * x / z + k[0, 2]), float(k[1, 1] * y / z + k[1, 2])] if z > 0 else None
            for x, y, z in cam]


def mask_centroid(mask: np.ndarray, class_id: int = ANOMALY) -> list[float] | None:
    """[u, v]: the mean column and row of a class's pixels (OpenCV pixel centres), or None."""
    rows, cols = np.nonzero(mask == class_id)
    return [float(cols.mean()), float(rows.mean())] if rows.size else None


def _model_frame(desc, meshes, recorded=None) -> tuple[np.ndarray, np.ndarray]:
    """(model-to-world 4x4, (N, 3) every vertex of `meshes` in the model frame). The model frame is the
    anomaly object's own (`recorded`: the reader's local_to_world of the object's prim, the frame of
    the file it references); without it (a description made another way) its first mesh's."""
    m = np.asarray(recorded if recorded is not None else meshes[0].matrix, dtype=np.float64)
    inv = fm.inv4(m)
    pts = []
    for mesh in meshes:
        to_model = fm.matmul(inv, mesh.matrix)
        pts.append(fm.apply(to_model[:3, :3], np.asarray(mesh.points, dtype=np.float64)) + to_model[:3, 3])
    return m, np.concatenate(pts)


CANVAS_RAYS = 1 << 19   # rays per embree call of the canvas cast (bounds its temporaries to ~40 MB)


class _Silhouette:
    """The triangles of some meshes in one embree scene (scene.raycast), cast through pixel centres:
    the mask's pixel rule (column c, row r: the ray through (u, v) = (c, r) of the OpenCV image), at
    any (c, r), inside the image or not."""

    def __init__(self, meshes, k: np.ndarray, w2c: np.ndarray):
        from allo_usd.assets.mesh import fan_triangulate
        from allo_usd.scene.raycast import RayScene

        parts = [(_world_points(m), fan_triangulate(m.face_counts, m.face_indices), ANOMALY) for m in meshes]
        self.k, self.c2w = k, np.linalg.inv(w2c)
        self.scene = RayScene(parts)
        uv, z = project(k, w2c, np.concatenate([p for p, _, _ in parts]))
        # every vertex in front of the camera: the silhouette lies inside the vertices' image box
        # (the convex hull's); else (an object around the lens) it can be anywhere
        self.box = ((int(np.floor(uv[:, 0].min())), int(np.floor(uv[:, 1].min())),
                     int(np.ceil(uv[:, 0].max())), int(np.ceil(uv[:, 1].max()))) if (z > 0).all() else None)

    def region(self, c0: int, r0: int, c1: int, r1: int) -> tuple[int, int, int, int]:
        """[c0, c1] x [r0, r1] cut to where the silhouette can be (empty: c0 > c1 or r0 > r1)."""
        if self.box is None:
            return c0, r0, c1, r1
        return max(c0, self.box[0]), max(r0, self.box[1]), min(c1, self.box[2]), min(r1, self.box[3])

    def first_hit(self, c0: int, r0: int, c1: int, r1: int) -> np.ndarray:
        """(r1 - r0 + 1, c1 - c0 + 1) bool: the pixels whose centre ray's first hit is these triangles
        (RayScene.first_hit, as the in-image ray cast always did)."""
        rows, cols = np.mgrid[r0:r1 + 1, c0:c1 + 1]
        dirs = self._dirs(cols.ravel(), rows.ravel())
        owner, _ = self.scene.first_hit(np.broadcast_to(self.c2w[:3, 3], dirs.shape), dirs)
        return (owner == ANOMALY).reshape(rows.shape)

    def _dirs(self, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
        k = self.k
        d_cam = np.stack([(cols - k[0, 2]) / k[0, 0], (rows - k[1, 2]) / k[1, 1], np.ones(cols.size)], axis=1)
        return d_cam @ self.c2w[:3, :3].T

    def hits(self, c0: int, r0: int, c1: int, r1: int) -> tuple[int, list[int] | None]:
        """(how many pixel centres of [c0, c1] x [r0, r1] see the triangles, [x_min, y_min, x_max, y_max]
        of those pixels or None): RayScene.hits_from, the same hits as first_hit without distances,
        in slices of CANVAS_RAYS rays."""
        from allo_usd.scene.raycast import RayFan

        if c0 > c1 or r0 > r1:
            return 0, None
        n_cols = c1 - c0 + 1
        step = max(1, CANVAS_RAYS // n_cols)
        count, box = 0, None
        for top in range(r0, r1 + 1, step):
            rows, cols = np.mgrid[top:min(r1, top + step - 1) + 1, c0:c1 + 1]
            rays, _ = self.scene.hits_from(self.c2w[:3, 3], RayFan.of_rows(self._dirs(cols.ravel(), rows.ravel())),
                                           distances=False)
            if rays.size:
                u, v = cols.ravel()[rays], rows.ravel()[rays]
                found = [int(u.min()), int(v.min()), int(u.max()), int(v.max())]
                box = found if box is None else [min(box[0], found[0]), min(box[1], found[1]),
                                                 max(box[2], found[2]), max(box[3], found[3])]
                count += int(rays.size)
        return count, box


def amodal_raycast(desc, k: np.ndarray, w2c: np.ndarray, width: int, height: int, meshes=None) -> np.ndarray:
    """(H, W) bool: pixels whose centre ray meets `meshes`' triangles (default: every anomaly-class mesh),
    nothing else in the scene (scene.raycast, embree), only where their vertices' image box says it can be."""
    meshes = [m for m in desc.meshes if m.class_id == ANOMALY] if meshes is None else meshes
    return _amodal_in_image(_Silhouette(meshes, k, w2c), width, height)


def _amodal_in_image(cast: _Silhouette, width: int, height: int) -> np.ndarray:
    out = np.zeros((height, width), dtype=bool)
    c0, r0, c1, r1 = cast.region(0, 0, width - 1, height - 1)
    if c0 <= c1 and r0 <= r1:
        out[r0:r1 + 1, c0:c1 + 1] = cast.first_hit(c0, r0, c1, r1)
    return out


def amodal_canvas(cast: _Silhouette, inside: np.ndarray) -> tuple[int, list[int] | None]:
    """(pixel count, [x_min, y_min, x_max, y_max] in image pixels or None) of a full silhouette on the
    BOP toolkit's canvas (module docstring): `inside`, its (H, W) pixels in the image, joined with
    the ray cast of every canvas pixel outside the image, pixel centres (c, r) with c in [-W, 2W),
    r in [-H, 2H) (only where the silhouette can be: _Silhouette.region)."""
    height, width = inside.shape
    count, box = int(np.count_nonzero(inside)), mask_bbox(inside.astype(np.uint8), 1)
    c0, r0, c1, r1 = cast.region(-width, -height, 2 * width - 1, 2 * height - 1)
    bands = ((c0, r0, c1, min(r1, -1)), (c0, max(r0, height), c1, r1),             # above and below the image
             (c0, max(r0, 0), min(c1, -1), min(r1, height - 1)),                    # left of it
             (max(c0, width), max(r0, 0), c1, min(r1, height - 1)))                 # right of it
    for band in bands:
        n, found = cast.hits(*band)
        count += n
        if found is not None:
            box = found if box is None else [min(box[0], found[0]), min(box[1], found[1]),
                                             max(box[2], found[2]), max(box[3], found[3])]
    return count, box


def object_paths(desc) -> list[str]:
    """The scene's object paths in object-id order (id = index + 1; blender.build.object_ids's table)."""
    return sorted({m.object_path for m in desc.meshes})


def anomaly_objects(desc) -> list[str]:
    """The paths of the scene's anomaly objects: /World/Anomaly (the planned anomaly) first, then the
    others in path order."""
    paths = sorted({m.object_path for m in desc.meshes if m.class_id == ANOMALY})
    return sorted(paths, key=lambda p: (p != ANOMALY_PRIM, p))


def anomaly_record(desc, mask: np.ndarray, k: np.ndarray, w2c: np.ndarray,
                   amodal: np.ndarray | None = None, path: str | None = None, ids: np.ndarray | None = None) -> dict | None:
    """One anomaly object's annotations (module docstring), None when the scene has no such object.
    `path`: the object (default: the first of anomaly_objects, /World/Anomaly when it is there); its
    visible pixels are those of its id in `ids` (the object index pass), or the class mask's anomaly
    pixels when the scene has one anomaly object. `amodal`: the `amodal` pass's mask (STEM_amodal.png,
    /World/Anomaly alone), the full silhouette of /World/Anomaly; any other object's is ray-cast over
    its own meshes."""
    objects = anomaly_objects(desc)
    path = path or (objects[0] if objects else None)
    meshes = [m for m in desc.meshes if m.class_id == ANOMALY and m.object_path == path]
    if not meshes:
        return None
    height, width = mask.shape
    labels = next((o for o in desc.meta.get("anomalies") or () if isinstance(o, dict) and o.get("path") == path), {})
    planned = path == ANOMALY_PRIM or not labels and len(objects) == 1
    recorded = labels.get("local_to_world")
    if recorded is None and planned:
        recorded = (desc.meta.get("anomaly_model") or {}).get("local_to_world")
    m2w, model_pts = _model_frame(desc, meshes, recorded)
    m2c = fm.matmul(w2c, m2w)
    rot, scale = split_rotation_scale(m2c[:3, :3])
    lo, hi = model_pts.min(axis=0), model_pts.max(axis=0)
    corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[n][2]]
                        for i in (0, 1) for j in (0, 1) for n in (0, 1)])
    box_cam = fm.apply(m2c[:3, :3], corners) + m2c[:3, 3]
    centre = fm.matmul(m2c[:3, :3], (lo + hi) / 2.0) + m2c[:3, 3]
    instance = object_paths(desc).index(path) + 1
    if ids is not None:
        visible = ids == instance
    elif len(objects) == 1:
        visible = mask == ANOMALY
    else:
        raise ValueError(f"{len(objects)} anomaly objects: their pixels need the object index pass (ids)")
    cast = _Silhouette(meshes, k, w2c)
    if amodal is not None and path == ANOMALY_PRIM:
        full, source = amodal == ANOMALY, "amodal_pass"
    else:
        full, source = _amodal_in_image(cast, width, height) | visible, "raycast"
    pixels, amodal_pixels = int(np.count_nonzero(visible)), int(np.count_nonzero(full))
    canvas_pixels, canvas_box = amodal_canvas(cast, full)
    info = (desc.meta.get("anomaly") or {}) if planned else {}
    asset, variant = (info.get("asset"), info.get("assetVariant")) if planned else (None, None)
    asset, variant = asset or labels.get("asset"), variant or labels.get("variant")
    offset = info.get("depthOffset")
    model_path = labels.get("reference") if labels else (desc.meta.get("anomaly_model") or {}).get("reference")
    vmask = visible.astype(np.uint8)
    return {"path": path, "instance_id": instance, "bbox_xyxy_px": mask_bbox(vmask, 1), "pixels": pixels,
            "center_cam_opencv_m": centre.tolist(), "distance_m": fm.norm(centre),
            "center_px": _pixels(k, centre)[0], "mask_centroid_px": mask_centroid(vmask, 1),
            "depth_offset_m": None if offset is None else float(offset),
            "model": {"asset": asset, "variant": variant, "model_id": model_id(asset, variant), "path": model_path},
            "pose": {"cam_R_m2c": rot.ravel().tolist(), "cam_t_m2c": (m2c[:3, 3] * 1000.0).tolist(),
                     "model_units": "m", "model_scale": scale.tolist()},
            "bbox3d_cam_m": box_cam.tolist(), "bbox3d_px": _pixels(k, box_cam),
            "bbox_amodal_xyxy_px": mask_bbox(full.astype(np.uint8), 1), "amodal_pixels": amodal_pixels,
            "amodal_segmentation": visible_rle(full) if amodal_pixels else None,
            "bbox_amodal_canvas_xyxy_px": canvas_box, "amodal_pixels_canvas": canvas_pixels,
            "visib_fract": pixels / canvas_pixels if canvas_pixels else 0.0, "visib_source": source,
            "segmentation": visible_rle(visible) if pixels else None}


def model_id(asset, variant) -> str | None:
    """"ASSET/VARIANT", "ASSET" for an asset without variants, None without an asset."""
    return None if asset is None else asset if variant is None else f"{asset}/{variant}"


def visible_rle(visible: np.ndarray) -> dict:
    """COCO compressed RLE of an object's visible pixels (allo_usd.output.rle)."""
    from allo_usd.output.rle import rle

    return rle(visible)


def bodies_in_view(desc, k: np.ndarray, w2c: np.ndarray, width: int, height: int) -> dict:
    """{body: in_view} for sun, earth, moon (None for a body the scene has no sphere of)."""
    half_x, half_y = width / 2.0 / k[0, 0], height / 2.0 / k[1, 1]
    view_centre = (((width - 1) / 2.0 - k[0, 2]) / k[0, 0], ((height - 1) / 2.0 - k[1, 2]) / k[1, 1])
    out = {}
    for body in BODIES:
        prefix = body_path(body.capitalize()) + "/"
        meshes = [m for m in desc.meshes if m.path.startswith(prefix)]
        if not meshes:
            out[body] = None
            continue
        m = meshes[0].matrix
        centre = fm.matmul(w2c[:3, :3], m[:3, 3]) + w2c[:3, 3]
        radius = float(fm.norm(m[:3, :3], axis=0).mean())   # a unit sphere scaled by the body's radius
        dist = fm.norm(centre)
        out[body] = True if dist <= radius else disc_in_view(centre, fm.arcsin(radius / dist), half_x, half_y,
                                                                         view_centre)
    return out


def image_annotations(desc, mask: np.ndarray, amodal: np.ndarray | None = None, ids: np.ndarray | None = None) -> dict:
    """The render JSON's `annotations` block: camera, anomalies (one entry per anomaly object,
    anomaly_objects' order; absent without one), anomaly (the planned anomaly's entry, /World/Anomaly's,
    else the first object's; None for a normal scene), in_view. `amodal`: the `amodal` pass's mask when
    it was rendered (else every silhouette is ray-cast); `ids`: the object index pass (needed with more
    than one anomaly object)."""
    height, width = mask.shape
    camera = camera_record(desc, width, height)
    k, w2c = np.array(camera["K_px"]), np.array(camera["world_to_cam_opencv"])
    anomalies = [anomaly_record(desc, mask, k, w2c, amodal, path, ids) for path in anomaly_objects(desc)]
    out = {"camera": camera, "anomaly": anomalies[0] if anomalies else None,
           "in_view": bodies_in_view(desc, k, w2c, width, height)}
    return out | ({"anomalies": anomalies} if anomalies else {})


# ---------------------------------------------------------------- manifest columns (from an untrusted JSON)
CAMERA_COLUMNS = ("width", "height", "fx", "fy", "cx", "cy", "focal_length_mm", "sensor_width_mm", "sensor_height_mm",
                  "clip_near", "clip_far", "K_px", "cam_to_world_usd", "world_to_cam_opencv")
ANNOTATION_COLUMNS = ("bbox_x_min", "bbox_y_min", "bbox_x_max", "bbox_y_max", "anomaly_pixels", "anomaly_cam_x",
                      "anomaly_cam_y", "anomaly_cam_z", "anomaly_distance_m", "station_fraction", "sun_pixels",
                      "earth_pixels", "moon_pixels", "sun_in_view", "earth_in_view", "moon_in_view")


def _num(value, integer: bool = False):
    """A finite number from a JSON value, else "" (the record is not trusted)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or integer and not isinstance(value, int):
        return ""
    if isinstance(value, int):
        return value if integer else (float(value) if abs(value) < 1e300 else "")
    return value if math.isfinite(value) else ""


def _matrix(value, n: int) -> str:
    """Compact JSON of an n x n matrix of finite numbers, else ""."""
    if not (isinstance(value, list) and len(value) == n and all(isinstance(r, list) and len(r) == n for r in value)):
        return ""
    rows = [[_num(x) for x in r] for r in value]
    return "" if any(x == "" for r in rows for x in r) else json.dumps(rows, separators=(",", ":"))


def _get(d, *keys):
    for key in keys:
        d = d.get(key) if isinstance(d, dict) else None
    return d


def _dict(value) -> dict:
    return value if isinstance(value, dict) else {}


def annotation_columns(meta: RenderRecord | dict) -> dict:
    """The CAMERA_COLUMNS and ANNOTATION_COLUMNS of a render record (or its JSON object); "" where it
    records nothing."""
    meta = RenderRecord.given(meta)
    cam = _dict(_get(meta.annotations, "camera"))
    k = cam.get("K_px")
    k_ok = _matrix(k, 3) != ""
    row = {"width": _num(cam.get("width"), True), "height": _num(cam.get("height"), True),
           "fx": k[0][0] if k_ok else "", "fy": k[1][1] if k_ok else "", "cx": k[0][2] if k_ok else "",
           "cy": k[1][2] if k_ok else "", "focal_length_mm": _num(cam.get("focal_length_mm")),
           "sensor_width_mm": _num(cam.get("sensor_width_mm")), "sensor_height_mm": _num(cam.get("sensor_height_mm")),
           "clip_near": _num(cam.get("clip_near_m")), "clip_far": _num(cam.get("clip_far_m")),
           "K_px": _matrix(k, 3), "cam_to_world_usd": _matrix(cam.get("cam_to_world_usd"), 4),
           "world_to_cam_opencv": _matrix(cam.get("world_to_cam_opencv"), 4)}
    anomaly = _dict(_get(meta.annotations, "anomaly"))
    bbox = anomaly.get("bbox_xyxy_px")
    bbox = bbox if isinstance(bbox, list) and len(bbox) == 4 else [None] * 4
    centre = anomaly.get("center_cam_opencv_m")
    centre = centre if isinstance(centre, list) and len(centre) == 3 else [None] * 3
    row |= {f"bbox_{k}": _num(v, True) for k, v in zip(("x_min", "y_min", "x_max", "y_max"), bbox)}
    row |= {"anomaly_pixels": _num(anomaly.get("pixels"), True),
            "anomaly_cam_x": _num(centre[0]), "anomaly_cam_y": _num(centre[1]), "anomaly_cam_z": _num(centre[2]),
            "anomaly_distance_m": _num(anomaly.get("distance_m")),
            "station_fraction": _num(meta.station_fraction)}
    for body in BODIES:
        row[f"{body}_pixels"] = _num(_get(meta.bodies, body, "pixels"), True)
        seen = _get(meta.annotations, "in_view", body)
        row[f"{body}_in_view"] = seen if isinstance(seen, bool) else ""
    return row


# The render's own estimate of its accuracy (the JSON's "accuracy", allo_usd.blender.render.RenderResult):
# est_psnr_db is its estimated_psnr_db (8-bit sRGB, against the converged image) and est_psnr_low_db its
# lower_psnr_db (the PSNR the image is at least, at two standard errors of the estimate: what a target
# render stopped on), each "" when not recorded or not a finite number in ESTIMATED_PSNR_DB (an 8-bit image
# is never below 0 dB; 200 dB is past any render).
ACCURACY_COLUMNS = ("est_psnr_db", "est_psnr_low_db")
ESTIMATED_PSNR_DB = (0.0, 200.0)
_ACCURACY_KEYS = {"est_psnr_db": "estimated_psnr_db", "est_psnr_low_db": "lower_psnr_db"}


def accuracy_columns(meta: RenderRecord | dict) -> dict:
    """The ACCURACY_COLUMNS of a render record (or its JSON object): "" where it records no usable estimate."""
    accuracy = RenderRecord.given(meta).accuracy
    lo, hi = ESTIMATED_PSNR_DB
    out = {}
    for column, key in _ACCURACY_KEYS.items():
        value = _num(_get(accuracy, key))
        out[column] = value if value != "" and lo <= value <= hi else ""
    return out
