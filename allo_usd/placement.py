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
from .raycast import Scene, pixel_rays

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


def visible_fraction(station: Scene, anomaly: Scene, cam_pos, cam_rot, width: int, height: int,
                     rays=None, sphere=None) -> float:
    """Fraction of pixel centres whose first hit is the anomaly (station and anomaly BVHs kept apart,
    so the station's is built once per camera and only the small one per candidate).

    `rays`: the camera's pixel rays, if already computed. `sphere`: (centre, radius) bounding the
    anomaly; rays that miss it cannot hit the anomaly and are not cast (exact, and ~20x faster
    for a small object in a large image)."""
    o, d = pixel_rays(cam_pos, cam_rot, width, height) if rays is None else rays
    if sphere is not None:
        c, r = np.asarray(sphere[0], dtype=np.float64), float(sphere[1]) * 1.001 + 1e-9
        v = c - o[0]                                   # every ray starts at the camera
        t = d @ v
        miss = (np.dot(v, v) - t * t > r * r) | (t < -r)
        keep = np.flatnonzero(~miss)
        if keep.size == 0:
            return 0.0
        o, d = o[keep], d[keep]
    a_owner, a_dist = anomaly.first_hit(o, d)
    hit = a_owner > 0
    if not hit.any():
        return 0.0
    _, s_dist = station.first_hit(o[hit], d[hit])
    return float((a_dist[hit] < s_dist).sum() / (width * height))


def check(station: Scene, anomaly_points, anomaly_tris, position, rotation, cam_pos, cam_rot,
          width, height, min_fraction=MIN_FRACTION, rays=None) -> tuple[bool, float, str]:
    """(accepted, visible fraction, reason) for one candidate placement."""
    cam_pos = np.asarray(cam_pos, dtype=np.float64)
    radius = np.linalg.norm(anomaly_points, axis=1).max()
    if np.dot(position - cam_pos, -cam_rot[:, 2]) <= radius:
        return False, 0.0, "behind or against the camera"
    # Touching the station: a station surface closer to the object's centre than its bounding radius.
    dirs = _SPHERE_DIRS
    _, dist = station.first_hit(np.repeat(position[None], len(dirs), 0), dirs)
    if (dist < radius * 1.05).any():
        return False, 0.0, "intersects the station"
    anomaly = Scene([(_posed(anomaly_points, rotation, position), anomaly_tris, ANOMALY)])
    frac = visible_fraction(station, anomaly, cam_pos, cam_rot, width, height, rays, (position, radius))
    if frac == 0.0:
        return False, 0.0, "fully occluded or outside the frame"
    if frac < min_fraction:
        return False, frac, f"covers {frac:.4%} of the image, under {min_fraction:.1%}"
    return True, frac, ""


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


_SPHERE_DIRS = _fibonacci_sphere(128)


def place(station_parts: "Scene | list", anomaly_points, anomaly_tris, cam_pos, cam_rot, rng: np.random.Generator,
          width: int, height: int, max_attempts: int = 60, check_width: int | None = None,
          min_fraction: float = MIN_FRACTION) -> list[Placement]:
    """Place one object and its four extra depths; raises PlacementError if no initial placement."""
    cw = check_width or width
    ch = max(1, round(height * cw / width))
    cam_pos = np.asarray(cam_pos, dtype=np.float64)
    station = station_parts if isinstance(station_parts, Scene) else Scene(station_parts)
    o, d = pixel_rays(cam_pos, cam_rot, cw, ch)
    radius = float(np.linalg.norm(anomaly_points, axis=1).max())
    for attempt in range(1, max_attempts + 1):
        u, v = rng.uniform(0.15, 0.85), rng.uniform(0.15, 0.85)
        px, py = int(u * cw), int(v * ch)
        ray = d[py * cw + px]
        _, hit = station.first_hit(cam_pos[None].astype(np.float64), ray[None])
        far = hit[0] - radius - 0.5 if np.isfinite(hit[0]) else 12.0
        near = 1.0 + radius
        if far <= near:
            continue
        depth = rng.uniform(max(near, far - 6.0), far)
        rot = random_rotation(rng)
        pos = cam_pos + depth * ray
        ok, frac, _ = check(station, anomaly_points, anomaly_tris, pos, rot, cam_pos, cam_rot, cw, ch,
                            min_fraction, (o, d))
        if not ok:
            continue
        out = []
        for k, off in enumerate(DEPTH_OFFSETS):
            p = cam_pos + (depth + off) * ray
            if off == 0.0:
                out.append(Placement(k, off, p, rot, frac, attempt))
                continue
            ok_k, frac_k, why = check(station, anomaly_points, anomaly_tris, p, rot, cam_pos, cam_rot,
                                      cw, ch, min_fraction, (o, d))
            out.append(Placement(k, off, p if ok_k else None, rot, frac_k, attempt, "" if ok_k else why))
        return out
    raise PlacementError(f"no visible placement in {max_attempts} attempts (object radius {radius:.2f} m); "
                         "the view may show no station nearby — use another pose or a smaller object")
