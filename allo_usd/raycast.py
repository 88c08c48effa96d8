"""Ray casting against known meshes (trimesh + embree): visibility and pixel areas without rendering."""

from __future__ import annotations

import numpy as np

from .geometry import camera_intrinsics


class Scene:
    """Triangles tagged by owner id (1 station, 2 anomaly), one embree BVH over all of them."""

    def __init__(self, parts: list[tuple[np.ndarray, np.ndarray, int]]):
        import trimesh

        pts, tris, owner, off = [], [], [], 0
        for p, t, oid in parts:
            pts.append(np.asarray(p, dtype=np.float64))
            tris.append(np.asarray(t, dtype=np.int64) + off)
            owner.append(np.full(len(t), oid, dtype=np.uint8))
            off += len(p)
        self.mesh = trimesh.Trimesh(np.concatenate(pts), np.concatenate(tris), process=False)
        self.owner = np.concatenate(owner)
        self.intersector = trimesh.ray.ray_pyembree.RayMeshIntersector(self.mesh)

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(owner id or 0, distance or inf) of the first hit of each ray."""
        locs, ray_idx, tri_idx = self.intersector.intersects_location(origins, dirs, multiple_hits=False)
        owner = np.zeros(len(origins), dtype=np.uint8)
        dist = np.full(len(origins), np.inf)
        if len(ray_idx):
            owner[ray_idx] = self.owner[tri_idx]
            dist[ray_idx] = np.linalg.norm(locs - origins[ray_idx], axis=1)
        return owner, dist


    def inside(self, point: np.ndarray) -> bool:
        """Parity test: a point is enclosed when most of 7 rays cross the surface an odd number of
        times (a majority vote tolerates small holes in non-watertight meshes)."""
        dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                         [0.577, 0.577, 0.577]], dtype=np.float64)
        origins = np.repeat(np.asarray(point, dtype=np.float64)[None], len(dirs), 0)
        _, ray_idx, _ = self.intersector.intersects_location(origins, dirs, multiple_hits=True)
        crossings = np.bincount(ray_idx, minlength=len(dirs))
        return int((crossings % 2 == 1).sum()) >= 4


def pixel_rays(cam_pos, cam_rot, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """One ray through each pixel centre, row-major from the top-left pixel."""
    k = camera_intrinsics(width, height)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (u - k[0, 2]) / k[0, 0]
    y = -(v - k[1, 2]) / k[1, 1]
    d_cam = np.stack([x, y, -np.ones_like(x)], axis=-1).reshape(-1, 3)
    d = d_cam @ np.asarray(cam_rot).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(np.asarray(cam_pos, dtype=np.float64), d.shape).copy()
    return o, d


def class_image(scene: Scene, cam_pos, cam_rot, width: int, height: int) -> np.ndarray:
    """(H, W) uint8 owner ids seen at each pixel centre: a geometric mask."""
    o, d = pixel_rays(cam_pos, cam_rot, width, height)
    owner, _ = scene.first_hit(o, d)
    return owner.reshape(height, width)
