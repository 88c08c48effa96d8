"""Anomaly placement in the view frustum, checked by ray casting (never by rendering).

An attempt picks a pixel, walks along its ray to near the station surface it sees, gives the
object a uniformly random orientation, and accepts it if the object does not touch the
station and covers at least `min_fraction` of the image at pixel centres. Four more depths
(+-1 m, +-2 m along the same ray) are checked the same way; a depth that fails is reported as
skipped, never silently dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .description import ANOMALY
from .errors import PlacementError
from .geometry import quat_to_matrix
from .raycast import Scene, class_image, pixel_rays

DEPTH_OFFSETS = (0.0, -1.0, 1.0, -2.0, 2.0)
MIN_FRACTION = 0.001


@dataclass(frozen=True)
class Placement:
    depth_index: int
    depth_offset: float
    position: np.ndarray | None   # None when skipped
    rotation: np.ndarray
    area_fraction: float
    attempts: int
    skipped_reason: str = ""


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quat_to_matrix(q / np.linalg.norm(q))


def _posed(points, rotation, position):
    return points @ rotation.T + position


def check(station_parts, anomaly_points, anomaly_tris, position, rotation, cam_pos, cam_rot,
          width, height, min_fraction=MIN_FRACTION) -> tuple[bool, float, str]:
    """(accepted, visible fraction, reason) for one candidate placement."""
    pts = _posed(anomaly_points, rotation, position)
    radius = np.linalg.norm(anomaly_points, axis=1).max()
    to_obj = position - cam_pos
    fwd = -cam_rot[:, 2]
    if np.dot(to_obj, fwd) <= radius:
        return False, 0.0, "behind or against the camera"
    station = Scene(station_parts)
    # Touching the station: any station hit from the object's centre closer than its radius.
    dirs = np.random.default_rng(0).normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    _, dist = station.first_hit(np.repeat(position[None], len(dirs), 0), dirs)
    if (dist < radius * 1.05).any():
        return False, 0.0, "intersects the station"
    scene = Scene(list(station_parts) + [(pts, anomaly_tris, ANOMALY)])
    mask = class_image(scene, cam_pos, cam_rot, width, height)
    frac = float((mask == ANOMALY).mean())
    if frac == 0.0:
        return False, 0.0, "fully occluded or outside the frame"
    if frac < min_fraction:
        return False, frac, f"covers {frac:.4%} of the image, under {min_fraction:.1%}"
    return True, frac, ""


def place(station_parts, anomaly_points, anomaly_tris, cam_pos, cam_rot, rng: np.random.Generator,
          width: int, height: int, max_attempts: int = 60, check_width: int | None = None,
          min_fraction: float = MIN_FRACTION) -> list[Placement]:
    """Place one object and its four extra depths; raises PlacementError if no initial placement."""
    cw = check_width or width
    ch = max(1, round(height * cw / width))
    station = Scene(station_parts)
    radius = float(np.linalg.norm(anomaly_points, axis=1).max())
    for attempt in range(1, max_attempts + 1):
        u, v = rng.uniform(0.15, 0.85), rng.uniform(0.15, 0.85)
        px, py = int(u * cw), int(v * ch)
        o, d = pixel_rays(cam_pos, cam_rot, cw, ch)
        ray = d[py * cw + px]
        _, hit = station.first_hit(cam_pos[None].astype(np.float64), ray[None])
        far = hit[0] - radius - 0.5 if np.isfinite(hit[0]) else 12.0
        near = 1.0 + radius
        if far <= near:
            continue
        depth = rng.uniform(max(near, far - 6.0), far)
        rot = random_rotation(rng)
        pos = cam_pos + depth * ray
        ok, frac, _ = check(station_parts, anomaly_points, anomaly_tris, pos, rot, cam_pos, cam_rot, cw, ch,
                            min_fraction)
        if not ok:
            continue
        out = []
        for k, off in enumerate(DEPTH_OFFSETS):
            p = cam_pos + (depth + off) * ray
            if off == 0.0:
                out.append(Placement(k, off, p, rot, frac, attempt))
                continue
            ok_k, frac_k, why = check(station_parts, anomaly_points, anomaly_tris, p, rot, cam_pos, cam_rot,
                                      cw, ch, min_fraction)
            out.append(Placement(k, off, p if ok_k else None, rot, frac_k, attempt, "" if ok_k else why))
        return out
    raise PlacementError(f"no visible placement in {max_attempts} attempts (object radius {radius:.2f} m); "
                         "the view may show no station nearby — use another pose or a smaller object")
