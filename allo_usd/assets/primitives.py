"""Mesh primitives in metres, numpy only, shared by every procedural builder.

Every function returns a MeshPart with outward-facing counter-clockwise faces. Placement is
by an optional 4x4 matrix (see `transform`); rotations are built in float64.
"""

from __future__ import annotations

import numpy as np

from ..mesh import MeshPart


def transform(translate=(0.0, 0.0, 0.0), rotate: np.ndarray | None = None, scale=1.0) -> np.ndarray:
    """4x4 matrix = T @ R @ S (float64)."""
    m = np.eye(4)
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    r = np.eye(3) if rotate is None else np.asarray(rotate, dtype=np.float64)
    m[:3, :3] = r * s[None, :]
    m[:3, 3] = translate
    return m


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def frame_from_z(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third column is unit(axis): maps local +Z onto `axis`."""
    z = np.asarray(axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _place(part: MeshPart, matrix: np.ndarray | None) -> MeshPart:
    return part if matrix is None else part.transformed(matrix)


def box(name: str, size, material: str, matrix: np.ndarray | None = None, uv_scale: float = 1.0) -> MeshPart:
    """Axis-aligned box of `size` (sx, sy, sz) centred at the origin; 24 vertices, hard edges.

    UVs map each face to [0, size_u * uv_scale] x [0, size_v * uv_scale], so a tiling texture
    keeps its scale in metres.
    """
    sx, sy, sz = (np.asarray(size, dtype=np.float64) / 2.0)
    faces = [  # (normal axis, sign) -> four corners CCW from outside
        [(-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)],      # +z
        [(-1, -1, -1), (-1, 1, -1), (1, 1, -1), (1, -1, -1)],  # -z
        [(1, -1, -1), (1, 1, -1), (1, 1, 1), (1, -1, 1)],      # +x
        [(-1, -1, -1), (-1, -1, 1), (-1, 1, 1), (-1, 1, -1)],  # -x
        [(-1, 1, -1), (-1, 1, 1), (1, 1, 1), (1, 1, -1)],      # +y
        [(-1, -1, -1), (1, -1, -1), (1, -1, 1), (-1, -1, 1)],  # -y
    ]
    half = np.array([sx, sy, sz])
    pts = np.array([c for f in faces for c in f], dtype=np.float64) * half
    counts = np.full(6, 4)
    idx = np.arange(24)
    uv = []
    for f in faces:
        c = np.array(f, dtype=np.float64) * half
        span = c.max(axis=0) - c.min(axis=0)
        axes = [i for i in range(3) if span[i] > 0] or [0, 1]
        a, b = (axes + [0, 1])[:2]
        uv.extend(((c[:, [a, b]] - c[:, [a, b]].min(axis=0)) * uv_scale).tolist())
    return _place(MeshPart(name, pts, counts, idx, material, np.array(uv)), matrix)


def cylinder(name: str, radius: float, length: float, material: str, segments: int = 24,
             matrix: np.ndarray | None = None, caps: bool = True, radius_top: float | None = None) -> MeshPart:
    """Cylinder (or cone frustum) along local +Z from z=0 to z=length, smooth sides, flat caps."""
    r0, r1 = float(radius), float(radius if radius_top is None else radius_top)
    t = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t)], axis=1)
    bottom = np.column_stack([ring * r0, np.zeros(segments)])
    top = np.column_stack([ring * r1, np.full(segments, length)])
    pts = [bottom, top]
    i = np.arange(segments)
    j = (i + 1) % segments
    faces = np.stack([i, j, j + segments, i + segments], axis=1)
    counts = [np.full(segments, 4)]
    indices = [faces.ravel()]
    uv = [np.stack([
        np.stack([i / segments, np.zeros(segments)], 1), np.stack([(i + 1) / segments, np.zeros(segments)], 1),
        np.stack([(i + 1) / segments, np.ones(segments)], 1), np.stack([i / segments, np.ones(segments)], 1),
    ], axis=1).reshape(-1, 2) * np.array([2 * np.pi * max(r0, r1), length])]
    if caps:
        base = 2 * segments
        pts += [bottom, top]  # duplicated rims so smooth sides do not bend the cap normals
        counts += [np.array([segments]), np.array([segments])]
        indices += [base + i[::-1], base + segments + i]
        cap_uv = (ring * 0.5 + 0.5) * 2 * max(r0, r1)
        uv += [cap_uv[::-1], cap_uv]
    part = MeshPart(name, np.concatenate(pts), np.concatenate(counts), np.concatenate(indices),
                    material, np.concatenate(uv), smooth=True)
    return _place(part, matrix)


def cylinder_between(name: str, a, b, radius: float, material: str, segments: int = 16, caps: bool = True) -> MeshPart:
    """Cylinder from point a to point b."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    axis = b - a
    return cylinder(name, radius, float(np.linalg.norm(axis)), material, segments,
                    transform(a, frame_from_z(axis)), caps)


def uv_sphere(name: str, radius: float, material: str, segments: int = 32, rings: int = 16,
              matrix: np.ndarray | None = None) -> MeshPart:
    """Sphere centred at the origin, poles on Z, with equirectangular UVs (u along longitude)."""
    theta = np.linspace(0.0, np.pi, rings + 1)          # polar angle from +Z
    phi = np.linspace(0.0, 2 * np.pi, segments + 1)      # seam duplicated for UVs
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    pts = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3) * radius
    r, s = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    w = segments + 1
    a = r * w + s
    quads = np.stack([a, a + w, a + w + 1, a + 1], -1).reshape(-1, 4)
    uvs = np.stack([ph / (2 * np.pi), 1.0 - th / np.pi], -1).reshape(-1, 2)
    return _place(MeshPart(name, pts, np.full(len(quads), 4), quads.ravel(), material,
                           uvs[quads.ravel()], smooth=True), matrix)


def grid(name: str, size_u: float, size_v: float, material: str, nu: int = 1, nv: int = 1,
         matrix: np.ndarray | None = None, height: np.ndarray | None = None,
         double_sided_thickness: float = 0.0) -> MeshPart:
    """A flat nu x nv quad grid in the XY plane centred at the origin, facing +Z.

    `height` ((nv+1, nu+1) metres) displaces vertices along Z (crumpled sheets). UVs span
    [0, 1]^2. With double_sided_thickness > 0 a back face is added that thickness below.
    """
    u = np.linspace(-size_u / 2, size_u / 2, nu + 1)
    v = np.linspace(-size_v / 2, size_v / 2, nv + 1)
    uu, vv = np.meshgrid(u, v)
    zz = np.zeros_like(uu) if height is None else np.asarray(height, dtype=np.float64)
    pts = np.stack([uu, vv, zz], -1).reshape(-1, 3)
    r, s = np.meshgrid(np.arange(nv), np.arange(nu), indexing="ij")
    a = r * (nu + 1) + s
    quads = np.stack([a, a + 1, a + nu + 2, a + nu + 1], -1).reshape(-1, 4)
    uvgrid = np.stack([(uu - u[0]) / size_u, (vv - v[0]) / size_v], -1).reshape(-1, 2)
    all_pts, all_quads, all_uv = [pts], [quads], [uvgrid[quads.ravel()]]
    if double_sided_thickness > 0:
        back = pts - np.array([0.0, 0.0, double_sided_thickness])
        bq = quads[:, ::-1] + len(pts)
        all_pts.append(back)
        all_quads.append(bq)
        all_uv.append(uvgrid[quads[:, ::-1].ravel()])
    q = np.concatenate(all_quads)
    return _place(MeshPart(name, np.concatenate(all_pts), np.full(len(q), 4), q.ravel(), material,
                           np.concatenate(all_uv), smooth=height is not None), matrix)


def tube(name: str, path: np.ndarray, radius: float, material: str, segments: int = 12,
         caps: bool = True) -> MeshPart:
    """A tube of constant radius along a polyline (K, 3), with parallel-transported frames."""
    path = np.asarray(path, dtype=np.float64)
    k = len(path)
    tang = np.gradient(path, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    n = frame_from_z(tang[0])[:, 0]
    normals = []
    for t in tang:  # parallel transport keeps the tube from twisting
        n = n - np.dot(n, t) * t
        n /= np.linalg.norm(n)
        normals.append(n.copy())
    normals = np.array(normals)
    binormals = np.cross(tang, normals)
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = (np.cos(ang)[None, :, None] * normals[:, None, :] + np.sin(ang)[None, :, None] * binormals[:, None, :])
    pts = (path[:, None, :] + radius * ring).reshape(-1, 3)
    r, s = np.meshgrid(np.arange(k - 1), np.arange(segments), indexing="ij")
    a = r * segments + s
    b = r * segments + (s + 1) % segments
    quads = np.stack([a, b, b + segments, a + segments], -1).reshape(-1, 4)
    counts = [np.full(len(quads), 4)]
    indices = [quads.ravel()]
    all_pts = [pts]
    if caps:
        base = len(pts)
        all_pts += [pts[:segments], pts[-segments:]]
        counts += [np.array([segments]), np.array([segments])]
        indices += [base + np.arange(segments)[::-1], base + segments + np.arange(segments)]
    return MeshPart(name, np.concatenate(all_pts), np.concatenate(counts), np.concatenate(indices),
                    material, None, smooth=True)


def merge(name: str, parts: list[MeshPart], material: str | None = None) -> MeshPart:
    """One part from several (same material), keeping UVs only if all have them."""
    pts, counts, idx, uvs, off = [], [], [], [], 0
    for p in parts:
        pts.append(p.points)
        counts.append(p.face_counts)
        idx.append(p.face_indices + off)
        uvs.append(p.uv)
        off += len(p.points)
    uv = None if any(u is None for u in uvs) else np.concatenate(uvs)
    return MeshPart(name, np.concatenate(pts), np.concatenate(counts), np.concatenate(idx),
                    material or parts[0].material, uv, smooth=any(p.smooth for p in parts))
