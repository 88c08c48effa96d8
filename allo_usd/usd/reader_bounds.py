"""What the scene-layer reader lets through, and the checks that hold a layer to it.

The bounds table (the constants below: docs/reliability/reliability.md, section 2) keeps every value the
reader hands to Blender inside the hard limits of the bpy property it ends in, and bounds the size
of what the reader takes in at all. The checks turn a value outside it into a LayerError that
names the attribute, the value, the allowed range and the fix: numbers and vectors (`_number`,
`_vector`, `_colour`), lens values stored as float32 (`as_stored`, `snap`, `_millimetres`), a
prim's transform (`world_matrix`: finite xformOps, real scale, distance from the station), a
mesh's topology (`mesh_topology`), a texture file (`check_texture_file`) and the hierarchy's size
(`_check_size`). The reader (allo_usd.usd.read), the base stage's geometry
(allo_usd.usd.stage_geometry) and a plan's own hazards (allo_usd.usd.hazard) read through them.
"""

from __future__ import annotations

import os

import numpy as np

from allo_usd.core.camera_model import CLIP_M, LENS_MM, MAX_SHIFT, SENSOR_MM  # the lens rows of the table below
from allo_usd.core.errors import LayerError
from allo_usd.core.files import file_problem
from allo_usd.core.limits import resolution_problem
from allo_usd.core import fixedmath as fm
from allo_usd.plan.settings import TARGET_PSNR_DB, TIME_LIMIT_S


# Sanity bounds on what a layer may ask for (the fuzz tests feed absurd values through here).
MAX_POSITION_M = 1e12          # any prim, from the station at the origin (the Sun is ~1.5e11 m away)
MAX_CAMERA_DISTANCE_M = 1e4    # the camera, from the station (ALLO cameras sit within ~70 m of it)
# |aperture offset| may pass MAX_SHIFT x its aperture by this fraction (then it is read as the edge): a
# plan's principal point at the image's edge, stored as float32 offset and aperture (and a sensor whose
# width and height a plan may give with their aspect 1e-6 off the image's), lands within it.
OFFSET_TOLERANCE = 4e-6

# What the reader lets through to Blender (docs/reliability/reliability.md, section 2). Each range lies
# inside the hard limits of the bpy RNA property the value ends in, so Blender never clamps a value the
# layer records: tests/usd/test_reader_bounds.py reads those limits from bpy and checks every one.
# LENS_MM, SENSOR_MM, CLIP_M, MAX_SHIFT: core.camera_model (a plan's [camera] is held to the same bounds).
SUN_ANGLE_DEG = (0.0, 180.0)      # SunLight.angle, 0..pi
SPOT_CONE_DEG = (0.5, 90.0)       # half angle; SpotLight.spot_size (the full cone) is 1..180 degrees
SPOT_SOFTNESS = (0.0, 1.0)        # SpotLight.spot_blend
SPOT_RADIUS_M = (0.0, 1000.0)     # SpotLight.shadow_soft_size
MAX_LIGHT = 1e20                  # irradiance (W/m^2) or radiance, after inputs:exposure: even a spot's power
                                  # 4 pi^2 r^2 L at the largest radius stays a finite float32 (Light.energy)
MAX_COLOUR = 1e6                  # light colour, diffuse colour, texture scale (Blender colours: 0..FLT_MAX)
UNIT_INTERVAL = (0.0, 1.0)        # metallic, roughness (Principled BSDF sockets, hard 0..1)
IOR = (1.0, 10.0)                 # UsdPreviewSurface ior (1: no specular layer)
MIN_SCALE = 1e-6                  # the smallest scale along any axis (a transform's smallest singular value):
MAX_SCALE = MAX_POSITION_M        # below it a prim is degenerate (a camera renders black, a mesh vanishes)
RENDER_SAMPLES = (1, 65536)       # Cycles samples (hard 1..16777216)
RENDER_BOUNCES = (0, 1024)        # Cycles max_bounces
RENDER_ADAPTIVE = (0.0, 1.0)      # Cycles adaptive_threshold
RENDER_SEED = (0, 2 ** 31 - 1)    # Cycles seed (hard 0..2^31-1; plans author seed % 2^31)
RENDER_THREADS = (0, 1024)        # RenderSettings.threads (1..1024; 0 = one per core)
RENDER_EXPOSURE = (0.0, 2.0 ** 32)  # Cycles film_exposure (> 0): the camera's linear exposure scale
RENDER_TARGET_PSNR = TARGET_PSNR_DB  # allo:render:targetPsnr, dB: (0, 100], 0 (or not authored) = fixed samples
RENDER_TIME_LIMIT = TIME_LIMIT_S      # allo:render:timeLimit, s: 0..1e6, 0 = none (only with a target)
CAMERA_EV = (-64.0, 64.0)         # UsdGeom.Camera exposure (EV, log2), like a light's inputs:exposure
CAMERA_EXPOSURE_FACTOR = (1e-9, 1e9)  # exposure:fStop, :time, :iso, :responsivity (each > 0)
# Size of what the reader takes in at all, checked before the expensive work.
MAX_DEPTH = 128                   # prim nesting depth (/World/Station/Geom/Truss is 4; the real stage reaches 6)
MAX_PRIMS = 200_000               # prims traversed (the real base stage composes ~180)
MAX_MESH_POINTS = 10_000_000      # per mesh (the real stage's largest has ~26k; 10M points is 120 MB as float32)
MAX_MESH_FACE_VERTICES = 40_000_000
MAX_SCENE_POINTS = 20_000_000     # over all meshes
MAX_TEXTURE_BYTES = 256 << 20     # a texture file
IMAGE_SIGNATURES = {b"\x89PNG\r\n\x1a\n": "PNG", b"\xff\xd8\xff": "JPEG", b"v/1\x01": "OpenEXR",
                    b"II*\x00": "TIFF", b"MM\x00*": "TIFF", b"#?RADIANCE": "Radiance HDR", b"#?RGBE": "Radiance HDR",
                    b"BM": "BMP"}
PNG_END = b"IEND\xaeB`\x82"       # the last chunk of every complete PNG


def _tf_message(exc) -> str:
    """The telling line of a Tf error: a parse error keeps USD's FILE:LINE:COL (allo_usd.usd.dependencies)."""
    from allo_usd.usd.dependencies import tf_message

    return tf_message(exc)


def _fmt(x) -> str:
    return str(x) if isinstance(x, (int, np.integer)) else f"{x:g}"


def _range(lo, hi, unit: str = "") -> str:
    return f"{_fmt(lo)}..{_fmt(hi)}" + (f" {unit}" if unit else "")


def _number(value, what: str, integer: bool = False, lo: float = -np.inf, hi: float = np.inf, unit: str = "",
            why: str = ""):
    """A finite int/float within [lo, hi], or a LayerError naming the attribute, the value and the range."""
    kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(value, bool) or not isinstance(value, kinds):
        raise LayerError(f"{what} must be {'an integer' if integer else 'a number'}, got {value!r}; fix the layer")
    if not (np.isfinite(value) and lo <= value <= hi):
        raise LayerError(f"{what} = {value!r} is outside {_range(lo, hi, unit)}{why}; fix the layer")
    return int(value) if integer else float(value)


def _vector(value, what: str, n: int, lo: float = -np.inf, hi: float = np.inf) -> tuple[float, ...]:
    """n finite numbers within [lo, hi] each (a vector or colour), or a LayerError naming the attribute."""
    out = None
    if not isinstance(value, (str, bytes, bool)) and value is not None:
        try:
            out = tuple(float(c) for c in value)
        except (TypeError, ValueError):
            pass
    if out is None or len(out) != n or not np.isfinite(out).all():
        raise LayerError(f"{what} must be {n} finite numbers, got {value!r}; fix the layer")
    if not all(lo <= c <= hi for c in out):
        raise LayerError(f"{what} = {tuple(out)} has a component outside {_range(lo, hi)}; fix the layer")
    return out


def _colour(value, what: str, hi: float = MAX_COLOUR) -> tuple[float, float, float]:
    """An RGB triple, each component finite and within 0..hi (Blender clamps negative colours to 0)."""
    return _vector(value, what, 3, 0.0, hi)


def _check_op_values(prim) -> None:
    """Every xformOp on `prim` holds finite values of its op's type."""
    from pxr import Gf, UsdGeom

    if not prim.IsA(UsdGeom.Xformable):
        return
    for op in UsdGeom.Xformable(prim).GetOrderedXformOps():
        v = op.Get()
        if isinstance(v, (Gf.Quatd, Gf.Quatf, Gf.Quath)):
            values = [v.GetReal(), *v.GetImaginary()]
            ok = op.GetOpType() == UsdGeom.XformOp.TypeOrient
        elif isinstance(v, (Gf.Matrix4d, Gf.Matrix4f)):
            values = [c for row in v for c in row]
            ok = op.GetOpType() == UsdGeom.XformOp.TypeTransform
        elif isinstance(v, (Gf.Vec3d, Gf.Vec3f, Gf.Vec3h)):
            values, ok = list(v), op.GetOpType() not in (UsdGeom.XformOp.TypeOrient,
                                                          UsdGeom.XformOp.TypeTransform)
        elif isinstance(v, (float, int)) and not isinstance(v, bool):
            values, ok = [v], op.GetOpType() in (UsdGeom.XformOp.TypeRotateX, UsdGeom.XformOp.TypeRotateY,
                                                 UsdGeom.XformOp.TypeRotateZ)
        else:
            values, ok = [], False
        if not ok:
            raise LayerError(f"{op.GetAttr().GetPath()} holds {v!r}, not a value of its op type; fix the "
                             "layer that sets it")
        if not np.isfinite(np.asarray(values, dtype=np.float64)).all():
            raise LayerError(f"{op.GetAttr().GetPath()} = {v} is not finite; fix the layer that sets it")
        if op.GetOpType() == UsdGeom.XformOp.TypeOrient:
            _check_quaternion(op.GetAttr().GetPath(), v, values)


def _check_xform_ops(prim, checked: set | None = None) -> None:
    """Every xformOp on the prim and its ancestors holds finite values of a transform type. With
    `checked` (a set of prim paths, shared across calls) each prim is checked once: the walk stops at
    an ancestor already checked, so reading a stage is linear in its prims, not in prims x depth."""
    p = prim
    while p and not p.IsPseudoRoot():
        if checked is not None:
            if p.GetPath() in checked:
                return
        _check_op_values(p)
        if checked is not None:
            checked.add(p.GetPath())
        p = p.GetParent()


def _check_quaternion(where, value, wxyz) -> None:
    """An orient op's quaternion must have a length: USD reads (0, 0, 0, 0) as no rotation, silently."""
    norm = float(fm.norm(np.asarray(wxyz, dtype=np.float64)))
    if norm < 1e-6:
        raise LayerError(f"{where} = {value} is not a rotation (a quaternion of length {norm:.3g}, which USD would "
                         "silently read as no rotation); fix the layer: write a unit quaternion (real, i, j, k), "
                         "e.g. (1, 0, 0, 0) for none")


def _check_position(cache, prim, m: np.ndarray, max_distance: float) -> None:
    """The prim's world position lies within `max_distance` metres of the station (the origin);
    the error names the outermost prim that is already too far (the one whose transform to fix)."""
    distance = float(fm.norm(m[:3, 3]))
    if distance <= max_distance:
        return
    culprit, where = prim, m[:3, 3]
    parent = prim.GetParent()
    while parent and not parent.IsPseudoRoot():
        t = np.array(cache.GetLocalToWorldTransform(parent), dtype=np.float64)[3, :3]  # row-vector: last row
        if not fm.norm(t) > max_distance:
            break
        culprit, where, parent = parent, t, parent.GetParent()
    raise LayerError(f"{culprit.GetPath()} is at {tuple(float(c) for c in where)}, {fm.norm(where):.3g} m "
                     f"from the station at the origin, beyond the {max_distance:,.0f} m allowed for it; fix the "
                     "xformOp:translate (or parent transform) that puts it there")


def _scales(m: np.ndarray) -> np.ndarray | None:
    """The scales along a transform's principal axes (singular values of its 3x3, largest first), or
    None if it is projective (its last row, column-vector convention, is not 0 0 0 1)."""
    if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), rtol=0, atol=1e-12):
        return None
    return np.linalg.svd(m[:3, :3], compute_uv=False)


def _degenerate(m: np.ndarray) -> bool:
    s = _scales(m)
    return s is None or not (s[-1] >= MIN_SCALE and s[0] <= MAX_SCALE)


def _check_scale(cache, prim, m: np.ndarray) -> None:
    """The transform scales every axis by MIN_SCALE..MAX_SCALE: a zero scale renders a camera black with an
    all-background mask and makes a mesh or a light vanish, silently. The error names the outermost prim
    whose own world transform is already degenerate (the one to fix)."""
    if not _degenerate(m):
        return
    culprit, culprit_m = prim, m
    parent = prim.GetParent()
    while parent and not parent.IsPseudoRoot():
        pm = np.array(cache.GetLocalToWorldTransform(parent), dtype=np.float64).T
        if not _degenerate(pm):
            break
        culprit, culprit_m, parent = parent, pm, parent.GetParent()
    s = _scales(culprit_m)
    what = ("is projective (its last row is not 0 0 0 1)" if s is None else
            f"scales its axes by {s[-1]:.3g}..{s[0]:.3g}, outside {_range(MIN_SCALE, MAX_SCALE)}")
    raise LayerError(f"{culprit.GetPath()} has a degenerate transform: it {what}, so {prim.GetPath()} would render "
                     "as nothing (a camera black, a mesh or light vanished); fix the layer: its xformOp:scale "
                     "(or xformOp:transform) must scale every axis by a real amount, e.g. (1, 1, 1)")


def _check_resolution(w: int, h: int, where) -> None:
    problem = resolution_problem(w, h)
    if problem:
        raise LayerError(f"{where}.resolution = ({w}, {h}): {problem}; fix the layer")


def world_matrix(cache, prim, max_distance: float = MAX_POSITION_M, checked: set | None = None) -> np.ndarray:
    """The prim's local-to-world matrix (column-vector convention), after checking every xformOp on it
    and its ancestors (`checked`: see _check_xform_ops), its scale and its distance from the station."""
    from pxr import Tf

    _check_xform_ops(prim, checked)
    try:
        m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64).T  # USD is row-vector
    except Tf.ErrorException as exc:
        raise LayerError(f"{prim.GetPath()} has an unreadable transform ({_tf_message(exc)}); fix the layer") from None
    if not np.isfinite(m).all():
        raise LayerError(f"{prim.GetPath()} has a non-finite transform; fix the layer that sets it")
    _check_scale(cache, prim, m)
    _check_position(cache, prim, m, max_distance)
    return m


def check_texture_file(path: str, where) -> None:
    """A texture must be a regular file of at most MAX_TEXTURE_BYTES that starts with a known image
    signature (a complete PNG also ends with its IEND chunk), or Blender renders it magenta or black and
    only logs an error. `where` names the attribute that points at it."""
    problem = file_problem(path, MAX_TEXTURE_BYTES)
    if problem:
        raise LayerError(f"texture {path} ({where}) {problem}; point it at an image file (fix the layer) or restore "
                         "the asset's texture")
    size = os.stat(path).st_size
    try:
        with open(path, "rb") as f:
            head = f.read(16)
            f.seek(max(0, size - 16))
            tail = f.read()
    except OSError as exc:
        raise LayerError(f"texture {path} ({where}) cannot be read ({exc.strerror}); restore the file") from None
    kind = next((k for sig, k in IMAGE_SIGNATURES.items() if head.startswith(sig)), None)
    if kind is None:
        raise LayerError(f"texture {path} ({where}) is not an image: it does not start with a "   # its bytes unshown
                         f"{', '.join(sorted(set(IMAGE_SIGNATURES.values())))} signature; restore the real image "
                         "(fix the asset)")
    if kind == "PNG" and not tail.endswith(PNG_END):
        raise LayerError(f"texture {path} ({where}) is a PNG cut short (it does not end with an IEND chunk); "
                         "restore the complete file (fix the asset)")


def _mesh_array(attr, what: str, kind: str, width: int | None, limit: int) -> np.ndarray:
    """A mesh's array attribute as numpy: `kind` "i" (integers) or "f" (numbers), `width` values per
    element (None: scalars), at most `limit` elements (checked before the copy)."""
    value = attr.Get() if attr else None
    if value is None:
        raise LayerError(f"mesh {what} is missing; regenerate its asset (fix the layer)")
    try:
        n = len(value)
    except TypeError:
        n = None
    if n is None or isinstance(value, (str, bytes)):
        raise LayerError(f"mesh {what} must be an array, got {value!r}; regenerate its asset (fix the layer)")
    if n > limit:
        raise LayerError(f"mesh {what} holds {n:,} values, at most {limit:,} allowed; decimate the mesh "
                         "(regenerate its asset)")
    arr = np.asarray(value)
    shape_ok = arr.ndim == 1 if width is None else (arr.ndim == 2 and arr.shape[1] == width) or n == 0
    if arr.dtype.kind not in ("iu" if kind == "i" else "iuf") or not shape_ok:
        want = "integers" if kind == "i" else f"{width}-vectors of numbers"
        raise LayerError(f"mesh {what} must hold {want}, got {attr.GetTypeName()}; regenerate its asset")
    return arr


def object_meshes(root, too_many):
    """The meshes that make an object's shape under `root` (a prim, or a stage's pseudo-root): every Mesh
    prim, instance proxies included, that is not invisible and whose purpose is not guide or proxy (those are
    not the object itself). More than MAX_PRIMS prims traversed raises too_many(MAX_PRIMS), an exception."""
    from pxr import Usd, UsdGeom

    for n, prim in enumerate(Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)), 1):
        if n > MAX_PRIMS:
            raise too_many(MAX_PRIMS)
        if not prim.IsA(UsdGeom.Mesh):
            continue
        imageable = UsdGeom.Imageable(prim)
        if (imageable.ComputeVisibility() != UsdGeom.Tokens.invisible
                and imageable.ComputePurpose() not in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy)):
            yield prim


def mesh_topology(prim) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points float32 (N, 3), faceVertexCounts int32, faceVertexIndices int32) of a UsdGeom.Mesh, checked:
    bounded sizes, finite points within MAX_POSITION_M of the mesh's origin, every face at least 3 vertices,
    counts summing to the indices, indices within the points (Blender crashes on a negative face count)."""
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    path = str(prim.GetPath())
    points = _mesh_array(mesh.GetPointsAttr(), f"{path}.points", "f", 3, MAX_MESH_POINTS)
    counts = _mesh_array(mesh.GetFaceVertexCountsAttr(), f"{path}.faceVertexCounts", "i", None, MAX_MESH_FACE_VERTICES)
    indices = _mesh_array(mesh.GetFaceVertexIndicesAttr(), f"{path}.faceVertexIndices", "i", None,
                          MAX_MESH_FACE_VERTICES)
    if len(points) == 0 or len(counts) == 0:
        raise LayerError(f"mesh {path} has no points or faces; regenerate its asset")
    with np.errstate(over="ignore", invalid="ignore"):
        points = points.astype(np.float32)
    if not np.isfinite(points).all():
        raise LayerError(f"mesh {path} has NaN or infinite points; regenerate its asset")
    reach = float(np.abs(points).max())
    if reach > MAX_POSITION_M:
        raise LayerError(f"mesh {path}.points reach {reach:.3g} m from the mesh's origin, beyond the "
                         f"{MAX_POSITION_M:g} m allowed; regenerate its asset")
    if counts.min() < 3:
        face = int(np.argmin(counts))
        raise LayerError(f"mesh {path}.faceVertexCounts[{face}] = {int(counts[face])}: every face needs at least 3 "
                         "vertices; regenerate its asset")
    total = int(counts.astype(np.int64).sum())
    if total != len(indices):
        raise LayerError(f"mesh {path}.faceVertexCounts sum to {total:,}, but faceVertexIndices holds "
                         f"{len(indices):,}; regenerate its asset")
    if indices.min() < 0 or indices.max() >= len(points):
        bad = int(indices.min()) if indices.min() < 0 else int(indices.max())
        raise LayerError(f"mesh {path}.faceVertexIndices holds {bad}, outside the points 0..{len(points) - 1}; "
                         "regenerate its asset")
    return points, counts.astype(np.int32), indices.astype(np.int32)


def as_stored(bounds: tuple[float, float]) -> tuple[float, float]:
    """`bounds` widened to what a float attribute can hold of them: the float32 at or just outside
    each end. A layer stores a lens value as a float32, so a plan's edge (focal_length_mm = 1, stored as
    0.0099999998 scene units) must pass. The plan's bounds and the reader's then agree at every edge
    (tests/usd/test_camera_bounds.py); `snap` brings such a value back to the edge before it reaches Blender."""
    lo, hi = float(np.float32(bounds[0])), float(np.float32(bounds[1]))
    return min(lo, bounds[0]), max(hi, bounds[1])


def snap(value: float, bounds: tuple[float, float]) -> float:
    """`value`, within as_stored(bounds), moved onto `bounds` if the float32 rounding put it just outside."""
    return min(max(value, bounds[0]), bounds[1])


def _millimetres(value, what: str, bounds: tuple[float, float], blender: str) -> float:
    """A lens value in tenths of a scene unit (metres: 100 mm per unit), in mm within `bounds` (a
    float32 just outside an edge, as a plan's edge is stored, is read as the edge: as_stored, snap)."""
    v = _number(value, what)
    lo, hi = as_stored((bounds[0] / 100.0, bounds[1] / 100.0))
    mm = v * 100.0
    if not lo <= v <= hi:
        raise LayerError(f"{what} = {value!r} ({mm:.3g} mm) is outside {_range(bounds[0] / 100, bounds[1] / 100)} "
                         f"({_range(*bounds, 'mm')}, within Blender's {blender}, which would clamp it); fix the layer")
    return snap(mm, bounds)


def _short(path) -> str:
    parts = str(path).split("/")
    return str(path) if len(parts) <= 6 else "/".join(parts[:4] + ["..."] + parts[-1:])


def _check_size(prim, count: int, layer_path) -> None:
    """Bound the hierarchy as it is traversed, before anything costly happens at a prim (reading time
    grew with the square of the nesting depth: 10,000 nested Xforms took about 30 s)."""
    if count > MAX_PRIMS:
        raise LayerError(f"{layer_path}: the composed stage holds more than {MAX_PRIMS:,} prims, the most a scene may "
                         "have; fix the layer: simplify or merge its prims")
    depth = prim.GetPath().pathElementCount
    if depth > MAX_DEPTH:
        raise LayerError(f"{layer_path}: {_short(prim.GetPath())} is nested {depth} levels deep, beyond the "
                         f"{MAX_DEPTH} allowed; fix the layer: flatten its hierarchy")
