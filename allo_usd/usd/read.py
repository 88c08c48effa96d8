"""Composed USD stage -> SceneDescription. Uses pxr only; never imports bpy.

One reader function per prim type (mesh, material, camera, lights, render settings); the
stage is the scene, this module is a one-way translation of it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from allo_usd.usd import attributes as A
from allo_usd.usd import layout, schema
from allo_usd.core.labels import BACKGROUND, CLASS_IDS
from allo_usd.plan.settings import DENOISE_PREFILTERS, DENOISE_QUALITIES
from allo_usd.usd.description import (CameraDesc, EffectsDesc, LightLink, MaterialDesc, MeshDesc, RenderDesc,
                                      SceneDescription, SpotDesc, SunDesc)
from allo_usd.core.errors import LayerError
from allo_usd.core.limits import resolution_problem
from allo_usd.usd.base_stage import BASE_PRODUCT_VARS, RENDER_VARS


# Sanity bounds on what a layer may ask for (the fuzz tests feed absurd values through here).
MAX_POSITION_M = 1e12          # any prim, from the station at the origin (the Sun is ~1.5e11 m away)
MAX_CAMERA_DISTANCE_M = 1e4    # the camera, from the station (ALLO cameras sit within ~70 m of it)


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


def _number(value, what: str, integer: bool = False, lo: float = -np.inf, hi: float = np.inf):
    """A finite int/float within [lo, hi], or a LayerError naming the attribute and the value."""
    kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(value, bool) or not isinstance(value, kinds):
        raise LayerError(f"{what} must be {'an integer' if integer else 'a number'}, got {value!r}; fix the layer")
    if not (np.isfinite(value) and lo <= value <= hi):
        raise LayerError(f"{what}={value!r} is outside {lo}..{hi}; fix the layer")
    return int(value) if integer else float(value)


def _vector(value, what: str, n: int) -> tuple[float, ...]:
    try:
        out = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        raise LayerError(f"{what} must be {n} numbers, got {value!r}; fix the layer") from None
    if len(out) != n or not np.isfinite(out).all():
        raise LayerError(f"{what} must be {n} finite numbers, got {value!r}; fix the layer")
    return out


def _check_xform_ops(prim) -> None:
    """Every xformOp on the prim and its ancestors holds finite values of a transform type."""
    from pxr import Gf, UsdGeom

    p = prim
    while p and not p.IsPseudoRoot():
        if p.IsA(UsdGeom.Xformable):
            for op in UsdGeom.Xformable(p).GetOrderedXformOps():
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
        p = p.GetParent()


def _check_quaternion(where, value, wxyz) -> None:
    """An orient op's quaternion must have a length: USD reads (0, 0, 0, 0) as no rotation, silently."""
    norm = float(np.linalg.norm(np.asarray(wxyz, dtype=np.float64)))
    if norm < 1e-6:
        raise LayerError(f"{where} = {value} is not a rotation (a quaternion of length {norm:.3g}, which USD would "
                         "silently read as no rotation); fix the layer: write a unit quaternion (real, i, j, k), "
                         "e.g. (1, 0, 0, 0) for none")


def _check_position(cache, prim, m: np.ndarray, max_distance: float) -> None:
    """The prim's world position lies within `max_distance` metres of the station (the origin);
    the error names the outermost prim that is already too far (the one whose transform to fix)."""
    distance = float(np.linalg.norm(m[:3, 3]))
    if distance <= max_distance:
        return
    culprit, where = prim, m[:3, 3]
    parent = prim.GetParent()
    while parent and not parent.IsPseudoRoot():
        t = np.array(cache.GetLocalToWorldTransform(parent), dtype=np.float64)[3, :3]  # row-vector: last row
        if not np.linalg.norm(t) > max_distance:
            break
        culprit, where, parent = parent, t, parent.GetParent()
    raise LayerError(f"{culprit.GetPath()} is at {tuple(float(c) for c in where)}, {np.linalg.norm(where):.3g} m "
                     f"from the station at the origin, beyond the {max_distance:,.0f} m allowed for it; fix the "
                     "xformOp:translate (or parent transform) that puts it there")


def _check_resolution(w: int, h: int, where) -> None:
    problem = resolution_problem(w, h)
    if problem:
        raise LayerError(f"{where}.resolution = ({w}, {h}): {problem}; fix the layer")


def world_matrix(cache, prim, max_distance: float = MAX_POSITION_M) -> np.ndarray:
    from pxr import Tf

    _check_xform_ops(prim)
    try:
        m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64).T  # USD is row-vector
    except Tf.ErrorException as exc:
        raise LayerError(f"{prim.GetPath()} has an unreadable transform ({_tf_message(exc)}); fix the layer") from None
    if not np.isfinite(m).all():
        raise LayerError(f"{prim.GetPath()} has a non-finite transform; fix the layer that sets it")
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


def read_material(material) -> MaterialDesc:
    from pxr import UsdShade

    path = str(material.GetPath())
    surface = material.ComputeSurfaceSource()[0]
    if not surface or surface.GetIdAttr().Get() != "UsdPreviewSurface":
        raise LayerError(f"material {path} has no UsdPreviewSurface; allo-usd renders UsdPreviewSurface only")
    color, src = _input(surface, "diffuseColor", (0.18, 0.18, 0.18))
    texture = None
    if src is not None:
        tex = UsdShade.Shader(src[0].GetPrim())
        asset = tex.GetInput("file").Get()
        texture = asset.resolvedPath if asset else None
        if not texture:
            raise LayerError(f"material {path}: texture {asset} does not resolve to a file; restore the "
                             "asset's textures/ folder")
        scale = tex.GetInput("scale").Get() if tex.GetInput("scale") else None
        color = tuple(scale)[:3] if scale is not None else (1.0, 1.0, 1.0)
    metallic, _ = _input(surface, "metallic", 0.0)
    roughness, _ = _input(surface, "roughness", 0.5)
    emissive, _ = _input(surface, "emissiveColor", (0.0, 0.0, 0.0))
    ior = _number(_input(surface, "ior", 1.5)[0], f"{path} inputs:ior", lo=1.0, hi=10.0)
    return MaterialDesc(path, tuple(float(c) for c in color), float(metallic), float(roughness), texture,
                        tuple(float(c) for c in emissive), ior)


def read_mesh(prim, cache, materials: dict) -> MeshDesc:
    from pxr import UsdGeom, UsdShade

    mesh = UsdGeom.Mesh(prim)
    path = str(prim.GetPath())
    points = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float32)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int32)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int32)
    if points.ndim != 2 or len(points) == 0 or len(counts) == 0:
        raise LayerError(f"mesh {path} has no points or faces; regenerate its asset")
    if not np.isfinite(points).all():
        raise LayerError(f"mesh {path} has NaN or infinite points; regenerate its asset")
    if counts.sum() != len(indices) or indices.min() < 0 or indices.max() >= len(points):
        raise LayerError(f"mesh {path} has inconsistent face indices; regenerate its asset")
    uv = None
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if st and st.HasValue():
        if st.GetInterpolation() != UsdGeom.Tokens.faceVarying:
            raise LayerError(f"mesh {path}: primvars:st must be faceVarying")
        uv = np.asarray(st.ComputeFlattened(), dtype=np.float32)
    smooth = bool(mesh.GetNormalsAttr().HasAuthoredValue()) and mesh.GetNormalsInterpolation() != UsdGeom.Tokens.faceVarying
    bound = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
    if bound:
        key = str(bound.GetPath())
        if key not in materials:
            materials[key] = read_material(bound)
    else:
        key = "__default__"
        materials.setdefault(key, MaterialDesc(key, (0.5, 0.5, 0.5), 0.0, 0.5))
    return MeshDesc(path, points, counts, indices, uv, smooth, key, world_matrix(cache, prim), _class_id(prim),
                    _ray_visibility(prim))


def read_camera(prim, cache) -> CameraDesc:
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    # Lens values are tenths of a scene unit; with metersPerUnit = 1 that is 100 mm per unit.
    to_mm = 100.0
    clip = cam.GetClippingRangeAttr().Get()
    values = [cam.GetFocalLengthAttr().Get(), cam.GetHorizontalApertureAttr().Get(),
              cam.GetVerticalApertureAttr().Get()]
    if not all(v is not None and np.isfinite(v) and v > 0 for v in values):
        raise LayerError(f"camera {prim.GetPath()} needs positive focalLength and apertures, got {values}")
    m = world_matrix(cache, prim, MAX_CAMERA_DISTANCE_M)
    return CameraDesc(m, values[0] * to_mm, values[1] * to_mm, values[2] * to_mm,
                      (float(clip[0]), float(clip[1])), str(prim.GetPath()))


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


def read_sun(prim, cache, mesh_paths=None) -> SunDesc | None:
    """A UsdLux.DistantLight as a sun lamp; None when it is off (intensity 0: umbra, or a total eclipse
    of the body it lights) or lights none of `mesh_paths` (when given, its light linking is resolved
    against them)."""
    from pxr import UsdLux

    light = UsdLux.DistantLight(prim)
    where = prim.GetPath()
    intensity = _number(light.GetIntensityAttr().Get(), f"{where}.inputs:intensity", lo=0.0) * 2.0 ** _number(
        light.GetExposureAttr().Get() or 0.0, f"{where}.inputs:exposure", lo=-64, hi=64)
    if intensity == 0.0:
        return None  # the lamp is off
    link = None if mesh_paths is None else read_light_link(prim, mesh_paths)
    if link is not None and not (link.exclude or link.paths):
        return None  # it lights nothing
    m = world_matrix(cache, prim)
    direction = m[:3, 2] / np.linalg.norm(m[:3, 2])  # light travels along -Z, so +Z points at the Sun
    return SunDesc(tuple(direction), intensity, _number(light.GetAngleAttr().Get(), f"{where}.inputs:angle", lo=0, hi=180),
                   _vector(light.GetColorAttr().Get(), f"{where}.inputs:color", 3), str(where), link)


def read_spot(prim, cache) -> SpotDesc:
    from pxr import UsdLux

    light = UsdLux.SphereLight(prim)
    shaping = UsdLux.ShapingAPI(prim)
    cone = shaping.GetShapingConeAngleAttr().Get() if prim.HasAPI(UsdLux.ShapingAPI) else 180.0
    softness = shaping.GetShapingConeSoftnessAttr().Get() if prim.HasAPI(UsdLux.ShapingAPI) else 0.0
    where = prim.GetPath()
    intensity = _number(light.GetIntensityAttr().Get(), f"{where}.inputs:intensity", lo=0.0) * 2.0 ** _number(
        light.GetExposureAttr().Get() or 0.0, f"{where}.inputs:exposure", lo=-64, hi=64)
    return SpotDesc(world_matrix(cache, prim), _number(light.GetRadiusAttr().Get(), f"{where}.inputs:radius", lo=0.0),
                    intensity, _vector(light.GetColorAttr().Get(), f"{where}.inputs:color", 3),
                    _number(cone, f"{where}.shaping:cone:angle", lo=0, hi=180),
                    _number(softness or 0.0, f"{where}.shaping:cone:softness", lo=0), str(where))


def _get(prim, name, default=None):
    attr = prim.GetAttribute(name)
    value = attr.Get() if attr else None
    return default if value is None else value


def read_render(settings_prim) -> tuple[RenderDesc, EffectsDesc]:
    from pxr import UsdRender

    from pxr import Gf

    settings = UsdRender.Settings(settings_prim)
    res = settings.GetResolutionAttr().Get()
    if not isinstance(res, Gf.Vec2i):
        raise LayerError(f"{settings_prim.GetPath()}.resolution must be an int2, got {res!r}; fix the layer")
    w, h = int(res[0]), int(res[1])
    _check_resolution(w, h, settings_prim.GetPath())

    def num(name, default, integer=False, lo=-np.inf, hi=np.inf):
        return _number(_get(settings_prim, name, default), name, integer, lo, hi)

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

    samples = num(A.RENDER_SAMPLES.name, 64, True, 1, 65536)
    outputs = []
    for product_path in settings.GetProductsRel().GetForwardedTargets():
        product = UsdRender.Product(settings_prim.GetStage().GetPrimAtPath(product_path))
        for var_path in product.GetOrderedVarsRel().GetForwardedTargets():
            var = UsdRender.Var(settings_prim.GetStage().GetPrimAtPath(var_path))
            outputs.append(str(var.GetSourceNameAttr().Get()))
    exposure = num(A.RENDER_EXPOSURE.name, 1.0)
    if not exposure > 0:
        raise LayerError(f"{A.RENDER_EXPOSURE.name} must be a positive number, got {exposure}; fix the layer")
    render = RenderDesc(resolution=(w, h), preset=str(_get(settings_prim, A.RENDER_PRESET.name, "preview")),
                        samples=samples,
                        adaptive_threshold=num(A.RENDER_ADAPTIVE_THRESHOLD.name, 0.0, lo=0.0, hi=1.0),
                        denoise=flag(A.RENDER_DENOISE.name, True),
                        max_bounces=num(A.RENDER_MAX_BOUNCES.name, 8, True, 0, 1024),
                        seed=num(A.RENDER_SEED.name, 0, True, -2 ** 31, 2 ** 32 - 1), exposure=exposure,
                        threads=num(A.RENDER_THREADS.name, 0, True, 0, 4096), outputs=tuple(outputs),
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
    return meta


def read_scene(layer_path: str | Path) -> SceneDescription:
    """Read a scene layer (composed over its base stage) into a plain description."""
    from pxr import Usd, UsdGeom, UsdLux

    stage = open_stage(layer_path)
    settings_path = stage.GetMetadata("renderSettingsPrimPath") or layout.RENDER_SETTINGS
    settings_prim = stage.GetPrimAtPath(settings_path)
    if not settings_prim:
        raise LayerError(f"{layer_path}: no render settings at {settings_path}; the base stage sublayer is "
                         "missing or broken (check subLayers)")
    render, effects = read_render(settings_prim)
    from pxr import UsdRender
    cam_targets = UsdRender.Settings(settings_prim).GetCameraRel().GetForwardedTargets()
    if not cam_targets or not stage.GetPrimAtPath(cam_targets[0]).IsA(UsdGeom.Camera):
        raise LayerError(f"{layer_path}: render settings name no camera; set {settings_path}.camera")
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    camera = read_camera(stage.GetPrimAtPath(cam_targets[0]), cache)

    meshes, materials, sun_prims, spot = [], {}, [], None
    it = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.PrimIsActive & Usd.PrimIsDefined & ~Usd.PrimIsAbstract))
    for prim in it:
        if prim.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(prim).ComputeVisibility() == UsdGeom.Tokens.invisible:
            it.PruneChildren()
            continue
        if prim.GetPath().HasPrefix(layout.RIG) or prim.GetPath().HasPrefix(layout.RENDER):
            it.PruneChildren()
            continue
        _check_variants(prim)
        if prim.IsA(UsdGeom.Mesh):
            meshes.append(read_mesh(prim, cache, materials))
        elif prim.IsA(UsdLux.DistantLight):
            sun_prims.append(prim)  # read once every mesh is known: light linking names meshes
        elif prim.IsA(UsdLux.SphereLight):
            spot = read_spot(prim, cache)
    if not meshes:
        raise LayerError(f"{layer_path}: the composed stage has no meshes; the base stage or its station "
                         "payload did not load (check subLayers and stages/)")
    mesh_paths = [m.path for m in meshes]
    suns = tuple(s for s in (read_sun(p, cache, mesh_paths) for p in sun_prims) if s is not None)
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


def read_triangles(layer_path: str | Path, root: str, variant: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World-space (points, triangles) of every mesh under `root`, for ray casting."""
    from pxr import Usd, UsdGeom

    from allo_usd.assets.mesh import fan_triangulate

    stage = open_stage(layer_path)
    prim = stage.GetPrimAtPath(root) if root else stage.GetDefaultPrim()
    if not prim:
        raise LayerError(f"{layer_path} has no prim {root}")
    if variant is not None:
        vs = prim.GetVariantSets().GetVariantSet("variant")
        if variant not in vs.GetVariantNames():
            raise LayerError(f"{layer_path}: unknown variant {variant!r}; choose one of {vs.GetVariantNames()}")
        vs.SetVariantSelection(variant)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    pts, tris, off = [], [], 0
    for p in Usd.PrimRange(prim):
        if p.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(p)
            local = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
            m = world_matrix(cache, p)
            pts.append(local @ m[:3, :3].T + m[:3, 3])
            t = fan_triangulate(np.asarray(mesh.GetFaceVertexCountsAttr().Get()),
                                np.asarray(mesh.GetFaceVertexIndicesAttr().Get()))
            tris.append(t + off)
            off += len(local)
    if not pts:
        raise LayerError(f"{layer_path}: no meshes under {root}")
    return np.concatenate(pts), np.concatenate(tris)


class StageGeometry:
    """A base stage's geometry for scene resolution (allo_usd.scene.resolve.StationGeometry): its
    camera rig, the station's triangles and each anomaly asset's triangles, read with pxr."""

    def __init__(self, base_stage: str | Path):
        self.base_stage = Path(base_stage)

    def poses(self) -> list:
        return read_rig(self.base_stage)

    def station_triangles(self) -> tuple[np.ndarray, np.ndarray]:
        return read_triangles(self.base_stage, layout.STATION)

    def anomaly_triangles(self, asset: str, variant: str) -> tuple[np.ndarray, np.ndarray]:
        return read_triangles(self.base_stage.parent / "anomalies" / f"{asset}.usda", layout.asset_root(asset), variant)


def scene_inputs(base_stage: str | Path, sky, perilune_epoch: str):
    """SceneInputs over a base stage: what allo_usd.scene.resolve needs, read from USD."""
    from allo_usd.scene.resolve import SceneInputs

    return SceneInputs(StageGeometry(base_stage), sky, perilune_epoch)


VAR_SOURCES = {name: source for name, (source, _, _) in RENDER_VARS.items()}   # var prim name -> source
DEFAULT_OUTPUTS = tuple(VAR_SOURCES[name] for name in BASE_PRODUCT_VARS)


def layer_outputs(layer: Path) -> tuple[str, ...]:
    """The render vars a scene layer orders (its own override of the product, else the base's
    color + class mask), read from the layer file alone: cheap enough for resume checks."""
    from pxr import Sdf, Tf

    try:
        sdf = Sdf.Layer.FindOrOpen(str(layer))
    except Tf.ErrorException:
        return DEFAULT_OUTPUTS  # unreadable: read_scene will say what is wrong with it
    rel = sdf.GetRelationshipAtPath(f"{layout.IMAGE_PRODUCT}.orderedVars") if sdf else None
    if not rel or not rel.targetPathList.explicitItems:
        return DEFAULT_OUTPUTS
    return tuple(VAR_SOURCES.get(t.name, t.name) for t in rel.targetPathList.explicitItems)
