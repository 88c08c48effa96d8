"""Lights as the reader sees them: UsdLux prims -> SunDesc (DistantLight), SpotDesc (SphereLight: a spot
with ShapingAPI, else a point lamp), AreaDesc (RectLight, DiskLight), CylinderDesc (CylinderLight) and
DomeDesc (DomeLight), with the units UsdLux defines (inputs:intensity x 2^inputs:exposure is radiance,
W/m^2/sr; inputs:normalize divides by the world-space area; inputs:color times the blackbody colour of
inputs:colorTemperature when enabled) and light linking resolved against the scene's meshes. Whatever
Cycles cannot show as UsdLux means it is a LayerError naming the prim. pxr only."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from allo_usd.core import fixedmath as fm
from allo_usd.core.errors import LayerError
from allo_usd.usd.description import (AreaDesc, CylinderDesc, DomeDesc, LampRays, LightLink, SpotDesc,
                                      SunDesc)
from allo_usd.usd.layout import INSPECTION_LIGHT
from allo_usd.usd.reader_bounds import (MAX_LIGHT, SPOT_CONE_DEG, SPOT_RADIUS_M, SPOT_SOFTNESS, SUN_ANGLE_DEG, _colour,
                                        _number, world_matrix)


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
    value = intensity * fm.exp2(exposure)
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


LIGHT_SIZE_M = SPOT_RADIUS_M         # a lamp's radius, width, height, length (Blender: 0..FLT_MAX)
COLOR_TEMPERATURE_K = (1000.0, 10000.0)  # the range of UsdLux's blackbody table (BlackbodyTemperatureAsRgb)
_SHADOW_DEFAULTS = {"inputs:shadow:color": (0.0, 0.0, 0.0), "inputs:shadow:distance": -1.0,
                    "inputs:shadow:falloff": -1.0, "inputs:shadow:falloffGamma": 1.0}


def _refuse(where, what: str, fix: str):
    raise LayerError(f"{where}: {what}; {fix}")


def _colour_of(prim, light, where) -> tuple[float, float, float]:
    """inputs:color, times UsdLux's blackbody colour of inputs:colorTemperature when
    inputs:enableColorTemperature is true (UsdLux.BlackbodyTemperatureAsRgb: the Planckian locus in
    linear Rec.709, normalised to luminance 1; 6500 K is near white)."""
    from pxr import UsdLux

    colour = _colour(light.GetColorAttr().Get(), f"{where}.inputs:color")
    enabled = light.GetEnableColorTemperatureAttr().Get()
    if enabled is None or enabled is False:
        return colour
    if not isinstance(enabled, bool):
        raise LayerError(f"{where}.inputs:enableColorTemperature must be a bool, got {enabled!r}; fix the layer")
    kelvin = _number(light.GetColorTemperatureAttr().Get(), f"{where}.inputs:colorTemperature",
                     lo=COLOR_TEMPERATURE_K[0], hi=COLOR_TEMPERATURE_K[1], unit="K",
                     why=" (UsdLux's blackbody table)")
    rgb = UsdLux.BlackbodyTemperatureAsRgb(kelvin)
    return _colour(tuple(float(c) * float(k) for c, k in zip(colour, rgb)), f"{where}.inputs:color x colorTemperature")


def _rays(prim, light, where, mesh_paths) -> LampRays | None:
    """UsdLux's per-light ray switches as Cycles has them (None: all on, the default), after refusing
    what Cycles cannot show: a multiplier other than 0 or 1, light filters, a shadow colour, distance or
    falloff, and shadow linking that leaves any mesh out."""
    from pxr import Sdf, UsdLux

    flags = {}
    for name, attr in (("diffuse", light.GetDiffuseAttr()), ("specular", light.GetSpecularAttr())):
        value = attr.Get()
        value = 1.0 if value is None else _number(value, f"{where}.inputs:{name}")
        if value not in (0.0, 1.0):
            _refuse(where, f"inputs:{name} = {value:g}: Cycles turns a lamp's {name} light only on or off (1 or 0)",
                    "set it to 1 or 0 (fix the layer)")
        flags[name] = value == 1.0
    if light.GetFiltersRel().GetTargets():
        _refuse(where, "light filters (light:filters) are not rendered by allo-usd",
                "remove the light:filters relationship (fix the layer)")
    shadow = True
    if prim.HasAPI(UsdLux.ShadowAPI):
        api = UsdLux.ShadowAPI(prim)
        enable = api.GetShadowEnableAttr().Get()
        if enable is not None and not isinstance(enable, bool):
            raise LayerError(f"{where}.inputs:shadow:enable must be a bool, got {enable!r}; fix the layer")
        shadow = enable is not False
        for name, default in _SHADOW_DEFAULTS.items():
            attr = prim.GetAttribute(name)
            value = attr.Get() if attr else None
            if value is not None and tuple(np.atleast_1d(np.asarray(value, dtype=float))) != \
                    tuple(np.atleast_1d(np.asarray(default, dtype=float))):
                _refuse(where, f"{name} = {value} is not rendered (Cycles has only shadows on or off)",
                        "remove it (fix the layer)")
    if mesh_paths is not None:
        query = UsdLux.LightAPI(prim).GetShadowLinkCollectionAPI().ComputeMembershipQuery()
        skipped = [p for p in mesh_paths if not query.IsPathIncluded(Sdf.Path(p))]
        if skipped:
            _refuse(where, f"collection:shadowLink leaves {skipped[0]} out ({len(skipped)} meshes): shadow linking "
                    "is not rendered", "remove the shadowLink collection's includes/excludes (fix the layer)")
    rays = LampRays(flags["diffuse"], flags["specular"], shadow)
    return None if rays == LampRays() else rays


def _check_shaping(prim, where, allowed: bool) -> None:
    """ShapingAPI: only a sphere light's cone (angle, softness) is rendered; focus and IES profiles are
    refused, and on any other light the whole API (Blender's area `spread` is a different falloff)."""
    from pxr import UsdLux

    if not prim.HasAPI(UsdLux.ShapingAPI):
        return
    shaping = UsdLux.ShapingAPI(prim)
    if not allowed:
        _refuse(where, "ShapingAPI on this light is not rendered (Cycles shapes only a sphere light's cone; an "
                "area lamp's spread is another falloff)", "remove the ShapingAPI (fix the layer)")
    focus = shaping.GetShapingFocusAttr().Get()
    if focus not in (None, 0.0):
        _refuse(where, f"inputs:shaping:focus = {focus:g} is not rendered (Blender's spot has no focus falloff)",
                "remove it or set 0 (fix the layer)")
    ies = shaping.GetShapingIesFileAttr().Get()
    if ies is not None and ies.path:
        _refuse(where, "inputs:shaping:ies:file is not rendered", "remove it (fix the layer)")


def _link(prim, mesh_paths) -> LightLink | None:
    return None if mesh_paths is None else read_light_link(prim, mesh_paths)


def _lights_nothing(link: LightLink | None) -> bool:
    return link is not None and not (link.exclude or link.paths)


def _size(value, what: str) -> float:
    return _number(value, what, lo=LIGHT_SIZE_M[0], hi=LIGHT_SIZE_M[1], unit="m")


def read_sun(prim, cache, mesh_paths=None, checked: set | None = None) -> SunDesc | None:
    """A UsdLux.DistantLight as a sun lamp, its irradiance as the spec defines it (inputs:normalize
    honoured); None when it is off (intensity 0: umbra, or a total eclipse of the body it lights) or
    lights none of `mesh_paths` (when given, its light linking is resolved against them). A lamp whose
    light link names only some objects (a body's own lamp) is not drawn in camera rays; any other is
    (the Sun's disc, as a renderer that draws a DistantLight's angular extent shows it)."""
    from pxr import UsdLux

    light = UsdLux.DistantLight(prim)
    where = prim.GetPath()
    _check_shaping(prim, where, allowed=False)
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
    return SunDesc(tuple(direction), irradiance, angle, _colour_of(prim, light, where), str(where), link,
                   camera_visible=link is None or link.exclude, rays=_rays(prim, light, where, mesh_paths))


def read_spot(prim, cache, checked: set | None = None, mesh_paths=None) -> SpotDesc:
    """A UsdLux.SphereLight: with ShapingAPI a Blender spot lamp (its cone and softness), without one a
    point lamp of the same radius (it emits in every direction)."""
    from pxr import UsdLux

    light = UsdLux.SphereLight(prim)
    shaping = UsdLux.ShapingAPI(prim)
    shaped = prim.HasAPI(UsdLux.ShapingAPI)
    where = prim.GetPath()
    _check_shaping(prim, where, allowed=True)
    if light.GetTreatAsPointAttr().Get():
        _refuse(where, "treatAsPoint = true is not rendered (Blender's point lamp keeps its radius)",
                "set inputs:radius to 0 instead (fix the layer)")
    cone = shaping.GetShapingConeAngleAttr().Get() if shaped else SPOT_CONE_DEG[1]
    softness = shaping.GetShapingConeSoftnessAttr().Get() if shaped else None
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
    return SpotDesc(matrix, radius, intensity, _colour_of(prim, light, where), cone, softness, str(where), shaped,
                    _link(prim, mesh_paths), _rays(prim, light, where, mesh_paths))


def _area(matrix: np.ndarray) -> float:
    """How much the prim's transform scales an area in its local XY plane (|M x| x |M y| for a rotation
    and scale: the parallelogram the unit square becomes)."""
    return float(np.linalg.norm(np.cross(matrix[:3, 0], matrix[:3, 1])))


def read_area(prim, cache, checked: set | None, mesh_paths) -> AreaDesc | None:
    """A UsdLux RectLight (width x height) or DiskLight (radius) as a Blender area lamp: one-sided,
    emitting along local -Z as both define; Blender's energy is its power, radiance x world-space area x
    pi (a Lambertian emitter: tests/system/test_user_layer_lights.py measures it). None when off."""
    from pxr import UsdLux

    where = prim.GetPath()
    rect = prim.IsA(UsdLux.RectLight)
    light = UsdLux.RectLight(prim) if rect else UsdLux.DiskLight(prim)
    _check_shaping(prim, where, allowed=False)
    radiance = _intensity(light, where)
    if radiance == 0.0:
        return None
    if rect:
        tex = light.GetTextureFileAttr().Get()
        if tex is not None and tex.path:
            _refuse(where, "inputs:texture:file on a RectLight is not rendered (a Cycles area lamp has no image)",
                    "remove it (fix the layer)")
        size = (_size(light.GetWidthAttr().Get(), f"{where}.inputs:width"),
                _size(light.GetHeightAttr().Get(), f"{where}.inputs:height"))
        local_area = size[0] * size[1]
    else:
        radius = _size(light.GetRadiusAttr().Get(), f"{where}.inputs:radius")
        size = (2.0 * radius, 2.0 * radius)
        local_area = np.pi * radius ** 2
    matrix = world_matrix(cache, prim, checked=checked)
    area = local_area * _area(matrix)
    if _normalize(light, where):  # UsdLux: radiance = intensity / the world-space area
        radiance = radiance / area if area > 0 else radiance
    link = _link(prim, mesh_paths)
    if _lights_nothing(link):
        return None
    return AreaDesc(str(where), matrix, "RECTANGLE" if rect else "DISK", size, radiance,
                    _number(radiance * area * np.pi, f"{where} power (W)", lo=0.0, hi=MAX_LIGHT),
                    _colour_of(prim, light, where), None, link, _rays(prim, light, where, mesh_paths))


def read_cylinder(prim, cache, checked: set | None, mesh_paths) -> CylinderDesc | None:
    """A UsdLux CylinderLight (radius, length along its local X, no end caps) as an emission-only mesh of
    that radiance; ShadowAPI's shadows off cannot be had for a mesh emitter and is refused."""
    from pxr import UsdLux

    where = prim.GetPath()
    light = UsdLux.CylinderLight(prim)
    _check_shaping(prim, where, allowed=False)
    if light.GetTreatAsLineAttr().Get():
        _refuse(where, "treatAsLine = true is not rendered (the cylinder keeps its radius)",
                "remove it (fix the layer)")
    radiance = _intensity(light, where)
    if radiance == 0.0:
        return None
    radius = _size(light.GetRadiusAttr().Get(), f"{where}.inputs:radius")
    length = _size(light.GetLengthAttr().Get(), f"{where}.inputs:length")
    matrix = world_matrix(cache, prim, checked=checked)
    if _normalize(light, where):  # the world-space side area: length along X, circumference in Y, Z
        s = np.linalg.norm(matrix[:3, :3], axis=0)
        area = 2.0 * np.pi * radius * float(np.sqrt(s[1] * s[2])) * length * float(s[0])
        radiance = radiance / area if area > 0 else radiance
    rays = _rays(prim, light, where, mesh_paths)
    if rays is not None and not rays.shadow:
        _refuse(where, "inputs:shadow:enable = false on a CylinderLight is not rendered (it is an emitting mesh, "
                "whose light always casts shadows)", "remove it (fix the layer)")
    link = _link(prim, mesh_paths)
    if _lights_nothing(link):
        return None
    return CylinderDesc(str(where), matrix, radius, length, radiance, _colour_of(prim, light, where), link, rays)


LATLONG_FORMATS = ("automatic", "latlong")   # DomeLight inputs:texture:format this reader maps (automatic: lat-long)


def read_dome(prim, cache, checked: set | None, mesh_paths) -> DomeDesc | None:
    """A UsdLux DomeLight as the world background: radiance inputs:color x intensity x 2^exposure
    (inputs:normalize has no area to divide by: a dome is left as it is), times its lat-long
    inputs:texture:file where it has one, oriented as UsdLux's DomeLight says (the OpenEXR lat-long
    convention in the dome's own frame: pole +Y, longitude 0 towards +Z, pi/2 towards +X), turned by
    the dome's world rotation (`DomeDesc.rotation`). No light linking."""
    from pxr import UsdLux

    from allo_usd.usd.read_material import texture_file

    where = prim.GetPath()
    light = UsdLux.DomeLight(prim)
    _check_shaping(prim, where, allowed=False)
    asset = light.GetTextureFileAttr().Get()
    texture = rotation = None
    if asset is not None and asset.path:
        fmt = str(light.GetTextureFormatAttr().Get() or "automatic")
        if fmt not in LATLONG_FORMATS:
            _refuse(where, f"inputs:texture:format = {fmt!r} is not rendered (a lat-long map is)",
                    "convert the image to lat-long and set inputs:texture:format = \"latlong\" (fix the layer)")
        texture = texture_file(asset, f"{where}.inputs:texture:file", f"DomeLight {where}", prim)
        m = world_matrix(cache, prim, checked=checked)[:3, :3]
        u, _, vt = np.linalg.svd(m)
        rotation = u @ vt                       # the dome's orientation, its scale aside (a dome is at infinity)
        if np.linalg.det(rotation) < 0:
            _refuse(where, "a mirrored transform turns the dome's image inside out", "remove the negative scale "
                    "(fix the layer)")
    if light.GetPortalsRel().GetTargets():
        _refuse(where, "portals are not rendered", "remove the portals relationship (fix the layer)")
    strength = _intensity(light, where)
    if strength == 0.0:
        return None
    link = _link(prim, mesh_paths)
    if link is not None:
        _refuse(where, "collection:lightLink on a DomeLight is not rendered (Blender's world lights every object)",
                "remove the lightLink collection's includes/excludes (fix the layer)")
    rays = _rays(prim, light, where, mesh_paths)
    if rays is not None and not rays.shadow:
        _refuse(where, "inputs:shadow:enable = false on a DomeLight is not rendered", "remove it (fix the layer)")
    return DomeDesc(str(where), _colour_of(prim, light, where), strength, texture, rotation, rays=rays)


def read_lights(prims, cache, mesh_paths, checked: set, effects) -> Lights:
    """The scene's lamps from its UsdLux light prims (in stage order): the sun lamps that are on
    (read_sun), the inspection spot (read_spot at layout.INSPECTION_LIGHT; None when `effects` turns it
    off), every other lamp that is on (sphere, rect, disk, cylinder lights, each added to the others)
    and the one dome. A light type Cycles cannot show is refused."""
    from pxr import UsdLux

    suns, spot, others, dome, dome_path = [], None, [], None, None
    for prim in prims:
        where = prim.GetPath()
        if prim.IsA(UsdLux.DistantLight):
            sun = read_sun(prim, cache, mesh_paths, checked)
            if sun is not None:
                suns.append(sun)
        elif prim.IsA(UsdLux.SphereLight):
            if str(where) == INSPECTION_LIGHT:
                spot = read_spot(prim, cache, checked, mesh_paths)
                continue
            lamp = read_spot(prim, cache, checked, mesh_paths)
            if lamp.intensity > 0.0 and not _lights_nothing(lamp.link):
                others.append(lamp)
        elif prim.IsA(UsdLux.RectLight) or prim.IsA(UsdLux.DiskLight):
            lamp = read_area(prim, cache, checked, mesh_paths)
            if lamp is not None:
                others.append(lamp)
        elif prim.IsA(UsdLux.CylinderLight):
            lamp = read_cylinder(prim, cache, checked, mesh_paths)
            if lamp is not None:
                others.append(lamp)
        elif prim.GetTypeName() == "DomeLight":
            if dome_path is not None:
                _refuse(where, f"a second DomeLight ({dome_path} is the first): Blender has one world",
                        "keep one DomeLight (fix the layer)")
            dome_path = where
            dome = read_dome(prim, cache, checked, mesh_paths)
        else:
            _refuse(where, f"a {prim.GetTypeName() or 'typeless'} light is not rendered by allo-usd (it renders "
                    "DistantLight, SphereLight, RectLight, DiskLight, CylinderLight and DomeLight)",
                    "remove it or use one of those (fix the layer)")
    return Lights(tuple(suns), spot if effects.inspection_light else None, tuple(others), dome)


class Lights(NamedTuple):
    suns: tuple
    spot: SpotDesc | None
    others: tuple
    dome: DomeDesc | None
