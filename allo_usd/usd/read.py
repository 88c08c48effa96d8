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

from allo_usd.core import fixedmath as fm
from allo_usd.usd import attributes as A
from allo_usd.usd import layout, schema
from allo_usd.plan.settings import DENOISE_PREFILTERS, DENOISE_QUALITIES, TARGET_WITH_GLARE
from allo_usd.usd.description import CameraDesc, EffectsDesc, RenderDesc, SceneDescription
from allo_usd.core.errors import LayerError
from allo_usd.usd.base_stage import RENDER_VARS
from allo_usd.usd.read_geometry import included_purposes, is_geometry, read_geometry
from allo_usd.usd.read_labels import check_variants, read_meta
from allo_usd.usd.read_lights import read_lights
from allo_usd.usd.reader_bounds import (CAMERA_EV, CAMERA_EXPOSURE_FACTOR, CLIP_M, LENS_MM, MAX_CAMERA_DISTANCE_M,
                                        MAX_SCENE_POINTS, MAX_SHIFT, OFFSET_TOLERANCE, RENDER_ADAPTIVE, RENDER_BOUNCES,
                                        RENDER_EXPOSURE, RENDER_SAMPLES, RENDER_SEED, RENDER_TARGET_PSNR,
                                        RENDER_THREADS, RENDER_TIME_LIMIT, SENSOR_MM,
                                        as_stored, _check_resolution, _check_size, _millimetres, _number, _range, snap,
                                        _vector, world_matrix)


def open_stage(layer_path: str | Path):
    """Open a scene layer as a stage, turning every USD failure into a LayerError with a fix.

    Before USD opens anything, every file the composition reads is checked (allowed roots,
    regular file, size, layer extension: allo_usd.usd.dependencies.walk); the stage must then
    compose without errors, and the composed stage is checked against the roots again
    (allo_usd.usd.safety.check_stage, a second line of defence).
    """
    from pxr import Tf, Usd, UsdGeom

    from allo_usd.usd.dependencies import REAUTHOR, project_layer, unreadable, walk
    from allo_usd.usd.safety import check_stage

    schema.register()
    path = Path(layer_path)
    if not path.exists():
        raise LayerError(f"scene layer {path} does not exist; check the path")
    opened = walk(path)  # its Sdf layers stay open until the stage holds them: USD parses each once
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise LayerError(unreadable(str(path), path, exc)) from None
    del opened
    if stage is None:
        raise LayerError(f"{path} could not be opened as a USD stage; "
                         f"{REAUTHOR if project_layer(str(path)) else 'fix the layer'}")
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
def read_camera(prim, cache, checked: set | None = None, settings_prim=None) -> CameraDesc:
    """The UsdGeom.Camera the render settings name, as Blender's camera: projection (perspective
    only), lens, apertures conformed to the image as the settings' aspectRatioConformPolicy says,
    offsets, clipping range, depth of field (fStop, focusDistance; the settings'
    disableDepthOfField) and its transform. `settings_prim`: the UsdRender.Settings prim (None: the
    apertures as authored, no depth of field switch)."""
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
    planes = cam.GetClippingPlanesAttr().Get()
    if planes is not None and len(planes):
        raise LayerError(f"{where}.clippingPlanes holds {len(planes)} plane(s): Cycles has no clipping planes beyond "
                         "the clipping range; fix the layer: remove clippingPlanes (or cut the geometry itself)")
    role = cam.GetStereoRoleAttr().Get()
    if role not in (UsdGeom.Tokens.mono, UsdGeom.Tokens.left, UsdGeom.Tokens.right):
        raise LayerError(f"{where}.stereoRole = {role!r} is not mono, left or right; fix the layer")
    offsets = []
    for attr, aperture in ((cam.GetHorizontalApertureOffsetAttr(), width), (cam.GetVerticalApertureOffsetAttr(), height)):
        mm = _number(attr.Get(), f"{where}.{attr.GetName()}") * 100.0
        edge = MAX_SHIFT * aperture
        if not abs(mm) <= edge * (1.0 + OFFSET_TOLERANCE):
            raise LayerError(f"{where}.{attr.GetName()} = {attr.Get()!r} ({mm:.3g} mm) puts the principal point outside "
                             f"the image (|offset| <= {MAX_SHIFT:g} x the {aperture:.3g} mm aperture); fix the layer")
        offsets.append(snap(mm, (-edge, edge)) + 0.0)
    f_stop, focus = _depth_of_field(cam, where, settings_prim)
    if settings_prim is not None:
        width, height = conform_aperture(width, height, settings_prim, where)
    m = world_matrix(cache, prim, MAX_CAMERA_DISTANCE_M, checked)
    return CameraDesc(m, focal, width, height, (near, far), str(where), *offsets, f_stop=f_stop, focus_distance_m=focus)


def _depth_of_field(cam, where, settings_prim) -> tuple[float, float]:
    """(fStop, focusDistance in m) as UsdGeom.Camera defines them: fStop 0 (the fallback) is no depth
    of field, and so is the settings' disableDepthOfField = true; else focusDistance must be > 0."""
    f_stop = _number(cam.GetFStopAttr().Get(), f"{where}.fStop", lo=0.0, hi=F_STOP[1])
    focus = _number(cam.GetFocusDistanceAttr().Get(), f"{where}.focusDistance", lo=0.0)
    disabled = settings_prim is not None and _get(settings_prim, "disableDepthOfField", False) is True
    if f_stop == 0.0 or disabled:
        return 0.0, 0.0
    if not F_STOP[0] <= f_stop:
        raise LayerError(f"{where}.fStop = {f_stop:g}: a lens opens to f/{F_STOP[0]:g} at most; fix the layer: 0 for no "
                         f"depth of field, else an f-number in {_range(*F_STOP)}")
    if not FOCUS_M[0] <= focus <= FOCUS_M[1]:
        raise LayerError(f"{where}.focusDistance = {focus:g} with fStop = {f_stop:g}: depth of field needs a focus "
                         f"distance in {_range(*FOCUS_M, 'm')}; fix the layer: set focusDistance (scene units, m), or "
                         "fStop = 0 for none")
    return f_stop, focus


F_STOP = (0.5, 1e4)      # a non-zero UsdGeom.Camera fStop (f-number): Blender's dof.aperture_fstop
FOCUS_M = (1e-3, 1e9)    # UsdGeom.Camera focusDistance (m) when fStop > 0: Blender's dof.focus_distance


# UsdRender.SettingsBase aspectRatioConformPolicy: how the camera's aperture is fitted to the image
# when their aspect ratios differ (square pixels: pixelAspectRatio is 1).
CONFORM_POLICIES = ("expandAperture", "cropAperture", "adjustApertureWidth", "adjustApertureHeight",
                    "adjustPixelAspectRatio")
ASPECT_TOLERANCE = 1e-5   # a float32 aperture pair (0.36 x 0.2025) matches its 16:9 image within this


def conform_aperture(width: float, height: float, settings_prim, where) -> tuple[float, float]:
    """The apertures (mm) the image uses, by UsdRender's aspectRatioConformPolicy: where the
    aperture's aspect (width/height) differs from the image's, expandAperture grows the dimension
    that falls short, cropAperture shrinks the one that overhangs, adjustApertureWidth/Height
    changes that one; adjustPixelAspectRatio would need non-square pixels and is refused. Equal
    aspects (within ASPECT_TOLERANCE) keep the authored values exactly. Blender fits the sensor
    horizontally (the vertical field of view follows from the width and the image's aspect), so the
    width is what the render uses; the height is returned as authored."""
    res = _get(settings_prim, "resolution")
    image = res[0] / res[1]
    if abs(width / height - image) <= ASPECT_TOLERANCE * image:
        return width, height
    policy = str(_get(settings_prim, "aspectRatioConformPolicy", "expandAperture"))
    wider = image > width / height   # the image is wider than the aperture
    if policy == "adjustApertureWidth" or (policy == "expandAperture" and wider) or \
            (policy == "cropAperture" and not wider):
        conformed = height * image
    elif policy in ("adjustApertureHeight", "expandAperture", "cropAperture"):
        conformed = width
    else:
        raise LayerError(f"{settings_prim.GetPath()}.aspectRatioConformPolicy = {policy!r} with {where}'s aperture "
                         f"{width:.4g} x {height:.4g} mm (aspect {width / height:.4g}) and a {res[0]}x{res[1]} image "
                         f"(aspect {image:.4g}): allo-usd renders square pixels only; fix the layer: another policy "
                         "(the fallback is expandAperture), or apertures of the image's aspect")
    if not as_stored(SENSOR_MM)[0] <= conformed <= as_stored(SENSOR_MM)[1]:
        raise LayerError(f"{where}: its aperture conformed to the {res[0]}x{res[1]} image by {policy} is {conformed:.4g} "
                         f"mm wide, outside {_range(*SENSOR_MM, 'mm')} (Blender's Camera.sensor_width); fix the layer: "
                         "apertures nearer the image's aspect")
    return snap(conformed, SENSOR_MM), height


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
    scale = time * iso / 100.0 / (f_stop * f_stop) * fm.exp2(ev) * responsivity   # as the author's film_exposure
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
    check_settings(settings_prim)
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
                        denoise_quality=choice(A.RENDER_DENOISE_QUALITY.name, "BALANCED", DENOISE_QUALITIES),
                        **read_target(settings_prim))
    noise = flag(A.EFFECTS_SENSOR_NOISE.name, False)
    effects = EffectsDesc(sensor_noise=noise, glare=flag(A.EFFECTS_GLARE.name, False),
                          inspection_light=flag(A.EFFECTS_INSPECTION_LIGHT.name, True),
                          body_shine=flag(A.EFFECTS_BODY_SHINE.name, True),
                          sensor=read_sensor(settings_prim) if noise else None)
    if render.target_psnr > 0 and effects.glare:
        raise LayerError(f"{A.RENDER_TARGET_PSNR.name} and {A.EFFECTS_GLARE.name} are both on: " + TARGET_WITH_GLARE)
    return render, effects


def read_target(settings_prim) -> dict:
    """The target mode's allo:render:targetPsnr and allo:render:timeLimit (0.0 each when not authored):
    finite, the target in (0, 100] dB or 0, the time limit in 0..1e6 s and only beside a target; else
    one LayerError naming the attribute and the fix (the value itself is printed only as a number)."""
    values = {}
    for attr, bounds, fix in ((A.RENDER_TARGET_PSNR, RENDER_TARGET_PSNR, "a PSNR in dB, e.g. 40, or remove it for "
                               "fixed samples"),
                              (A.RENDER_TIME_LIMIT, RENDER_TIME_LIMIT, "seconds, e.g. 60, or remove it for no limit")):
        value = _get(settings_prim, attr.name, 0.0)
        lo, hi = bounds
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise LayerError(f"{attr.name} is not a number (a {type(value).__name__}); fix the layer: author it as a "
                             f"float, {fix}")
        if not (np.isfinite(value) and lo <= value <= hi):
            raise LayerError(f"{attr.name} = {float(value):g} is outside {lo:g}..{hi:g}; fix the layer: {fix}")
        values[attr.field] = float(value)
    if values["time_limit"] > 0 and values["target_psnr"] == 0:
        raise LayerError(f"{A.RENDER_TIME_LIMIT.name} is authored without {A.RENDER_TARGET_PSNR.name}: a time limit "
                         f"stops the target mode only; fix the layer: author {A.RENDER_TARGET_PSNR.name} too or "
                         "remove the time limit")
    return values


PRODUCT_NAME = "image"    # the base stage's one RenderProduct's productName (base_stage.define_render_settings)
SETTINGS_FALLBACKS = {    # UsdRender.SettingsBase attributes a product could override for itself
    "resolution", "pixelAspectRatio", "aspectRatioConformPolicy", "dataWindowNDC", "instantaneousShutter",
    "disableMotionBlur", "disableDepthOfField"}
COLOR_SPACES = ("", "lin_rec709_scene")   # renderingColorSpace: Cycles renders linear Rec.709 (scene-referred)


def check_settings_prim(settings_prim) -> None:
    """The prim renderSettingsPrimPath names is a UsdRender.Settings prim."""
    from pxr import UsdRender

    if not settings_prim.IsA(UsdRender.Settings):
        raise LayerError(f"renderSettingsPrimPath names {settings_prim.GetPath()}, a "
                         f"{settings_prim.GetTypeName() or 'typeless'} prim, not a RenderSettings prim; fix the layer: "
                         f"point it at a RenderSettings prim (the scene's is {layout.RENDER_SETTINGS})")


def check_settings(settings_prim) -> None:
    """What of UsdRender.Settings, its product and vars allo-usd renders, each else refused in one
    line (docs/usd/what_renders.md, camera and render settings): square pixels, the whole image
    (dataWindowNDC), a known aspectRatioConformPolicy, materialBindingPurposes ["full", ""],
    linear Rec.709 rendering, one camera, one raster product named as the base stage names it with
    no settings of its own, vars as the base stage defines them, and one instant: no time samples
    anywhere on the stage (the default time code is what is rendered)."""
    from pxr import UsdRender

    where = settings_prim.GetPath()
    check_settings_prim(settings_prim)
    pixel = _number(_get(settings_prim, "pixelAspectRatio", 1.0), f"{where}.pixelAspectRatio")
    if pixel != 1.0:
        raise LayerError(f"{where}.pixelAspectRatio = {pixel:g}: allo-usd renders square pixels only (its masks, boxes "
                         "and intrinsics assume them); fix the layer: pixelAspectRatio = 1, and set the shape with "
                         "resolution")
    window = tuple(float(v) for v in _get(settings_prim, "dataWindowNDC", (0.0, 0.0, 1.0, 1.0)))
    if window != (0.0, 0.0, 1.0, 1.0):
        raise LayerError(f"{where}.dataWindowNDC = {window}: allo-usd renders the whole image (0, 0, 1, 1) only; fix "
                         "the layer: remove dataWindowNDC, and crop the images afterwards if you need part of them")
    policy = str(_get(settings_prim, "aspectRatioConformPolicy", "expandAperture"))
    if policy not in CONFORM_POLICIES:
        raise LayerError(f"{where}.aspectRatioConformPolicy = {policy!r} is not one of {', '.join(CONFORM_POLICIES)}; "
                         "fix the layer")
    for name in ("instantaneousShutter", "disableMotionBlur", "disableDepthOfField"):
        if not isinstance(_get(settings_prim, name, False), bool):
            raise LayerError(f"{where}.{name} must be a bool, got {_get(settings_prim, name)!r}; fix the layer")
    purposes = [str(p) for p in _get(settings_prim, "materialBindingPurposes", ["full", ""])]
    if purposes != ["full", ""]:
        raise LayerError(f"{where}.materialBindingPurposes = {purposes}: allo-usd binds materials as the fallback "
                         "[\"full\", \"\"] says (a full-purpose binding, else the all-purpose one); fix the layer: "
                         "remove the opinion, and bind the material you want to render with that purpose")
    space = str(_get(settings_prim, "renderingColorSpace", ""))
    if space not in COLOR_SPACES:
        raise LayerError(f"{where}.renderingColorSpace = {space!r}: Cycles renders in linear Rec.709 "
                         f"({COLOR_SPACES[1]!r}); fix the layer: remove the opinion or set {COLOR_SPACES[1]!r}")
    settings = UsdRender.Settings(settings_prim)
    cameras = settings.GetCameraRel().GetForwardedTargets()
    if len(cameras) > 1:
        raise LayerError(f"{where}.camera names {len(cameras)} cameras ({', '.join(map(str, cameras))}); a render has "
                         "one: fix the layer: name one camera")
    products = settings.GetProductsRel().GetForwardedTargets()
    if len(products) > 1:
        raise LayerError(f"{where}.products names {len(products)} products ({', '.join(map(str, products))}); allo-usd "
                         f"writes one, {layout.IMAGE_PRODUCT}, whose orderedVars choose the passes: fix the layer: "
                         "order the vars you want on that product")
    stage = settings_prim.GetStage()
    for path in products:
        _check_product(stage.GetPrimAtPath(path), path)
    _check_one_instant(stage)


def _check_product(prim, path) -> None:
    from pxr import UsdRender

    if not prim or not prim.IsA(UsdRender.Product):
        raise LayerError(f"the render settings' product {path} is not a RenderProduct prim; fix the layer")
    product = UsdRender.Product(prim)
    kind, name = str(product.GetProductTypeAttr().Get()), str(product.GetProductNameAttr().Get())
    if kind != "raster" or name != PRODUCT_NAME:
        raise LayerError(f"{path}: productType {kind!r}, productName {name!r}: allo-usd writes one raster product and "
                         f"names its files after the layer (STEM.png, STEM.exr, ...; docs/formats/render_outputs.md); "
                         f"fix the layer: productType \"raster\", productName \"{PRODUCT_NAME}\"")
    own = sorted(a.GetName() for a in prim.GetAttributes() if a.GetName() in SETTINGS_FALLBACKS and a.HasAuthoredValue())
    own += [r.GetName() for r in prim.GetRelationships() if r.GetName() == "camera" and r.HasAuthoredTargets()]
    if own:
        raise LayerError(f"{path} authors {', '.join(own)} for itself; allo-usd reads them from the render settings "
                         f"only: fix the layer: set them on {layout.RENDER_SETTINGS} and remove them from the product")
    for var_path in product.GetOrderedVarsRel().GetForwardedTargets():
        var = prim.GetStage().GetPrimAtPath(var_path)
        _, source, dtype, _ = RENDER_VARS.get(var_path.name, (None, None, None, None))
        if source is None:
            continue   # var_pass refuses it by name
        got = tuple(str(_get(var, n, "")) for n in ("sourceName", "dataType", "sourceType"))
        if not var.IsA(UsdRender.Var) or got != (source, dtype, "raw"):
            raise LayerError(f"{var_path}: sourceName {got[0]!r}, dataType {got[1]!r}, sourceType {got[2]!r}: a var "
                             f"named {var_path.name} is written as sourceName {source!r}, dataType {dtype!r}, "
                             "sourceType 'raw' (the base stage's); fix the layer: order the var that writes what you "
                             f"want (one of {', '.join(VAR_PASSES)}) instead of changing this one")


def _check_one_instant(stage) -> None:
    """allo-usd renders one instant, Usd.TimeCode.Default(): a time-sampled value anywhere on the
    stage (an animated transform, light, camera, shutter) is refused, naming the first one, so that
    nothing is read at a time the user did not mean. Sdf lists a layer's sample times cheaply."""
    from pxr import Sdf

    for layer in stage.GetUsedLayers():
        if not layer.ListAllTimeSamples():
            continue
        found: list = []

        def visit(path, layer=layer, found=found):
            if not found and path.IsPropertyPath() and layer.GetNumTimeSamplesForPath(path):
                found.append(path)
        layer.Traverse(Sdf.Path.absoluteRootPath, visit)
        what = found[0] if found else "a property"
        raise LayerError(f"{layer.identifier}: {what} has time samples; allo-usd renders one instant, the default "
                         "time code (no animation, no motion blur): fix the layer: author the value itself "
                         "(`= value`) instead of timeSamples")


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
    check_settings_prim(settings_prim)
    cam_targets = UsdRender.Settings(settings_prim).GetCameraRel().GetForwardedTargets()
    if not cam_targets or not stage.GetPrimAtPath(cam_targets[0]).IsA(UsdGeom.Camera):
        raise LayerError(f"{layer_path}: render settings name no camera; set {settings_path}.camera")
    render, effects = read_render(settings_prim, camera_exposure(stage.GetPrimAtPath(cam_targets[0]))[0])
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    checked: set = set()  # prims whose xformOps are checked (world_matrix)
    camera = read_camera(stage.GetPrimAtPath(cam_targets[0]), cache, checked, settings_prim)

    meshes, materials, light_prims = [], {}, []
    count = points = 0
    purposes = included_purposes(settings_prim)
    # instance proxies too: an instanceable prim's meshes render at their proxies' (unique) paths
    it = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies(
        Usd.PrimIsActive & Usd.PrimIsDefined & ~Usd.PrimIsAbstract)))
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
        if is_geometry(prim):
            if prim.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()   # its prototypes are drawn through it only
            found = read_geometry(prim, cache, materials, checked, purposes, MAX_SCENE_POINTS - points)
            meshes.extend(found)
            points += sum(len(m.points) for m in found)
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
                            lights.spot, render, effects, read_meta(stage, meshes), lights.others, lights.dome)


VAR_PASSES = {name: p for name, (p, _, _, _) in RENDER_VARS.items()}   # var prim name -> pass


def var_pass(name: str) -> str:
    """The pass (allo_usd.plan.settings.PASSES) of a render var the product orders, by its prim name."""
    if name not in VAR_PASSES:
        raise LayerError(f"the image product orders a render var {name!r} this renderer does not write; order only "
                         f"{', '.join(VAR_PASSES)} under {layout.VARS} (fix the layer)")
    return VAR_PASSES[name]
