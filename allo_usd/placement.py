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
from .geometry import camera_intrinsics, quat_to_matrix
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


def sphere_pixels(cam_pos, cam_rot, width: int, height: int, centre, radius: float) -> np.ndarray | None:
    """Row-major indices of the pixels whose centre ray may pass within `radius` of `centre`: the
    sphere's exact image-space bounding box (tangent planes through the camera), widened by one
    pixel. None when the sphere reaches the camera plane (then every pixel is a candidate)."""
    k = camera_intrinsics(width, height)
    c = (np.asarray(centre, dtype=np.float64) - np.asarray(cam_pos, dtype=np.float64)) @ np.asarray(cam_rot)
    depth = -c[2]
    if depth <= radius * 1.01:
        return None
    bounds = []
    for lateral in (c[0], c[1]):
        h = np.hypot(lateral, depth)
        theta, beta = np.arctan2(lateral, depth), np.arcsin(min(1.0, radius / h))
        bounds.append((np.tan(theta - beta), np.tan(theta + beta)))
    (sx0, sx1), (sy0, sy1) = bounds
    u0, u1 = sx0 * k[0, 0] + k[0, 2], sx1 * k[0, 0] + k[0, 2]
    v0, v1 = k[1, 2] - sy1 * k[1, 1], k[1, 2] - sy0 * k[1, 1]
    i0, i1 = max(0, int(np.floor(u0 - 0.5)) - 1), min(width - 1, int(np.ceil(u1 - 0.5)) + 1)
    j0, j1 = max(0, int(np.floor(v0 - 0.5)) - 1), min(height - 1, int(np.ceil(v1 - 0.5)) + 1)
    if i0 > i1 or j0 > j1:
        return np.zeros(0, dtype=np.int64)
    return (np.arange(j0, j1 + 1)[:, None] * width + np.arange(i0, i1 + 1)[None, :]).ravel()


def visible_fraction(station: Scene, anomaly: Scene, cam_pos, cam_rot, width: int, height: int,
                     rays=None, sphere=None, pose=None) -> float:
    """Fraction of pixel centres whose first hit is the anomaly (station and anomaly BVHs kept apart,
    so the station's is built once per world and the anomaly's once per asset).

    `rays`: the camera's pixel rays (`pixel_rays(cam_pos, cam_rot, width, height)`), if already
    computed. `sphere`: (centre, radius) bounding the anomaly; only rays that pass within it are
    cast (exact: a ray that misses the sphere cannot hit the anomaly). `pose`: (position,
    rotation) when `anomaly` holds the object in its own frame; the rays are then moved into that
    frame (p_obj = R^T (p - position)) instead of building a BVH for the posed object."""
    if sphere is not None:
        c, r = np.asarray(sphere[0], dtype=np.float64), float(sphere[1]) * 1.001 + 1e-9
        idx = sphere_pixels(cam_pos, cam_rot, width, height, c, r)
        if rays is None:
            o, d = pixel_rays(cam_pos, cam_rot, width, height, idx)
        else:
            o, d = rays if idx is None else (rays[0][idx], rays[1][idx])
        v = c - o[0] if len(o) else c                  # every ray starts at the camera
        t = d @ v
        miss = (np.dot(v, v) - t * t > r * r) | (t < -r)
        keep = np.flatnonzero(~miss)
        if keep.size == 0:
            return 0.0
        o, d = o[keep], d[keep]
    else:
        o, d = pixel_rays(cam_pos, cam_rot, width, height) if rays is None else rays
    if pose is None:
        a_owner, a_dist = anomaly.first_hit(o, d)
    else:
        position, rotation = np.asarray(pose[0], dtype=np.float64), np.asarray(pose[1], dtype=np.float64)
        a_owner, a_dist = anomaly.first_hit((o - position) @ rotation, d @ rotation)
    hit = a_owner > 0
    if not hit.any():
        return 0.0
    _, s_dist = station.first_hit(o[hit], d[hit])
    return float((a_dist[hit] < s_dist).sum() / (width * height))


def anomaly_scene(anomaly_points, anomaly_tris) -> Scene:
    """The object's BVH in its own frame, built once per asset and reused for every pose."""
    return Scene([(anomaly_points, anomaly_tris, ANOMALY)])


def check(station: Scene, anomaly_points, anomaly_tris, position, rotation, cam_pos, cam_rot,
          width, height, min_fraction=MIN_FRACTION, rays=None, anomaly: Scene | None = None
          ) -> tuple[bool, float, str]:
    """(accepted, visible fraction, reason) for one candidate placement. `anomaly`: the object's
    BVH in its own frame (`anomaly_scene`), if already built."""
    cam_pos = np.asarray(cam_pos, dtype=np.float64)
    radius = np.linalg.norm(anomaly_points, axis=1).max()
    if np.dot(position - cam_pos, -cam_rot[:, 2]) <= radius:
        return False, 0.0, "behind or against the camera"
    # Touching the station: a station surface closer to the object's centre than its bounding radius.
    dirs = _SPHERE_DIRS
    _, dist = station.first_hit(np.repeat(position[None], len(dirs), 0), dirs)
    if (dist < radius * 1.05).any():
        return False, 0.0, "intersects the station"
    if anomaly is None:
        anomaly = anomaly_scene(anomaly_points, anomaly_tris)
    frac = visible_fraction(station, anomaly, cam_pos, cam_rot, width, height, rays, (position, radius),
                            (position, rotation))
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
          min_fraction: float = MIN_FRACTION, anomaly: Scene | None = None) -> list[Placement]:
    """Place one object and its four extra depths; raises PlacementError if no initial placement.
    `anomaly`: the object's BVH in its own frame (`anomaly_scene`), if cached by the caller."""
    cw = check_width or width
    ch = max(1, round(height * cw / width))
    cam_pos = np.asarray(cam_pos, dtype=np.float64)
    station = station_parts if isinstance(station_parts, Scene) else Scene(station_parts)
    radius = float(np.linalg.norm(anomaly_points, axis=1).max())
    if anomaly is None:
        anomaly = anomaly_scene(anomaly_points, anomaly_tris)
    for attempt in range(1, max_attempts + 1):
        u, v = rng.uniform(0.15, 0.85), rng.uniform(0.15, 0.85)
        px, py = int(u * cw), int(v * ch)
        ray = pixel_rays(cam_pos, cam_rot, cw, ch, [py * cw + px])[1][0]
        _, hit = station.first_hit(cam_pos[None].astype(np.float64), ray[None])
        far = hit[0] - radius - 0.5 if np.isfinite(hit[0]) else 12.0
        near = 1.0 + radius
        if far <= near:
            continue
        depth = rng.uniform(max(near, far - 6.0), far)
        rot = random_rotation(rng)
        pos = cam_pos + depth * ray
        ok, frac, _ = check(station, anomaly_points, anomaly_tris, pos, rot, cam_pos, cam_rot, cw, ch,
                            min_fraction, None, anomaly)
        if not ok:
            continue
        out = []
        for k, off in enumerate(DEPTH_OFFSETS):
            p = cam_pos + (depth + off) * ray
            if off == 0.0:
                out.append(Placement(k, off, p, rot, frac, attempt))
                continue
            ok_k, frac_k, why = check(station, anomaly_points, anomaly_tris, p, rot, cam_pos, cam_rot,
                                      cw, ch, min_fraction, None, anomaly)
            out.append(Placement(k, off, p if ok_k else None, rot, frac_k, attempt, "" if ok_k else why))
        return out
    raise PlacementError(f"no visible placement in {max_attempts} attempts (object radius {radius:.2f} m); "
                         "the view may show no station nearby — use another pose or a smaller object")
