"""Mesh primitives in metres, numpy only, shared by every procedural builder.

Every function returns a MeshPart with outward-facing counter-clockwise faces. Placement is
by an optional 4x4 matrix (see `transform`); rotations are built in float64.
"""

from __future__ import annotations

import math

import numpy as np

from allo_usd.assets.mesh import MeshPart
from allo_usd.core import fixedmath as fm


def transform(translate=(0.0, 0.0, 0.0), rotate: np.ndarray | None = None, scale=1.0) -> np.ndarray:
    """4x4 matrix = T @ R @ S (float64)."""
    m = np.eye(4)
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    r = np.eye(3) if rotate is None else np.asarray(rotate, dtype=np.float64)
    m[:3, :3] = r * s[None, :]
    m[:3, 3] = translate
    return m


def frame_from_z(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third column is unit(axis): maps local +Z onto `axis`."""
    z = np.asarray(axis, dtype=np.float64)
    z = z / fm.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= fm.norm(x)
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
    ring = np.stack([fm.cos(t), fm.sin(t)], axis=1)
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
    return cylinder(name, radius, float(fm.norm(axis)), material, segments,
                    transform(a, frame_from_z(axis)), caps)


def sphere_outline_scale(segments: int, rings: int) -> float:
    """Radius of a `uv_sphere` whose drawn outline has, on average around it, radius 1 to within x^2 / 3,
    x = pi / segments, from any view at 1.87 radii or more (8.9e-5 relative angular radius at 192 segments).

    A UV sphere with its vertices on the unit sphere draws an outline inside the unit circle. With
    rings = segments / 2 (the same angular step, 2x, along a meridian and along the equator), the
    outline's mean radius falls short of 1 by D x^2, D between 1/3 and 5/6 depending on the view:
    - 1/3: the outline is an N-gon of the mesh's vertices (seen from far over a pole: the equator; from
      the equator in a meridian's plane: that meridian), and an N-gon's mean radius over azimuth is
      1 - x^2 / 3;
    - up to 1/4 more seen from the equator midway between meridians (the two meridians beside the
      limb, foreshortened by cos x across the line of sight: 1 - x^2 cos^2(azimuth) / 2, mean 1/4);
    - up to 1/2 more seen over a pole from a distance at which the limb (a small circle parallel to
      the rings) falls midway between two rings, whose projections then bound the outline.
    Scaling the vertices by 1 + c x^2 makes the relative angular radius err by c x^2 T - D x^2 S, with
    T = tan(b) / b and S = sin(b) cos(b) / b for the angular radius b: 1 far away, but T = 1.12 and
    S = 0.80 for the Moon at the orbit's perilune (1.87 radii). c = 1/2 balances the far worst case
    (1/2 - 5/6 = -1/3) against the near one (1.12 / 2 - 0.80 / 3 = +0.30); the middle of D's range, 7/12,
    would leave +0.39 near perilune. tests/sky/test_silhouettes.py measures the committed meshes.
    """
    if segments != 2 * rings:
        raise ValueError(f"sphere_outline_scale needs segments = 2 x rings, got {segments} x {rings}")
    x = math.pi / segments
    return 1.0 + x * x / 2.0


def uv_sphere(name: str, radius: float, material: str, segments: int = 32, rings: int = 16,
              matrix: np.ndarray | None = None) -> MeshPart:
    """Sphere centred at the origin, poles on Z, with equirectangular UVs (u along longitude)."""
    theta = np.linspace(0.0, np.pi, rings + 1)          # polar angle from +Z
    phi = np.linspace(0.0, 2 * np.pi, segments + 1)      # seam duplicated for UVs
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    pts = np.stack([fm.sin(th) * fm.cos(ph), fm.sin(th) * fm.sin(ph), fm.cos(th)], -1).reshape(-1, 3) * radius
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
        flip = [0, 3, 2, 1]  # reversed winding that keeps the front face's fan diagonal (a-c)
        bq = quads[:, flip] + len(pts)
        all_pts.append(back)
        all_quads.append(bq)
        all_uv.append(uvgrid[quads[:, flip].ravel()])
    q = np.concatenate(all_quads)
    return _place(MeshPart(name, np.concatenate(all_pts), np.full(len(q), 4), q.ravel(), material,
                           np.concatenate(all_uv), smooth=height is not None), matrix)


def tube(name: str, path: np.ndarray, radius: float, material: str, segments: int = 12,
         caps: bool = True) -> MeshPart:
    """A tube of constant radius along a polyline (K, 3), with parallel-transported frames."""
    path = np.asarray(path, dtype=np.float64)
    k = len(path)
    tang = np.gradient(path, axis=0)
    tang /= fm.norm(tang, axis=1, keepdims=True)
    n = frame_from_z(tang[0])[:, 0]
    normals = []
    for t in tang:  # parallel transport keeps the tube from twisting
        n = n - fm.dot(n, t) * t
        n /= fm.norm(n)
        normals.append(n.copy())
    normals = np.array(normals)
    binormals = np.cross(tang, normals)
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = (fm.cos(ang)[None, :, None] * normals[:, None, :] + fm.sin(ang)[None, :, None] * binormals[:, None, :])
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


def box_between(name: str, a, b, width: float, material: str, depth: float | None = None,
                up=None, uv_scale: float = 1.0) -> MeshPart:
    """A square (width x depth) beam from point a to point b: struts, longerons, rails.

    `up` (optional) picks the direction of the `depth` side; otherwise any perpendicular.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    axis = b - a
    length = float(fm.norm(axis))
    z = axis / length
    if up is None:
        rot = frame_from_z(z)
    else:
        y = np.asarray(up, dtype=np.float64)
        y = y - fm.dot(y, z) * z
        y /= fm.norm(y)
        rot = np.stack([np.cross(y, z), y, z], axis=1)
    d = width if depth is None else depth
    return box(name, (width, d, length), material, transform((a + b) / 2.0, rot), uv_scale)


def dish(name: str, radius: float, depth: float, material: str, segments: int = 24, rings: int = 4,
         matrix: np.ndarray | None = None, thickness: float = 0.02, hub: float = 0.1) -> MeshPart:
    """A paraboloid dish antenna opening toward +Z (vertex at the origin), double-sided.

    The concave front faces +Z, the convex back is `thickness` below, joined at the rim; a hole of
    radius `hub * radius` is left at the vertex for a feed or mount. UVs are planar, in metres.
    """
    rr = np.linspace(hub * radius, radius, rings + 1)
    t = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    x = rr[:, None] * fm.cos(t)[None, :]
    y = rr[:, None] * fm.sin(t)[None, :]
    z = depth * np.square(rr[:, None] / radius) * np.ones_like(x)
    front = np.stack([x, y, z], -1).reshape(-1, 3)
    back = front - np.array([0.0, 0.0, thickness])
    i, j = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    quads_front = np.stack([a, a + segments, b + segments, b], -1).reshape(-1, 4)
    n = len(front)
    quads_back = quads_front[:, ::-1] + n
    # rim strip: outer ring of front (row `rings`) to outer ring of back, facing outward
    jj = np.arange(segments)
    ra = rings * segments + jj
    rb = rings * segments + (jj + 1) % segments
    rim = np.stack([ra + n, rb + n, rb, ra], -1)
    pts = np.concatenate([front, back])
    quads = np.concatenate([quads_front, quads_back, rim])
    uv = pts[quads.ravel()][:, :2] + radius
    return _place(MeshPart(name, pts, np.full(len(quads), 4), quads.ravel(), material, uv, smooth=True),
                  matrix)


def scale_uv(part: MeshPart, su: float, sv: float | None = None) -> MeshPart:
    """A copy with UVs multiplied by (su, sv): set how many texture tiles a metre holds."""
    if part.uv is None:
        return part
    s = np.array([su, su if sv is None else sv], dtype=np.float64)
    return MeshPart(part.name, part.points, part.face_counts, part.face_indices, part.material,
                    part.uv * s, part.smooth)


# ---------------------------------------------------------------------------------------------
# Swept, turned and extruded shapes (used by the anomaly builders; general purpose).
# ---------------------------------------------------------------------------------------------

def _sgnpow(x: np.ndarray, e: float) -> np.ndarray:
    return np.sign(x) * fm.power(np.abs(x), e)


def smooth_path(control, samples: int, closed: bool = False, alpha: float = 0.5) -> np.ndarray:
    """A centripetal Catmull-Rom spline through `control` (K, 3), resampled to `samples` points
    evenly spaced by arc length. Open paths start and end on the first and last control point;
    closed paths do not repeat their first point."""
    p = np.asarray(control, dtype=np.float64)
    if len(p) < 2 or (fm.norm(np.diff(p, axis=0), axis=1) <= 0).any():
        raise ValueError("smooth_path needs at least two control points, none repeated in a row")
    ext = np.vstack([p[-1], p, p[0], p[1]]) if closed else np.vstack([2 * p[0] - p[1], p, 2 * p[-1] - p[-2]])
    dense = []
    m = 48
    for i in range(len(ext) - 3):
        p0, p1, p2, p3 = ext[i:i + 4]
        t0 = 0.0
        t1 = t0 + fm.power(fm.norm(p1 - p0), alpha)
        t2 = t1 + fm.power(fm.norm(p2 - p1), alpha)
        t3 = t2 + fm.power(fm.norm(p3 - p2), alpha)
        t = np.linspace(t1, t2, m, endpoint=False)[:, None]
        a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
        a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
        a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
        b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
        b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
        dense.append((t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2)
    dense.append((p[0] if closed else p[-1])[None, :])
    d = np.concatenate(dense)
    s = np.concatenate([[0.0], np.cumsum(fm.norm(np.diff(d, axis=0), axis=1))])
    target = np.linspace(0.0, s[-1], samples, endpoint=not closed)
    return np.stack([np.interp(target, s, d[:, k]) for k in range(3)], axis=1)


def path_frames(path: np.ndarray, closed: bool = False, up=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit tangents T, normals N and binormals B = T x N along a polyline (K, 3).

    Without `up`, N is parallel-transported (no twist; on a closed path the leftover twist is
    spread evenly so the ends meet). With `up` ((3,) or (K, 3)), N is `up` made perpendicular
    to T, which keeps flat profiles (straps, rails) facing a chosen way.
    """
    path = np.asarray(path, dtype=np.float64)
    k = len(path)
    if closed:
        tang = np.roll(path, -1, axis=0) - np.roll(path, 1, axis=0)
    else:
        tang = np.gradient(path, axis=0)
    tang /= fm.norm(tang, axis=1, keepdims=True)
    normals = np.empty_like(path)
    if up is not None:
        ups = np.broadcast_to(np.asarray(up, dtype=np.float64), path.shape)
        prev = frame_from_z(tang[0])[:, 0]
        for i in range(k):
            n = ups[i] - fm.dot(ups[i], tang[i]) * tang[i]
            norm = fm.norm(n)
            if norm < 1e-9:  # up along the tangent here: keep the previous normal
                n = prev - fm.dot(prev, tang[i]) * tang[i]
                norm = fm.norm(n)
            n = n / norm
            normals[i] = prev = n
    else:
        n = frame_from_z(tang[0])[:, 0]
        for i in range(k):
            n = n - fm.dot(n, tang[i]) * tang[i]
            n /= fm.norm(n)
            normals[i] = n
        if closed:
            t0 = tang[0]
            back = n - fm.dot(n, t0) * t0
            back /= fm.norm(back)
            phi = fm.arctan2(fm.dot(np.cross(normals[0], back), t0), fm.dot(normals[0], back))
            theta = -phi * np.arange(k) / k
            cr = np.cross(tang, normals)
            normals = normals * fm.cos(theta)[:, None] + cr * fm.sin(theta)[:, None]
    binormals = np.cross(tang, normals)
    return tang, normals, binormals


def sweep(name: str, path: np.ndarray, radius, material: str, segments: int = 12, closed: bool = False,
          caps: bool = True, aspect: float = 1.0, exponent: float = 1.0, up=None,
          matrix: np.ndarray | None = None) -> MeshPart:
    """A tube along a polyline (K, 3) with a per-point radius and an elliptic or boxy profile.

    `radius` (scalar or (K,)) is the half-size along the normal N, `radius * aspect` along the
    binormal B; `exponent` < 1 squares the profile off (0.3 is a rounded rectangle). A radius of
    0 at an end closes the tube there (rounded tips); otherwise `caps` closes the ends flat.
    `closed` joins the last point back to the first (rings, loops). See `path_frames` for `up`.
    """
    path = np.asarray(path, dtype=np.float64)
    k = len(path)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (k,)).copy()
    tang, normals, binormals = path_frames(path, closed, up)
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    cu, su = _sgnpow(fm.cos(ang), exponent), _sgnpow(fm.sin(ang), exponent) * aspect
    ring = cu[None, :, None] * normals[:, None, :] + su[None, :, None] * binormals[:, None, :]
    pts = (path[:, None, :] + r[:, None, None] * ring).reshape(-1, 3)
    rows = k if closed else k - 1
    rr, ss = np.meshgrid(np.arange(rows), np.arange(segments), indexing="ij")
    a = rr * segments + ss
    b = rr * segments + (ss + 1) % segments
    a2 = ((rr + 1) % k) * segments + ss
    b2 = ((rr + 1) % k) * segments + (ss + 1) % segments
    quads = np.stack([a, b, b2, a2], -1).reshape(-1, 4)
    counts, indices, all_pts = [np.full(len(quads), 4)], [quads.ravel()], [pts]
    if caps and not closed:
        base = len(pts)
        if r[0] > 0:
            all_pts.append(pts[:segments])
            counts.append(np.array([segments]))
            indices.append(base + np.arange(segments)[::-1])
            base += segments
        if r[-1] > 0:
            all_pts.append(pts[-segments:])
            counts.append(np.array([segments]))
            indices.append(base + np.arange(segments))
    part = MeshPart(name, np.concatenate(all_pts), np.concatenate(counts), np.concatenate(indices),
                    material, None, smooth=True)
    return _place(part, matrix)


def lathe(name: str, profile, material: str, segments: int = 24, closed: bool = False,
          crease_deg: float = 35.0, matrix: np.ndarray | None = None) -> MeshPart:
    """A surface of revolution about local +Z from a (radius, z) profile (K, 2).

    Walk the profile counter-clockwise around the solid's cross-section (radius to the right,
    z up: up the outside, down the inside) and the faces point outwards. Corners sharper than
    `crease_deg` get their own vertices so smooth shading keeps them crisp; `closed` joins the
    last profile point back to the first (rings, washers).
    """
    prof = np.asarray(profile, dtype=np.float64)
    keep = np.concatenate([[True], fm.norm(np.diff(prof, axis=0), axis=1) > 1e-12])
    prof = prof[keep]
    if closed and fm.norm(prof[0] - prof[-1]) <= 1e-12:
        prof = prof[:-1]
    if len(prof) < 2 or (prof[:, 0] < 0).any():
        raise ValueError(f"lathe {name!r}: profile needs 2+ distinct points with radius >= 0")
    kp = len(prof)
    nseg = kp if closed else kp - 1
    seg_dir = np.array([prof[(i + 1) % kp] - prof[i] for i in range(nseg)])
    seg_dir /= fm.norm(seg_dir, axis=1, keepdims=True)
    cos_crease = fm.cos(fm.radians(crease_deg))

    def sharp(i_seg_in: int, i_seg_out: int) -> bool:
        return float(fm.dot(seg_dir[i_seg_in], seg_dir[i_seg_out])) < cos_crease

    # Runs of segments joined smoothly; each run gets its own rings.
    corners = [v for v in range(kp) if (closed or 0 < v < kp - 1) and sharp((v - 1) % nseg, v % nseg)]
    if closed and not corners:
        runs = [(list(range(kp)), True)]
    elif closed:
        start = corners[0]
        order = [(start + i) % kp for i in range(kp)] + [start]
        runs, cur = [], [order[0]]
        for v in order[1:]:
            cur.append(v)
            if v in corners:
                runs.append((cur, False))
                cur = [v]
    else:
        runs, cur = [], [0]
        for v in range(1, kp):
            cur.append(v)
            if v in corners:
                runs.append((cur, False))
                cur = [v]
        if len(cur) > 1:
            runs.append((cur, False))
    t = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    cs, sn = fm.cos(t), fm.sin(t)
    pts, quads, off = [], [], 0
    for run, wrap in runs:
        rings = np.stack([np.column_stack([prof[v, 0] * cs, prof[v, 0] * sn, np.full(segments, prof[v, 1])])
                          for v in run])
        n = len(run)
        pts.append(rings.reshape(-1, 3))
        rows = n if wrap else n - 1
        rr, ss = np.meshgrid(np.arange(rows), np.arange(segments), indexing="ij")
        a = off + rr * segments + ss
        b = off + rr * segments + (ss + 1) % segments
        a2 = off + ((rr + 1) % n) * segments + ss
        b2 = off + ((rr + 1) % n) * segments + (ss + 1) % segments
        quads.append(np.stack([a, b, b2, a2], -1).reshape(-1, 4))
        off += n * segments
    q = np.concatenate(quads)
    part = MeshPart(name, np.concatenate(pts), np.full(len(q), 4), q.ravel(), material, None, smooth=True)
    return _place(part, matrix)


def triangulate_polygon(polygon) -> np.ndarray:
    """Ear-clipping triangulation of a simple polygon (N, 2) given counter-clockwise: (N-2, 3)."""
    p = np.asarray(polygon, dtype=np.float64)
    idx = list(range(len(p)))
    tris = []
    scale = max(float(np.ptp(p, axis=0).max()), 1e-12)
    eps = 1e-12 * scale * scale

    def cross(o, a, b):
        return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])

    while len(idx) > 3:
        n = len(idx)
        ring = p[idx]
        prev, nxt = np.roll(ring, 1, axis=0), np.roll(ring, -1, axis=0)
        convex = cross(prev, ring, nxt) > eps
        clipped = False
        for k in np.flatnonzero(convex):
            a, b, c = prev[k], ring[k], nxt[k]
            others = np.delete(ring, [(k - 1) % n, k, (k + 1) % n], axis=0)
            same = (np.abs(others[:, None, :] - np.stack([a, b, c])[None]) < 1e-12 * scale).all(-1).any(-1)
            q = others[~same]
            inside = (cross(a, b, q) >= -eps) & (cross(b, c, q) >= -eps) & (cross(c, a, q) >= -eps)
            if not inside.any():
                tris.append((idx[(k - 1) % n], idx[k], idx[(k + 1) % n]))
                idx.pop(k)
                clipped = True
                break
        if not clipped:  # only flat corners left: drop the flattest (a zero-area ear)
            idx.pop(int(np.argmin(np.abs(cross(prev, ring, nxt)))))
    tris.append(tuple(idx))
    return np.array(tris, dtype=np.int64)


def _ccw(polygon) -> np.ndarray:
    p = np.asarray(polygon, dtype=np.float64)
    area = 0.5 * np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])
    return p if area > 0 else p[::-1]


def extrude_polygon(name: str, polygon, thickness: float, material: str,
                    matrix: np.ndarray | None = None) -> MeshPart:
    """A simple (possibly concave) polygon (N, 2) in XY extruded from z=-t/2 to z=+t/2; hard edges."""
    p = _ccw(polygon)
    n = len(p)
    h = thickness / 2.0
    tri = triangulate_polygon(p)
    top = np.column_stack([p, np.full(n, h)])
    bot = np.column_stack([p, np.full(n, -h)])
    i = np.arange(n)
    j = (i + 1) % n
    side_pts = np.concatenate([bot, top])
    sides = np.stack([i, j, n + j, n + i], axis=1) + 2 * n
    pts = np.concatenate([top, bot, side_pts])
    counts = np.concatenate([np.full(len(tri), 3), np.full(len(tri), 3), np.full(n, 4)])
    idx = np.concatenate([tri.ravel(), (tri[:, ::-1] + n).ravel(), sides.ravel()])
    return _place(MeshPart(name, pts, counts, idx, material), matrix)


def ring_prism(name: str, outer, inner, thickness: float, material: str,
               matrix: np.ndarray | None = None) -> MeshPart:
    """A plate with a hole, extruded from z=-t/2 to z=+t/2: outer and inner outlines (N, 2),
    both counter-clockwise with the same N, the inner one inside the outer (nuts, washers,
    box-end wrench rings); hard edges."""
    o, q = _ccw(outer), _ccw(inner)
    if len(o) != len(q):
        raise ValueError(f"ring_prism {name!r}: outer and inner outlines need the same vertex count")
    n = len(o)
    h = thickness / 2.0
    i = np.arange(n)
    j = (i + 1) % n
    ot, ob = np.column_stack([o, np.full(n, h)]), np.column_stack([o, np.full(n, -h)])
    it, ib = np.column_stack([q, np.full(n, h)]), np.column_stack([q, np.full(n, -h)])
    # vertex blocks: top (ot, it), bottom (ob, ib), outer wall (ob, ot), inner wall (ib, it)
    pts = np.concatenate([ot, it, ob, ib, ob, ot, ib, it])
    top = np.stack([i, j, n + j, n + i], 1)
    bot = np.stack([2 * n + j, 2 * n + i, 3 * n + i, 3 * n + j], 1)
    outer_wall = np.stack([4 * n + i, 4 * n + j, 5 * n + j, 5 * n + i], 1)
    inner_wall = np.stack([6 * n + j, 6 * n + i, 7 * n + i, 7 * n + j], 1)
    q4 = np.concatenate([top, bot, outer_wall, inner_wall])
    return _place(MeshPart(name, pts, np.full(len(q4), 4), q4.ravel(), material), matrix)


def superellipsoid(name: str, size, material: str, exponent: float = 0.5, segments: int = 32,
                   rings: int = 16, matrix: np.ndarray | None = None) -> MeshPart:
    """A rounded box of `size` (sx, sy, sz) centred at the origin: exponent 1 is an ellipsoid,
    smaller values square it off (0.2 is a soft box: bags, housings, battery packs)."""
    s = uv_sphere(name, 1.0, material, segments, rings)
    half = np.asarray(size, dtype=np.float64) / 2.0
    pts = _sgnpow(s.points, exponent) * half
    return _place(MeshPart(name, pts, s.face_counts, s.face_indices, material, s.uv, smooth=True), matrix)
