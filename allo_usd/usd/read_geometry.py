"""Geometry as the reader sees it: a UsdGeom.Mesh, an implicit shape (tessellated: implicit_shapes) or
a point instancer's instances -> MeshDesc (points, topology, UVs, shading, material or display colour,
world matrix, class and ray visibility); every other Gprim is refused in one line. pxr only."""

from __future__ import annotations

import dataclasses

import numpy as np

from allo_usd.core import fixedmath as fm
from allo_usd.core.errors import LayerError
from allo_usd.core.labels import ANOMALY, CLASS_IDS, STATION
from allo_usd.usd import attributes as A
from allo_usd.usd import implicit_shapes as S
from allo_usd.usd.description import DISPLAY_COLOR_ATTRIBUTE, MaterialDesc, MeshDesc
from allo_usd.usd.read_material import read_material
from allo_usd.usd.reader_bounds import (MAX_COLOUR, MAX_POSITION_M, MAX_SCALE, MAX_SCENE_POINTS, MIN_SCALE, _number,
                                        mesh_topology, world_matrix)


def class_and_object(prim) -> tuple[int, str]:
    """(class id, object path) of a mesh prim: the class of the nearest ancestor-or-self whose
    UsdSemantics.LabelsAPI "class" instance (semantics:labels:class) holds a label of CLASS_IDS (its
    first such label); labels outside CLASS_IDS are passed over. Unlabelled geometry (a user's own)
    is STATION, "station and bodies": it occludes and is part of the scene, so the mask must not call
    it empty space (every mesh an authored layer holds is labelled). An anomaly-class mesh is part of
    the anomaly object that prim is (one instance id for all its meshes); any other mesh is its own
    object ("")."""
    from pxr import UsdSemantics

    p = prim
    while p and not p.IsPseudoRoot():
        if p.HasAPI(UsdSemantics.LabelsAPI, "class"):
            labels = UsdSemantics.LabelsAPI(p, "class").GetLabelsAttr().Get() or []
            for name in labels:
                if name in CLASS_IDS:
                    cls = CLASS_IDS[name]
                    return cls, (str(p.GetPath()) if cls == ANOMALY else "")
        p = p.GetParent()
    return STATION, ""


def _class_id(prim) -> int:
    """The mesh prim's class (label)."""
    return class_and_object(prim)[0]


def _ray_visibility(prim) -> str:
    p = prim
    while p and not p.IsPseudoRoot():
        attr = p.GetAttribute(A.RAY_VISIBILITY.name)
        if attr and attr.HasAuthoredValue():
            return str(attr.Get())
        p = p.GetParent()
    return "all"


def flattened(primvar) -> np.ndarray | None:
    """A primvar's values with its indices applied (UsdGeom.Primvar.ComputeFlattened), or None when USD
    cannot flatten them (an index outside the values)."""
    from pxr import Tf

    try:
        flat = primvar.ComputeFlattened()
    except Tf.ErrorException:
        return None
    return None if flat is None else np.asarray(flat)


def _read_uv(prim, n_face_vertices: int) -> np.ndarray | None:
    """primvars:st, face-varying: one finite (u, v) per face vertex, or None when the mesh has none."""
    from pxr import UsdGeom

    path = prim.GetPath()
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if not (st and st.HasValue()):
        return None
    if st.GetInterpolation() != UsdGeom.Tokens.faceVarying:
        raise LayerError(f"mesh {path}: primvars:st must be faceVarying, not {st.GetInterpolation()}; regenerate "
                         "its asset")
    uv = flattened(st)
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
    """A UsdGeom.Mesh; a subdivision surface (subdivisionScheme other than none) is its control cage."""
    from pxr import UsdGeom

    path = str(prim.GetPath())
    points, counts, indices = mesh_topology(prim)
    uv = _read_uv(prim, len(indices))
    smooth = _smooth(UsdGeom.Mesh(prim), path, len(points), len(counts), len(indices))
    key, colors = _material(prim, materials, (points, counts, indices))
    subsets = material_subsets(prim, key, materials, len(counts))
    if UsdGeom.Mesh(prim).GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        corners = right_handed_corners(counts)   # Blender winds faces right-handed (counter-clockwise)
        indices = indices[corners]
        uv = None if uv is None else uv[corners]
        colors = None if colors is None else colors[corners]
    class_id, obj = class_and_object(prim)   # every MeshDesc's class and object come from here
    return MeshDesc(path, points, counts, indices, uv, smooth, key, world_matrix(cache, prim, checked=checked),
                    class_id, _ray_visibility(prim), object=obj, colors=colors, subsets=subsets)


def right_handed_corners(counts: np.ndarray) -> np.ndarray:
    """The face-vertex order that turns a leftHanded mesh (UsdGeom.Mesh orientation: its faces wind
    clockwise seen from the front) right-handed: each face's corners reversed, so the front (and the
    normals Blender computes) are the ones USD means. Per-corner data (uv, colours) follows the order."""
    counts = np.asarray(counts, dtype=np.int64)
    ends = np.cumsum(counts)
    starts = ends - counts
    face = np.repeat(np.arange(len(counts)), counts)
    k = np.arange(int(ends[-1]) if len(ends) else 0) - starts[face]
    return (ends[face] - 1 - k).astype(np.int64)


RENDERED = ("allo-usd renders Mesh and the implicit shapes (Cube, Sphere, Cylinder, Cone, Capsule, Plane), "
            "instanced or not")
IMPLICIT = ("Cube", "Sphere", "Cylinder", "Cylinder_1", "Cone", "Capsule", "Capsule_1", "Plane")
VOLUME_FIELDS = ("OpenVDBAsset", "Field3DAsset")     # UsdVol fields: Imageable, not Gprims
DEFAULT_PURPOSES = ("default", "render")             # UsdRender.Settings includedPurposes' fallback
# Meshes one point instancer may expand into: each is a Blender object, and the object index pass
# numbers at most 32767 objects in all (allo_usd.blender.build.MAX_OBJECT_ID checks the scene's total).
MAX_INSTANCED_GPRIMS = 32_767
DEFAULT_MATERIAL = MaterialDesc("__default__", (0.5, 0.5, 0.5), 0.0, 0.5)
LINEAR_COLOUR_SPACES = ("", "lin_rec709_scene", "lin_rec709", "linear")


def included_purposes(settings_prim) -> frozenset:
    """The render settings' includedPurposes (UsdRender.Settings; fallback default and render)."""
    from pxr import UsdRender

    attr = UsdRender.Settings(settings_prim).GetIncludedPurposesAttr()
    value = attr.Get() if attr else None
    value = DEFAULT_PURPOSES if value is None else value
    known = ("default", "render", "proxy", "guide")
    if isinstance(value, (str, bytes)) or not all(v in known for v in value):
        raise LayerError(f"{attr.GetPath()} = {value!r}: includedPurposes holds only {', '.join(known)}; fix the layer")
    return frozenset(str(v) for v in value)


def is_geometry(prim) -> bool:
    """A prim read_geometry renders or refuses: every Gprim, point instancer and UsdVol field."""
    from pxr import UsdGeom

    return prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer) or prim.GetTypeName() in VOLUME_FIELDS


def read_geometry(prim, cache, materials: dict, checked: set, purposes: frozenset, room: int) -> list[MeshDesc]:
    """The MeshDescs a geometry prim (is_geometry) renders as: none when its computed purpose is not
    one of the render settings' `purposes`, one for a Mesh or implicit shape, one per prototype gprim and
    instance for a point instancer (at most `room` points in all); any other geometry is refused."""
    from pxr import UsdGeom

    if UsdGeom.Imageable(prim).ComputePurpose() not in purposes:
        return []
    if prim.IsA(UsdGeom.PointInstancer):
        return _expand_instancer(prim, cache, materials, checked, purposes, room)
    return [read_gprim(prim, cache, materials, checked)]


def _refuse_unrendered(prim) -> None:
    from pxr import UsdGeom, UsdLux

    path = prim.GetPath()
    if prim.HasAPI(UsdLux.LightAPI):
        apis = ", ".join(a for a in prim.GetAppliedSchemas() if "Light" in a)
        raise LayerError(f"{path} ({prim.GetTypeName()}) applies {apis}: geometry that emits light is not rendered by "
                         "allo-usd; fix the layer: remove the API and give it a UsdPreviewSurface with emissiveColor, "
                         "or add a UsdLux light")
    if not prim.IsA(UsdGeom.Mesh) and prim.GetTypeName() not in IMPLICIT:
        raise LayerError(f"{path} is a {prim.GetTypeName() or 'typeless prim'}: {RENDERED}; fix the layer: convert it to "
                         "a Mesh or remove it")


def read_gprim(prim, cache, materials: dict, checked: set | None = None) -> MeshDesc:
    """A Mesh or implicit shape -> MeshDesc; any other Gprim, or one that emits light, is refused."""
    from pxr import UsdGeom

    _refuse_unrendered(prim)
    if prim.IsA(UsdGeom.Mesh):
        return read_mesh(prim, cache, materials, checked)
    shape = read_implicit(prim)
    key = _material(prim, materials, None)[0]
    class_id, obj = class_and_object(prim)
    return MeshDesc(str(prim.GetPath()), shape.points, shape.face_counts, shape.face_indices, None, shape.smooth, key,
                    world_matrix(cache, prim, checked=checked), class_id, _ray_visibility(prim), object=obj)


def _size(prim, name: str, zero_ok: bool = False) -> float:
    attr = prim.GetAttribute(name)
    value = _number(attr.Get(), str(attr.GetPath()), lo=0.0, hi=MAX_POSITION_M)
    if value == 0.0 and not zero_ok:
        raise LayerError(f"{attr.GetPath()} = 0: a {prim.GetTypeName()} needs it > 0; fix the layer")
    return value


def read_implicit(prim) -> S.Shape:
    """UsdGeom.Cube/Sphere/Cylinder(_1)/Cone/Capsule(_1)/Plane -> its tessellation (implicit_shapes);
    the schema's fallbacks stand for what is not authored, `extent` is not read."""
    kind = prim.GetTypeName()
    axis = None
    if prim.HasAttribute("axis"):
        axis = str(prim.GetAttribute("axis").Get())
        if axis not in ("X", "Y", "Z"):
            raise LayerError(f"{prim.GetPath()}.axis = {axis!r} is not X, Y or Z; fix the layer")
    if kind == "Cube":
        return S.cube(_size(prim, "size"))
    if kind == "Sphere":
        return S.sphere(_size(prim, "radius"))
    if kind == "Cylinder":
        r = _size(prim, "radius")
        return S.cylinder(r, r, _size(prim, "height"), axis)
    if kind == "Cylinder_1":
        bottom, top = _size(prim, "radiusBottom", True), _size(prim, "radiusTop", True)
        if bottom == top == 0.0:
            raise LayerError(f"{prim.GetPath()}: radiusBottom and radiusTop are both 0 (a line); fix the layer")
        return S.cylinder(bottom, top, _size(prim, "height"), axis)
    if kind == "Cone":
        return S.cone(_size(prim, "radius"), _size(prim, "height"), axis)
    if kind == "Capsule":
        return S.capsule(_size(prim, "radius"), _size(prim, "height", True), axis)
    if kind == "Capsule_1":
        bottom, top = _size(prim, "radiusBottom"), _size(prim, "radiusTop")
        if bottom != top:
            raise LayerError(f"{prim.GetPath()}: a Capsule_1 with radiusBottom {bottom:g} != radiusTop {top:g} is not "
                             "rendered by allo-usd (only equal radii); fix the layer: give both the same radius")
        return S.capsule(bottom, _size(prim, "height", True), axis)
    return S.plane(_size(prim, "width"), _size(prim, "length"), axis)


def _primvar_values(primvar, width: int, hi: float) -> tuple[np.ndarray, str]:
    """An authored display primvar's (values (k, width) float32, interpolation), values finite in 0..hi."""
    where = primvar.GetAttr().GetPath()
    space = primvar.GetAttr().GetColorSpace() if width == 3 else ""
    if space not in LINEAR_COLOUR_SPACES:
        raise LayerError(f"{where} is in colour space {space!r}; allo-usd reads display colours as linear Rec.709 "
                         "(USD's default): fix the layer: remove the colorSpace or convert the values")
    v = flattened(primvar)
    if v is not None and v.ndim == 0:
        v = v.reshape(1)   # a scalar value authored where an array belongs: one value
    if v is None or v.dtype.kind not in "iuf" or len(v) == 0 or v.reshape(len(v), -1).shape[1] != width:
        raise LayerError(f"{where} holds {'nothing usable' if v is None else primvar.GetTypeName()}; it needs "
                         f"{'colours (color3f[])' if width == 3 else 'opacities (float[])'}; fix the layer")
    v = v.reshape(len(v), width).astype(np.float64)
    if not (np.isfinite(v).all() and v.min() >= 0.0 and v.max() <= hi):
        raise LayerError(f"{where} has values outside 0..{hi:g} (or not finite); fix the layer")
    return v.astype(np.float32), str(primvar.GetInterpolation())


def _corners(values: np.ndarray, interp: str, where, topology) -> np.ndarray:
    """Values of a primvar of `interp` interpolation, one per face vertex of `topology`
    (points, counts, indices), or a LayerError if their count does not fit it."""
    points, counts, indices = topology
    need = {"uniform": len(counts), "vertex": len(points), "varying": len(points), "faceVarying": len(indices)}
    if need.get(interp) != len(values):
        raise LayerError(f"{where} holds {len(values):,} values, but {interp} interpolation on this mesh needs "
                         f"{need.get(interp, 1):,}; fix the layer")
    if interp == "uniform":
        return np.repeat(values, counts, axis=0)
    if interp in ("vertex", "varying"):
        return values[indices]
    return values


def _material(prim, materials: dict, topology) -> tuple[str, np.ndarray | None]:
    """(material key, per-corner RGBA or None): the bound material; else the display colour and opacity
    (primvars:displayColor/displayOpacity, inherited as USD's constant primvars are) as USD's fallback;
    else the default grey. `topology` (points, counts, indices): a Mesh's, None for an implicit shape
    (which takes one display colour only)."""
    from pxr import UsdGeom, UsdShade

    # the render settings' materialBindingPurposes ["full", ""] (read.read_render): full, else allPurpose
    bound = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial(UsdShade.Tokens.full)[0]
    if bound:
        key = str(bound.GetPath())
        if key not in materials:
            materials[key] = read_material(bound)
        return key, None
    api = UsdGeom.PrimvarsAPI(prim)
    found = [api.FindPrimvarWithInheritance(n) for n in ("displayColor", "displayOpacity")]
    colour, opacity = (p if p and p.HasAuthoredValue() else None for p in found)
    if colour is None and opacity is None:
        materials.setdefault(DEFAULT_MATERIAL.path, DEFAULT_MATERIAL)
        return DEFAULT_MATERIAL.path, None
    rgb = ((np.asarray([DEFAULT_MATERIAL.base_color], np.float32), "constant") if colour is None
           else _primvar_values(colour, 3, MAX_COLOUR))
    alpha = (np.ones((1, 1), np.float32), "constant") if opacity is None else _primvar_values(opacity, 1, 1.0)
    for (v, interp), p in ((rgb, colour), (alpha, opacity)):
        if len(v) > 1 and interp == "constant":
            raise LayerError(f"{p.GetAttr().GetPath()} holds {len(v):,} values, but constant interpolation takes one; "
                             "fix the layer")
    varying = [(v, i, p) for (v, i), p in ((rgb, colour), (alpha, opacity)) if len(v) > 1]   # one value: constant
    if not varying:
        c, a = tuple(float(x) for x in rgb[0][0]), float(alpha[0][0, 0])
        key = "__displayColor__ " + " ".join(f"{x:.9g}" for x in (*c, a))
        materials.setdefault(key, MaterialDesc(key, c, 0.0, 0.5, opacity=a))
        return key, None
    if topology is None:
        where = varying[0][2].GetAttr().GetPath()
        raise LayerError(f"{where} holds {len(varying[0][0]):,} values ({varying[0][1]}): an implicit shape takes one "
                         "display colour (constant interpolation) in allo-usd; fix the layer")
    n = len(topology[2])
    per = [np.broadcast_to(v, (n, v.shape[1])) if len(v) == 1 else _corners(v, i, p.GetAttr().GetPath(), topology)
           for (v, i), p in ((rgb, colour), (alpha, opacity))]
    key = "__displayColor__ per corner"
    materials.setdefault(key, MaterialDesc(key, (1.0, 1.0, 1.0), 0.0, 0.5, color_attribute=DISPLAY_COLOR_ATTRIBUTE))
    return key, np.ascontiguousarray(np.concatenate(per, axis=1), dtype=np.float32)


def material_subsets(prim, key: str, materials: dict, n_faces: int) -> tuple:
    """The mesh's faces bound to other materials than `key`, the whole mesh's: its GeomSubsets of the
    materialBind family (UsdShade MaterialBindingAPI GetMaterialBindSubsets) with a material bound,
    as ((material key, face indices), ...). Faces of no such subset keep the mesh's material. A subset
    whose indices are not faces of the mesh, or that shares faces with another, is refused."""
    from pxr import UsdGeom, UsdShade

    out, taken = [], np.zeros(n_faces, dtype=bool)
    for subset in UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets():
        bound = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial(UsdShade.Tokens.full)[0]
        if not bound or str(bound.GetPath()) == key:
            continue
        where = subset.GetPath()
        if subset.GetElementTypeAttr().Get() != UsdGeom.Tokens.face:
            raise LayerError(f"GeomSubset {where} binds material {bound.GetPath()} to {subset.GetElementTypeAttr().Get()}"
                             "s; a material binds to faces (UsdGeom.Subset elementType face); fix the layer")
        faces = np.asarray(subset.GetIndicesAttr().Get() or [], dtype=np.int64)
        if faces.size and (faces.min() < 0 or faces.max() >= n_faces):
            raise LayerError(f"GeomSubset {where}.indices names face {int(faces.max() if faces.min() >= 0 else faces.min())}"
                             f", but {prim.GetPath()} has {n_faces:,} faces; fix the layer")
        if taken[faces].any() or len(np.unique(faces)) != len(faces):
            raise LayerError(f"GeomSubset {where} shares faces with another materialBind subset of {prim.GetPath()}; "
                             "a face takes one material: fix the layer (make the subsets non-overlapping)")
        taken[faces] = True
        sub_key = str(bound.GetPath())
        if sub_key not in materials:
            materials[sub_key] = read_material(bound)
        out.append((sub_key, faces.astype(np.int32)))
    return tuple(out)


def _proto_gprims(proto, instancer_path) -> list:
    """The gprims a point instancer's prototype draws: its visible subtree (visibility from the prototype
    root down), instance proxies included."""
    from pxr import Usd, UsdGeom

    out = []
    it = iter(Usd.PrimRange(proto, Usd.TraverseInstanceProxies(Usd.PrimIsActive & Usd.PrimIsLoaded)))
    for p in it:
        img = UsdGeom.Imageable(p)
        if img and img.GetVisibilityAttr().Get() == UsdGeom.Tokens.invisible:
            it.PruneChildren()
            continue
        if p.IsA(UsdGeom.PointInstancer):
            raise LayerError(f"point instancer {instancer_path}: its prototype {proto.GetPath()} holds another point "
                             f"instancer ({p.GetPath()}), which allo-usd does not expand; fix the layer: flatten it")
        if is_geometry(p):
            out.append(p)
    return out


def _check_instance_matrix(m: np.ndarray, where: str) -> None:
    if not np.isfinite(m).all():
        raise LayerError(f"{where} has a non-finite transform; fix the point instancer's positions, orientations and "
                         "scales")
    s = np.linalg.svd(m[:3, :3], compute_uv=False)
    if not (np.allclose(m[3], (0, 0, 0, 1)) and s[-1] >= MIN_SCALE and s[0] <= MAX_SCALE):
        raise LayerError(f"{where} has a degenerate transform (its axes scale by {s[-1]:.3g}..{s[0]:.3g}, outside "
                         f"{MIN_SCALE:g}..{MAX_SCALE:g}); fix the point instancer's scales")
    if not fm.norm(m[:3, 3]) <= MAX_POSITION_M:
        raise LayerError(f"{where} is {fm.norm(m[:3, 3]):.3g} m from the station, beyond the "
                         f"{MAX_POSITION_M:g} m allowed; fix the point instancer's positions")


def _expand_instancer(prim, cache, materials: dict, checked: set, purposes: frozenset, room: int) -> list[MeshDesc]:
    """A UsdGeom.PointInstancer's instances: for instance i (its index in protoIndices, masked ones by
    invisibleIds and inactiveIds left out) of prototype P, every visible gprim G of P's subtree (whose
    purpose is included) becomes a MeshDesc at <instancer>/<P's name>_<i>[/<G's path below P>], placed at
    instancer x instance (which holds P's own transform: IncludeProtoXform) x G's transform below P."""
    from pxr import Usd, UsdGeom

    inst = UsdGeom.PointInstancer(prim)
    path = str(prim.GetPath())
    indices = inst.GetProtoIndicesAttr().Get()
    if indices is None or len(indices) == 0:
        return []
    indices = np.asarray(indices)
    stage = prim.GetStage()
    protos = [stage.GetPrimAtPath(t) for t in inst.GetPrototypesRel().GetForwardedTargets()]
    if indices.min() < 0 or indices.max() >= len(protos):
        raise LayerError(f"point instancer {path}.protoIndices holds {int(indices.max() if indices.min() >= 0 else indices.min())}, "
                         f"but it has {len(protos)} prototypes (prototypes targets 0..{len(protos) - 1}); fix the layer")
    for k, p in enumerate(protos):
        if not p:
            raise LayerError(f"point instancer {path}: prototype {k} names no prim; fix its prototypes relationship")
    positions = inst.GetPositionsAttr().Get()
    if positions is None or len(positions) != len(indices):
        raise LayerError(f"point instancer {path} has {0 if positions is None else len(positions):,} positions for "
                         f"{len(indices):,} protoIndices; fix the layer: one position per instance")
    time = Usd.TimeCode.Default()
    xforms = inst.ComputeInstanceTransformsAtTime(time, time, UsdGeom.PointInstancer.IncludeProtoXform,
                                                  UsdGeom.PointInstancer.IgnoreMask)
    if len(xforms) != len(indices):
        raise LayerError(f"point instancer {path}: its orientations, scales or protoIndices do not match its "
                         f"{len(indices):,} positions; fix the layer: one value per instance in each")
    mask = inst.ComputeMaskAtTime(time)
    keep = np.ones(len(indices), bool) if len(mask) == 0 else np.asarray(mask, bool)
    base = world_matrix(cache, prim, checked=checked)
    templates = []   # per prototype: (MeshDesc where it sits, path below the prototype, transform below it)
    for proto in protos:
        rows = []
        for g in _proto_gprims(proto, path):
            if UsdGeom.Imageable(g).ComputePurpose() not in purposes:
                continue
            desc = read_gprim(g, cache, materials, checked)
            if desc.class_id == ANOMALY:   # an anomaly object is a prim: its pose, model and record are the prim's
                raise LayerError(f"point instancer {path}: prototype {proto.GetPath()} is labelled anomaly; an anomaly "
                                 "is one prim of its own (its instance id, pose and record), not a point instance; fix "
                                 "the layer: reference the asset once per anomaly instead")
            below = np.array(cache.ComputeRelativeTransform(g, proto)[0], dtype=np.float64).T
            rel = str(g.GetPath().MakeRelativePath(proto.GetPath()))
            rows.append((desc, "" if rel == "." else "/" + rel, below))
        templates.append(rows)
    chosen = np.flatnonzero(keep)
    n_meshes = sum(len(templates[indices[i]]) for i in chosen)
    n_points = sum(sum(len(d.points) for d, _, _ in templates[indices[i]]) for i in chosen)
    if n_points > room or n_meshes > MAX_INSTANCED_GPRIMS:
        raise LayerError(f"point instancer {path} expands to {n_meshes:,} meshes of {n_points:,} points in all "
                         f"({len(chosen):,} instances); a scene holds at most {MAX_SCENE_POINTS:,} points "
                         f"({room:,} left for it) and {MAX_INSTANCED_GPRIMS:,} instanced meshes; fix the layer: fewer "
                         "instances or lighter prototypes")
    out = []
    for i in chosen:
        k = int(indices[i])
        m_i = np.array(xforms[int(i)], dtype=np.float64).T
        for desc, rel, below in templates[k]:
            where = f"{path}/{protos[k].GetName()}_{int(i)}{rel}"
            m = fm.matmul(fm.matmul(base, m_i), below)   # fixed order (no BLAS): the annotations read it
            _check_instance_matrix(m, where)
            out.append(dataclasses.replace(desc, path=where, matrix=m))
    return out
