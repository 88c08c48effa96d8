"""Import glTF/GLB, OBJ (+MTL) and STL files as an `Asset` in metres, Z up.

    report = import_mesh_report("ISS_2016.glb", up_axis="-z")
    report.asset, report.unit, report.scale, report.transform

`import_mesh(...)` is the same call returning only the Asset. Files are read with trimesh
(`trimesh.load(path, force="scene")`); every geometry instance is taken with its node's world
transform, so scene graphs, instancing and mirrored nodes (winding is reversed) come out right.

Conversion, in this order, all in float64 (a file point p in its world frame):

    p_out = R_user @ U @ (scale * p) + offset        (report.transform is this as a 4x4)

* scale: from `units` ('m', 'cm', 'mm', 'in', 'ft', or 'auto'; see "Unit heuristic").
* U: the exact integer rotation taking the file's up axis to +Z (see `UP_AXIS_ROTATIONS`).
  'auto' is 'y' for glTF (Y up by spec) and OBJ (Y up by convention), 'z' for STL. glTF 'y'
  maps (x, y, z) -> (x, -z, y), i.e. +90 degrees about X. The up axis and the unit come from
  the format (and for units='auto', the size heuristic below) or from the caller (`up_axis`,
  `units`: `allo-usd asset import --up-axis/--units`, a plan's [station]); never from the
  file's name, so a renamed copy imports identically. (USD files, which carry their own
  upAxis and metersPerUnit, are not imported here: this package reads meshes with trimesh.)
* R_user: the optional `rotation` (3x3 proper rotation), e.g. `ISS_2016_ROTATION`.
* offset: with recenter=True the translation putting the bounding-box centre at the origin.

Unit heuristic (units='auto'). Let L be the largest bounding-box extent of the kept triangles
in file units. glTF is metres by spec and OBJ/STL carry no unit, so 'auto' reads metres, except
that a station is at most a few hundred metres long, so an absurd L is taken as a unit error:

    L <= 1000          -> metres          (up to a 1 km object)
    1000 < L <= 20000  -> inches (0.0254)  (25 m .. 508 m: station scale in inches; NASA models
                                            such as ISS_2016.glb are in inches)
    L > 20000          -> AssetError: too large to guess (mm and cm overlap there); pass units.

Small models (an anomaly part of a few centimetres) stay metres. The chosen unit, the scale
factor and the reason are recorded on the ImportReport (`unit`, `scale`, `unit_reason`).

Parts and materials. Faces are grouped by material: one MeshPart per material, named like its
material (names sanitised to identifiers: other characters become '_', a leading digit gets
the prefix 'm_', an unnamed material becomes 'material_<n>', duplicates get '_2', '_3', ...;
the asset is named after `name` or the file stem, a leading digit prefixed 'a_'). Per-vertex
UVs (trimesh's, origin bottom-left as in USD; trimesh already flips glTF's V) become
face-varying `uv`; in a part where only some
geometries have UVs the others get (0, 0). `smooth` is True exactly when every geometry of the
part came with vertex normals from the file (glTF NORMAL, OBJ vn): such files split vertices
where they want hard edges, so averaging normals over shared vertices reproduces them; files
without normals (STL, plain OBJ) give smooth=False. Vertex colours are ignored.

Materials:
* glTF PBR (trimesh PBRMaterial): base_color = baseColorFactor RGB (linear by spec; trimesh
  keeps it as uint8, so it is quantised to 1/255), default white; metallic/roughness = the
  factors, default 1.0 each as in glTF; emissive_color = emissiveFactor. baseColorTexture ->
  Asset.textures[<material>_base_color], uint8 (H, W, 3) sRGB (alpha dropped), downsized
  (Lanczos, aspect kept) to at most max_texture_size on its longer side. As in glTF the author
  should multiply the texture by base_color. Normal, metallic-roughness, occlusion and emissive
  textures are ignored.
* OBJ/MTL (trimesh SimpleMaterial): base_color = Kd converted sRGB -> linear, metallic 0,
  roughness = sqrt(2 / (Ns + 2)) clipped to [0.05, 1] (Blinn-Phong exponent to roughness),
  map_Kd -> texture as above.
* No material (STL, OBJ without MTL, glTF primitive without material) -> DEFAULT_MATERIAL, a
  grey metal named 'default_metal'.
* A textured material on a part without UVs keeps no texture; its base_color becomes the factor
  times the texture's mean linear colour.

Cleaning: triangles with a non-finite vertex, a vertex index outside the mesh's points, or zero
area (area <= 1e-12 * longest edge^2, a scale-free test that also catches collinear float noise)
are dropped, then unused vertices. Every dropped triangle is counted (ImportReport.
dropped_triangles, a hazard's droppedTriangles): the file's triangles are counted as trimesh
parsed them, before its own processing (which silently removes faces touching a NaN or infinite
vertex in OBJ and STL files) runs, so those count too. A file whose triangles are all degenerate
raises DegenerateMeshError; a file with no triangle mesh at all (empty, or garbage trimesh reads
as nothing) raises AssetError.

ISS_2016.glb (NASA's ISS model, which the tests read from shared/assets beside the checkout): 30,000 triangles in one mesh, one
PBR material (baseColorTexture 1024x1024 JPEG, metallic 0, roughness 0.5, double sided),
extent 3162 x 4268 x 1005 file units -> inches by the heuristic -> 80.3 x 108.4 x 25.5 m. 39
triangles have exactly zero area and are dropped (29,961 kept). Despite glTF's Y-up rule its
native axes are the ISS analysis frame: +X forward (velocity, the US segment / Harmony end;
Zvezda and the Russian segment at -X), +Y starboard (Columbus at +Y, Kibo at -Y), +Z nadir
(truss on the -Z side of the modules, Rassvet and the Kibo logistics module on the +Z / -Z
sides respectively), so the truss runs along Y. The default glTF conversion therefore puts the
108 m truss along Z. Our station frame is +X flight direction, Z zenith, truss along Y;
`ISS_2016_ROTATION` (+90 degrees about X, applied after the glTF conversion) gives that:
the combined map is (x, y, z) -> (x, -y, -z), extent 80 (X) x 108 (Y, truss) x 26 (Z) m, and
+Y is then port. `up_axis='-z'` is an equivalent spelling for this file, and the one to give
(`--up-axis=-z`, or `up_axis = "-z"` in a plan's [station]): nothing in the file says its axes
break glTF's rule, so only the caller can.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from allo_usd.core.errors import AssetError, DegenerateMeshError, ImportOptionError
from allo_usd.core.interrupts import interrupt_held
from allo_usd.assets.mesh import Asset, Material, MeshPart
from allo_usd.core import fixedmath as fm

__all__ = [
    "DEFAULT_MATERIAL",
    "ISS_2016_ROTATION",
    "ImportReport",
    "SUPPORTED_EXTENSIONS",
    "UNIT_SCALES",
    "UP_AXIS_ROTATIONS",
    "check_options",
    "guess_unit",
    "import_mesh",
    "import_mesh_report",
]

SUPPORTED_EXTENSIONS: dict[str, str] = {".glb": "gltf", ".gltf": "gltf", ".obj": "obj", ".stl": "stl"}

UNIT_SCALES: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}

# Heuristic bounds for units='auto' (largest extent in file units); see the module docstring.
AUTO_METRES_MAX = 1000.0
AUTO_INCHES_MAX = 20000.0
MAX_MODEL_BYTES = 1 << 31   # a model file the importer reads (2 GiB: a bound, not a size any station model needs)

# Exact rotations (integer entries, det +1) taking the named file axis onto +Z; each is the
# smallest rotation doing so, about X for y/-y/-z and about Y for x/-x.
UP_AXIS_ROTATIONS: dict[str, np.ndarray] = {
    "z": np.eye(3),
    "y": np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64),   # (x, -z, y)
    "-y": np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64),  # (x, z, -y)
    "-z": np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=np.float64),  # (x, -y, -z)
    "x": np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]], dtype=np.float64),   # (-z, y, x)
    "-x": np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype=np.float64),  # (z, y, -x)
}
_AUTO_UP = {"gltf": "y", "obj": "y", "stl": "z"}

# For NASA's ISS_2016.glb imported with the default glTF up axis: +90 degrees about X, taking
# (x, y, z) -> (x, -z, y). Result: +X flight direction, truss along Y, Z zenith (see above).
ISS_2016_ROTATION = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)

DEFAULT_MATERIAL = Material("default_metal", base_color=(0.5, 0.5, 0.5), metallic=1.0, roughness=0.4)

_DEGENERATE_REL_AREA = 1e-12

for _m in (*UP_AXIS_ROTATIONS.values(), ISS_2016_ROTATION):
    _m.setflags(write=False)


@dataclass(frozen=True)
class ImportReport:
    """An imported Asset and how it was made from the file.

    transform: 4x4 float64, file world coordinates -> asset metres (p_out = M @ [p, 1]),
    i.e. [scale * rotation | offset]. rotation: R_user @ U (3x3, no scale). offset: the translation added last (metres, output
    frame; zero with recenter=False). source_extent: bounding-box size in file units and
    axes. triangles: kept; dropped_triangles: the file's triangles (as parsed) not kept:
    non-finite, an index out of range or zero area (kept_triangles).
    """

    asset: Asset
    path: Path
    format: str
    unit: str
    scale: float
    unit_reason: str
    source_up_axis: str
    rotation: np.ndarray
    offset: np.ndarray
    transform: np.ndarray
    source_extent: np.ndarray
    triangles: int
    dropped_triangles: int


def import_mesh(path, *, units: str = "auto", up_axis: str = "auto", name: str | None = None,
                recenter: bool = True, max_texture_size: int = 1024,
                rotation=None) -> Asset:
    """Read a glTF/GLB, OBJ or STL file as an Asset in metres, Z up (see the module docstring)."""
    return import_mesh_report(path, units=units, up_axis=up_axis, name=name, recenter=recenter,
                              max_texture_size=max_texture_size, rotation=rotation).asset


def import_mesh_report(path, *, units: str = "auto", up_axis: str = "auto", name: str | None = None,
                       recenter: bool = True, max_texture_size: int = 1024,
                       rotation=None) -> ImportReport:
    """Like import_mesh, returning an ImportReport with the unit, scale and transform chosen.

    rotation: optional 3x3 proper rotation applied after the up-axis conversion (before
    recentering), e.g. ISS_2016_ROTATION.
    """
    path = Path(os.fspath(path))
    fmt = _check_path(path)
    units = _check_units(units)
    up = _check_up_axis(up_axis, fmt)
    user_rot = _check_rotation(rotation)
    if isinstance(max_texture_size, bool) or not isinstance(max_texture_size, (int, np.integer)) \
            or max_texture_size < 1:
        raise ImportOptionError(f"max_texture_size must be a positive integer, got {max_texture_size!r}")

    with interrupt_held():   # trimesh's imports and loaders catch BaseException: a Ctrl-C waits for them
        scene, parsed = _load_scene(path, fmt)
        groups, n_in = _collect(scene, path, fmt, parsed)

    # clean in file units (the degeneracy test is scale free)
    kept_total = 0
    for g in groups:
        _clean(g)
        kept_total += len(g["faces"])
    if kept_total == 0:
        raise DegenerateMeshError(
            f"{path}: all {n_in} triangles are degenerate (zero area or non-finite points); "
            f"nothing is left to import - check the file's export")
    groups = [g for g in groups if len(g["faces"])]

    lo = np.min([g["points"].min(axis=0) for g in groups], axis=0)
    hi = np.max([g["points"].max(axis=0) for g in groups], axis=0)
    source_extent = hi - lo
    unit, scale, reason = _resolve_units(units, float(source_extent.max()), path)

    rot = fm.matmul(user_rot, UP_AXIS_ROTATIONS[up])
    for g in groups:
        g["points"] = fm.apply(rot, g["points"] * scale)
    offset = np.zeros(3)
    if recenter:
        lo = np.min([g["points"].min(axis=0) for g in groups], axis=0)
        hi = np.max([g["points"].max(axis=0) for g in groups], axis=0)
        offset = -(lo + hi) / 2.0
        for g in groups:
            g["points"] = g["points"] + offset

    asset_name = _sanitise(name if name is not None else path.stem, "a_", "asset")
    namer = _Namer()
    parts, materials, textures = [], [], {}
    for g in groups:
        mat_name = namer(g["label"])
        mat, tex = _convert_material(g["material"], mat_name, max_texture_size,
                                     has_uv=g["uv"] is not None, path=path)
        if tex is not None:
            textures[mat.base_color_texture] = tex
        materials.append(mat)
        faces = g["faces"]
        parts.append(MeshPart(mat_name, g["points"], np.full(len(faces), 3, dtype=np.int32),
                              faces.reshape(-1), mat_name, g["uv"], g["smooth"]))
    asset = Asset(asset_name, tuple(parts), tuple(materials), textures)

    transform = np.eye(4)
    transform[:3, :3] = scale * rot
    transform[:3, 3] = offset
    return ImportReport(asset=asset, path=path, format=fmt, unit=unit, scale=scale, unit_reason=reason,
                        source_up_axis=up, rotation=rot, offset=offset, transform=transform,
                        source_extent=source_extent, triangles=kept_total,
                        dropped_triangles=n_in - kept_total)


def guess_unit(largest_extent: float) -> tuple[str, float]:
    """The units='auto' heuristic: (unit, scale) for a largest extent in file units.

    Raises ImportOptionError when the extent is too large to guess (> AUTO_INCHES_MAX).
    """
    if not np.isfinite(largest_extent) or largest_extent < 0:
        raise ImportOptionError(f"largest extent must be a finite non-negative number, got {largest_extent!r}")
    if largest_extent <= AUTO_METRES_MAX:
        return "m", 1.0
    if largest_extent <= AUTO_INCHES_MAX:
        return "in", UNIT_SCALES["in"]
    raise ImportOptionError(
        f"cannot guess units for a largest extent of {largest_extent:g} file units "
        f"(over {AUTO_INCHES_MAX:g}: millimetres and centimetres both fit); pass units= one of "
        f"{sorted(UNIT_SCALES)}")


# ----------------------------------------------------------------------------- arguments

def _check_path(path: Path) -> str:
    fmt = SUPPORTED_EXTENSIONS.get(path.suffix.lower())
    if fmt is None:
        raise AssetError(f"{path}: unsupported mesh file extension {path.suffix!r}; supported: "
                         f"{', '.join(SUPPORTED_EXTENSIONS)}")
    if not path.exists():
        raise AssetError(f"mesh file not found: {path}")
    from allo_usd.core.files import file_problem

    problem = file_problem(path, MAX_MODEL_BYTES)   # the read gate: a FIFO, a device or a pseudo-file is refused
    if problem:
        raise AssetError(f"{path} {problem}; fix: give the path of a glTF/OBJ/STL model file")
    return fmt


def check_options(units: str = "auto", up_axis: str = "auto") -> tuple[str, str]:
    """(units, up_axis) normalised ('MM' -> 'mm', '+Z' -> 'z'; 'auto' stays), or an ImportOptionError naming
    the values allowed (what `allo-usd asset import` checks before it reads the file)."""
    return _check_units(units), _check_axis_name(up_axis)


_AXIS_ORDER = ("x", "y", "z", "-x", "-y", "-z")   # how the allowed axes are listed


def _check_units(units: str) -> str:
    u = str(units).strip().lower()
    if u != "auto" and u not in UNIT_SCALES:
        raise ImportOptionError(f"units {str(units)[:40]!r} is not one of {', '.join(UNIT_SCALES)} or auto; fix: give the "
                                "file's length unit (--units; units in a plan), e.g. mm for a CAD export")
    return u


def _check_axis_name(up_axis: str) -> str:
    u = str(up_axis).strip().lower().lstrip("+")
    if u != "auto" and u not in UP_AXIS_ROTATIONS:
        raise ImportOptionError(f"up axis {str(up_axis)[:40]!r} is not one of {', '.join(_AXIS_ORDER)} or auto (the "
                                "format's); fix: give the file axis that points up (--up-axis; up_axis in a plan), "
                                "e.g. y for glTF and most OBJ files, z for STL")
    return u


def _check_up_axis(up_axis: str, fmt: str) -> str:
    u = _check_axis_name(up_axis)
    return _AUTO_UP[fmt] if u == "auto" else u


def _check_rotation(rotation) -> np.ndarray:
    if rotation is None:
        return np.eye(3)
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.isfinite(r).all():
        raise ImportOptionError(f"rotation must be a finite 3x3 matrix, got shape {r.shape}")
    if not np.allclose(fm.matmul(r, r.T), np.eye(3), atol=1e-9) or not fm.det3(r) > 0:
        raise ImportOptionError("rotation must be a proper rotation (orthonormal, determinant +1); "
                                "use up_axis for axis flips and fix any scale in units")
    return r


def _resolve_units(units: str, largest: float, path: Path) -> tuple[str, float, str]:
    if units != "auto":
        return units, UNIT_SCALES[units], f"given: units={units!r}"
    try:
        unit, scale = guess_unit(largest)
    except ImportOptionError as e:
        raise AssetError(f"{path}: {e}") from None
    if unit == "m":
        why = f"auto: largest extent {largest:g} file units <= {AUTO_METRES_MAX:g}, read as metres"
    else:
        why = (f"auto: largest extent {largest:g} file units is over {AUTO_METRES_MAX:g} m, absurd for "
               f"a station, and within inch scale (<= {AUTO_INCHES_MAX:g}), read as inches")
    return unit, scale, why


# ----------------------------------------------------------------------------- reading

def _load_scene(path: Path, fmt: str):
    """(trimesh Scene, {geometry name: its triangle count as the file gives it}). trimesh's own
    processing (NaN/inf removal, vertex merging; OBJ and STL only, as `trimesh.load` would run it)
    runs after the count, so the faces it removes are counted as dropped."""
    import trimesh

    if path.suffix.lower() == ".gltf":  # trimesh's own error for bad JSON is misleading
        from allo_usd.core.files import InputRefused, read_user_json

        try:
            read_user_json(path, MAX_MODEL_BYTES, "glTF file")   # the read gate; its message names line and column
        except InputRefused as e:
            raise AssetError(f"{path}: not a glTF file, {e.reason}; fix: give a glTF model") from None
    try:
        scene = trimesh.load(str(path), force="scene", process=False)
        if not isinstance(scene, trimesh.Scene):
            raise AssetError(f"{path}: trimesh returned {type(scene).__name__}, not a scene")
        parsed = {}
        for key, geom in scene.geometry.items():
            if isinstance(geom, trimesh.Trimesh):
                parsed[key] = len(geom.faces)
                if fmt != "gltf":   # trimesh.load processes OBJ and STL meshes (its glTF loader does not)
                    geom.process()
    except AssetError:
        raise
    except Exception as e:  # trimesh raises many types on bad input
        raise AssetError(f"{path}: trimesh could not read it as {fmt}: {type(e).__name__}: {e}") from e
    return scene, parsed


def _collect(scene, path: Path, fmt: str, parsed: dict | None = None) -> tuple[list[dict], int]:
    """World-space float64 triangles from every mesh instance, grouped by material, and the number
    of triangles the instances had as parsed (`parsed`: per geometry, before trimesh's processing)."""
    import trimesh
    from trimesh.visual.texture import TextureVisuals

    groups: dict[object, dict] = {}
    n_in = 0
    for node in scene.graph.nodes_geometry:
        matrix, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh):
            continue
        n_in += (parsed or {}).get(geom_name, len(geom.faces))
        if len(geom.faces) == 0:
            continue
        has_normals = _has_file_normals(geom)
        m = np.asarray(matrix, dtype=np.float64)
        verts = np.asarray(geom.vertices, dtype=np.float64)
        pts = fm.apply(m[:3, :3], verts) + m[:3, 3]
        faces = np.asarray(geom.faces, dtype=np.int64).reshape(-1, 3)
        faces = faces[((faces >= 0) & (faces < len(verts))).all(axis=1)]   # an index outside: dropped, counted
        if not len(faces):
            continue
        if fm.det3(m[:3, :3]) < 0:  # mirrored instance: keep faces counter-clockwise
            faces = faces[:, ::-1]
        visual = geom.visual
        material, uv = None, None
        if isinstance(visual, TextureVisuals):
            material = visual.material
            if _is_placeholder(material):
                material = None
            if visual.uv is not None and len(visual.uv) == len(verts):
                uv = np.asarray(visual.uv, dtype=np.float64)[faces].reshape(-1, 2)
        key = id(material) if material is not None else None
        g = groups.get(key)
        if g is None:
            label = getattr(material, "name", None) if material is not None else DEFAULT_MATERIAL.name
            g = groups[key] = {"material": material, "label": label, "chunks": []}
        g["chunks"].append((pts, faces, uv, has_normals))
    if n_in == 0:
        raise AssetError(f"{path}: no triangle mesh found; the {fmt} file is empty or trimesh could not "
                         f"make sense of it (corrupt file?)")

    out = []
    for g in groups.values():
        pts, faces, uvs, any_uv, smooth, offset = [], [], [], False, True, 0
        for p, f, uv, has_n in g["chunks"]:
            pts.append(p)
            faces.append(f + offset)
            offset += len(p)
            any_uv = any_uv or uv is not None
            smooth = smooth and has_n
        for p, f, uv, _ in g["chunks"]:
            uvs.append(uv if uv is not None else np.zeros((3 * len(f), 2)))
        out.append({"material": g["material"], "label": g["label"], "points": np.concatenate(pts),
                    "faces": np.concatenate(faces), "uv": np.concatenate(uvs) if any_uv else None,
                    "smooth": smooth})
    return out, n_in


def _has_file_normals(geom) -> bool:
    # trimesh caches vertex normals it was given by the loader; it has not computed any yet
    try:
        return "vertex_normals" in geom._cache
    except Exception:
        return False


def _is_placeholder(material) -> bool:
    """trimesh's stand-in for a textured mesh without material: an unnamed SimpleMaterial."""
    from trimesh.visual.material import SimpleMaterial

    return material is None or (isinstance(material, SimpleMaterial) and material.name is None)


def kept_triangles(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which triangles (faces: (M, 3) vertex indices into points (N, 3)) an import keeps: every
    index inside the points, every vertex finite, and a non-zero area (the scale-free test of the
    module doc). The one rule of every importer (mesh files here, USD hazards in
    allo_usd.usd.hazard), so each counts the same triangles as dropped."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    inside = ((f >= 0) & (f < len(points))).all(axis=1)
    tri = np.asarray(points, dtype=np.float64)[np.where(inside[:, None], f, 0)]
    finite = inside & np.isfinite(tri).all(axis=(1, 2))
    tri = np.where(finite[:, None, None], tri, 0.0)
    area2 = fm.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    edge2 = np.square(np.diff(tri[:, [0, 1, 2, 0]], axis=1)).sum(axis=2).max(axis=1)
    return finite & (area2 > 2.0 * _DEGENERATE_REL_AREA * edge2) & (area2 > 0.0)


def _clean(g: dict) -> None:
    """Drop the triangles `kept_triangles` refuses, then unused vertices (in place)."""
    p, f = g["points"], g["faces"]
    keep = kept_triangles(p, f)
    f = f[keep]
    if g["uv"] is not None:
        g["uv"] = g["uv"].reshape(-1, 3, 2)[keep].reshape(-1, 2)
    used, inverse = np.unique(f, return_inverse=True)
    g["points"] = p[used]
    g["faces"] = inverse.reshape(-1, 3).astype(np.int64)


# ----------------------------------------------------------------------------- materials

def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, fm.power((c + 0.055) / 1.055, 2.4))


def _as_unit_floats(value, n: int) -> np.ndarray | None:
    if value is None:
        return None
    a = np.asarray(value).reshape(-1)
    a = a / 255.0 if a.dtype.kind in "ui" else a.astype(np.float64)
    return np.clip(a[:n], 0.0, 1.0) if len(a) >= n else None


def _texture_array(image, max_size: int) -> np.ndarray:
    from PIL import Image

    img = image if isinstance(image, Image.Image) else Image.fromarray(np.asarray(image))
    img = img.convert("RGB")
    w, h = img.size
    if max(w, h) > max_size:
        s = max_size / max(w, h)
        img = img.resize((max(1, round(w * s)), max(1, round(h * s))), Image.LANCZOS)
    return np.ascontiguousarray(np.asarray(img, dtype=np.uint8))


def _convert_material(src, name: str, max_size: int, *, has_uv: bool, path: Path
                      ) -> tuple[Material, np.ndarray | None]:
    from trimesh.visual.material import PBRMaterial, SimpleMaterial

    if src is None:
        return Material(name, DEFAULT_MATERIAL.base_color, DEFAULT_MATERIAL.metallic,
                        DEFAULT_MATERIAL.roughness), None
    emissive = (0.0, 0.0, 0.0)
    if isinstance(src, PBRMaterial):
        base = _as_unit_floats(src.baseColorFactor, 3)
        base = np.ones(3) if base is None else base  # glTF factors are linear already
        metallic = 1.0 if src.metallicFactor is None else float(src.metallicFactor)
        roughness = 1.0 if src.roughnessFactor is None else float(src.roughnessFactor)
        e = _as_unit_floats(src.emissiveFactor, 3)
        emissive = (0.0, 0.0, 0.0) if e is None else tuple(float(x) for x in e)
        image = src.baseColorTexture
    elif isinstance(src, SimpleMaterial):
        kd = _as_unit_floats(src.diffuse, 3)
        base = np.full(3, 0.8) if kd is None else _srgb_to_linear(kd)
        metallic = 0.0
        ns = src.glossiness
        roughness = 0.5 if ns is None else float(np.clip(np.sqrt(2.0 / (max(float(ns), 0.0) + 2.0)), 0.05, 1.0))
        image = src.image
    else:  # an unknown trimesh material type: use the default look
        return Material(name, DEFAULT_MATERIAL.base_color, DEFAULT_MATERIAL.metallic,
                        DEFAULT_MATERIAL.roughness), None

    tex = None
    if image is not None:
        try:
            tex = _texture_array(image, max_size)
        except Exception as e:
            raise AssetError(f"{path}: base colour texture of material {name!r} could not be read: "
                             f"{type(e).__name__}: {e}") from e
        if not has_uv:  # nothing can map it: fold its mean colour into the base colour
            base = base * _srgb_to_linear(tex.reshape(-1, 3).mean(axis=0) / 255.0)
            tex = None
    key = f"{name}_base_color" if tex is not None else None
    mat = Material(name, tuple(float(x) for x in np.clip(base, 0.0, 1.0)),
                   float(np.clip(metallic, 0.0, 1.0)), float(np.clip(roughness, 0.0, 1.0)),
                   key, emissive)
    return mat, tex


# ----------------------------------------------------------------------------- names

def _sanitise(raw: str | None, prefix: str, fallback: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_]", "_", str(raw or "").strip())
    if not s:
        return fallback
    if s[0].isdigit():
        s = prefix + s
    return s


class _Namer:
    """Unique identifier names for materials (and their parts)."""

    def __init__(self) -> None:
        self.seen: set[str] = set()
        self.count = 0

    def __call__(self, raw: str | None) -> str:
        self.count += 1
        base = _sanitise(raw, "m_", f"material_{self.count}")
        name, k = base, 1
        while name in self.seen:
            k += 1
            name = f"{base}_{k}"
        self.seen.add(name)
        return name
