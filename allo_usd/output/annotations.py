"""Per-image camera and object annotations: the render JSON's `annotations` block and the manifest's
CAMERA/ANNOTATION columns, computed from the scene description and the class mask (no pxr, no bpy).

Conventions (README "Dataset" repeats them; tests/test_camera_record.py checks each):
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
- Anomaly bounding box `bbox_xyxy_px`: [x_min, y_min, x_max, y_max] of the anomaly class in the
  mask, inclusive pixel indices (COCO's [x, y, w, h] is [x_min, y_min, x_max - x_min + 1,
  y_max - y_min + 1]); null when no anomaly pixel is visible. `center_cam_opencv_m` is the centre
  of the axis-aligned world box around the anomaly's vertices, in the OpenCV camera frame;
  `distance_m` its distance from the camera; `center_px` its projection.
- `in_view`: whether a body's disc (centre and angular radius asin(R / d) from its sphere's
  recorded translate and scale, seen from the camera) intersects the image's field of view,
  geometrically: occlusion by the station is ignored.
"""

from __future__ import annotations

import json
import math

import numpy as np

from allo_usd.core.labels import ANOMALY
from allo_usd.sky.model import BODIES
from allo_usd.usd.layout import body_path

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
    return USD_TO_OPENCV @ np.linalg.inv(np.asarray(cam_to_world_usd, dtype=np.float64))


def project(k: np.ndarray, world_to_cam: np.ndarray, points) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) pixel coordinates, (N,) depth z) of world points through K and an OpenCV pose."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cam = p @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
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
    d = d / np.linalg.norm(d)
    cx, cy = centre
    corners = np.array([[cx - half_x, cy - half_y, 1.0], [cx + half_x, cy - half_y, 1.0],
                        [cx + half_x, cy + half_y, 1.0], [cx - half_x, cy + half_y, 1.0]])
    corners /= np.linalg.norm(corners, axis=1, keepdims=True)
    normals = np.cross(corners, np.roll(corners, -1, axis=0))     # inward: the optical axis is on their + side
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    if np.all(normals @ d >= 0.0):
        return True
    best = float(np.arccos(np.clip(corners @ d, -1.0, 1.0)).min())  # edge rays
    for i, n in enumerate(normals):
        p = d - (n @ d) * n                                        # nearest direction on this face's plane
        a, b = np.linalg.lstsq(np.stack([corners[i], corners[(i + 1) % 4]], axis=1), p, rcond=None)[0]
        if a >= 0.0 and b >= 0.0:                                  # within the face's wedge
            best = min(best, math.asin(min(1.0, abs(float(n @ d)))))
    return best < angular_radius


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


def anomaly_record(desc, mask: np.ndarray, k: np.ndarray, w2c: np.ndarray) -> dict | None:
    meshes = [m for m in desc.meshes if m.class_id == ANOMALY]
    if not meshes:
        return None
    pts = np.concatenate([_world_points(m) for m in meshes])
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2.0
    cam = w2c[:3, :3] @ centre + w2c[:3, 3]
    uv, z = project(k, w2c, centre)
    offset = (desc.meta.get("anomaly") or {}).get("depthOffset")
    return {"bbox_xyxy_px": mask_bbox(mask), "pixels": int(np.count_nonzero(mask == ANOMALY)),
            "center_cam_opencv_m": cam.tolist(), "distance_m": float(np.linalg.norm(cam)),
            "center_px": uv[0].tolist() if z[0] > 0 else None,
            "depth_offset_m": None if offset is None else float(offset)}


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
        centre = w2c[:3, :3] @ m[:3, 3] + w2c[:3, 3]
        radius = float(np.linalg.norm(m[:3, :3], axis=0).mean())   # a unit sphere scaled by the body's radius
        dist = float(np.linalg.norm(centre))
        out[body] = True if dist <= radius else disc_in_view(centre, math.asin(radius / dist), half_x, half_y,
                                                                         view_centre)
    return out


def image_annotations(desc, mask: np.ndarray) -> dict:
    """The render JSON's `annotations` block: camera, anomaly (None for a normal scene), in_view."""
    height, width = mask.shape
    camera = camera_record(desc, width, height)
    k, w2c = np.array(camera["K_px"]), np.array(camera["world_to_cam_opencv"])
    return {"camera": camera, "anomaly": anomaly_record(desc, mask, k, w2c),
            "in_view": bodies_in_view(desc, k, w2c, width, height)}


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


def annotation_columns(meta: dict) -> dict:
    """The CAMERA_COLUMNS and ANNOTATION_COLUMNS of a render record; "" where it records nothing."""
    cam = _dict(_get(meta, "annotations", "camera"))
    k = cam.get("K_px")
    k_ok = _matrix(k, 3) != ""
    row = {"width": _num(cam.get("width"), True), "height": _num(cam.get("height"), True),
           "fx": k[0][0] if k_ok else "", "fy": k[1][1] if k_ok else "", "cx": k[0][2] if k_ok else "",
           "cy": k[1][2] if k_ok else "", "focal_length_mm": _num(cam.get("focal_length_mm")),
           "sensor_width_mm": _num(cam.get("sensor_width_mm")), "sensor_height_mm": _num(cam.get("sensor_height_mm")),
           "clip_near": _num(cam.get("clip_near_m")), "clip_far": _num(cam.get("clip_far_m")),
           "K_px": _matrix(k, 3), "cam_to_world_usd": _matrix(cam.get("cam_to_world_usd"), 4),
           "world_to_cam_opencv": _matrix(cam.get("world_to_cam_opencv"), 4)}
    anomaly = _dict(_get(meta, "annotations", "anomaly"))
    bbox = anomaly.get("bbox_xyxy_px")
    bbox = bbox if isinstance(bbox, list) and len(bbox) == 4 else [None] * 4
    centre = anomaly.get("center_cam_opencv_m")
    centre = centre if isinstance(centre, list) and len(centre) == 3 else [None] * 3
    row |= {f"bbox_{k}": _num(v, True) for k, v in zip(("x_min", "y_min", "x_max", "y_max"), bbox)}
    row |= {"anomaly_pixels": _num(anomaly.get("pixels"), True),
            "anomaly_cam_x": _num(centre[0]), "anomaly_cam_y": _num(centre[1]), "anomaly_cam_z": _num(centre[2]),
            "anomaly_distance_m": _num(anomaly.get("distance_m")),
            "station_fraction": _num(meta.get("station_fraction"))}
    for body in BODIES:
        row[f"{body}_pixels"] = _num(_get(meta, "bodies", body, "pixels"), True)
        seen = _get(meta, "annotations", "in_view", body)
        row[f"{body}_in_view"] = seen if isinstance(seen, bool) else ""
    return row
