"""A bound material as the reader sees it: a UsdPreviewSurface (and the UsdUVTexture its diffuseColor
may read) -> MaterialDesc, every input type-checked and bounded (allo_usd.usd.reader_bounds). pxr only."""

from __future__ import annotations

from allo_usd.core.errors import LayerError
from allo_usd.usd.description import MaterialDesc
from allo_usd.usd.reader_bounds import (IOR, MAX_COLOUR, MAX_LIGHT, UNIT_INTERVAL, check_texture_file, _colour, _number,
                                        _vector)


def _input(shader, name, default):
    inp = shader.GetInput(name)
    if not inp:
        return default, None
    src = inp.GetConnectedSource()
    if src and src[0]:
        return default, src
    value = inp.Get()
    return (default if value is None else value), None


def texture_file(asset, where: str, owner: str, prim=None) -> str:
    """The image file an asset-valued texture input names (`where`: the attribute, `owner`: who reads
    it, `prim`: the prim that holds it), resolved and checked (reader_bounds.check_texture_file); an
    entry of a package (a .usdz scene) is read through a copy of it
    (allo_usd.usd.dependencies.unpacked_file): Blender reads files only. A texture that does not
    resolve is restored in a tree; in a package (the stage of `prim` is one), the package lacks it
    and is packed again with the texture inside."""
    from pxr import Ar, Sdf

    if not isinstance(asset, Sdf.AssetPath):
        raise LayerError(f"{where} must be an asset path, got {asset!r}; fix the layer")
    texture = asset.resolvedPath
    if not texture:
        package = _package_of(prim)
        if package:
            raise LayerError(f"{owner}: texture {asset} is not an entry of the package {package}; a package (.usdz) "
                             "may use only the files it holds: put the texture inside the scene's folders and pack "
                             "it again with `allo-usd pack LAYER --out SCENE.usdz`")
        raise LayerError(f"{owner}: texture {asset} does not resolve to a file; restore the asset's textures/ folder")
    if texture.endswith("]") and Ar.IsPackageRelativePath(texture):  # PKG.usdz[entry]
        from allo_usd.usd.dependencies import unpacked_file

        texture = unpacked_file(texture, where)
    check_texture_file(texture, where)
    return texture


def _package_of(prim) -> str | None:
    """The package file (.usdz) whose stage holds `prim`, or None (not a package, or no prim)."""
    from allo_usd.usd.dependencies import is_package

    if prim is None:
        return None
    root = prim.GetStage().GetRootLayer()
    path = root.realPath or root.identifier
    return path if is_package(path) else None


def _read_texture(material_path: str, prim) -> tuple[str, tuple[float, float, float]]:
    """(file, colour scale) of the UsdUVTexture a diffuseColor is connected to; an entry of a package
    (a .usdz scene) is read through a copy of it (allo_usd.usd.dependencies.unpacked_file)."""
    from pxr import UsdShade

    tex = UsdShade.Shader(prim)
    where = prim.GetPath()
    if tex.GetIdAttr().Get() != "UsdUVTexture":
        raise LayerError(f"material {material_path}: diffuseColor is connected to {where}, which is not a "
                         "UsdUVTexture (the only texture allo-usd renders); fix the layer")
    inp = tex.GetInput("file")
    texture = texture_file(inp.Get() if inp else None, f"{where}.inputs:file", f"material {material_path}",
                           prim)
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
