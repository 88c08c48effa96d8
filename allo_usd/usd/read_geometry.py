"""Geometry as the reader sees it: a UsdGeom.Mesh prim -> MeshDesc (points, topology, UVs, shading,
material, world matrix, class and ray visibility). pxr only."""

from __future__ import annotations

import numpy as np

from allo_usd.core.errors import LayerError
from allo_usd.core.labels import BACKGROUND, CLASS_IDS
from allo_usd.usd import attributes as A
from allo_usd.usd.description import MaterialDesc, MeshDesc
from allo_usd.usd.read_material import read_material
from allo_usd.usd.reader_bounds import mesh_topology, world_matrix


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
    return MeshDesc(path, points, counts, indices, uv, smooth, key, world_matrix(cache, prim, checked=checked),
                    _class_id(prim), _ray_visibility(prim))
