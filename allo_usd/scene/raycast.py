"""Ray casting against known meshes (embree): visibility and pixel areas without rendering.

`RayScene` calls embree (embreex) directly. It does what trimesh's `RayMeshIntersector` did for us
before (same float32 BVH over vertices shifted to their bounding-box minimum and scaled to a
~100-unit box, the hit distance recomputed in float64 from the hit triangle's plane, hits on
near-parallel planes dropped) without trimesh's per-call overhead (mesh hashing, cache checks),
which dominated for the small ray batches placement casts.
"""

from __future__ import annotations

import math

import numpy as np

from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.geometry import box_corners, camera_intrinsics
from allo_usd.core import fixedmath as fm

_RAY_OFFSET_FACTOR, _RAY_OFFSET_FLOOR = 1e-6, 1e-8   # step past a hit face (multiple hits)
_PARALLEL = 1e-5                                      # |cos| under this: the ray grazes the plane
_ZERO = 1e-13                                         # a shorter normal or direction has none (trimesh's tol.zero)
_FEW = 16                                             # up to this many rays, a hit's float64 work runs on Python floats


def _unitize(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows of `v` scaled to unit length, which rows had a length): trimesh's `unitize` (times the
    reciprocal length; a zero row stays zero), with the length summed in a fixed order rather than
    by a BLAS product, so that hits and distances are the same on every CPU (core.fixedmath).
    When every row has a length (the usual case) the reciprocal is taken directly: the same bits
    as the masked form, two passes fewer."""
    length = fm.norm(v, axis=-1)
    ok = length > _ZERO
    if ok.all():
        return v * (1.0 / length)[:, None], ok
    inv = np.where(ok, 1.0 / np.where(ok, length, 1.0), 1.0)
    return v * inv[:, None], ok


_EMBREEX: list = []


def _embreex():
    """embreex's scene and mesh modules, imported once with Ctrl-C held (core.interrupts): they are
    Cython modules that take numpy's C API as they load, and a KeyboardInterrupt landing there comes
    out as "ImportError: numpy.core.multiarray failed to import" (the command failed with a
    traceback instead of stopping with exit 130; seen in test_sigint)."""
    if not _EMBREEX:
        import importlib

        from allo_usd.core.interrupts import interrupt_held

        with interrupt_held():
            _EMBREEX[:] = [importlib.import_module(f"embreex.{name}") for name in ("rtcore_scene", "mesh_construction")]
    return _EMBREEX


def _unit_row(v: list) -> list:
    """`_unitize` of one row of Python floats: the same operations (fm.norm's sum in index order,
    times the reciprocal length; a row without a length is kept as it is, times 1.0)."""
    v0, v1, v2 = v
    length = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    inv = 1.0 / length if length > _ZERO else 1.0
    return [v0 * inv, v1 * inv, v2 * inv]


class RayFan:
    """Ray directions (three component arrays, need not be unit) made ready for `RayScene.first_hit_fan`:
    their unit vectors (`_unitize`'s operations, component by component) and the float32 copy
    embree reads. Built once for a fixed set of directions cast from many points (placement's
    clearance probes), or per call (placement's pixel rays in the object's frame)."""

    def __init__(self, d0: np.ndarray, d1: np.ndarray, d2: np.ndarray):
        length = d0 * d0                                  # _unitize: fm.norm's sum, in its order
        length = length + d1 * d1
        length = np.sqrt(length + d2 * d2)
        ok = length > _ZERO
        inv = 1.0 / length if ok.all() else np.where(ok, 1.0 / np.where(ok, length, 1.0), 1.0)
        self.unit = (d0 * inv, d1 * inv, d2 * inv)
        self.dirs32 = np.empty((len(d0), 3), dtype=np.float32)   # _run's float32 copy (the same cast)
        for j in range(3):
            self.dirs32[:, j] = self.unit[j]
        # the unit vectors as rows of Python floats, for a fan of _FEW rays or fewer (RayScene._few_hits)
        self.rows = np.stack(self.unit, axis=1).tolist() if len(d0) <= _FEW else None

    @classmethod
    def of_rows(cls, dirs: np.ndarray) -> "RayFan":
        """The fan of (n, 3) direction rows."""
        d = np.asarray(dirs, dtype=np.float64)
        return cls(*(np.ascontiguousarray(d[:, j]) for j in range(3)))


class RayScene:
    """Triangles tagged by owner id (1 station, 2 anomaly), one embree BVH over all of them."""

    def __init__(self, parts: list[tuple[np.ndarray, np.ndarray, int]]):
        rtcore_scene, mesh_construction = _embreex()
        TriangleMesh = mesh_construction.TriangleMesh

        pts, tris, owner, off = [], [], [], 0
        for p, t, oid in parts:
            pts.append(np.asarray(p, dtype=np.float64).reshape(-1, 3))
            tris.append(np.asarray(t, dtype=np.int64).reshape(-1, 3) + off)
            owner.append(np.full(len(tris[-1]), oid, dtype=np.uint8))
            off += len(pts[-1])
        self.vertices = np.concatenate(pts)
        self.faces = np.concatenate(tris)
        self.owner = np.concatenate(owner)
        self._owned = bool((self.owner > 0).all())   # every triangle has an owner above 0 (hits_from keeps all)
        used = self.vertices[np.unique(self.faces)] if len(self.faces) else self.vertices
        lo, hi = used.min(axis=0), used.max(axis=0)
        self.scale = float(fm.norm(hi - lo))             # bounding-box diagonal
        self._origin = lo
        self._factor = 100.0 / self.scale if self.scale > 0 else 1.0
        tri = self.vertices[self.faces]
        self._plane_origin = tri[:, 0].copy()
        normals, ok = _unitize(fm.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
        self._normal = np.where(ok[:, None], normals, 0.0)
        # the same, one contiguous array per component (first_hit_fan's per-component hits)
        self._normal_cols = tuple(np.ascontiguousarray(self._normal[:, j]) for j in range(3))
        self._plane_origin_cols = tuple(np.ascontiguousarray(self._plane_origin[:, j]) for j in range(3))
        self._parts: dict = {}   # part_boxes and part_corner_columns, by levels
        self.memo: dict = {}     # what callers derive once per scene (placement's object extent)
        self._embree = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self._embree, vertices=((self.vertices - lo) * self._factor).astype(np.float32),
                     indices=self.faces.astype(np.int32))

    def part_boxes(self, levels: int = 5) -> np.ndarray:
        """(P, 8, 3) corners of axis-aligned boxes that together hold every triangle: the triangles
        split `levels` times at the median centroid along the longest axis (up to 2^levels parts),
        built once per scene. Each triangle lies in its part's box, so the union of the boxes'
        images bounds the image of the mesh much more tightly than its overall box."""
        if levels not in self._parts:
            cent = self.vertices[self.faces].mean(axis=1)
            groups = [np.arange(len(self.faces))]
            for _ in range(levels):
                split = []
                for g in groups:
                    if len(g) < 2:
                        split.append(g)
                        continue
                    c = cent[g]
                    order = np.argsort(c[:, int(np.argmax(np.ptp(c, axis=0)))], kind="stable")
                    split += [g[order[:len(g) // 2]], g[order[len(g) // 2:]]]
                groups = split
            boxes = []
            for g in groups:   # the corners of each triangle (repeats change no min or max)
                boxes.append(box_corners(self.vertices[self.faces[g].ravel()]))
            self._parts[levels] = np.array(boxes, dtype=np.float64).reshape(-1, 8, 3)
        return self._parts[levels]

    def part_corner_columns(self, levels: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`part_boxes(levels)`'s corners as three contiguous coordinate arrays (P * 8,), eight per part
        in order: the form placement projects with elementwise products, built once per scene."""
        key = ("columns", levels)
        if key not in self._parts:
            corners = self.part_boxes(levels).reshape(-1, 3)
            self._parts[key] = tuple(np.ascontiguousarray(corners[:, j]) for j in range(3))
        return self._parts[key]

    def _origins32(self, origins: np.ndarray) -> np.ndarray:
        """Ray origins in the BVH's float32 frame. Every ray from one point (a broadcast camera
        position): its row converted once, the same float32 bits for every ray, and handed to embree
        broadcast (it reads by stride)."""
        if origins.ndim == 2 and len(origins) > 1 and origins.strides[0] == 0:
            return np.broadcast_to(((origins[:1] - self._origin) * self._factor).astype(np.float32), origins.shape)
        return ((origins - self._origin) * self._factor).astype(np.float32)

    def _run(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        return self._embree.run(self._origins32(origins), dirs.astype(np.float32))

    def _plane_distance(self, tri: np.ndarray, origins: np.ndarray, dirs: np.ndarray):
        """(valid, signed distance t along each unit ray to its hit triangle's plane), in float64
        (trimesh's `planes_lines`, operation for operation, the dot products in a fixed order)."""
        n = self._normal[tri]
        ori = fm.dot(self._plane_origin[tri] - origins, n)
        den = fm.dot(dirs, n)
        valid = np.abs(den) > _PARALLEL
        return valid, np.divide(ori[valid], den[valid])

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(owner id or 0, distance or inf) of the first hit of each ray (directions need not be unit)."""
        origins = np.asarray(origins, dtype=np.float64)
        dirs = np.asarray(dirs, dtype=np.float64)
        if 0 < len(origins) <= _FEW and origins.shape == dirs.shape == (len(origins), 3):
            rows = [_unit_row(d) for d in dirs.tolist()]
            return self._few_hits(origins.tolist(), self._origins32(origins),
                                  np.array(rows, dtype=np.float64).astype(np.float32), rows)
        dirs = _unitize(dirs)[0]
        owner = np.zeros(len(origins), dtype=np.uint8)
        dist = np.full(len(origins), np.inf)
        if not len(origins):
            return owner, dist
        prim = self._run(origins, dirs)
        rays = np.flatnonzero(prim != -1)
        if rays.size:
            self._record_hits(owner, dist, rays, prim[rays], origins[rays], dirs[rays])
        return owner, dist

    def first_hit_fan(self, origin: np.ndarray, fan: "RayFan"):
        """`first_hit(np.broadcast_to(origin, (n, 3)), fan's directions as rows)` bit for bit, for rays
        that all start at `origin` (3,): the same operations element by element, the directions'
        unit vectors and float32 copy taken from `fan` (made once for directions cast from many
        points), without the (n, 3) float64 temporaries of the rays that miss."""
        n = len(fan.unit[0])
        if fan.rows is not None and n:
            o = np.asarray(origin, dtype=np.float64).reshape(1, 3)
            return self._few_hits(o.tolist() * n, np.broadcast_to(self._origins32(o), (n, 3)), fan.dirs32, fan.rows)
        owner = np.zeros(n, dtype=np.uint8)
        dist = np.full(n, np.inf)
        origin, rays, tri, dirs, normals, den = self._fan_hits(origin, fan)
        if rays.size:
            owner[rays] = self.owner[tri]
            dist[rays] = self._hit_lengths(origin, tri, dirs, normals, den)
        return owner, dist

    def hits_from(self, origin: np.ndarray, fan: "RayFan", distances: bool = True):
        """(indices of the rays of `fan` cast from `origin` whose first hit has an owner id above 0, in
        increasing order; their hit distances, or None without `distances`): what a count of an
        object's pixels needs of `first_hit_fan`, bit for bit, without its full-size owner and
        distance arrays, and without the distances when only the count matters (a silhouette)."""
        origin, rays, tri, dirs, normals, den = self._fan_hits(origin, fan)
        keep = None if self._owned else self.owner[tri] > 0
        if keep is not None and not keep.all():
            rays, tri, den = rays[keep], tri[keep], den[keep]
            dirs, normals = tuple(c[keep] for c in dirs), tuple(c[keep] for c in normals)
        if not distances:
            return rays, None
        return rays, self._hit_lengths(origin, tri, dirs, normals, den)

    def _fan_hits(self, origin: np.ndarray, fan: "RayFan"):
        """embree's first hits of `fan` from `origin` with the near-parallel ones dropped: (origin as a
        (3,) float64 array, the rays that hit, their triangles, their unit directions and the
        triangles' normals as component arrays, the directions' dot products with the normals).
        `_record_hits`' operations, component by component, in its order."""
        origin = np.asarray(origin, dtype=np.float64).reshape(3)
        unit = fan.unit
        if not len(unit[0]):
            return origin, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), unit, unit, np.zeros(0)
        o32 = ((origin[None] - self._origin) * self._factor).astype(np.float32)
        prim = self._embree.run(np.broadcast_to(o32, (len(unit[0]), 3)), fan.dirs32)
        rays = np.flatnonzero(prim != -1)
        tri = prim[rays]
        d0, d1, d2 = (u[rays] for u in unit)
        n0, n1, n2 = (c[tri] for c in self._normal_cols)
        den = d0 * n0                                  # fm.dot(dirs, normal), left to right
        den = den + d1 * n1
        den = den + d2 * n2
        valid = np.abs(den) > _PARALLEL
        if not valid.all():
            rays, tri, den, d0, d1, d2, n0, n1, n2 = (a[valid] for a in (rays, tri, den, d0, d1, d2, n0, n1, n2))
        return origin, rays, tri, (d0, d1, d2), (n0, n1, n2), den

    def _hit_lengths(self, origin, tri, dirs, normals, den) -> np.ndarray:
        """The distances along unit `dirs` from `origin` to the planes of triangles `tri`: the plane
        distance (`_plane_distance`'s dot products) and the hit distance (fm.norm of loc - origin)
        written out per component, `_record_hits`' operations in its order."""
        n0, n1, n2 = normals
        p0, p1, p2 = (c[tri] for c in self._plane_origin_cols)
        ori = (p0 - origin[0]) * n0
        ori = ori + (p1 - origin[1]) * n1
        ori = ori + (p2 - origin[2]) * n2
        t = np.divide(ori, den)
        length = None
        for j, d in enumerate(dirs):     # loc = d * t + origin; |loc - origin|
            part = (d * t + origin[j]) - origin[j]
            length = part * part if length is None else length + part * part
        return np.sqrt(length)

    def _few_hits(self, origins: list, o32: np.ndarray, d32: np.ndarray, dirs: list):
        """`first_hit` of a few rays (origins and unit directions as rows of Python floats, and their
        float32 copies for embree): `_record_hits`' operations on Python floats, in its order (IEEE
        doubles either way, so the same bits), where numpy's per-call costs were most of the rig's
        clearance probe (10 rays) and placement's one-ray look along a candidate's line of sight."""
        n = len(dirs)
        owner, dist = [0] * n, [math.inf] * n
        prim = self._embree.run(o32, d32).tolist()
        rays = [r for r in range(n) if prim[r] != -1]
        if rays:
            tri = [prim[r] for r in rays]
            for r, (n0, n1, n2), (p0, p1, p2), who in zip(rays, self._normal[tri].tolist(),
                                                          self._plane_origin[tri].tolist(), self.owner[tri].tolist()):
                (o0, o1, o2), (d0, d1, d2) = origins[r], dirs[r]
                den = d0 * n0                       # _plane_distance's fm.dot, left to right
                den = den + d1 * n1
                den = den + d2 * n2
                if not abs(den) > _PARALLEL:
                    continue                        # near-parallel: dropped
                ori = (p0 - o0) * n0
                ori = ori + (p1 - o1) * n1
                ori = ori + (p2 - o2) * n2
                t = ori / den
                a, b, c = (d0 * t + o0) - o0, (d1 * t + o1) - o1, (d2 * t + o2) - o2   # loc - origin
                owner[r], dist[r] = who, math.sqrt(a * a + b * b + c * c)             # fm.norm's order
        return np.array(owner, dtype=np.uint8), np.array(dist, dtype=np.float64)

    def _record_hits(self, owner, dist, rays, tri, hit_origins, hit_dirs) -> None:
        """Fill `owner` and `dist` at the rays embree reports a hit for (hit triangle `tri`), the
        distance recomputed in float64 from the triangle's plane; near-parallel hits are dropped."""
        valid, t = self._plane_distance(tri, hit_origins, hit_dirs)
        if not valid.all():
            rays, tri, hit_origins, hit_dirs = rays[valid], tri[valid], hit_origins[valid], hit_dirs[valid]
        owner[rays] = self.owner[tri]
        loc = hit_dirs * t.reshape((-1, 1))
        loc += hit_origins
        dist[rays] = fm.norm(loc - hit_origins, axis=1)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        """True where a ray (unit direction) meets a surface before distance `tmax` (an any-hit query:
        it stops at the first surface found and never looks past tmax, so it is much cheaper than
        `first_hit` for short rays in a large scene)."""
        origins = np.asarray(origins, dtype=np.float64)
        if not len(origins):
            return np.zeros(0, dtype=bool)
        t = (np.asarray(tmax, dtype=np.float64) * self._factor).astype(np.float32)
        return self._embree.run(self._origins32(origins), np.asarray(dirs, dtype=np.float32), dists=t,
                                query="OCCLUDED") != -1

    def hits(self, origins: np.ndarray, dirs: np.ndarray, max_hits: int = 100) -> np.ndarray:
        """Ray index of every surface crossing (one entry per crossing), stepping past each hit face."""
        out = [r for crossed, _ in self._crossings(origins, dirs, max_hits) for r in crossed]
        return np.array(out, dtype=np.int64)

    def _crossings(self, origins: np.ndarray, dirs: np.ndarray, max_hits: int, fan=None):
        """`hits` one step at a time: per step, (the rays that crossed a surface, the rays still
        going), as lists of ray indices; a ray missing from the second has crossed its last surface.

        Each step casts the rays still going from where they are (embree), and moves each that hit
        a new face just past its plane: o + d t (t recomputed in float64 from the face's plane, as
        `_plane_distance`), plus an offset of `base` along d; a ray that meets the face it has just
        left (a float32 re-hit) is pushed on by an offset doubled each time, and one that grazes the
        plane stops. The bookkeeping runs on Python floats, the same operations in the same order
        as elementwise numpy (so the same bits): `inside` casts 7 rays and is usually decided in one
        step, where numpy's per-call costs were most of a camera sample's clearance check."""
        o = np.array(origins, dtype=np.float64).reshape(-1, 3).tolist()
        d, d32 = _unit_fan(dirs) if fan is None else fan   # fan: _unit_fan(dirs), made beforehand
        base = max(_RAY_OFFSET_FLOOR, self.scale * _RAY_OFFSET_FACTOR)
        offsets = [[c * base for c in row] for row in d]
        last = [-1] * len(o)
        live = list(range(len(o)))
        for _ in range(max_hits):
            if not live:
                break
            prim = self._embree.run(self._origins32(np.array([o[r] for r in live])),
                                    d32 if len(live) == len(o) else d32[live]).tolist()
            new = [tri for r, tri in zip(live, prim) if tri != -1 and last[r] != tri]   # faces to step past
            if not new:
                if all(t == -1 for t in prim):
                    break
                faces = iter(())
            else:
                faces = zip(self._normal[new].tolist(), self._plane_origin[new].tolist())
            crossed, dupes = [], []
            for r, tri in zip(live, prim):
                if tri == -1:
                    continue
                if last[r] == tri:
                    last[r] = tri
                    dupes.append(r)
                    continue
                last[r] = tri
                (n0, n1, n2), (p0, p1, p2) = next(faces)
                (o0, o1, o2), (d0, d1, d2) = o[r], d[r]
                ori = (p0 - o0) * n0                 # _plane_distance's fm.dot, left to right
                ori = ori + (p1 - o1) * n1
                ori = ori + (p2 - o2) * n2
                den = d0 * n0
                den = den + d1 * n1
                den = den + d2 * n2
                if not abs(den) > _PARALLEL:
                    continue                         # grazes the plane: the ray stops
                t = ori / den
                f0, f1, f2 = offsets[r]
                o[r] = [(o0 + d0 * t) + f0, (o1 + d1 * t) + f1, (o2 + d2 * t) + f2]
                offsets[r] = [d0 * base, d1 * base, d2 * base]
                crossed.append(r)
            for r in dupes:
                f = offsets[r] = [c * 2.0 for c in offsets[r]]
                o[r] = [o[r][0] + f[0], o[r][1] + f[1], o[r][2] + f[2]]
            live = crossed + dupes
            yield crossed, live

    def inside(self, point: np.ndarray) -> bool:
        """Parity test: a point is enclosed when most of 7 rays cross the surface an odd number of
        times (a majority vote tolerates small holes in non-watertight meshes). The rays are followed
        only until the vote is decided: once 4 rays that have crossed their last surface agree, the
        rest cannot change the outcome (`hits` would follow every ray to its end)."""
        n = len(_PARITY_DIRS)
        origins = np.repeat(np.asarray(point, dtype=np.float64).reshape(1, 3), n, 0)
        crossings = [0] * n
        for crossed, live in self._crossings(origins, _PARITY_DIRS, 100, _PARITY_FAN):
            for r in crossed:
                crossings[r] += 1
            going = set(live)
            odd = sum(1 for r in range(n) if r not in going and crossings[r] % 2 == 1)
            even = sum(1 for r in range(n) if r not in going and crossings[r] % 2 == 0)
            if odd >= 4 or even > n - 4:
                break
        return sum(c % 2 for c in crossings) >= 4


_PARITY_DIRS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                         [0.577, 0.577, 0.577]], dtype=np.float64)   # inside's seven rays (made unit by hits)


def _unit_fan(dirs) -> tuple[list, np.ndarray]:
    """(`_unitize`d rows of `dirs` as Python floats, their float32 copy): `_crossings`' directions."""
    unit = _unitize(np.asarray(dirs, dtype=np.float64).reshape(-1, 3))[0]
    return unit.tolist(), unit.astype(np.float32)


_PARITY_FAN = _unit_fan(_PARITY_DIRS)   # inside's seven directions, made once


def pixel_rays(cam_pos, cam_rot, width: int, height: int, index=None,
               lens: CameraModel = DEFAULT_CAMERA) -> tuple[np.ndarray, np.ndarray]:
    """One ray through each pixel centre, row-major from the top-left pixel; with `index` (row-major
    pixel numbers), only those pixels' rays. Every ray is computed element-wise on its own, so a
    subset gives exactly the bits the full grid would. (Each direction component is computed as
    its own contiguous array, the same operations in the same order as R @ (x, y, -1) per ray.)
    `lens`: the camera's lens and sensor (core.camera_model), with its principal point offset."""
    columns = pixel_ray_columns(cam_rot, width, height, index, lens)
    d = np.empty((len(columns[0]), 3))
    for j in range(3):
        d[:, j] = columns[j]
    o = np.broadcast_to(np.asarray(cam_pos, dtype=np.float64), d.shape)
    return o, d


_INTRINSICS: dict = {}


def intrinsic_rows(width: int, height: int, lens: CameraModel = DEFAULT_CAMERA) -> list:
    """`camera_intrinsics(width, height, lens)` as nested lists of floats (the same values), computed
    once per (size, lens): placement checks every candidate at the same few sizes."""
    key = (width, height, lens)
    try:
        rows = _INTRINSICS.get(key)
    except TypeError:              # a lens that cannot be a key (unhashable fields): computed each time
        return camera_intrinsics(width, height, lens).tolist()
    if rows is None:
        rows = _INTRINSICS[key] = camera_intrinsics(width, height, lens).tolist()
    return rows


def pixel_ray_columns(cam_rot, width: int, height: int, index=None,
                      lens: CameraModel = DEFAULT_CAMERA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`pixel_rays`' unit directions as three contiguous component arrays (the same bits): for
    callers that go on component by component (placement.visible_fraction)."""
    n = width * height
    row, col = np.divmod(np.arange(n) if index is None else np.asarray(index, dtype=np.int64), width)
    return subgrid_ray_columns(cam_rot, width, height, np.arange(width), np.arange(height), col, row, lens)


def subgrid_ray_columns(cam_rot, width: int, height: int, xs, ys, ii, jj,
                        lens: CameraModel = DEFAULT_CAMERA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`pixel_ray_columns` of the pixels in column xs[ii] and row ys[jj] (pixel numbers from the top
    left; `ii`, `jj` index arrays), the same bits: each ray is R @ (x, y, -1) normalised, x of its
    column and y of its row, so x * R[k, 0] is computed once per column and y * R[k, 1] once per row
    and gathered (elementwise products give the same bits wherever they are taken)."""
    (fx, _, cx), (_, fy, cy), _ = intrinsic_rows(width, height, lens)
    x = (np.asarray(xs, dtype=np.int64) + 0.5 - cx) / fx
    y = -(np.asarray(ys, dtype=np.int64) + 0.5 - cy) / fy
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(cam_rot, dtype=np.float64).tolist()
    d0 = (x * r00)[ii] + (y * r01)[jj] - r02   # R @ (x, y, -1)
    d1 = (x * r10)[ii] + (y * r11)[jj] - r12
    d2 = (x * r20)[ii] + (y * r21)[jj] - r22
    n = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return np.divide(d0, n), np.divide(d1, n), np.divide(d2, n)


def class_image(scene: RayScene, cam_pos, cam_rot, width: int, height: int,
                lens: CameraModel = DEFAULT_CAMERA) -> np.ndarray:
    """(H, W) uint8 owner ids seen at each pixel centre through `lens`: a geometric mask."""
    o, d = pixel_rays(cam_pos, cam_rot, width, height, lens=lens)
    owner, _ = scene.first_hit(o, d)
    return owner.reshape(height, width)
