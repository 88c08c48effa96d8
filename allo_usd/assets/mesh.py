"""Plain mesh and material data shared by the procedural builders and the USD author.

Builders (station, anomalies, imports) make these with numpy only; the author turns them
into UsdGeom.Mesh + UsdPreviewSurface. Keeping this layer free of pxr and bpy lets geometry
be tested, measured and ray-cast without either.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from allo_usd.core.errors import DegenerateMeshError


@dataclass(frozen=True)
class Material:
    """A UsdPreviewSurface-style material. Colours are linear RGB in [0, 1]."""

    name: str
    base_color: tuple[float, float, float]
    metallic: float = 0.0
    roughness: float = 0.5
    # Optional texture: key into Asset.textures (an (H, W, 3) uint8 sRGB array written as PNG).
    base_color_texture: str | None = None
    emissive_color: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # UsdPreviewSurface `ior` (default 1.5): the dielectric specular layer. 1.0 removes it, leaving
    # a purely diffuse (Lambertian) surface whose reflectance is exactly its base colour.
    ior: float = 1.5
    # UsdPreviewSurface `opacity` (default 1): 0 is fully transparent (the Sun's sphere, a mask label only).
    opacity: float = 1.0


@dataclass(frozen=True)
class MeshPart:
    """One mesh in metres, in its asset's frame (Z up).

    face_counts[i] vertices make face i, taken in order from face_indices; faces wind
    counter-clockwise seen from outside. `uv`, when given, is face-varying: one (u, v) per
    entry of face_indices. `smooth` asks for averaged vertex normals (cylinders, spheres); a
    smooth part must not share vertices across hard edges (cap rims are duplicated).
    """

    name: str
    points: np.ndarray
    face_counts: np.ndarray
    face_indices: np.ndarray
    material: str
    uv: np.ndarray | None = None
    smooth: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "points", np.ascontiguousarray(self.points, dtype=np.float64))
        object.__setattr__(self, "face_counts", np.ascontiguousarray(self.face_counts, dtype=np.int32))
        object.__setattr__(self, "face_indices", np.ascontiguousarray(self.face_indices, dtype=np.int32))
        if self.uv is not None:
            object.__setattr__(self, "uv", np.ascontiguousarray(self.uv, dtype=np.float64))
        validate_part(self)

    def triangles(self) -> np.ndarray:
        """(T, 3) vertex indices from fan triangulation of every face (faces are convex)."""
        return fan_triangulate(self.face_counts, self.face_indices)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)

    def transformed(self, matrix: np.ndarray, name: str | None = None) -> "MeshPart":
        """A copy with points mapped by a 4x4 row-vector-free matrix (p' = M @ [p, 1])."""
        m = np.asarray(matrix, dtype=np.float64)
        pts = self.points @ m[:3, :3].T + m[:3, 3]
        return MeshPart(name or self.name, pts, self.face_counts, self.face_indices,
                        self.material, self.uv, self.smooth)


@dataclass(frozen=True)
class Asset:
    """A set of mesh parts with the materials they use and any textures those name."""

    name: str
    parts: tuple[MeshPart, ...]
    materials: tuple[Material, ...]
    textures: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = {m.name for m in self.materials}
        for part in self.parts:
            if part.material not in names:
                raise DegenerateMeshError(
                    f"asset {self.name!r}: part {part.name!r} uses material {part.material!r}, "
                    f"which is not among its materials {sorted(names)}; add it to the asset")
        for m in self.materials:
            if m.base_color_texture and m.base_color_texture not in self.textures:
                raise DegenerateMeshError(
                    f"asset {self.name!r}: material {m.name!r} names texture "
                    f"{m.base_color_texture!r}, which the asset does not carry")
        seen: set[str] = set()
        for part in self.parts:
            if part.name in seen:
                raise DegenerateMeshError(f"asset {self.name!r}: two parts are named {part.name!r}")
            seen.add(part.name)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.min([p.points.min(axis=0) for p in self.parts], axis=0)
        hi = np.max([p.points.max(axis=0) for p in self.parts], axis=0)
        return lo, hi

    def triangle_soup(self) -> tuple[np.ndarray, np.ndarray]:
        """All parts merged: (V, 3) points and (T, 3) triangle indices, for ray casting."""
        pts, tris, offset = [], [], 0
        for p in self.parts:
            pts.append(p.points)
            tris.append(p.triangles() + offset)
            offset += len(p.points)
        return np.concatenate(pts), np.concatenate(tris)


def fan_triangulate(face_counts: np.ndarray, face_indices: np.ndarray) -> np.ndarray:
    counts = np.asarray(face_counts, dtype=np.int64)
    idx = np.asarray(face_indices, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ntri = counts - 2
    face_of_tri = np.repeat(np.arange(len(counts)), ntri)
    k = np.arange(ntri.sum()) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    s = starts[face_of_tri]
    return np.stack([idx[s], idx[s + k + 1], idx[s + k + 2]], axis=1)


def validate_part(part: MeshPart) -> None:
    """Raise DegenerateMeshError naming what is wrong with a part."""
    where = f"mesh part {part.name!r}"
    if not part.name.isidentifier():
        raise DegenerateMeshError(f"{where}: name must be a valid identifier (letters, digits, _)")
    if part.points.ndim != 2 or part.points.shape[1] != 3 or len(part.points) < 3:
        raise DegenerateMeshError(f"{where}: points must be an (N>=3, 3) array, got {part.points.shape}")
    if not np.isfinite(part.points).all():
        raise DegenerateMeshError(f"{where}: points contain NaN or infinity; fix the generator or the file")
    if len(part.face_counts) == 0 or (part.face_counts < 3).any():
        raise DegenerateMeshError(f"{where}: needs at least one face, each with 3 or more vertices")
    if part.face_counts.sum() != len(part.face_indices):
        raise DegenerateMeshError(f"{where}: face_counts sum to {part.face_counts.sum()} but there are "
                                  f"{len(part.face_indices)} face indices")
    if part.face_indices.min() < 0 or part.face_indices.max() >= len(part.points):
        raise DegenerateMeshError(f"{where}: face indices out of range [0, {len(part.points)})")
    if part.uv is not None and part.uv.shape != (len(part.face_indices), 2):
        raise DegenerateMeshError(f"{where}: uv must be face-varying, shape ({len(part.face_indices)}, 2)")
    tri = part.triangles()
    p = part.points
    area = 0.5 * np.linalg.norm(np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]), axis=1).sum()
    if not area > 0.0:
        raise DegenerateMeshError(f"{where}: total surface area is zero; the mesh is degenerate")
