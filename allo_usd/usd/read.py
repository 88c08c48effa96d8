"""Composed USD stage -> SceneDescription. Uses pxr only; never imports bpy.

One reader function per prim type (mesh, material, camera, lights, render settings); the
stage is the scene, this module is a one-way translation of it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from allo_usd.usd import attributes as A
from allo_usd.usd import layout, schema
from allo_usd.core.labels import BACKGROUND, CLASS_IDS
from allo_usd.plan.settings import DENOISE_PREFILTERS, DENOISE_QUALITIES
from allo_usd.usd.description import (CameraDesc, EffectsDesc, LightLink, MaterialDesc, MeshDesc, RenderDesc,
                                      SceneDescription, SpotDesc, SunDesc)
from allo_usd.core.camera_model import CLIP_M, LENS_MM, MAX_SHIFT, SENSOR_MM
from allo_usd.core.errors import LayerError
from allo_usd.core.files import file_problem
from allo_usd.core.limits import resolution_problem
from allo_usd.core.scene_labels import SPLITS, VARIANTS, label_problem
from allo_usd.usd.base_stage import RENDER_VARS
from allo_usd.plan.settings import DEFAULT_PASSES
from allo_usd.core import fixedmath as fm


# Sanity bounds on what a layer may ask for (the fuzz tests feed absurd values through here).
MAX_POSITION_M = 1e12          # any prim, from the station at the origin (the Sun is ~1.5e11 m away)
MAX_CAMERA_DISTANCE_M = 1e4    # the camera, from the station (ALLO cameras sit within ~70 m of it)
# |aperture offset| may pass MAX_SHIFT x its aperture by this fraction (then it is read as the edge): a
# plan's principal point at the image's edge, stored as float32 offset and aperture (and a sensor whose
# width and height a plan may give with their aspect 1e-6 off the image's), lands within it.
OFFSET_TOLERANCE = 4e-6

# What the reader lets through to Blender (docs/reliability.md, section 2). Each range lies
# inside the hard limits of the bpy RNA property the value ends in, so Blender never clamps a value the
# layer records: tests/test_reader_bounds.py reads those limits from bpy and checks every one.
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


def open_stage(layer_path: str | Path):
    """Open a scene layer as a stage, turning every USD failure into a LayerError with a fix.

    Before USD opens anything, every file the composition reads is checked (allowed roots,
    regular file, size, layer extension: allo_usd.usd.dependencies.walk); the stage must then
    compose without errors, and the composed stage is checked against the roots again
    (allo_usd.usd.safety.check_stage, a second line of defence).
    """
    from pxr import Tf, Usd, UsdGeom

    from allo_usd.usd.dependencies import walk
    from allo_usd.usd.safety import check_stage

    schema.register()
    path = Path(layer_path)
    if not path.exists():
        raise LayerError(f"scene layer {path} does not exist; check the path")
    opened = walk(path)  # its Sdf layers stay open until the stage holds them: USD parses each once
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise LayerError(f"{path} is not a readable USD layer ({_tf_message(exc)}); "
                         "re-author it with `allo-usd author` or restore it from the plan") from None
    del opened
    if stage is None:
        raise LayerError(f"{path} could not be opened as a USD stage; re-author it")
    errors = stage.GetCompositionErrors()
    if errors:
        raise LayerError(f"{path} does not compose: {_tf_message_list(errors)}; restore the missing "
                         "sublayer/reference or fix its path in the layer")
    check_stage(stage, path)
    if UsdGeom.GetStageUpAxis(stage) != UsdGeom.Tokens.z or UsdGeom.GetStageMetersPerUnit(stage) != 1.0:
        raise LayerError(f"{path}: stage must be Z-up in metres (upAxis='Z', metersPerUnit=1)")
    return stage


def _tf_message_list(errors) -> str:
    out = []
    for e in errors[:3]:
        try:
            out.append(str(e).strip())
        except UnicodeDecodeError:
            out.append("an error whose text is not UTF-8")
    return "; ".join(out) + (f" (and {len(errors) - 3} more)" if len(errors) > 3 else "")


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


def _class_id(prim) -> int:
    from pxr import UsdSemantics

    p = prim
    while p and not p.IsPseudoRoot():
        if p.HasAPI(UsdSemantics.LabelsAPI, "class"):
            labels = UsdSemantics.LabelsAPI(p, "class").GetLabelsAttr().Get() or []
            for label in labels:
                if label in CLASS_IDS:
                    return CLASS_IDS[label]
        p = p.GetParent()
    return BACKGROUND


def _ray_visibility(prim) -> str:
    p = prim
    while p and not p.IsPseudoRoot():
        attr = p.GetAttribute(A.RAY_VISIBILITY.name)
        if attr and attr.HasAuthoredValue():
            return str(attr.Get())
        p = p.GetParent()
    return "all"


def _input(shader, name, default):
    inp = shader.GetInput(name)
    if not inp:
        return default, None
    src = inp.GetConnectedSource()
    if src and src[0]:
        return default, src
    value = inp.Get()
    return (default if value is None else value), None


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
        raise LayerError(f"texture {path} ({where}) is not an image: it starts with {head[:8]!r}, not a "
                         f"{', '.join(sorted(set(IMAGE_SIGNATURES.values())))} signature; restore the real image "
                         "(fix the asset)")
    if kind == "PNG" and not tail.endswith(PNG_END):
        raise LayerError(f"texture {path} ({where}) is a PNG cut short (it does not end with an IEND chunk); "
                         "restore the complete file (fix the asset)")


def _read_texture(material_path: str, prim) -> tuple[str, tuple[float, float, float]]:
    """(file, colour scale) of the UsdUVTexture a diffuseColor is connected to; an entry of a package
    (a .usdz scene) is read through a copy of it (allo_usd.usd.dependencies.unpacked_file)."""
    from pxr import Ar, Sdf, UsdShade

    tex = UsdShade.Shader(prim)
    where = prim.GetPath()
    if tex.GetIdAttr().Get() != "UsdUVTexture":
        raise LayerError(f"material {material_path}: diffuseColor is connected to {where}, which is not a "
                         "UsdUVTexture (the only texture allo-usd renders); fix the layer")
    inp = tex.GetInput("file")
    asset = inp.Get() if inp else None
    if not isinstance(asset, Sdf.AssetPath):
        raise LayerError(f"{where}.inputs:file must be an asset path, got {asset!r}; fix the layer")
    texture = asset.resolvedPath
    if not texture:
        raise LayerError(f"material {material_path}: texture {asset} does not resolve to a file; restore the "
                         "asset's textures/ folder")
    if texture.endswith("]") and Ar.IsPackageRelativePath(texture):  # PKG.usdz[entry]: Blender reads files only
        from allo_usd.usd.dependencies import unpacked_file

        texture = unpacked_file(texture, f"{where}.inputs:file")
    check_texture_file(texture, f"{where}.inputs:file")
    scale = tex.GetInput("scale").Get() if tex.GetInput("scale") else None
    colour = (1.0, 1.0, 1.0) if scale is None else _vector(scale, f"{where}.inputs:scale", 4, 0.0, MAX_COLOUR)[:3]
    return texture, colour


def read_material(material) -> MaterialDesc:
    """A UsdPreviewSurface material; every input is type-checked and bounded to what Blender's
    Principled BSDF takes without clamping."""
    path = str(material.GetPath())
    surface = material.ComputeSurfaceSource()[0]
    if not surface or surface.GetIdAttr().Get() != "UsdPreviewSurface":
        raise LayerError(f"material {path} has no UsdPreviewSurface; allo-usd renders UsdPreviewSurface only")

    def where(name: str) -> str:
        return f"{surface.GetPath()}.inputs:{name}"

    color, src = _input(surface, "diffuseColor", (0.18, 0.18, 0.18))
    texture = None
    if src is not None:
        texture, color = _read_texture(path, src[0].GetPrim())
    else:
        color = _colour(color, where("diffuseColor"))
    metallic = _number(_input(surface, "metallic", 0.0)[0], where("metallic"), lo=UNIT_INTERVAL[0], hi=UNIT_INTERVAL[1])
    roughness = _number(_input(surface, "roughness", 0.5)[0], where("roughness"), lo=UNIT_INTERVAL[0],
                        hi=UNIT_INTERVAL[1])
    emissive = _colour(_input(surface, "emissiveColor", (0.0, 0.0, 0.0))[0], where("emissiveColor"), MAX_LIGHT)
    ior = _number(_input(surface, "ior", 1.5)[0], where("ior"), lo=IOR[0], hi=IOR[1])
    opacity = _number(_input(surface, "opacity", 1.0)[0], where("opacity"), lo=UNIT_INTERVAL[0], hi=UNIT_INTERVAL[1])
    threshold = _number(_input(surface, "opacityThreshold", 0.0)[0], where("opacityThreshold"), lo=UNIT_INTERVAL[0],
                        hi=UNIT_INTERVAL[1])
    if threshold > 0:  # UsdPreviewSurface: drawn only where opacity >= opacityThreshold (a cut-out mask)
        opacity = 1.0 if opacity >= threshold else 0.0
    return MaterialDesc(path, color, metallic, roughness, texture, emissive, ior, opacity)


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


def _read_uv(prim, n_face_vertices: int) -> np.ndarray | None:
    """primvars:st, face-varying: one finite (u, v) per face vertex, or None when the mesh has none."""
    from pxr import Tf, UsdGeom

    path = prim.GetPath()
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if not (st and st.HasValue()):
        return None
    if st.GetInterpolation() != UsdGeom.Tokens.faceVarying:
        raise LayerError(f"mesh {path}: primvars:st must be faceVarying, not {st.GetInterpolation()}; regenerate "
                         "its asset")
    try:
        flat = st.ComputeFlattened()
    except Tf.ErrorException:
        flat = None
    uv = None if flat is None else np.asarray(flat)
    if uv is None or uv.dtype.kind not in "iuf" or uv.shape != (n_face_vertices, 2):
        shape = "nothing usable" if uv is None else f"{uv.shape[0]:,} values of {st.GetTypeName()}"
        raise LayerError(f"mesh {path}.primvars:st holds {shape}; faceVarying needs one (u, v) per face vertex "
                         f"({n_face_vertices:,}); regenerate its asset")
    if not np.isfinite(uv).all():
        raise LayerError(f"mesh {path}.primvars:st has NaN or infinite values; regenerate its asset")
    return uv.astype(np.float32)


def _smooth(mesh, path, n_points: int, n_faces: int, n_face_vertices: int) -> bool:
    """Whether the mesh is smooth-shaded: it has per-vertex normals (whose count must match their
    interpolation)."""
    from pxr import UsdGeom

    attr = mesh.GetNormalsAttr()
    if not attr.HasAuthoredValue():
        return False
    interp = mesh.GetNormalsInterpolation()
    need = {UsdGeom.Tokens.vertex: n_points, UsdGeom.Tokens.varying: n_points,
            UsdGeom.Tokens.faceVarying: n_face_vertices, UsdGeom.Tokens.uniform: n_faces,
            UsdGeom.Tokens.constant: 1}.get(interp)
    value = attr.Get()
    n = len(value) if value is not None and not isinstance(value, (str, bytes)) and hasattr(value, "__len__") else None
    if need is None or n != need:
        raise LayerError(f"mesh {path}.normals holds {n} values, but {interp} interpolation needs {need}; "
                         "regenerate its asset")
    return interp != UsdGeom.Tokens.faceVarying


def read_mesh(prim, cache, materials: dict, checked: set | None = None) -> MeshDesc:
    from pxr import UsdGeom, UsdShade

    path = str(prim.GetPath())
    points, counts, indices = mesh_topology(prim)
    uv = _read_uv(prim, len(indices))
    smooth = _smooth(UsdGeom.Mesh(prim), path, len(points), len(counts), len(indices))
    bound = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
    if bound:
        key = str(bound.GetPath())
        if key not in materials:
            materials[key] = read_material(bound)
    else:
        key = "__default__"
        materials.setdefault(key, MaterialDesc(key, (0.5, 0.5, 0.5), 0.0, 0.5))
    return MeshDesc(path, points, counts, indices, uv, smooth, key, world_matrix(cache, prim, checked=checked),
                    _class_id(prim), _ray_visibility(prim))


def as_stored(bounds: tuple[float, float]) -> tuple[float, float]:
    """`bounds` widened to what a float attribute can hold of them: the float32 at or just outside
    each end. A layer stores a lens value as a float32, so a plan's edge (focal_length_mm = 1, stored as
    0.0099999998 scene units) must pass. The plan's bounds and the reader's then agree at every edge
    (tests/test_camera_bounds.py); `snap` brings such a value back to the edge before it reaches Blender."""
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


def read_camera(prim, cache, checked: set | None = None) -> CameraDesc:
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    where = prim.GetPath()
    projection = cam.GetProjectionAttr().Get()
    if projection != UsdGeom.Tokens.perspective:
        raise LayerError(f"{where}.projection = {projection!r}: allo-usd renders perspective cameras only; fix the "
                         "layer")
    focal = _millimetres(cam.GetFocalLengthAttr().Get(), f"{where}.focalLength", LENS_MM, "Camera.lens")
    width = _millimetres(cam.GetHorizontalApertureAttr().Get(), f"{where}.horizontalAperture", SENSOR_MM,
                         "Camera.sensor_width")
    height = _millimetres(cam.GetVerticalApertureAttr().Get(), f"{where}.verticalAperture", SENSOR_MM,
                          "Camera.sensor_height")
    near, far = _vector(cam.GetClippingRangeAttr().Get(), f"{where}.clippingRange", 2)
    clip_lo, clip_hi = as_stored(CLIP_M)
    if not clip_lo <= near < far <= clip_hi:
        raise LayerError(f"{where}.clippingRange = ({near:g}, {far:g}) must be near < far within "
                         f"{_range(*CLIP_M, 'm')} (Blender's Camera.clip_start/clip_end); fix the layer")
    near, far = snap(near, CLIP_M), snap(far, CLIP_M)
    offsets = []
    for attr, aperture in ((cam.GetHorizontalApertureOffsetAttr(), width), (cam.GetVerticalApertureOffsetAttr(), height)):
        mm = _number(attr.Get(), f"{where}.{attr.GetName()}") * 100.0
        edge = MAX_SHIFT * aperture
        if not abs(mm) <= edge * (1.0 + OFFSET_TOLERANCE):
            raise LayerError(f"{where}.{attr.GetName()} = {attr.Get()!r} ({mm:.3g} mm) puts the principal point outside "
                             f"the image (|offset| <= {MAX_SHIFT:g} x the {aperture:.3g} mm aperture); fix the layer")
        offsets.append(snap(mm, (-edge, edge)) + 0.0)
    m = world_matrix(cache, prim, MAX_CAMERA_DISTANCE_M, checked)
    return CameraDesc(m, focal, width, height, (near, far), str(where), *offsets)


# UsdGeom.Camera exposure attributes: (attribute getter name, fallback, bounds). The fallbacks are the
# schema's (usd-core 26), so a camera with none authored has a linear exposure scale of 1.
CAMERA_EXPOSURE_ATTRS = (("GetExposureAttr", 0.0, CAMERA_EV), ("GetExposureFStopAttr", 1.0, CAMERA_EXPOSURE_FACTOR),
                         ("GetExposureTimeAttr", 1.0, CAMERA_EXPOSURE_FACTOR),
                         ("GetExposureIsoAttr", 100.0, CAMERA_EXPOSURE_FACTOR),
                         ("GetExposureResponsivityAttr", 1.0, CAMERA_EXPOSURE_FACTOR))


def camera_exposure(prim) -> tuple[float, dict]:
    """The camera's linear exposure scale as UsdGeom.Camera defines it (ComputeLinearExposureScale):
    (exposure:time x exposure:iso / 100 / exposure:fStop^2) x 2^exposure x exposure:responsivity, each
    attribute bounded; returns (scale, {attribute name: value}). The scale multiplies scene radiance
    into the film (Cycles film_exposure)."""
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    where = prim.GetPath()
    values = {}
    for getter, fallback, (lo, hi) in CAMERA_EXPOSURE_ATTRS:
        attr = getattr(cam, getter)()
        value = attr.Get() if attr else None
        values[attr.GetName()] = _number(fallback if value is None else value, f"{where}.{attr.GetName()}", lo=lo, hi=hi)
    ev, f_stop, time, iso, responsivity = values.values()
    scale = time * iso / 100.0 / f_stop ** 2 * 2.0 ** ev * responsivity
    if not RENDER_EXPOSURE[0] < scale <= RENDER_EXPOSURE[1]:
        raise LayerError(f"{where}: the exposure attributes ({', '.join(f'{k}={v:g}' for k, v in values.items())}) give "
                         f"a linear exposure scale of {scale:.3g}, outside {_range(*RENDER_EXPOSURE)} (exclusive of 0); "
                         "fix the layer: the scale is time x iso/100 / fStop^2 x 2^exposure x responsivity")
    return scale, values


def read_light_link(prim, mesh_paths) -> LightLink | None:
    """The meshes a light lights, from its UsdLux `collection:lightLink` membership: None when it
    lights every mesh, else the shorter list (the meshes it skips, or the only ones it lights)."""
    from pxr import Sdf, UsdLux

    query = UsdLux.LightAPI(prim).GetLightLinkCollectionAPI().ComputeMembershipQuery()
    lit = [query.IsPathIncluded(Sdf.Path(p)) for p in mesh_paths]
    if all(lit):
        return None
    on = tuple(p for p, x in zip(mesh_paths, lit) if x)
    off = tuple(p for p, x in zip(mesh_paths, lit) if not x)
    return LightLink(True, off) if len(off) <= len(on) else LightLink(False, on)


def _intensity(light, where) -> float:
    """inputs:intensity x 2^inputs:exposure (UsdLux: an un-normalised light's emitted radiance), non-negative
    and at most MAX_LIGHT."""
    intensity = _number(light.GetIntensityAttr().Get(), f"{where}.inputs:intensity", lo=0.0, hi=MAX_LIGHT)
    exposure_attr = light.GetExposureAttr().Get()
    exposure = _number(0.0 if exposure_attr is None else exposure_attr, f"{where}.inputs:exposure", lo=-64, hi=64)
    value = intensity * 2.0 ** exposure
    if value > MAX_LIGHT:
        raise LayerError(f"{where}.inputs:exposure = {exposure:g} makes the intensity {value:.3g}, above the "
                         f"{MAX_LIGHT:g} allowed; fix the layer")
    return value


def _normalize(light, where) -> bool:
    value = light.GetNormalizeAttr().Get()
    if value is None:
        return False  # the schema's fallback
    if not isinstance(value, bool):
        raise LayerError(f"{where}.inputs:normalize must be a bool, got {value!r}; fix the layer")
    return value


def distant_size_factor(angle_deg: float) -> float:
    """UsdLux's size factor of a DistantLight (the OpenUSD usdLux documentation, "Normalizing Distant
    Lights"): the cosine-weighted solid angle of its disc, pi sin^2(theta) with theta half the angular
    diameter (pi (2 - sin^2 theta) beyond a hemisphere; 1 for a zero angle). An un-normalised light's
    illuminance at normal incidence is its radiance (intensity) times this; a normalised light's
    intensity is that illuminance itself."""
    theta = np.radians(angle_deg) / 2.0
    if theta == 0.0:
        return 1.0
    s2 = float(np.sin(theta)) ** 2
    return float(np.pi * (s2 if theta <= np.pi / 2 else 2.0 - s2))


def sun_irradiance(intensity: float, angle_deg: float, normalize: bool) -> float:
    """The irradiance (W/m^2, at normal incidence) a DistantLight means under UsdLux: with normalize,
    intensity x 2^exposure itself; without, that radiance times the disc's size factor."""
    return intensity if normalize else intensity * distant_size_factor(angle_deg)


def read_sun(prim, cache, mesh_paths=None, checked: set | None = None) -> SunDesc | None:
    """A UsdLux.DistantLight as a sun lamp, its irradiance as the spec defines it (inputs:normalize
    honoured); None when it is off (intensity 0: umbra, or a total eclipse of the body it lights) or
    lights none of `mesh_paths` (when given, its light linking is resolved against them). A lamp whose
    light link names only some objects (a body's own lamp) is not drawn in camera rays; any other is
    (the Sun's disc, as a renderer that draws a DistantLight's angular extent shows it)."""
    from pxr import UsdLux

    light = UsdLux.DistantLight(prim)
    where = prim.GetPath()
    intensity = _intensity(light, where)
    if intensity == 0.0:
        return None  # the lamp is off
    link = None if mesh_paths is None else read_light_link(prim, mesh_paths)
    if link is not None and not (link.exclude or link.paths):
        return None  # it lights nothing
    m = world_matrix(cache, prim, checked=checked)
    direction = m[:3, 2] / np.linalg.norm(m[:3, 2])  # light travels along -Z, so +Z points at the Sun
    angle = _number(light.GetAngleAttr().Get(), f"{where}.inputs:angle", lo=SUN_ANGLE_DEG[0], hi=SUN_ANGLE_DEG[1],
                    unit="degrees", why=" (Blender's SunLight.angle)")
    irradiance = sun_irradiance(intensity, angle, _normalize(light, where))
    return SunDesc(tuple(direction), irradiance, angle, _colour(light.GetColorAttr().Get(), f"{where}.inputs:color"),
                   str(where), link, camera_visible=link is None or link.exclude)


def read_spot(prim, cache, checked: set | None = None) -> SpotDesc:
    """A UsdLux.SphereLight with ShapingAPI as a Blender spot lamp (without ShapingAPI: a hemisphere,
    the widest cone Blender's spot draws)."""
    from pxr import UsdLux

    light = UsdLux.SphereLight(prim)
    shaping = UsdLux.ShapingAPI(prim)
    shaped = prim.HasAPI(UsdLux.ShapingAPI)
    cone = shaping.GetShapingConeAngleAttr().Get() if shaped else SPOT_CONE_DEG[1]
    softness = shaping.GetShapingConeSoftnessAttr().Get() if shaped else None
    where = prim.GetPath()
    intensity = _intensity(light, where)
    radius = _number(light.GetRadiusAttr().Get(), f"{where}.inputs:radius", lo=SPOT_RADIUS_M[0], hi=SPOT_RADIUS_M[1],
                     unit="m")
    matrix = world_matrix(cache, prim, checked=checked)
    if _normalize(light, where):  # UsdLux: radiance = intensity / the sphere's world-space surface area
        world_radius = radius * float(np.prod(np.linalg.svd(matrix[:3, :3], compute_uv=False)) ** (1.0 / 3.0))
        area = 4.0 * np.pi * world_radius ** 2
        intensity = intensity / area if area > 0 else intensity
    cone = _number(cone, f"{where}.inputs:shaping:cone:angle", lo=SPOT_CONE_DEG[0], hi=SPOT_CONE_DEG[1],
                   unit="degrees", why=" (a half angle: Blender's spot cone is 1..180 degrees in all)")
    softness = _number(0.0 if softness is None else softness, f"{where}.inputs:shaping:cone:softness",
                       lo=SPOT_SOFTNESS[0], hi=SPOT_SOFTNESS[1])
    return SpotDesc(matrix, radius, intensity,
                    _colour(light.GetColorAttr().Get(), f"{where}.inputs:color"), cone, softness, str(where))


def _get(prim, name, default=None):
    attr = prim.GetAttribute(name)
    value = attr.Get() if attr else None
    return default if value is None else value


def read_render(settings_prim, exposure: float = 1.0) -> tuple[RenderDesc, EffectsDesc]:
    """The render settings prim; `exposure` is the camera's linear exposure scale (camera_exposure)."""
    from pxr import Gf, UsdRender

    settings = UsdRender.Settings(settings_prim)
    res = settings.GetResolutionAttr().Get()
    if not isinstance(res, Gf.Vec2i):
        raise LayerError(f"{settings_prim.GetPath()}.resolution must be an int2, got {res!r}; fix the layer")
    w, h = int(res[0]), int(res[1])
    _check_resolution(w, h, settings_prim.GetPath())

    def num(name, default, integer=False, bounds=(-np.inf, np.inf)):
        return _number(_get(settings_prim, name, default), name, integer, *bounds)

    def flag(name, default):
        value = _get(settings_prim, name, default)
        if not isinstance(value, bool):
            raise LayerError(f"{name} must be a bool, got {value!r}; fix the layer")
        return value

    def choice(name, default, allowed):
        value = str(_get(settings_prim, name, default))
        if value not in allowed:
            raise LayerError(f"{name} = {value!r} is not one of {', '.join(allowed)}; fix the layer")
        return value

    samples = num(A.RENDER_SAMPLES.name, 64, True, RENDER_SAMPLES)
    outputs = []
    for product_path in settings.GetProductsRel().GetForwardedTargets():
        product = UsdRender.Product(settings_prim.GetStage().GetPrimAtPath(product_path))
        for var_path in product.GetOrderedVarsRel().GetForwardedTargets():
            outputs.append(var_pass(var_path.name))
    render = RenderDesc(resolution=(w, h), preset=str(_get(settings_prim, A.RENDER_PRESET.name, "preview")),
                        samples=samples,
                        adaptive_threshold=num(A.RENDER_ADAPTIVE_THRESHOLD.name, 0.0, bounds=RENDER_ADAPTIVE),
                        denoise=flag(A.RENDER_DENOISE.name, True),
                        max_bounces=num(A.RENDER_MAX_BOUNCES.name, 8, True, RENDER_BOUNCES),
                        seed=num(A.RENDER_SEED.name, 0, True, RENDER_SEED), exposure=exposure,
                        threads=num(A.RENDER_THREADS.name, 0, True, RENDER_THREADS), outputs=tuple(outputs),
                        denoise_prefilter=choice(A.RENDER_DENOISE_PREFILTER.name, "FAST", DENOISE_PREFILTERS),
                        denoise_quality=choice(A.RENDER_DENOISE_QUALITY.name, "BALANCED", DENOISE_QUALITIES))
    noise = flag(A.EFFECTS_SENSOR_NOISE.name, False)
    effects = EffectsDesc(sensor_noise=noise, glare=flag(A.EFFECTS_GLARE.name, False),
                          inspection_light=flag(A.EFFECTS_INSPECTION_LIGHT.name, True),
                          body_shine=flag(A.EFFECTS_BODY_SHINE.name, True),
                          sensor=read_sensor(settings_prim) if noise else None)
    return render, effects


def read_sensor(settings_prim):
    """The sensor's EMVA 1288 parameters (allo:effects:sensor:*); unauthored ones take the schema's
    fallbacks, and a gain or exposure time of 0 means "derive it" (allo_usd.output.sensor_noise)."""
    from allo_usd.core.sensor import DERIVED_WHEN_ZERO, SensorParams
    from allo_usd.usd.attributes import SENSOR_ATTRIBUTES
    from allo_usd.core.errors import AlloError

    defaults = SensorParams()
    values = {}
    for key, (name, type_name) in SENSOR_ATTRIBUTES.items():
        integer = type_name != "double"
        default = getattr(defaults, key)
        value = _number(_get(settings_prim, name, 0 if default is None else default), name, integer, lo=0)
        values[key] = None if key in DERIVED_WHEN_ZERO and value == 0 else value
    params = SensorParams(**values)
    try:
        params.validate()
    except AlloError as exc:
        raise LayerError(f"{settings_prim.GetPath()}: {exc}; fix the {A.SENSOR_PREFIX}* attributes") from None
    return params


def _check_variants(prim) -> None:
    """Every variant selection names a variant the prim's asset has (else USD silently composes none)."""
    if not prim.HasVariantSets():
        return
    sets = prim.GetVariantSets()
    for name in sets.GetNames():
        vset = sets.GetVariantSet(name)
        selection, choices = vset.GetVariantSelection(), vset.GetVariantNames()
        if selection not in choices and (selection or prim.GetPath().name == "Anomaly"):
            raise LayerError(f"{prim.GetPath()}: variant {name}={selection!r} is not one of {choices}; choose one of "
                             "those (unknown anomaly variant?)")


def read_meta(stage) -> dict:
    world = stage.GetDefaultPrim()
    meta = {}
    for attr in world.GetAttributes():
        name = attr.GetName()
        if name.startswith(A.NAMESPACE):
            value = attr.Get()
            meta[name[len(A.NAMESPACE):]] = tuple(value) if hasattr(value, "__len__") and not isinstance(value, str) else value
    provenance = dict(stage.GetRootLayer().customLayerData.get("allo", {}))
    meta["provenance"] = provenance
    anomaly = stage.GetPrimAtPath(layout.ANOMALY)
    if anomaly and anomaly.IsActive():
        meta["anomaly"] = {a.GetName().split(":")[-1]: a.Get() for a in anomaly.GetAttributes()
                           if a.GetName().startswith(A.ANOMALY_PREFIX)}
        meta["anomaly_model"] = anomaly_model(stage, anomaly)
    problem = label_problem(meta, required=False)   # dataset's check (core.scene_labels): never record what it refuses
    if problem:
        raise LayerError(f"{stage.GetRootLayer().identifier}: {problem} ({layout.WORLD}'s {A.SPLIT.name}, "
                         f"{A.VARIANT.name} and {layout.ANOMALY}'s {A.ANOMALY_PREFIX}* attributes); fix the layer: "
                         f"{A.SPLIT.name} is {' or '.join(SPLITS)}, {A.VARIANT.name} {' or '.join(VARIANTS)}")
    return meta


def anomaly_model(stage, prim) -> dict:
    """The anomaly's model frame for its pose (output.annotations): the prim's local-to-world (column
    vectors; its meshes' points map into this frame) and the file its strongest reference or payload
    names, relative to the root layer's directory (None when it is authored inline)."""
    from pxr import Usd, UsdGeom

    m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()), dtype=np.float64).T
    ref = next((spec.layer.ComputeAbsolutePath(r.assetPath) for spec in prim.GetPrimStack()
                for r in (*spec.referenceList.GetAddedOrExplicitItems(), *spec.payloadList.GetAddedOrExplicitItems())
                if r.assetPath), None)
    here = Path(stage.GetRootLayer().realPath or ".").parent
    return {"reference": None if not ref else os.path.relpath(ref, here), "local_to_world": m.tolist()}


def _world(stage, layer_path):
    """The stage's default prim, which must be /World (else USD reports 'Accessed invalid null prim')."""
    from pxr import Sdf

    prim = stage.GetDefaultPrim()
    if not prim or prim.GetPath() != Sdf.Path(layout.WORLD):
        name = stage.GetRootLayer().defaultPrim
        raise LayerError(f"{layer_path}: defaultPrim is {name or 'not set'!r}" +
                         ("" if prim or not name else ", which names no prim") +
                         f"; fix the layer: set defaultPrim = \"{layout.WORLD_NAME}\" in its metadata")
    return prim


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


def read_scene(layer_path: str | Path) -> SceneDescription:
    """Read a scene layer (composed over its base stage) into a plain description."""
    from pxr import Usd, UsdGeom, UsdLux, UsdRender

    stage = open_stage(layer_path)
    _world(stage, layer_path)
    settings_path = stage.GetMetadata("renderSettingsPrimPath") or layout.RENDER_SETTINGS
    settings_prim = stage.GetPrimAtPath(settings_path)
    if not settings_prim:
        raise LayerError(f"{layer_path}: no render settings at {settings_path}; the base stage sublayer is "
                         "missing or broken (check subLayers)")
    cam_targets = UsdRender.Settings(settings_prim).GetCameraRel().GetForwardedTargets()
    if not cam_targets or not stage.GetPrimAtPath(cam_targets[0]).IsA(UsdGeom.Camera):
        raise LayerError(f"{layer_path}: render settings name no camera; set {settings_path}.camera")
    render, effects = read_render(settings_prim, camera_exposure(stage.GetPrimAtPath(cam_targets[0]))[0])
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    checked: set = set()  # prims whose xformOps are checked (world_matrix)
    camera = read_camera(stage.GetPrimAtPath(cam_targets[0]), cache, checked)

    meshes, materials, sun_prims, spot = [], {}, [], None
    count = points = 0
    it = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.PrimIsActive & Usd.PrimIsDefined & ~Usd.PrimIsAbstract))
    for prim in it:
        count += 1
        _check_size(prim, count, layer_path)
        if prim.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(prim).ComputeVisibility() == UsdGeom.Tokens.invisible:
            it.PruneChildren()
            continue
        if prim.GetPath().HasPrefix(layout.RIG) or prim.GetPath().HasPrefix(layout.RENDER):
            it.PruneChildren()
            continue
        _check_variants(prim)
        if prim.IsA(UsdGeom.Mesh):
            meshes.append(read_mesh(prim, cache, materials, checked))
            points += len(meshes[-1].points)
            if points > MAX_SCENE_POINTS:
                raise LayerError(f"{layer_path}: the scene's meshes hold more than {MAX_SCENE_POINTS:,} points in "
                                 f"all (at {prim.GetPath()}); fix the layer: use lighter assets")
        elif prim.IsA(UsdLux.DistantLight):
            sun_prims.append(prim)  # read once every mesh is known: light linking names meshes
        elif prim.IsA(UsdLux.SphereLight):
            spot = read_spot(prim, cache, checked)
    if not meshes:
        raise LayerError(f"{layer_path}: the composed stage has no meshes; the base stage or its station "
                         "payload did not load (check subLayers and stages/)")
    mesh_paths = [m.path for m in meshes]
    suns = tuple(s for s in (read_sun(p, cache, mesh_paths, checked) for p in sun_prims) if s is not None)
    if not effects.inspection_light:
        spot = None
    if not effects.body_shine:  # no earthshine/moonshine: the bodies are seen but light nothing
        import dataclasses

        meshes = [dataclasses.replace(m, ray_visibility="cameraOnly") if m.ray_visibility == "noShadow" else m
                  for m in meshes]
    return SceneDescription(str(Path(layer_path).resolve()), tuple(meshes), materials, camera, suns, spot,
                            render, effects, read_meta(stage))


def read_rig(base_stage: str | Path) -> list:
    """The base camera poses recorded in the base stage (the stage, not code, is the record)."""
    from pxr import Usd, UsdGeom

    from allo_usd.scene.spec import CameraPose

    stage = open_stage(base_stage)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    poses = []
    for prim in stage.GetPrimAtPath(layout.RIG).GetChildren():
        if not prim.HasAPI("AlloCameraPoseAPI"):
            continue
        m = world_matrix(cache, prim)
        poses.append(CameraPose(int(prim.GetAttribute(A.POSE_INDEX.name).Get()),
                                str(prim.GetAttribute(A.POSE_SPLIT.name).Get()), m[:3, 3].copy(), m[:3, :3].copy()))
    if not poses:
        raise LayerError(f"{base_stage} has no camera poses under {layout.RIG}; regenerate the base stage")
    return sorted(poses, key=lambda p: p.index)


def read_rig_lens(base_stage: str | Path, width: int | None = None):
    """The lens the rig's views were chosen through (core.camera_model.CameraModel), as each pose's
    AlloCameraPoseAPI records it in UsdGeom.Camera's units (the poses are Xforms, not cameras). The
    principal-point offset is in pixels of a `width`-pixel image (needs `width` when one is recorded)."""
    from allo_usd.core.camera_model import CameraModel

    stage = open_stage(base_stage)
    found = set()
    for prim in stage.GetPrimAtPath(layout.RIG).GetChildren():
        if prim.HasAPI("AlloCameraPoseAPI"):
            found.add(tuple(tuple(v) if hasattr(v, "__len__") else v
                            for v in (prim.GetAttribute(a.name).Get() for a in A.POSE_LENS)))
    if len(found) != 1:
        raise LayerError(f"{base_stage}: the rig's poses record {len(found)} different lenses under {layout.RIG} "
                         "(one expected); regenerate the base stage")
    from decimal import Decimal

    def mm(v) -> float:  # tenths of a unit (a float32) -> mm, from its shortest decimal: 0.36 -> 36.0, not 36.0000014
        return float(Decimal(str(np.float32(v))) * 100)

    *lens, clip = next(iter(found))
    focal, h_ap, v_ap, h_off, v_off = (mm(v) for v in lens)
    offset = (0.0, 0.0)
    if (h_off, v_off) != (0.0, 0.0):
        if width is None:
            raise LayerError(f"{base_stage}: the rig's lens has a principal-point offset; give the image width")
        px_per_mm = width / h_ap
        offset = (-h_off * px_per_mm + 0.0, v_off * px_per_mm + 0.0)
    clip = tuple(float(Decimal(str(np.float32(c)))) for c in clip)
    return CameraModel(focal, h_ap, v_ap, clip, offset)


def read_triangles(layer_path: str | Path, root: str, variant: str | None = None,
                   joint_angles: dict[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World-space (points, triangles) of every mesh under `root`, for ray casting; `joint_angles`
    ({joint prim name: degrees}) sets the joint op of each AlloJointAPI prim under `root` first (in
    the stage's session layer: the files are not touched)."""
    from pxr import Usd, UsdGeom

    from allo_usd.assets.mesh import fan_triangulate

    stage = open_stage(layer_path)
    prim = stage.GetPrimAtPath(root) if root else stage.GetDefaultPrim()
    if not prim:
        raise LayerError(f"{layer_path} has no prim {root}")
    if joint_angles:
        set_joint_angles(stage, prim, joint_angles, layer_path)
    if variant is not None:
        vs = prim.GetVariantSets().GetVariantSet("variant")
        if variant not in vs.GetVariantNames():
            raise LayerError(f"{layer_path}: unknown variant {variant!r}; choose one of {vs.GetVariantNames()}")
        vs.SetVariantSelection(variant)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    pts, tris, off = [], [], 0
    for p in Usd.PrimRange(prim):
        if p.IsA(UsdGeom.Mesh):
            points, counts, indices = mesh_topology(p)
            local = points.astype(np.float64)
            m = world_matrix(cache, p)
            pts.append(fm.apply(m[:3, :3], local) + m[:3, 3])   # fixed-order sums: placement reads these
            t = fan_triangulate(counts, indices)
            tris.append(t + off)
            off += len(local)
    if not pts:
        raise LayerError(f"{layer_path}: no meshes under {root}")
    return np.concatenate(pts), np.concatenate(tris)


def joint_op(prim):
    """The joint-angle xformOp of an AlloJointAPI prim: its last op, a single-axis rotate."""
    from pxr import UsdGeom

    ops = UsdGeom.Xformable(prim).GetOrderedXformOps()
    if not ops or ops[-1].GetOpType() not in (UsdGeom.XformOp.TypeRotateX, UsdGeom.XformOp.TypeRotateY,
                                              UsdGeom.XformOp.TypeRotateZ):
        raise LayerError(f"joint {prim.GetPath()} has no single-axis rotate as its last xformOp (its joint angle); "
                         "fix the base stage: regenerate it with scripts/make_base_stage.py")
    return ops[-1]


def station_joints(stage, root=None) -> dict:
    """{joint prim name: prim} of every AlloJointAPI prim under `root` (default the station)."""
    from pxr import Usd

    top = root if root is not None else stage.GetPrimAtPath(layout.STATION)
    if not top:
        return {}
    return {p.GetName(): p for p in Usd.PrimRange(top) if p.HasAPI("AlloJointAPI")}


def set_joint_angles(stage, root, angles: dict[str, float], where) -> None:
    """Author each joint's angle in the stage's session layer (the files stay as they are)."""
    from pxr import Usd

    joints = station_joints(stage, root)
    unknown = sorted(set(angles) - set(joints))
    if unknown:
        raise LayerError(f"{where}: the station has no joints {unknown} (it has {sorted(joints)}); fix: regenerate "
                         "the base stage with scripts/make_base_stage.py, or turn station.track_sun off")
    with Usd.EditContext(stage, stage.GetSessionLayer()):
        for name, value in angles.items():
            joint_op(joints[name]).Set(float(value))


def read_joint_angles(layer_path: str | Path) -> dict[str, dict]:
    """{joint name: {path, op, angle, axis, lower, upper, tracks}} of the station's joints as a layer composes them."""
    stage = open_stage(layer_path)
    out = {}
    for name, prim in station_joints(stage).items():
        op = joint_op(prim)
        rec = {"path": str(prim.GetPath()), "op": op.GetOpName(), "angle": float(op.Get())}
        for key, attr in (("axis", A.JOINT_AXIS), ("lower", A.JOINT_LOWER_LIMIT), ("upper", A.JOINT_UPPER_LIMIT),
                          ("tracks", A.JOINT_TRACKS)):
            value = prim.GetAttribute(attr.name).Get()
            rec[key] = value if isinstance(value, str) or value is None else float(value)
        out[name] = rec
    return out


class StageGeometry:
    """A base stage's geometry for scene resolution (allo_usd.scene.resolve.StationGeometry): its
    camera rig, the station's triangles and each anomaly asset's triangles, read with pxr."""

    def __init__(self, base_stage: str | Path, assets: dict | None = None):
        self.base_stage = Path(base_stage)
        self.assets = dict(assets or {})   # {anomaly id: interface layer} of a plan's own hazards

    def poses(self) -> list:
        return read_rig(self.base_stage)

    def station_triangles(self, angles: dict[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The station's triangles, its joints (read from the base stage, so an edited stage is seen)
        at `angles` ({joint name: degrees}) or as the base stage has them."""
        return read_triangles(self.base_stage, layout.STATION, joint_angles=angles)

    def anomaly_triangles(self, asset: str, variant: str) -> tuple[np.ndarray, np.ndarray]:
        path = self.assets.get(asset, self.base_stage.parent / "anomalies" / f"{asset}.usda")
        return read_triangles(path, layout.asset_root(asset), variant)


def scene_inputs(base_stage: str | Path, sky, perilune_epoch: str, assets: dict | None = None,
                 track_sun: bool = False):
    """SceneInputs over a base stage (and a plan's own hazards, {id: interface layer}): what
    allo_usd.scene.resolve needs, read from USD. `track_sun`: the station's arrays follow each day's Sun."""
    from allo_usd.scene.resolve import SceneInputs

    return SceneInputs(StageGeometry(base_stage, assets), sky, perilune_epoch, track_sun=track_sun)


VAR_PASSES = {name: p for name, (p, _, _, _) in RENDER_VARS.items()}   # var prim name -> pass


def var_pass(name: str) -> str:
    """The pass (allo_usd.plan.settings.PASSES) of a render var the product orders, by its prim name."""
    if name not in VAR_PASSES:
        raise LayerError(f"the image product orders a render var {name!r} this renderer does not write; order only "
                         f"{', '.join(VAR_PASSES)} under {layout.VARS} (fix the layer)")
    return VAR_PASSES[name]


def layer_outputs(layer: Path) -> tuple[str, ...]:
    """The passes a scene layer orders (its own override of the product, else the base's default
    passes), read from the layer file alone: cheap enough for resume checks."""
    from pxr import Sdf, Tf

    try:
        sdf = Sdf.Layer.FindOrOpen(str(layer))
    except Tf.ErrorException:
        return DEFAULT_PASSES  # unreadable: read_scene will say what is wrong with it
    rel = sdf.GetRelationshipAtPath(f"{layout.IMAGE_PRODUCT}.orderedVars") if sdf else None
    if not rel or not rel.targetPathList.explicitItems:
        return DEFAULT_PASSES
    return tuple(VAR_PASSES.get(t.name, t.name) for t in rel.targetPathList.explicitItems)
