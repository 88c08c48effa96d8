"""What a scene layer says: a composed scene layer -> the plain, frozen SceneDescription. Uses pxr
only; never imports bpy.

`open_stage` is the gate every read passes first (the dependency walk, composition errors, Z-up
metres); `read_scene` then reads the composed stage with one reader per prim type: meshes
(read_geometry), materials (read_material), lights (read_lights), the camera and the render settings
(here), the scene's identity and labels (read_labels): the stage is the scene, this package is a
one-way translation of it. Every value is held to the bounds in allo_usd.usd.reader_bounds on the way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from allo_usd.usd import attributes as A
from allo_usd.usd import layout, schema
from allo_usd.plan.settings import DENOISE_PREFILTERS, DENOISE_QUALITIES
from allo_usd.usd.description import CameraDesc, EffectsDesc, RenderDesc, SceneDescription
from allo_usd.core.errors import LayerError
from allo_usd.usd.base_stage import RENDER_VARS
from allo_usd.usd.read_geometry import read_mesh
from allo_usd.usd.read_labels import check_variants, read_meta
from allo_usd.usd.read_lights import read_lights
from allo_usd.usd.reader_bounds import (CAMERA_EV, CAMERA_EXPOSURE_FACTOR, CLIP_M, LENS_MM, MAX_CAMERA_DISTANCE_M,
                                        MAX_SCENE_POINTS, MAX_SHIFT, OFFSET_TOLERANCE, RENDER_ADAPTIVE, RENDER_BOUNCES,
                                        RENDER_EXPOSURE, RENDER_SAMPLES, RENDER_SEED, RENDER_THREADS, SENSOR_MM,
                                        as_stored, _check_resolution, _check_size, _millimetres, _number, _range, snap,
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

    meshes, materials, light_prims = [], {}, []
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
        check_variants(prim)
        if prim.IsA(UsdGeom.Mesh):
            meshes.append(read_mesh(prim, cache, materials, checked))
            points += len(meshes[-1].points)
            if points > MAX_SCENE_POINTS:
                raise LayerError(f"{layer_path}: the scene's meshes hold more than {MAX_SCENE_POINTS:,} points in "
                                 f"all (at {prim.GetPath()}); fix the layer: use lighter assets")
        elif prim.IsA(UsdLux.BoundableLightBase) or prim.IsA(UsdLux.NonboundableLightBase):
            light_prims.append(prim)  # read once every mesh is known: light linking names meshes
    if not meshes:
        raise LayerError(f"{layer_path}: the composed stage has no meshes; the base stage or its station "
                         "payload did not load (check subLayers and stages/)")
    lights = read_lights(light_prims, cache, [m.path for m in meshes], checked, effects)
    if not effects.body_shine:  # no earthshine/moonshine: the bodies are seen but light nothing
        import dataclasses

        meshes = [dataclasses.replace(m, ray_visibility="cameraOnly") if m.ray_visibility == "noShadow" else m
                  for m in meshes]
    return SceneDescription(str(Path(layer_path).resolve()), tuple(meshes), materials, camera, lights.suns,
                            lights.spot, render, effects, read_meta(stage), lights.others, lights.dome)


VAR_PASSES = {name: p for name, (p, _, _, _) in RENDER_VARS.items()}   # var prim name -> pass


def var_pass(name: str) -> str:
    """The pass (allo_usd.plan.settings.PASSES) of a render var the product orders, by its prim name."""
    if name not in VAR_PASSES:
        raise LayerError(f"the image product orders a render var {name!r} this renderer does not write; order only "
                         f"{', '.join(VAR_PASSES)} under {layout.VARS} (fix the layer)")
    return VAR_PASSES[name]
