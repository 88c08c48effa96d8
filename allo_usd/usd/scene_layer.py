"""Write one scene as a small USD layer over the base stage.

A scene's opinions fall into three groups, each built here as plain data (`Prim` lists):
- `sky_prims`: what the day decides (the station's sun lamp, and on an eclipse day each body's
  own lamp with the light linking; true-scale bodies, eclipse states, epoch);
- `pose_prims`: what the perturbed camera sample decides (camera transform, offsets, attempts);
- `scene_prims`: what only this image decides (identity and seed, anomaly, effects, render, and
  the camera's exposure and, when the plan's camera is not the paper's, its lens: `lens_attrs`).

`write_scene_layer` writes all three into one self-contained layer over the base stage;
`author.compose` writes the first two once as shared layers and stacks them under a scene layer
that holds only the third. Both write through allo_usd.usd.usda_writer.write_layer (the layer's
.usda text, byte for byte Sdf's, written atomically). `validate_spec` checks a spec first, so a bad
spec writes nothing.
"""

from __future__ import annotations

from pathlib import Path

from allo_usd.sky import eclipse as sky_eclipse
from allo_usd.core.sensor import SensorParams
from allo_usd.core.errors import AlloError, LayerError
from allo_usd.core import fixedmath as fm
from allo_usd.core.camera_model import CLIP_M, DEFAULT_CAMERA, LENS_MM, MAX_SHIFT, SENSOR_MM
from allo_usd.core.geometry import check_finite, rotation_towards
from allo_usd.scene.spec import AnomalySpec, BodySpec, CameraSpec, SceneSpec, SunSpec
from allo_usd.core.limits import resolution_problem
from allo_usd.usd import attributes as A
from allo_usd.usd import layout
from allo_usd.usd.attributes import SENSOR_ATTRIBUTES
from allo_usd.usd.base_stage import LIT_BODIES, camera_ev, gf_quatd, product_vars
from allo_usd.plan.settings import TARGET_WITH_GLARE, DEFAULT_PASSES, canonical_passes, target_problem
from allo_usd.usd.layout import STATION_SUN, body_sun_path
from allo_usd.core.files import relpath
from allo_usd.usd.usda_writer import Prim, write_layer


def _vec3d(v):
    from pxr import Gf

    return Gf.Vec3d(*map(float, v))


def validate_spec(spec: SceneSpec) -> None:
    """Check every number before authoring, so a bad spec writes nothing (validate, then author)."""
    check_finite("camera position", spec.camera.position)
    check_finite("camera rotation", spec.camera.rotation)
    _check_sun("sun", spec.sun)
    for name, body in spec.bodies.items():
        check_finite(f"{name} position", body.position)
        if not body.radius > 0:
            raise LayerError(f"{name} radius must be positive, got {body.radius}")
        if body.light is not None:
            _check_sun(f"{name}'s sun lamp", body.light)
        if body.geometric_direction is not None:
            check_finite(f"{name} geometric direction", body.geometric_direction)
            if name not in A.GEOMETRIC_DIRECTION:
                raise LayerError(f"body {name!r} has a geometric direction but the schema records one only for "
                                 f"{', '.join(A.GEOMETRIC_DIRECTION)}; drop it or rename the body")
    if spec.anomaly is not None:
        check_finite("anomaly position", spec.anomaly.position)
        check_finite("anomaly rotation", spec.anomaly.rotation)
    check_finite("render exposure", (spec.render.exposure,))
    if not 0 < spec.render.exposure <= 2.0 ** 32:
        raise LayerError(f"render exposure must be in (0, 2^32] (a linear film exposure), got {spec.render.exposure}")
    if spec.effects.sensor_noise:
        sensor_attrs(spec.effects.sensor, film_exposure(spec.render.exposure))  # raises on parameters out of range
    w, h = spec.render.resolution
    problem = resolution_problem(w, h)
    if problem:
        raise LayerError(problem)
    if not 1 <= spec.render.samples <= 65536:
        raise LayerError(f"samples={spec.render.samples} is outside 1..65536")
    problem = target_problem(spec.render.target_psnr, spec.render.time_limit)
    if problem:
        raise LayerError(problem)
    if spec.render.target_psnr > 0 and spec.effects.glare:
        raise LayerError(TARGET_WITH_GLARE)
    if spec.split not in ("train", "test"):
        raise LayerError(f"split must be 'train' or 'test', got {spec.split!r}")
    _check_lens(spec)


def _check_lens(spec: SceneSpec) -> None:
    """The plan's lens within what the reader (usd/read.py) accepts, so no layer authors what it refuses."""
    lens, (w, h) = spec.lens, spec.render.resolution
    values = (lens.focal_length_mm, lens.sensor_width_mm, lens.sensor_height_mm, *lens.clipping_range_m,
              *lens.principal_point_offset_px)
    check_finite("camera lens (focal length, sensor, clipping range, principal point offset)", values)
    for what, v, (lo, hi) in (("focal length", lens.focal_length_mm, LENS_MM),
                              ("sensor width", lens.sensor_width_mm, SENSOR_MM),
                              ("sensor height", lens.sensor_height_mm, SENSOR_MM)):
        if not lo <= v <= hi:
            raise LayerError(f"camera {what} {v:g} mm is outside {lo:g}..{hi:g} mm; fix the plan's [camera]")
    near, far = lens.clipping_range_m
    if not CLIP_M[0] <= near < far <= CLIP_M[1]:
        raise LayerError(f"camera clipping range ({near:g}, {far:g}) must be near < far within "
                         f"{CLIP_M[0]:g}..{CLIP_M[1]:g} m; fix the plan's [camera]")
    dx, dy = lens.principal_point_offset_px
    if abs(dx) > MAX_SHIFT * w or abs(dy) > MAX_SHIFT * h:
        raise LayerError(f"camera principal point offset ({dx:g}, {dy:g}) px leaves the {w}x{h} image; fix the "
                         "plan's camera.principal_point_offset_px")


def lens_attrs(spec: SceneSpec) -> dict:
    """The plan's lens as UsdGeom.Camera attributes (tenths of a scene unit, metersPerUnit = 1: mm / 100;
    core.camera_model for the aperture offsets), or {} for the paper's camera (the base stage's)."""
    from pxr import Gf

    lens = spec.lens
    if lens == DEFAULT_CAMERA:
        return {}
    h_off, v_off = lens.aperture_offsets_mm(spec.render.resolution[0])
    return {"focalLength": ("float", lens.focal_length_mm / 100.0),
            "horizontalAperture": ("float", lens.sensor_width_mm / 100.0),
            "verticalAperture": ("float", lens.sensor_height_mm / 100.0),
            "horizontalApertureOffset": ("float", h_off / 100.0),
            "verticalApertureOffset": ("float", v_off / 100.0),
            "clippingRange": ("float2", Gf.Vec2f(*lens.clipping_range_m))}


ECLIPSE_STATES = sky_eclipse.ECLIPSE_STATES                 # allo:eclipseState's allowed tokens
ECLIPSE_BODIES = ("none", *sky_eclipse.SHADOW_BODIES)      # allo:eclipseBody's allowed tokens


def _check_sun(what: str, sun: SunSpec) -> None:
    check_finite(f"{what} direction", sun.direction)
    values = (sun.irradiance, sun.irradiance_unoccluded, sun.angular_diameter_deg, sun.distance_m, sun.lit_fraction)
    check_finite(f"{what} irradiance, angle, distance and lit fraction", values)
    if sun.irradiance < 0 or sun.irradiance_unoccluded < 0 or not 0 <= sun.lit_fraction <= 1:
        raise LayerError(f"{what}: irradiance must be >= 0 and the lit fraction in [0, 1], got "
                         f"{sun.irradiance} W/m^2 and {sun.lit_fraction}")
    for field, value, allowed in (("eclipse_state", sun.eclipse_state, ECLIPSE_STATES),
                                  ("eclipse_body", sun.eclipse_body, ECLIPSE_BODIES)):
        if value not in allowed:
            raise LayerError(f"{what}: {field} {value!r} is not one of {', '.join(allowed)} (the schema's "
                             "allowed tokens); fix the spec")


def body_light(body: BodySpec, sun: SunSpec) -> SunSpec:
    """The lamp that lights only `body`: its own, or (a spec made by hand without one) the station's
    Sun unoccluded, so the body is never darkened by the station's eclipse."""
    if body.light is not None:
        return body.light
    return SunSpec(sun.direction, sun.irradiance_unoccluded, sun.irradiance_unoccluded, sun.angular_diameter_deg,
                   sun.distance_m)


def film_exposure(exposure: float) -> float:
    """The linear film exposure a reader gets back from the camera's authored `exposure` (EV as a float)."""
    return fm.exp2(camera_ev(exposure))   # not 2.0 ** EV: glibc's pow rounds by CPU (FMA or not)


def sun_prim(path: str, sun: SunSpec, **kw) -> Prim:
    """A sun lamp's opinions: direction, irradiance (lit fraction included; the base stage authors
    inputs:normalize = true, so intensity is irradiance), angle and eclipse state."""
    return Prim(path, **kw, attrs={
        "xformOp:orient": ("quatd", gf_quatd(rotation_towards(sun.direction))),
        "inputs:intensity": ("float", float(sun.irradiance)),
        "inputs:angle": ("float", float(sun.angular_diameter_deg)),
        **A.opinions((A.LIT_FRACTION, float(sun.lit_fraction)), (A.ECLIPSE_STATE, sun.eclipse_state),
                     (A.ECLIPSE_BODY, sun.eclipse_body),
                     (A.IRRADIANCE_UNOCCLUDED, float(sun.irradiance_unoccluded)),
                     (A.SUN_DISTANCE, float(sun.distance_m)))})


def eclipse_day(sun: SunSpec, bodies: dict) -> bool:
    """Whether the day needs light linking: the station's lit fraction and a lit body's differ (an
    eclipse of the station, of the Moon, or of the Earth's face). On any other day one lamp lights all."""
    return any(abs(body_light(bodies[name], sun).lit_fraction - sun.lit_fraction) > 1e-12
               for name in LIT_BODIES if name in bodies)


def sky_prims(epoch: str, perilune_epoch: str, day: int, sun: SunSpec, bodies: dict,
              joints: dict[str, float] | None = None) -> list[Prim]:
    """The day's opinions: epoch, the station's sun lamp and each body's position (apparent) with its
    geometric direction for the record (docs/physics.md section 11). On an eclipse day
    (eclipse_day) also the light linking: the station's lamp excludes the lit bodies, each of which
    gets its own active lamp (the Sun from its centre, its own lit fraction). With `joints` (a plan
    that tracks the Sun: {station joint name: degrees}) also each joint's angle (joint_prims)."""
    lit = [name for name in LIT_BODIES if name in bodies]
    linked = eclipse_day(sun, bodies)
    excludes = {"collection:lightLink:excludes": [layout.body_path(name) for name in lit]} if linked else {}
    geometric = [(A.GEOMETRIC_DIRECTION[name], _vec3d(body.geometric_direction)) for name, body in bodies.items()
                 if body.geometric_direction is not None]
    out = [Prim(layout.WORLD, A.opinions((A.EPOCH, epoch), (A.PERILUNE_EPOCH, perilune_epoch), (A.DAY, int(day)),
                                         *geometric), api=("AlloSceneAPI",)),
           sun_prim(STATION_SUN, sun, rels=excludes)]
    if linked:
        out += [sun_prim(body_sun_path(name), body_light(bodies[name], sun), active=True) for name in lit]
    for name, body in bodies.items():
        out.append(Prim(layout.body_path(name), {"xformOp:translate": ("double3", _vec3d(body.position)),
                                               "xformOp:scale": ("double3", _vec3d([body.radius] * 3))}))
    return out + joint_prims(joints or {})


def joint_prims(angles: dict[str, float]) -> list[Prim]:
    """An over per procedural-station joint setting its joint op (e.g. xformOp:rotateY:alpha) to
    `angles[name]` degrees, under /World/Station (allo_usd.scene.tracking computes the angles)."""
    from allo_usd.assets.mesh import joint_chain
    from allo_usd.assets.station import station_joints
    from allo_usd.usd.asset import joint_op_name

    joints = station_joints()
    by = {j.name: j for j in joints}
    unknown = sorted(set(angles) - set(by))
    if unknown:
        raise LayerError(f"joint angles for {unknown}, which the procedural station does not have "
                         f"({sorted(by)}); fix the caller")
    out = []
    for name, value in angles.items():
        check_finite(f"joint {name} angle", [value])
        out.append(Prim(layout.station_joint(joint_chain(joints, name)),
                        {joint_op_name(by[name]): ("double", float(value))}))
    return out


def pose_prims(pose: int, camera: CameraSpec) -> list[Prim]:
    """The camera sample's opinions: base pose number, perturbed transform and sampled offsets; for a
    pose file's pose its name and source, and the sigmas when they are not the paper's."""
    record = []
    if camera.pose_name:
        record += [(A.POSE_NAME, camera.pose_name), (A.POSE_SOURCE, camera.pose_source),
                   (A.POSE_SOURCE_SHA256, camera.pose_source_sha256)]
    if camera.sigmas is not None:
        record += [(A.POSITION_SIGMA, float(camera.sigmas[0])), (A.ANGLE_SIGMA, float(camera.sigmas[1]))]
    return [Prim(layout.WORLD, A.opinions((A.POSE, int(pose)), (A.PERTURBATION, camera.perturbation),
                                          (A.CAMERA_OFFSET_POSITION, _vec3d(camera.offset_position)),
                                          (A.CAMERA_OFFSET_ROTATION, _vec3d(camera.offset_rotation)),
                                          (A.CAMERA_ATTEMPTS, int(camera.attempts)), *record),
                 api=("AlloSceneAPI",)),
            Prim(layout.CAMERA, {"xformOp:translate": ("double3", _vec3d(camera.position)),
                                   "xformOp:orient": ("quatd", gf_quatd(camera.rotation))})]


def anomaly_prim(a: AnomalySpec, asset_ref: str) -> Prim:
    return Prim(layout.ANOMALY, {
        **A.opinions((A.ANOMALY_ASSET, a.asset), (A.ANOMALY_ASSET_VARIANT, a.variant),
                     (A.ANOMALY_DEPTH_INDEX, int(a.depth_index)), (A.ANOMALY_DEPTH_OFFSET, float(a.depth_offset)),
                     (A.ANOMALY_ATTEMPTS, int(a.attempts)),
                     (A.ANOMALY_PREDICTED_AREA_FRACTION, float(a.predicted_area_fraction))),
        "xformOp:translate": ("double3", _vec3d(a.position)), "xformOp:orient": ("quatd", gf_quatd(a.rotation)),
        "xformOpOrder": ("uniform token[]", ["xformOp:translate", "xformOp:orient"])},
        api=("AlloAnomalyAPI",), define="Xform", reference=asset_ref, variants={"variant": a.variant})


def sensor_attrs(sensor: SensorParams, film_exposure: float) -> dict:
    """The sensor's EMVA 1288 parameters as render-settings attributes, the derived ones resolved."""
    try:
        values = sensor.resolved(film_exposure).as_dict()
    except AlloError as exc:
        raise LayerError(f"{exc} (EffectsSpec.sensor)") from None
    cast = {"int": int, "int64": int, "double": float}
    return {name: (type_name, cast[type_name](values[key])) for key, (name, type_name) in SENSOR_ATTRIBUTES.items()}


def target_attrs(render) -> dict:
    """allo:render:targetPsnr and allo:render:timeLimit, each only when > 0: a layer without a target
    keeps the bytes it had before the target mode existed (and the time limit means nothing without one)."""
    if not render.target_psnr > 0:
        return {}
    return A.opinions((A.RENDER_TARGET_PSNR, float(render.target_psnr)),
                      *(((A.RENDER_TIME_LIMIT, float(render.time_limit)),) if render.time_limit > 0 else ()))


def scene_prims(spec: SceneSpec, anomaly_ref: str = "") -> list[Prim]:
    """Only this image's opinions: identity and seed, anomaly, effects and render settings."""
    from pxr import Gf

    out = [Prim(layout.WORLD, A.opinions((A.SCENE_ID, spec.scene_id), (A.SPLIT, spec.split), (A.VARIANT, spec.variant),
                                         (A.SEED, int(spec.seed)), (A.SEED_PATH, spec.seed_path)),
                api=("AlloSceneAPI",))]
    # The film exposure as UsdGeom.Camera defines it: 2^exposure (fStop, time, iso, responsivity at fallbacks).
    out.append(Prim(layout.CAMERA, {"exposure": ("float", camera_ev(spec.render.exposure)), **lens_attrs(spec)}))
    if not spec.effects.inspection_light:
        out.append(Prim(layout.INSPECTION_LIGHT, active=False))
    if spec.anomaly is not None:
        out.append(anomaly_prim(spec.anomaly, anomaly_ref))
    r, e = spec.render, spec.effects
    out.append(Prim(layout.RENDER_SETTINGS, {
        "resolution": ("uniform int2", Gf.Vec2i(*map(int, r.resolution))),
        **A.opinions((A.RENDER_PRESET, r.preset), (A.RENDER_SAMPLES, int(r.samples)),
                     (A.RENDER_ADAPTIVE_THRESHOLD, float(r.adaptive_threshold)), (A.RENDER_DENOISE, bool(r.denoise)),
                     (A.RENDER_MAX_BOUNCES, int(r.max_bounces)), (A.RENDER_SEED, int(r.seed)),
                     (A.RENDER_THREADS, int(r.threads)),
                     (A.RENDER_DENOISE_PREFILTER, r.denoise_prefilter), (A.RENDER_DENOISE_QUALITY, r.denoise_quality),
                     (A.EFFECTS_SENSOR_NOISE, bool(e.sensor_noise)), (A.EFFECTS_GLARE, bool(e.glare)),
                     (A.EFFECTS_INSPECTION_LIGHT, bool(e.inspection_light)), (A.EFFECTS_BODY_SHINE, bool(e.body_shine))),
        **target_attrs(r),
        **(sensor_attrs(e.sensor, film_exposure(r.exposure)) if e.sensor_noise else {})}))
    passes = canonical_passes(r.passes)
    if passes != DEFAULT_PASSES:  # the base product orders the default passes; change only if asked
        out.append(Prim(layout.IMAGE_PRODUCT, rels={"orderedVars": product_vars(passes)}))
    return out


def merge_prims(*groups: list[Prim]) -> list[Prim]:
    """Several groups as one list, with the opinions on the same prim merged (first group wins order)."""
    merged: dict[str, Prim] = {}
    for prim in (p for g in groups for p in g):
        if prim.path not in merged:
            merged[prim.path] = Prim(prim.path, dict(prim.attrs), prim.api, prim.define, prim.reference,
                                     dict(prim.variants), prim.active, dict(prim.rels))
            continue
        m = merged[prim.path]
        m.attrs.update(prim.attrs)
        m.rels.update(prim.rels)
        m.api = tuple(dict.fromkeys(m.api + prim.api))
    return list(merged.values())


def check_base_stage(base_stage: Path) -> Path:
    base_stage = Path(base_stage)
    if not base_stage.is_file():
        raise LayerError(f"base stage {base_stage} does not exist; run scripts/make_base_stage.py or "
                         "pass the path of stages/base.usda")
    return base_stage


def anomaly_asset_path(base_stage: Path, asset: str) -> Path:
    path = Path(base_stage).parent / "anomalies" / f"{asset}.usda"
    if not path.is_file():
        raise LayerError(f"anomaly asset {asset!r} has no file {path}; choose one of the "
                         f"assets in {path.parent}")
    return path


def scene_custom(spec: SceneSpec) -> dict:
    return {"seed": int(spec.seed), "seedPath": spec.seed_path, "sceneId": spec.scene_id}


def write_scene_layer(spec: SceneSpec, path: Path, base_stage: Path, anomaly_asset: Path | None = None) -> Path:
    """Author `spec` to `path` (atomically) as one self-contained layer over `base_stage` (`anomaly_asset`:
    a plan's own hazard's interface layer, else the base stage's built-in asset)."""
    validate_spec(spec)
    path = Path(path)
    base_stage = check_base_stage(base_stage)
    ref = ""
    if spec.anomaly is not None:
        ref = relpath(anomaly_asset if anomaly_asset is not None
                      else anomaly_asset_path(base_stage, spec.anomaly.asset), path.parent)
    prims = merge_prims(scene_prims(spec, ref)[:1], pose_prims(spec.pose, spec.camera),
                        sky_prims(spec.epoch, spec.perilune_epoch, spec.day, spec.sun, spec.bodies),
                        scene_prims(spec, ref)[1:])
    return write_layer(path, prims, [relpath(base_stage, path.parent)], scene_custom(spec),
                       f"allo-usd scene {spec.scene_id}")
