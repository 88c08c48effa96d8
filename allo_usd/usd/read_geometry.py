"""Geometry as the reader sees it: a UsdGeom.Mesh prim -> MeshDesc (points, topology, UVs, shading,
material, world matrix, class and ray visibility). pxr only."""

from __future__ import annotations

import numpy as np

from allo_usd.core.errors import LayerError
from allo_usd.core.labels import ANOMALY, CLASS_IDS, STATION
from allo_usd.usd import attributes as A
from allo_usd.usd.description import MaterialDesc, MeshDesc
from allo_usd.usd.read_material import read_material
from allo_usd.usd.reader_bounds import mesh_topology, world_matrix


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
    # the render settings' materialBindingPurposes ["full", ""] (read.read_render): full, else allPurpose
    bound = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial(UsdShade.Tokens.full)[0]
    if bound:
        key = str(bound.GetPath())
        if key not in materials:
            materials[key] = read_material(bound)
    else:
        key = "__default__"
        materials.setdefault(key, MaterialDesc(key, (0.5, 0.5, 0.5), 0.0, 0.5))
    class_id, obj = class_and_object(prim)   # every MeshDesc's class and object come from here
    return MeshDesc(path, points, counts, indices, uv, smooth, key, world_matrix(cache, prim, checked=checked),
                    class_id, _ray_visibility(prim), obj)
