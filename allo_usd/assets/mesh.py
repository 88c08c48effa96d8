"""Plain mesh and material data shared by the procedural builders and the USD author.

Builders (station, anomalies, imports) make these with numpy only; the author turns them
into UsdGeom.Mesh + UsdPreviewSurface. Keeping this layer free of pxr and bpy lets geometry
be tested, measured and ray-cast without either.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from allo_usd.core.errors import DegenerateMeshError
from allo_usd.core.geometry import rot_x, rot_y, rot_z
from allo_usd.core import fixedmath as fm

_AXES = {"X": rot_x, "Y": rot_y, "Z": rot_z}


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
    # UsdPreviewSurface `opacity` (default 1) and `opacityThreshold` (default 0): with a threshold above 0
    # the surface is drawn only where opacity reaches it (a cut-out, not refractive glass), so opacity 0
    # and threshold 0.5 make a surface that no renderer draws (the Sun's sphere, a mask label only).
    opacity: float = 1.0
    opacity_threshold: float = 0.0


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
    # The Asset joint the part hangs under (its points are then in the joint's frame), or None.
    joint: str | None = None

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
        pts = fm.apply(m[:3, :3], self.points) + m[:3, 3]
        return MeshPart(name or self.name, pts, self.face_counts, self.face_indices,
                        self.material, self.uv, self.smooth, self.joint)


@dataclass(frozen=True)
class Joint:
    """A revolute joint: an Xform under its parent joint (or the asset's geometry root) whose
    transform is translate(mount) @ rotateXYZ(mount_rotation) @ rotate<axis>(angle), all in degrees
    (USD's op order: the last op applies to points first). Parts naming it are in its frame."""

    name: str
    parent: str | None
    axis: str                                        # "X", "Y" or "Z"
    rest: float                                      # degrees: the pose the asset is built in
    lower: float = -180.0                            # limits, degrees; -180..180 = continuous
    upper: float = 180.0
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mount_rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)   # rotateXYZ, degrees (X first)
    tracks: str = "none"                             # the body it points at ("Sun"), or "none"
    op: str = "joint"                                # the joint op's suffix: xformOp:rotate<axis>:<op>

    def mount_matrix(self) -> np.ndarray:
        m = np.eye(4)
        rx, ry, rz = fm.radians(self.mount_rotation)
        m[:3, :3] = fm.matmul(fm.matmul(rot_z(rz), rot_y(ry)), rot_x(rx))
        m[:3, 3] = self.translate
        return m

    def local_matrix(self, angle: float) -> np.ndarray:
        """4x4 joint-to-parent matrix at `angle` degrees."""
        r = np.eye(4)
        r[:3, :3] = _AXES[self.axis](fm.radians(float(angle)))
        return fm.matmul(self.mount_matrix(), r)


@dataclass(frozen=True)
class Asset:
    """A set of mesh parts with the materials they use and any textures those name."""

    name: str
    parts: tuple[MeshPart, ...]
    materials: tuple[Material, ...]
    textures: dict[str, np.ndarray] = field(default_factory=dict)
    joints: tuple[Joint, ...] = ()   # parents before children

    def __post_init__(self) -> None:
        known: set[str] = set()
        for j in self.joints:
            if j.parent is not None and j.parent not in known:
                raise DegenerateMeshError(f"asset {self.name!r}: joint {j.name!r} names parent {j.parent!r}, "
                                          "which is not an earlier joint; list parents first")
            known.add(j.name)
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
        seen: set[tuple] = set()
        for part in self.parts:
            if part.joint is not None and part.joint not in known:
                raise DegenerateMeshError(f"asset {self.name!r}: part {part.name!r} hangs under joint "
                                          f"{part.joint!r}, which the asset does not define; add it to joints")
            if (part.joint, part.name) in seen:
                raise DegenerateMeshError(f"asset {self.name!r}: two parts are named {part.name!r}")
            seen.add((part.joint, part.name))

    def joint_chain(self, name: str | None) -> tuple[str, ...]:
        """The joint names from the root joint down to `name` (empty for None)."""
        return joint_chain(self.joints, name)

    def joint_matrices(self, angles: dict[str, float] | None = None) -> dict[str, np.ndarray]:
        """{joint: 4x4 joint-to-asset matrix} at `angles` (degrees; a joint not named is at rest)."""
        angles = angles or {}
        out: dict[str, np.ndarray] = {}
        for j in self.joints:
            parent = out[j.parent] if j.parent is not None else np.eye(4)
            out[j.name] = fm.matmul(parent, j.local_matrix(angles.get(j.name, j.rest)))
        return out

    def posed_points(self, angles: dict[str, float] | None = None) -> list[np.ndarray]:
        """Each part's points in the asset frame, the joints at `angles` (degrees, rest where not given)."""
        mats = self.joint_matrices(angles) if self.joints else {}
        return [p.points if p.joint is None else p.transformed(mats[p.joint]).points for p in self.parts]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The asset's axis-aligned bounds in its own frame, joints at rest."""
        pts = self.posed_points()
        return np.min([p.min(axis=0) for p in pts], axis=0), np.max([p.max(axis=0) for p in pts], axis=0)

    def triangle_soup(self, angles: dict[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """All parts merged in the asset frame, the joints at `angles` (degrees, rest where not
        given): (V, 3) points and (T, 3) triangle indices, for ray casting."""
        pts, tris, offset = self.posed_points(angles), [], 0
        for p, points in zip(self.parts, pts):
            tris.append(p.triangles() + offset)
            offset += len(points)
        return np.concatenate(pts), np.concatenate(tris)


def joint_chain(joints, name: str | None) -> tuple[str, ...]:
    """The joint names from the root joint down to `name` (empty for None) among `joints`."""
    by = {j.name: j for j in joints}
    chain: list[str] = []
    while name is not None:
        chain.insert(0, name)
        name = by[name].parent
    return tuple(chain)


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
    area = 0.5 * fm.norm(np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]), axis=1).sum()
    if not area > 0.0:
        raise DegenerateMeshError(f"{where}: total surface area is zero; the mesh is degenerate")
