"""Write a plain Asset as a USD asset: a small .usda interface over .usdc geometry.

Follows the ASWF asset structure: the root prim is the default prim with a `kind`, geometry
and materials are heavy and live in crate, the interface holds the class label and (for
anomalies) a variant set whose variants reference different geometry files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from allo_usd.core.errors import AlloError
from allo_usd.core.files import atomic_path, commit_temp, temp_beside
from allo_usd.assets.mesh import Asset, Joint, MeshPart
from allo_usd.usd import layout
from allo_usd.core import fixedmath as fm

LABEL_TAXONOMY = "class"
CLASS_LABELS = ("station", "celestial_body", "anomaly")


def _vertex_normals(part: MeshPart) -> np.ndarray:
    tri = part.triangles()
    p = part.points
    fn = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])  # area-weighted
    vn = np.zeros_like(p)
    for k in range(3):
        np.add.at(vn, tri[:, k], fn)
    norm = fm.norm(vn, axis=1, keepdims=True)
    vn = np.where(norm > 0, vn / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    return vn


def _write_png(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(array, dtype=np.uint8)).save(tmp, format="PNG", optimize=False)


def stage_metadata(stage, default_prim: str) -> None:
    from pxr import UsdGeom

    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(stage.GetPrimAtPath(layout.asset_root(default_prim)))


def write_geometry(asset: Asset, usdc_path: Path, root: str, texture_dir: str = "textures") -> None:
    """Write meshes and UsdPreviewSurface materials under /<root> into a crate file."""
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade, Vt

    usdc_path = Path(usdc_path)
    usdc_path.parent.mkdir(parents=True, exist_ok=True)
    for key, tex in sorted(asset.textures.items()):
        _write_png(usdc_path.parent / texture_dir / f"{key}.png", tex)

    layer, tmp = new_layer(usdc_path)
    stage = Usd.Stage.Open(layer)
    root_prim = UsdGeom.Xform.Define(stage, layout.asset_root(root)).GetPrim()
    Usd.ModelAPI(root_prim).SetKind(Kind.Tokens.component)
    stage_metadata(stage, root)
    UsdGeom.Scope.Define(stage, layout.asset_looks(root))
    UsdGeom.Scope.Define(stage, layout.asset_geom(root))

    materials = {}
    for mat in asset.materials:
        mpath = f"{layout.asset_looks(root)}/{mat.name}"
        material = UsdShade.Material.Define(stage, mpath)
        shader = UsdShade.Shader.Define(stage, f"{mpath}/PreviewSurface")
        shader.CreateIdAttr("UsdPreviewSurface")
        shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(float(mat.metallic))
        shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(mat.roughness))
        if mat.ior != 1.5:  # the UsdPreviewSurface default; authored only where it differs
            shader.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(float(mat.ior))
        if mat.opacity != 1.0:  # the UsdPreviewSurface default; authored only where it differs
            shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(float(mat.opacity))
        if mat.opacity_threshold != 0.0:
            shader.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(float(mat.opacity_threshold))
        if any(mat.emissive_color):
            shader.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, mat.emissive_color)))
        diffuse = shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
        if mat.base_color_texture:
            reader = UsdShade.Shader.Define(stage, f"{mpath}/StReader")
            reader.CreateIdAttr("UsdPrimvarReader_float2")
            reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
            tex = UsdShade.Shader.Define(stage, f"{mpath}/BaseColorTexture")
            tex.CreateIdAttr("UsdUVTexture")
            tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(
                Sdf.AssetPath(f"./{texture_dir}/{mat.base_color_texture}.png"))
            tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
            tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
            tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
            # The texture is multiplied by base_color through `scale`.
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*map(float, mat.base_color), 1.0))
            tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
            diffuse.ConnectToSource(tex.ConnectableAPI(), "rgb")
        else:
            diffuse.Set(Gf.Vec3f(*map(float, mat.base_color)))
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        materials[mat.name] = material

    define_joints(stage, asset, root)
    for part in asset.parts:
        parent = layout.asset_joint(root, asset.joint_chain(part.joint))
        mesh = UsdGeom.Mesh.Define(stage, f"{parent}/{part.name}")
        pts = part.points.astype(np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(part.face_counts))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(part.face_indices))
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(axis=0), pts.max(axis=0)])))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        if part.smooth:
            mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(_vertex_normals(part).astype(np.float32)))
            mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        if part.uv is not None:
            st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                         UsdGeom.Tokens.faceVarying)
            st.Set(Vt.Vec2fArray.FromNumpy(part.uv.astype(np.float32)))
        binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
        binding.Bind(materials[part.material])

    commit_layer(layer, tmp, usdc_path)


def joint_op_name(joint: Joint) -> str:
    """The joint angle's xformOp attribute (e.g. xformOp:rotateY:alpha)."""
    return f"xformOp:rotate{joint.axis}:{joint.op}"


def define_joints(stage, asset: Asset, root: str) -> None:
    """Each joint an Xform: translate and rotateXYZ mounting ops (suffix `mount`), then its one joint
    op at the rest angle; AlloJointAPI records axis, limits and what it tracks."""
    from pxr import Gf, UsdGeom

    from allo_usd.usd import attributes as A
    from allo_usd.usd import schema

    for joint in asset.joints:
        prim = UsdGeom.Xform.Define(stage, layout.asset_joint(root, asset.joint_chain(joint.name)))
        prim.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble, "mount").Set(Gf.Vec3d(*map(float, joint.translate)))
        if any(joint.mount_rotation):
            prim.AddRotateXYZOp(UsdGeom.XformOp.PrecisionDouble, "mount").Set(
                Gf.Vec3d(*map(float, joint.mount_rotation)))
        add = {"X": prim.AddRotateXOp, "Y": prim.AddRotateYOp, "Z": prim.AddRotateZOp}[joint.axis]
        add(UsdGeom.XformOp.PrecisionDouble, joint.op).Set(float(joint.rest))
        schema.apply(prim.GetPrim(), "AlloJointAPI")
        for attr, value in ((A.JOINT_AXIS, joint.axis), (A.JOINT_LOWER_LIMIT, float(joint.lower)),
                            (A.JOINT_UPPER_LIMIT, float(joint.upper)), (A.JOINT_TRACKS, joint.tracks)):
            prim.GetPrim().GetAttribute(attr.name).Set(value)


def new_layer(path: Path):
    """A new layer at a temporary name beside `path`, so relative asset paths resolve while
    authoring; `commit_layer` saves it and renames it into place (atomic on POSIX)."""
    from pxr import Sdf

    from allo_usd.usd import schema

    schema.register()  # before any stage opens: the schema registry reads plugins only once
    tmp = temp_beside(path)  # a .usda/.usdc name: Sdf picks the format by it
    tmp.unlink()  # Sdf creates the file itself
    layer = Sdf.Layer.CreateNew(str(tmp))
    if layer is None:
        raise AlloError(f"could not create {tmp}; check the directory is writable")
    return layer, tmp


def commit_layer(layer, tmp: Path, path: Path) -> None:
    try:
        ok = layer.Save()
    except Exception as exc:  # pxr raises Tf.ErrorException on I/O failure
        ok = False
        reason = str(exc)
    else:
        reason = ""
    if not ok:
        Path(tmp).unlink(missing_ok=True)
        raise AlloError(f"could not write {path} ({reason.strip() or 'save failed'}); check the disk "
                        "has space and the directory is writable; nothing was replaced")
    commit_temp(tmp, path)


def write_interface(usda_path: Path, root: str, label: str, geometry: dict[str, str] | str,
                    kind: str = "component", variant_set: str = "variant", doc: str = "",
                    custom: dict | None = None) -> None:
    """The small text layer of an asset: default prim, kind, class label, geometry reference(s).

    `geometry` is one relative .usdc path, or {variant name: relative .usdc path} to author a
    variant set (first key is the default selection).
    """
    from pxr import Sdf, Usd, UsdGeom, UsdSemantics

    if label not in CLASS_LABELS:
        raise AlloError(f"class label {label!r} is not one of {CLASS_LABELS}")
    layer, tmp = new_layer(usda_path)
    stage = Usd.Stage.Open(layer)
    prim = UsdGeom.Xform.Define(stage, layout.asset_root(root)).GetPrim()
    Usd.ModelAPI(prim).SetKind(kind)
    stage_metadata(stage, root)
    if doc:
        layer.documentation = doc
    if custom:
        layer.customLayerData = custom
    labels = UsdSemantics.LabelsAPI.Apply(prim, LABEL_TAXONOMY)
    labels.CreateLabelsAttr([label])
    if isinstance(geometry, str):
        prim.GetPayloads().AddPayload(geometry, Sdf.Path(layout.asset_root(root)))
    else:
        vset = prim.GetVariantSets().AddVariantSet(variant_set)
        for name, path in geometry.items():
            vset.AddVariant(name)
            vset.SetVariantSelection(name)
            with vset.GetVariantEditContext():
                prim.GetPayloads().AddPayload(path, Sdf.Path(layout.asset_root(root)))
        vset.SetVariantSelection(next(iter(geometry)))
    commit_layer(layer, tmp, Path(usda_path))


def write_asset(asset: Asset, directory: Path, label: str, root: str | None = None, doc: str = "") -> Path:
    """One-variant asset: <dir>/<name>.usda over <dir>/<name>_geom.usdc. Returns the .usda path."""
    directory = Path(directory)
    root = root or asset.name
    write_geometry(asset, directory / f"{asset.name}_geom.usdc", root)
    out = directory / f"{asset.name}.usda"
    write_interface(out, root, label, f"./{asset.name}_geom.usdc", doc=doc)
    return out


def write_variant_asset(variants: dict[str, Asset], directory: Path, name: str, label: str, doc: str = "",
                        custom: dict | None = None) -> Path:
    """<dir>/<name>.usda with a `variant` set; each variant's geometry in <dir>/<name>/<variant>.usdc."""
    directory = Path(directory)
    geometry = {}
    for vname, asset in variants.items():
        write_geometry(asset, directory / name / f"{vname}.usdc", name, texture_dir="textures")
        geometry[vname] = f"./{name}/{vname}.usdc"
    out = directory / f"{name}.usda"
    write_interface(out, name, label, geometry, doc=doc, custom=custom)
    return out
