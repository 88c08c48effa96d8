"""Anomaly placement in the view frustum, checked by ray casting (never by rendering).

A (day, pose, asset) group places one object at five depths along one pixel ray: an initial depth
and +-1 m, +-2 m (`DEPTH_OFFSETS`). An attempt draws a point in the central part of the frame
whose ray meets the station, a uniformly random orientation, and an initial depth on that ray so
that all five depths fit between the camera and the station surface the ray meets and the
farthest (+2 m) one still looks big enough (from the object's measured silhouette on that ray);
the +2 m depth is drawn within `DEPTH_SPREAD_M` of the farthest such point, so objects sit near the
structure behind them whenever their size allows. A depth passes when the object stays clear of
the camera, does not touch the station, has station structure within `NEAR_STRUCTURE_M`, and
covers at least `min_fraction` of the image at pixel centres. Attempts are redrawn until all five
depths pass (at most `max_attempts`); only then does the group fall back to its best attempt, and
each depth that fails is reported as skipped with its reason, never silently dropped.

Checks run first at `SCREEN_WIDTH` (cheap); an attempt that passes there is confirmed at the render
resolution, and the fractions recorded are those at the render resolution: every pixel centre in
the object's image box for objects up to `EXACT_PIXELS` pixels, a regular sub-grid with at least
that many samples on the object for larger ones (sub-percent error, far from the threshold).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from allo_usd.core.labels import ANOMALY
from allo_usd.core.errors import PlacementError
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.geometry import box_corners, camera_intrinsics, fibonacci_sphere, quat_to_matrix
from allo_usd.scene.raycast import (RayFan, RayScene, intrinsic_rows, pixel_ray_columns, pixel_rays,
                                    subgrid_ray_columns)
from allo_usd.core import fixedmath as fm

DEPTH_OFFSETS = (0.0, -1.0, 1.0, -2.0, 2.0)
MIN_FRACTION = 0.001
NEAR_STRUCTURE_M = 5.0     # every placed object has station structure within this distance of its centre
CAMERA_CLEARANCE_M = 0.25  # and its bounding sphere stays this far in front of the camera
DEPTH_SPREAD_M = 3.0       # the +2 m depth is drawn within this of the farthest point that can pass
MAX_ATTEMPTS = 100         # candidate placements per (day, pose, asset) group
PARTIAL_ATTEMPTS = 12      # if the first this many draws all lack room for five depths, stop drawing
FALLBACK_CHECKS = 4        # then (or after max_attempts) this many draws are checked for the best partial group
SCREEN_WIDTH = 480         # candidates are screened at this width, then confirmed at the render's
EXACT_PIXELS = 2000        # objects up to 4x this many render pixels are counted at every pixel
FRAME_REGION = (0.15, 0.85)  # the part of the frame (both axes) an object's centre is drawn in
_TARGET_GRID = (24, 14)    # rays over FRAME_REGION that find the station structure to place near
_SCREEN_ORDER = (4, 3, 0, 2, 1)  # depths screened first: +2 m (small, touching), -2 m (at the camera)


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
    return quat_to_matrix(q / fm.norm(q))


def _bounds_to_pixels(width: int, height: int, u0: float, u1: float, v0: float, v1: float):
    """(i0, i1, j0, j1): the pixels whose centre lies in image box [u0, u1] x [v0, v1], widened by
    one pixel and clipped to the image (empty when i0 > i1 or j0 > j1)."""
    i0, i1 = max(0, int(np.floor(u0 - 0.5)) - 1), min(width - 1, int(np.ceil(u1 - 0.5)) + 1)
    j0, j1 = max(0, int(np.floor(v0 - 0.5)) - 1), min(height - 1, int(np.ceil(v1 - 0.5)) + 1)
    return i0, i1, j0, j1


def _sphere_box(cam_pos, cam_rot, width: int, height: int, centre, radius: float, lens: CameraModel = DEFAULT_CAMERA):
    """The sphere's exact image-space bounding box (tangent planes through the camera) as pixel
    bounds, or None when the sphere reaches the camera plane (then every pixel is a candidate)."""
    (fx, _, cx), (_, fy, cy), _ = intrinsic_rows(width, height, lens)
    c0, c1, c2 = fm.matmul(np.asarray(centre, dtype=np.float64) - np.asarray(cam_pos, dtype=np.float64),
                           np.asarray(cam_rot, dtype=np.float64)).tolist()
    depth = -c2
    if depth <= radius * 1.01:
        return None
    bounds = []
    for lateral in (c0, c1):
        h = fm.hypot(lateral, depth)
        theta, beta = fm.arctan2(lateral, depth), fm.arcsin(min(1.0, radius / h))
        bounds.append((fm.tan(theta - beta), fm.tan(theta + beta)))
    (sx0, sx1), (sy0, sy1) = bounds
    return _bounds_to_pixels(width, height, sx0 * fx + cx, sx1 * fx + cx, cy - sy1 * fy, cy - sy0 * fy)


def _corner_box(cam_pos, cam_rot, width: int, height: int, corners, lens: CameraModel = DEFAULT_CAMERA):
    """Pixel bounds of points' projections (a convex object's box corners), or None when any lies
    on or behind the camera plane. Perspective maps a convex set in front of the camera to the
    convex hull of its corners' images, so every pixel whose ray meets the object is inside."""
    k = intrinsic_rows(width, height, lens)
    c = fm.matmul(np.asarray(corners, dtype=np.float64) - np.asarray(cam_pos, dtype=np.float64), np.asarray(cam_rot))
    depth = -c[:, 2]
    if depth.min() <= 1e-6:
        return None
    u = k[0][0] * c[:, 0] / depth + k[0][2]
    v = k[1][2] - k[1][1] * c[:, 1] / depth
    return _bounds_to_pixels(width, height, u.min(), u.max(), v.min(), v.max())


_PART_LEVELS = 6         # an object's image is bounded by those of 2^6 part boxes (raycast.RayScene.part_boxes)


def _box_indices(box, width: int, stride: int = 1) -> np.ndarray:
    """Row-major indices of the pixels in `box`; with `stride` s > 1, only those whose column and
    row are both s // 2 modulo s (a fixed sub-grid of the whole image, one pixel per s x s)."""
    i0, i1, j0, j1 = box
    phase = stride // 2
    i0, j0 = i0 + (phase - i0) % stride, j0 + (phase - j0) % stride
    if i0 > i1 or j0 > j1:
        return np.zeros(0, dtype=np.int64)
    return (np.arange(j0, j1 + 1, stride)[:, None] * width + np.arange(i0, i1 + 1, stride)[None, :]).ravel()


class _Cells(NamedTuple):
    """Pixels of a sub-grid, in row-major order: the one in column xs[ii[k]] and row ys[jj[k]] for each
    k (raycast.subgrid_ray_columns casts them without row-major numbers)."""
    xs: np.ndarray
    ys: np.ndarray
    ii: np.ndarray
    jj: np.ndarray

    def index(self, width: int) -> np.ndarray:
        """Their row-major pixel numbers in an image `width` pixels wide."""
        return self.ys[self.jj] * width + self.xs[self.ii]


def _parts_pixels(anomaly: RayScene, cam_pos, cam_rot, width: int, height: int, pose, stride: int = 1,
                  lens: CameraModel = DEFAULT_CAMERA) -> _Cells | None:
    """The pixels (on the stride sub-grid, as _Cells) whose centre lies in the image box, widened by
    CULL_MARGIN_PX, of some part of the object (`anomaly` in its own frame, posed by `pose`; its
    parts are `RayScene.part_boxes`), or None when a part's corner lies on or behind the camera
    plane. A part's image lies in the convex hull of its box corners' images, and each triangle's
    in its part's, so a ray that meets the object passes through one of these pixels: a cull that
    leaves the count unchanged (the margin's bound is CULL_MARGIN_PX's).

    Only the set matters, not the bits of the projection (a ray not cast is one that cannot hit),
    so the corners are taken to the camera frame by one composed 3x3 map (fm.matmul) and
    elementwise products (the same on every CPU): a few microseconds, where bounding sphere,
    corner box and per-triangle footprints cost ten times the rays they saved."""
    (fx, _, cx), (_, fy, cy), _ = intrinsic_rows(width, height, lens)
    q0, q1, q2 = anomaly.part_corner_columns(_PART_LEVELS)
    cam = np.asarray(cam_rot, dtype=np.float64).tolist()
    # camera frame: (R q + d) @ C, i.e. column j = sum_k q_k a[k][j] + b[j] with a = R^T C, b = d @ C
    a = fm.matmul_lists(np.asarray(pose[1], dtype=np.float64).T.tolist(), cam)
    (b,) = fm.matmul_lists([(np.asarray(pose[0], dtype=np.float64) - np.asarray(cam_pos, dtype=np.float64)).tolist()],
                           cam)
    depth = -(q0 * a[0][2] + q1 * a[1][2] + q2 * a[2][2] + b[2])
    if depth.min() <= 1e-6:
        return None
    inv = 1.0 / depth
    uv = np.empty((2, len(q0)))                    # u, then v, of every corner
    uv[0] = (q0 * a[0][0] + q1 * a[1][0] + q2 * a[2][0] + b[0]) * inv * fx + cx
    uv[1] = cy - (q0 * a[0][1] + q1 * a[1][1] + q2 * a[2][1] + b[1]) * inv * fy
    uv = uv.reshape(2, -1, 8)
    return _rects_union(width, height, stride, uv.min(axis=2), uv.max(axis=2))


CULL_MARGIN_PX = 0.05
"""How far outside a part box's exact image (in pixels) a cast pixel centre may lie. The box holds its
triangles in float64; embree sees them, and each ray, in float32 in a frame scaled to a ~100-unit
box, and its triangle test is watertight to about an ulp: together under 1e-3 pixel for any object
the placement accepts (it stays CAMERA_CLEARANCE_M in front of the camera, where a pixel spans over
1e-4 m, against float32 errors near 1e-7 m). The margin is 50 times that, and
tests/scene/test_rig_placement.py checks the cull against every pixel the 16 hazard objects cover, at 64
to 1920 pixels wide, from the clearance out to 40 m. A whole pixel of margin would cast 17% more
rays for the same counts."""


def _rects_union(width: int, height: int, stride: int, lo: np.ndarray, hi: np.ndarray) -> _Cells:
    """The pixels of the image on the stride sub-grid (column and row both s // 2 modulo s) whose
    centre lies within CULL_MARGIN_PX of at least one image box [lo[0], hi[0]] x [lo[1], hi[1]] (u
    then v, one column per box): each box marked on a grid over the sub-grid cells that any of them
    reaches (a few dozen part boxes). Both axes go through each step together, since numpy's
    per-call cost, not the arithmetic, is most of a call."""
    phase, m = stride // 2, CULL_MARGIN_PX
    if phase >= width or phase >= height:
        none = np.zeros(0, dtype=np.int64)
        return _Cells(none, none, none, none)
    # pixel k's centre k + 0.5 lies in [lo - m, hi + m] when ceil(lo - 0.5 - m) <= k <= floor(hi - 0.5 + m);
    # sub-grid cell t is pixel phase + stride * t
    first = np.ceil(lo - (0.5 + m)).astype(np.int64)
    last = np.floor(hi - (0.5 - m)).astype(np.int64)
    if stride == 1:                                # phase 0: the cells are the pixels
        first = np.maximum(first, 0)
        last = np.minimum(last, [[width - 1], [height - 1]])
    else:
        first = np.maximum(-((phase - first) // stride), 0)
        last = np.minimum((last - phase) // stride, [[(width - 1 - phase) // stride], [(height - 1 - phase) // stride]])
    some = (first <= last).all(axis=0)
    if not some.all():
        if not some.any():
            none = np.zeros(0, dtype=np.int64)
            return _Cells(none, none, none, none)
        first, last = first[:, some], last[:, some]
    (c0, w0), (c1, w1) = first.min(axis=1).tolist(), last.max(axis=1).tolist()
    covered = np.zeros((w1 - w0 + 1, c1 - c0 + 1), dtype=bool)
    (cs, rs), (ce, re) = (first - [[c0], [w0]]).tolist(), (last - [[c0 - 1], [w0 - 1]]).tolist()
    for a, b, c, d in zip(rs, re, cs, ce):
        covered[a:b, c:d] = True
    jj, ii = np.nonzero(covered)
    if stride == 1:
        return _Cells(np.arange(c0, c1 + 1), np.arange(w0, w1 + 1), ii, jj)
    return _Cells(phase + stride * np.arange(c0, c1 + 1), phase + stride * np.arange(w0, w1 + 1), ii, jj)


def sphere_pixels(cam_pos, cam_rot, width: int, height: int, centre, radius: float,
                  lens: CameraModel = DEFAULT_CAMERA) -> np.ndarray | None:
    """Row-major indices of the pixels whose centre ray may pass within `radius` of `centre`: the
    sphere's exact image-space bounding box (tangent planes through the camera), widened by one
    pixel. None when the sphere reaches the camera plane (then every pixel is a candidate)."""
    box = _sphere_box(cam_pos, cam_rot, width, height, centre, radius, lens)
    return None if box is None else _box_indices(box, width)


def visible_fraction(station: RayScene | None, anomaly: RayScene, cam_pos, cam_rot, width: int, height: int,
                     rays=None, sphere=None, pose=None, corners=None, stride: int = 1,
                     lens: CameraModel = DEFAULT_CAMERA) -> float:
    """Fraction of pixel centres whose first hit is the anomaly (station and anomaly BVHs kept apart,
    so the station's is built once per world and the anomaly's once per asset; `station` None:
    the object's silhouette alone).

    `rays`: the camera's pixel rays (`pixel_rays(cam_pos, cam_rot, width, height)`), if already
    computed. `sphere`: (centre, radius) bounding the anomaly; only rays that pass within it are
    cast (exact: a ray that misses the sphere cannot hit the anomaly). `pose`: (position,
    rotation) when `anomaly` holds the object in its own frame; the rays are then moved into that
    frame (p_obj = R^T (p - position)) instead of building a BVH for the posed object, and only
    the pixels inside the image box of some part of the object are cast (`_parts_pixels`: exact,
    and much tighter than the sphere for long, thin or hollow objects; the sphere test is then
    skipped). `corners`: the object's box corners in its own frame (`box_corners`), with `pose`:
    where a part reaches the camera plane, their projection narrows the sphere's pixels (also
    exact). `stride` s > 1 (with `sphere`): cast one pixel in s x s
    (`_box_indices`) and count each for s^2 pixels. Every cull only leaves out rays that cannot
    meet the object, so the count is the same whichever applies. `lens`: the camera's lens and sensor
    (core.camera_model; its principal point offset is in pixels of this width x height)."""
    if sphere is not None:
        c, r = np.asarray(sphere[0], dtype=np.float64), float(sphere[1]) * 1.001 + 1e-9
        cells = _parts_pixels(anomaly, cam_pos, cam_rot, width, height, pose, stride, lens) \
            if pose is not None and _PART_LEVELS else None
        fitted = cells is not None
        if fitted and rays is None:
            return _posed_fraction(station, anomaly, cam_pos, width, height, pose, stride, None,
                                   subgrid_ray_columns(cam_rot, width, height, *cells, lens))
        idx = cells.index(width) if fitted else None
        if not fitted:
            box = _sphere_box(cam_pos, cam_rot, width, height, c, r, lens)
            if corners is not None and pose is not None:
                world = np.asarray(pose[0], dtype=np.float64) + fm.apply(pose[1], corners)
                tight = _corner_box(cam_pos, cam_rot, width, height, world, lens)
                if tight is not None:
                    box = tight if box is None else (max(box[0], tight[0]), min(box[1], tight[1]),
                                                     max(box[2], tight[2]), min(box[3], tight[3]))
            if box is None and stride > 1:
                box = (0, width - 1, 0, height - 1)
            if box is not None:
                idx = _box_indices(box, width, stride)
        if rays is None and pose is not None:
            return _posed_fraction(station, anomaly, cam_pos, width, height, pose, stride, (c, r),
                                   pixel_ray_columns(cam_rot, width, height, idx, lens))
        if rays is None:
            o, d = pixel_rays(cam_pos, cam_rot, width, height, idx, lens)
        else:
            o, d = rays if idx is None else (rays[0][idx], rays[1][idx])
        if not len(o):
            return 0.0
        if not fitted:                                 # the parts' pixels are (nearly) only these
            v = c - o[0]                               # every ray starts at the camera
            t = fm.dot(d, v)
            miss = (fm.dot(v, v) - t * t > r * r) | (t < -r)
            keep = np.flatnonzero(~miss)
            if keep.size == 0:
                return 0.0
            o, d = o[keep], d[keep]
    else:
        if stride != 1:
            raise ValueError("stride needs sphere=(centre, radius)")
        o, d = pixel_rays(cam_pos, cam_rot, width, height, lens=lens) if rays is None else rays
    if pose is None:
        a_owner, a_dist = anomaly.first_hit(o, d)
    else:
        position, rotation = np.asarray(pose[0], dtype=np.float64), np.asarray(pose[1], dtype=np.float64)
        if rays is None:   # pixel_rays: every ray starts at the camera, so it is moved once (the same bits)
            origin = fm.matmul(np.asarray(cam_pos, dtype=np.float64)[None] - position, rotation)
            a_owner, a_dist = anomaly.first_hit(np.broadcast_to(origin, d.shape), fm.matmul(d, rotation))
        else:
            a_owner, a_dist = anomaly.first_hit(fm.matmul(o - position, rotation), fm.matmul(d, rotation))
    hit = a_owner > 0
    if not hit.any():
        return 0.0
    if station is None:
        return float(hit.sum() * stride * stride / (width * height))
    # Visible where no station surface lies between the camera and the object's surface.
    hidden = station.occluded(o[hit], d[hit], a_dist[hit])
    return float((~hidden).sum() * stride * stride / (width * height))


def _posed_fraction(station: RayScene | None, anomaly: RayScene, cam_pos, width: int, height: int, pose, stride: int,
                    sphere, columns) -> float:
    """`visible_fraction`'s count for camera rays (`columns`: pixel_ray_columns of the pixels cast) and an
    object posed by `pose`, component by component: the same operations in the same order as the
    (n, 3) form (the sphere cull's fm.dot, fm.matmul's sums, first_hit's), so the same bits, with
    the world-frame directions gathered only for the rays that hit the object. `sphere`: (centre,
    radius) to cull rays that pass outside it, None when a footprint already chose the pixels."""
    cam = np.asarray(cam_pos, dtype=np.float64)
    d0, d1, d2 = columns
    if not len(d0):
        return 0.0
    if sphere is not None:
        c, r = sphere
        v = c - cam                                    # every ray starts at the camera
        t = d0 * v[0]                                  # fm.dot(d, v), left to right
        t = t + d1 * v[1]
        t = t + d2 * v[2]
        miss = (fm.dot(v, v) - t * t > r * r) | (t < -r)
        keep = np.flatnonzero(~miss)
        if keep.size == 0:
            return 0.0
        d0, d1, d2 = d0[keep], d1[keep], d2[keep]
    position, rotation = np.asarray(pose[0], dtype=np.float64), np.asarray(pose[1], dtype=np.float64)
    (origin,) = fm.matmul_lists([(cam - position).tolist()], rotation.tolist())   # fm.matmul's sums
    local = []
    for j in range(3):                                 # fm.matmul(d, rotation), column by column
        col = d0 * rotation[0, j]
        col = col + d1 * rotation[1, j]
        local.append(col + d2 * rotation[2, j])
    rays, a_dist = anomaly.hits_from(np.array(origin), RayFan(*local), distances=station is not None)
    if not rays.size:
        return 0.0
    if station is None:
        return float(rays.size * stride * stride / (width * height))
    # Visible where no station surface lies between the camera and the object's surface.
    d = np.empty((rays.size, 3), dtype=np.float32)    # occluded's float32 copy, cast as it casts
    for j, comp in enumerate((d0, d1, d2)):
        d[:, j] = comp[rays]
    hidden = station.occluded(np.broadcast_to(cam, d.shape), d, a_dist)
    return float((~hidden).sum() * stride * stride / (width * height))


def anomaly_scene(anomaly_points, anomaly_tris) -> RayScene:
    """The object's BVH in its own frame, built once per asset and reused for every pose."""
    return RayScene([(anomaly_points, anomaly_tris, ANOMALY)])


def _clear_of(station: RayScene, position, radius: float, cam_pos, cam_rot) -> str:
    """Why a placement fails whatever the resolution ("" if it does not): its bounding sphere within
    CAMERA_CLEARANCE_M of the camera plane or behind it; a station surface closer to its centre
    than the bounding radius (touching), or none within NEAR_STRUCTURE_M (not near the station);
    both probed along 128 directions from the centre."""
    if fm.dot(position - cam_pos, -cam_rot[:, 2]) <= radius + CAMERA_CLEARANCE_M:
        return "behind or against the camera"
    _, dist = station.first_hit_fan(position, _SPHERE_FAN)   # first_hit from `position`, bit for bit
    if (dist < radius * 1.05).any():
        return "intersects the station"
    if dist.min() > NEAR_STRUCTURE_M:
        return f"farther than {NEAR_STRUCTURE_M:.0f} m from the station"
    return ""


def _visibility(station: RayScene, anomaly: RayScene, radius: float, corners, position, rotation, cam_pos, cam_rot,
                width: int, height: int, min_fraction: float, stride: int = 1,
                lens: CameraModel = DEFAULT_CAMERA) -> tuple[bool, float, str]:
    frac = visible_fraction(station, anomaly, cam_pos, cam_rot, width, height, None, (position, radius),
                            (position, rotation), corners, stride, lens)
    if frac == 0.0:
        return False, 0.0, "fully occluded or outside the frame"
    if frac < min_fraction:
        return False, frac, f"covers {frac:.4%} of the image, under {min_fraction:.1%}"
    return True, frac, ""


def check(station: RayScene, anomaly_points, anomaly_tris, position, rotation, cam_pos, cam_rot,
          width, height, min_fraction=MIN_FRACTION, rays=None, anomaly: RayScene | None = None,
          lens: CameraModel = DEFAULT_CAMERA) -> tuple[bool, float, str]:
    """(accepted, visible fraction at width x height, reason) for one candidate placement.
    `anomaly`: the object's BVH in its own frame (`anomaly_scene`), if already built."""
    cam_pos = np.asarray(cam_pos, dtype=np.float64)
    cam_rot = np.asarray(cam_rot, dtype=np.float64)
    position = np.asarray(position, dtype=np.float64)
    radius = float(fm.norm(anomaly_points, axis=1).max())
    why = _clear_of(station, position, radius, cam_pos, cam_rot)
    if why:
        return False, 0.0, why
    if anomaly is None:
        anomaly = anomaly_scene(anomaly_points, anomaly_tris)
    if rays is not None:
        frac = visible_fraction(station, anomaly, cam_pos, cam_rot, width, height, rays, (position, radius),
                                (position, rotation), lens=lens)
        if frac == 0.0:
            return False, 0.0, "fully occluded or outside the frame"
        if frac < min_fraction:
            return False, frac, f"covers {frac:.4%} of the image, under {min_fraction:.1%}"
        return True, frac, ""
    return _visibility(station, anomaly, radius, box_corners(anomaly_points), position, rotation, cam_pos,
                       cam_rot, width, height, min_fraction, 1, lens)


_SPHERE_DIRS = fibonacci_sphere(128)
_SPHERE_FAN = RayFan.of_rows(_SPHERE_DIRS)   # their unit vectors and float32 copy, made once


def _image_rays(cam_rot, k: np.ndarray, px, py) -> np.ndarray:
    """Unit world directions through image points (px, py) in pixels (continuous, from the top left)."""
    r = np.asarray(cam_rot, dtype=np.float64)
    x = (np.asarray(px, dtype=np.float64) - k[0, 2]) / k[0, 0]
    y = -(np.asarray(py, dtype=np.float64) - k[1, 2]) / k[1, 1]
    d = x[..., None] * r[:, 0] + y[..., None] * r[:, 1] - r[:, 2]
    return d / fm.norm(d, axis=-1, keepdims=True)


def _stride(fraction: float, n_pixels: int) -> int:
    """Sub-grid step for counting an object expected to cover `fraction` of `n_pixels`: 1 under
    4 x EXACT_PIXELS pixels (so every decision near the 0.1% threshold, 2,074 px at 1920x1080, is
    exact), else the largest step that keeps EXACT_PIXELS samples on it."""
    return max(1, int(np.sqrt(fraction * n_pixels / EXACT_PIXELS)))


def _extent(anomaly: RayScene, points) -> tuple[float, np.ndarray]:
    """(bounding radius, box_corners) of an object's points in its own frame, kept on its BVH (built
    once per asset) for as long as the caller passes the same points array: every group of an
    asset needs them, and the points can be thousands."""
    kept = anomaly.memo.get("extent")
    if kept is None or kept[0] is not points:
        kept = anomaly.memo["extent"] = (points, float(fm.norm(points, axis=1).max()), box_corners(points))
    return kept[1], kept[2]


class _Group:
    """One (day, pose, asset) group's fixed inputs and per-(attempt, depth) caches, so that placing
    it reads as steps (draw, room, screen, confirm, fall back) with nothing recomputed."""

    def __init__(self, station_parts, anomaly_points, anomaly_tris, cam_pos, cam_rot, width: int, height: int,
                 check_width: int | None, min_fraction: float, anomaly: RayScene | None,
                 lens: CameraModel = DEFAULT_CAMERA):
        self.cam_pos = np.asarray(cam_pos, dtype=np.float64)
        self.cam_rot = np.asarray(cam_rot, dtype=np.float64)
        self.station = station_parts if isinstance(station_parts, RayScene) else RayScene(station_parts)
        self.anomaly = anomaly_scene(anomaly_points, anomaly_tris) if anomaly is None else anomaly
        self.radius, self.corners = _extent(self.anomaly, anomaly_points)
        self.min_fraction = min_fraction
        self.width, self.height = width, height
        self.full = (int(width), int(height))
        self.screen = self.full if not check_width or check_width >= width else \
            (int(check_width), max(1, round(height * check_width / width)))
        self.k = camera_intrinsics(width, height, lens)
        # The lens at each checked size: its principal point offset is in pixels of the full size.
        self.lenses = {self.full: lens, self.screen: lens.scaled(self.screen[0] / width)}
        self.nearest = self.radius + CAMERA_CLEARANCE_M + 1e-6  # the closest an object's centre may come (depth)
        self.ref = max(self.nearest, 8.0 * self.radius)         # where an attempt measures the object's silhouette
        # A draw's checks are pure functions of (attempt, depth), so each is computed once: the
        # fallback reuses the screening of the main loop, and the render-resolution pass reuses
        # the resolution-free clearance test (speed only; every decision is the same).
        self.clear: dict[tuple[int, int], str] = {}
        self.screened: dict[tuple[int, int], tuple[bool, float, str]] = {}
        self._find_station()

    def _find_station(self) -> None:
        """Cast rays through a grid over the central part of the frame: candidates are drawn only in
        cells whose ray meets the station, so objects land in front of structure."""
        lo, hi = FRAME_REGION
        gx, gy = _TARGET_GRID
        px, py = np.meshgrid((lo + (hi - lo) * (np.arange(gx) + 0.5) / gx) * self.width,
                             (lo + (hi - lo) * (np.arange(gy) + 0.5) / gy) * self.height)
        self.px, self.py = px.ravel(), py.ravel()
        _, grid_hit = self.station.first_hit(np.broadcast_to(self.cam_pos, (self.px.size, 3)),
                                             _image_rays(self.cam_rot, self.k, self.px, self.py))
        self.cells = np.flatnonzero(np.isfinite(grid_hit))
        if self.cells.size == 0:
            raise PlacementError(f"the camera sees no station structure in the central {hi - lo:.0%} of its frame, "
                                 "so an object cannot be placed near it; use a pose that looks at the station")
        self.cell_w, self.cell_h = (hi - lo) * self.width / gx, (hi - lo) * self.height / gy

    def draw(self, rng: np.random.Generator):
        """(ray, u, rotation) of one candidate: a ray jittered within a grid cell that meets the station,
        the initial-depth draw and an orientation; the generator calls' order fixes authored layers."""
        c = self.cells[rng.integers(self.cells.size)]
        ray = _image_rays(self.cam_rot, self.k, self.px[c] + (rng.random() - 0.5) * self.cell_w,
                          self.py[c] + (rng.random() - 0.5) * self.cell_h)
        u = rng.random()
        rot = random_rotation(rng)
        return ray, u, rot

    def room(self, ray, rot) -> float | None:
        """The farthest centre depth on `ray` that clears the station and still looks big enough, or
        None when that is not beyond `nearest` (no depth can pass on this ray)."""
        _, hit = self.station.first_hit(self.cam_pos[None], ray[None])
        surface = float(hit[0]) - 1.05 * self.radius      # the farthest the centre may sit on this ray
        if not surface > self.nearest:
            return None
        # The object's silhouette at depth `ref` on this ray gives the farthest depth at which it
        # still covers min_fraction (coverage falls as 1/depth^2); 0.95 keeps a margin.
        at = self.cam_pos + self.ref * ray
        silhouette = visible_fraction(None, self.anomaly, self.cam_pos, self.cam_rot, *self.screen, None,
                                      (at, self.radius), (at, rot), self.corners, 1,
                                      self.lenses[self.screen])
        top = min(surface, 0.95 * self.ref * np.sqrt(silhouette / self.min_fraction))
        return top if top > self.nearest else None

    def initial_depth(self, top: float, u: float) -> float:
        """The initial depth for a ray with room for all five: the +2 m depth drawn within
        DEPTH_SPREAD_M of `top`, so objects sit near the structure behind them."""
        reach = max(DEPTH_OFFSETS)
        deepest = top - reach
        return deepest - u * min(DEPTH_SPREAD_M, deepest - self.nearest - reach)

    def one(self, attempt, depth_index, ray, depth, rot, size, stride=1):
        """(passes, fraction, reason) of one depth at `size`; the clearance test is cached because it
        does not depend on the resolution."""
        pos = self.cam_pos + (depth + DEPTH_OFFSETS[depth_index]) * ray
        if (attempt, depth_index) not in self.clear:
            self.clear[attempt, depth_index] = _clear_of(self.station, pos, self.radius, self.cam_pos, self.cam_rot)
        why = self.clear[attempt, depth_index]
        if why:
            return False, 0.0, why
        return _visibility(self.station, self.anomaly, self.radius, self.corners, pos, rot, self.cam_pos,
                           self.cam_rot, *size, self.min_fraction, stride, self.lenses[size])

    def at_screen(self, attempt, depth_index, ray, depth, rot):
        """One depth at the cheap screening size, cached so the fallback reuses the main loop's work."""
        if (attempt, depth_index) not in self.screened:
            self.screened[attempt, depth_index] = self.one(attempt, depth_index, ray, depth, rot, self.screen)
        return self.screened[attempt, depth_index]

    def at_full(self, attempt, ray, depth, rot, coarse, all_or_nothing=False):
        """Each depth re-checked at the render resolution (`coarse`: the screen results). With
        `all_or_nothing`, stop at the first depth that fails (the caller needs them all to pass)."""
        if self.screen == self.full:
            return coarse
        out = []
        for i, c in enumerate(coarse):
            out.append(self.one(attempt, i, ray, depth, rot, self.full, _stride(c[1], self.width * self.height))
                       if c[0] else c)
            if all_or_nothing and not out[-1][0]:
                break
        return out

    def all_five(self, attempt, ray, depth, rot):
        """The five depths' results when every one passes at the screen and the render resolution, else
        None; screening runs likeliest failures first and stops at the first, as most draws fail."""
        coarse = []
        for i in _SCREEN_ORDER:
            coarse.append((i, self.at_screen(attempt, i, ray, depth, rot)))
            if not coarse[-1][1][0]:
                return None
        results = self.at_full(attempt, ray, depth, rot, [r for _, r in sorted(coarse)], all_or_nothing=True)
        return results if all(r[0] for r in results) else None

    def fallback(self, drawn, budget: int) -> list[Placement] | None:
        """No draw passed at every depth: of the first few draws (most depths fitting first), the best
        ranked (`_ranked`) whose initial depth holds at the render resolution, so a group still gets
        as many depths as it can, each failing one reported; None when none holds."""
        kept = {attempt: (ray, depth, rot) for _, attempt, ray, depth, rot
                in sorted(drawn, key=lambda t: t[:2])[:FALLBACK_CHECKS]}
        for attempt in _ranked(list(kept), lambda a, i: self.at_screen(a, i, *kept[a])[0]):
            ray, depth, rot = kept[attempt]
            coarse = [self.at_screen(attempt, i, ray, depth, rot) for i in range(len(DEPTH_OFFSETS))]
            results = self.at_full(attempt, ray, depth, rot, coarse)
            if results[0][0]:
                return _placements(self.cam_pos, ray, depth, rot, results, budget)
        return None


def place(station_parts: "RayScene | list", anomaly_points, anomaly_tris, cam_pos, cam_rot, rng: np.random.Generator,
          width: int, height: int, max_attempts: int = MAX_ATTEMPTS, check_width: int | None = SCREEN_WIDTH,
          min_fraction: float = MIN_FRACTION, anomaly: RayScene | None = None,
          lens: CameraModel = DEFAULT_CAMERA) -> list[Placement]:
    """Place one object at all five depths (see the module doc); raises PlacementError when no
    attempt gives even a valid initial depth. `check_width`: the width candidates are screened at
    (None or >= width: every check at width x height); accepted depths are always confirmed, and
    their fractions computed, at width x height. `anomaly`: the object's BVH in its own frame
    (`anomaly_scene`), if cached by the caller. `lens`: the camera (core.camera_model; default the
    paper's), its principal point offset in pixels of width x height."""
    group = _Group(station_parts, anomaly_points, anomaly_tris, cam_pos, cam_rot, width, height, check_width,
                   min_fraction, anomaly, lens)
    drawn = []                                      # (-depths that fit, attempt, ray, depth, rot)
    budget, short = max_attempts, 0
    for attempt in range(1, max_attempts + 1):
        ray, u, rot = group.draw(rng)
        top = group.room(ray, rot)
        if top is None:
            continue
        fits = min(len(DEPTH_OFFSETS), int(np.floor(top - group.nearest)) + 1)   # depths that fit in [nearest, top]
        if fits < len(DEPTH_OFFSETS):                # too little room for five: as many as fit
            drawn.append((-fits, attempt, ray, _partial_depth(group.nearest, top, u), rot))
            short += 1
            if short == len(drawn) == PARTIAL_ATTEMPTS:  # the first draws all too short: the object is
                budget = attempt                     # too small (or the view too cramped) for five
                break
            continue
        depth = group.initial_depth(top, u)
        drawn.append((-fits, attempt, ray, depth, rot))
        results = group.all_five(attempt, ray, depth, rot)
        if results is not None:
            return _placements(group.cam_pos, ray, depth, rot, results, attempt)
    placements = group.fallback(drawn, budget)
    if placements is None:
        raise PlacementError(f"no visible placement in {budget} attempts (object radius {group.radius:.2f} m); "
                             "the view may show no station nearby — use another pose or a smaller object")
    return placements


def _ranked(attempts: list[int], passes):
    """The attempts whose initial depth passes at the screen width, in order of (most depths passing,
    earliest attempt), as screening each in full would rank them; `passes(attempt, depth)` screens
    one depth. A draw is screened only as far as its rank needs: the one with the most depths that
    could still pass is screened further (likeliest failures first), and comes next once complete."""
    known: dict[tuple[int, int], bool] = {}

    def ok(a: int, i: int) -> bool:
        if (a, i) not in known:
            known[a, i] = bool(passes(a, i))
        return known[a, i]

    left = [a for a in attempts if ok(a, 0)]
    while left:
        best = min(left, key=lambda a: (-sum(known.get((a, i), True) for i in range(len(DEPTH_OFFSETS))), a))
        todo = [i for i in _SCREEN_ORDER if (best, i) not in known]
        if todo:
            ok(best, todo[0])
            continue
        yield best
        left.remove(best)


def _partial_depth(nearest: float, top: float, u: float) -> float:
    """An initial depth for a ray with room for fewer than five depths in [nearest, top]: one that
    keeps as many of them as fit (n = floor(top - nearest) + 1), drawn with `u` in [0, 1) among
    those positions (a = how many of the n lie before the initial one)."""
    room = top - nearest
    n = min(len(DEPTH_OFFSETS), int(np.floor(room)) + 1)
    below = [a for a in range(n) if a <= 2 and n - 1 - a <= 2]
    x = u * len(below)
    a = below[min(int(x), len(below) - 1)]
    return nearest + a + (x - int(x)) * (room - (n - 1))



def _placements(cam_pos, ray, depth, rot, results, attempts: int) -> list[Placement]:
    out = []
    for k, (off, (ok, frac, why)) in enumerate(zip(DEPTH_OFFSETS, results)):
        pos = cam_pos + (depth + off) * ray
        out.append(Placement(k, off, pos if ok else None, rot, frac, attempts, "" if ok else why))
    return out
