"""Lights as the reader sees them: UsdLux prims -> SunDesc and SpotDesc, with the units UsdLux defines
(inputs:intensity x 2^inputs:exposure, inputs:normalize honoured) and light linking resolved against
the scene's meshes. pxr only."""

from __future__ import annotations

import numpy as np

from allo_usd.core.errors import LayerError
from allo_usd.usd.description import LightLink, SpotDesc, SunDesc
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


def read_lights(prims, cache, mesh_paths, checked: set, effects) -> tuple[tuple[SunDesc, ...], SpotDesc | None]:
    """The scene's lamps from its UsdLux light prims (in stage order): the sun lamps that are on
    (read_sun) and the inspection spot (read_spot; None when `effects` turns it off)."""
    from pxr import UsdLux

    suns, spot = [], None
    for prim in prims:
        if prim.IsA(UsdLux.DistantLight):
            sun = read_sun(prim, cache, mesh_paths, checked)
            if sun is not None:
                suns.append(sun)
        elif prim.IsA(UsdLux.SphereLight):
            spot = read_spot(prim, cache, checked)
    return tuple(suns), spot if effects.inspection_light else None
