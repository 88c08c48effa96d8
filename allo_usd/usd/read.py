"""What a scene layer says: a composed scene layer -> the plain, frozen SceneDescription. Uses pxr
only; never imports bpy.

`open_stage` is the gate every read passes first (the dependency walk, composition errors, Z-up
metres); `read_scene` then reads the composed stage with one reader function per prim type (mesh,
material, camera, lights, render settings): the stage is the scene, this module is a one-way
translation of it. Every value is held to the bounds in allo_usd.usd.reader_bounds on the way.
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
from allo_usd.core.errors import LayerError
from allo_usd.core.scene_labels import SPLITS, VARIANTS, label_problem
from allo_usd.usd.base_stage import RENDER_VARS
from allo_usd.usd.reader_bounds import (CAMERA_EV, CAMERA_EXPOSURE_FACTOR, CLIP_M, IOR, LENS_MM, MAX_CAMERA_DISTANCE_M,
                                        MAX_COLOUR, MAX_LIGHT, MAX_SCENE_POINTS, MAX_SHIFT, OFFSET_TOLERANCE,
                                        RENDER_ADAPTIVE, RENDER_BOUNCES, RENDER_EXPOSURE, RENDER_SAMPLES, RENDER_SEED,
                                        RENDER_THREADS, SENSOR_MM, SPOT_CONE_DEG, SPOT_RADIUS_M, SPOT_SOFTNESS,
                                        SUN_ANGLE_DEG, UNIT_INTERVAL, as_stored, _check_resolution, _check_size,
                                        check_texture_file, _colour, mesh_topology, _millimetres, _number, _range, snap,
                                        _tf_message, _vector, world_matrix)


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


VAR_PASSES = {name: p for name, (p, _, _, _) in RENDER_VARS.items()}   # var prim name -> pass


def var_pass(name: str) -> str:
    """The pass (allo_usd.plan.settings.PASSES) of a render var the product orders, by its prim name."""
    if name not in VAR_PASSES:
        raise LayerError(f"the image product orders a render var {name!r} this renderer does not write; order only "
                         f"{', '.join(VAR_PASSES)} under {layout.VARS} (fix the layer)")
    return VAR_PASSES[name]
