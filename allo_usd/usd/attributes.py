"""Every `allo:` attribute of the codeless schema (schemas/alloUsd/generatedSchema.usda), once.

Authoring (scene_layer, base_stage), reading (read) and inspection (inspect) take the names and
Sdf value types from here, so a renamed or retyped attribute is changed in one place;
tests/usd/test_attributes.py checks this table against the schema file. No pxr here.
"""

from __future__ import annotations

from dataclasses import dataclass

from allo_usd.usd import layout


@dataclass(frozen=True)
class AlloAttribute:
    name: str            # full attribute name, allo: namespace included
    sdf_type: str        # Sdf value type name as the schema declares it
    api_schema: str      # the single-apply API schema that declares it
    prim: str            # where it is authored (a layout path or pattern)
    field: str = ""      # the description/spec field it records, where there is one

    @property
    def short(self) -> str:
        """The last namespace part (e.g. quantumEfficiency)."""
        return self.name.rsplit(":", 1)[1]

    def typed(self, value) -> tuple[str, object]:
        """(Sdf type, value): one entry of usda_writer.Prim.attrs."""
        return self.sdf_type, value


def opinions(*pairs: tuple[AlloAttribute, object]) -> dict:
    """{name: (Sdf type, value)} for (attribute, value) pairs, in the order given."""
    return {a.name: a.typed(v) for a, v in pairs}


def _group(api: str, prim: str, *rows: tuple) -> tuple[AlloAttribute, ...]:
    return tuple(AlloAttribute(name, sdf_type, api, prim, *rest) for name, sdf_type, *rest in rows)


SUN_LAMPS = layout.body_sun_path("*")            # /World/Sky/*SunLight: the station's lamp and the bodies'
BODIES = layout.body_path("*")
RIG_POSES = f"{layout.RIG}/*"

# ---------------------------------------------------------------- AlloSceneAPI (default prim)
(SCENE_ID, EPOCH, PERILUNE_EPOCH, DAY, POSE, SPLIT, VARIANT, SEED, SEED_PATH, PERTURBATION,
 CAMERA_OFFSET_POSITION, CAMERA_OFFSET_ROTATION, CAMERA_ATTEMPTS) = SCENE = _group(
    "AlloSceneAPI", layout.WORLD,
    ("allo:sceneId", "string"), ("allo:epoch", "string"), ("allo:periluneEpoch", "string"), ("allo:day", "int"),
    ("allo:pose", "int"), ("allo:split", "token"), ("allo:variant", "token"), ("allo:seed", "int64"),
    ("allo:seedPath", "string"), ("allo:perturbation", "string"), ("allo:cameraOffsetPosition", "double3"),
    ("allo:cameraOffsetRotation", "double3"), ("allo:cameraAttempts", "int"))

# The sky's geometric record (AlloSceneAPI too): each body's geometric direction, beside the apparent
# one its prim is placed at (docs/physics.md section 11). {body prim name: attribute}.
GEOMETRIC_DIRECTION_SUN, GEOMETRIC_DIRECTION_EARTH, GEOMETRIC_DIRECTION_MOON = SKY_RECORD = _group(
    "AlloSceneAPI", layout.WORLD, ("allo:geometricDirection:sun", "double3"),
    ("allo:geometricDirection:earth", "double3"), ("allo:geometricDirection:moon", "double3"))
GEOMETRIC_DIRECTION = {"Sun": GEOMETRIC_DIRECTION_SUN, "Earth": GEOMETRIC_DIRECTION_EARTH,
                       "Moon": GEOMETRIC_DIRECTION_MOON}

# A camera sample's record beyond SCENE (AlloSceneAPI too), in its pose layer: a pose file's pose (its
# name, 'FILE:LINE' and the file's sha256; allo_usd.plan.posefile) and the plan's perturbation sigmas,
# each authored only where it applies (a pose-file pose; sigmas other than the paper's).
POSE_NAME, POSE_SOURCE, POSE_SOURCE_SHA256, POSITION_SIGMA, ANGLE_SIGMA = POSE_RECORD = _group(
    "AlloSceneAPI", layout.WORLD, ("allo:poseName", "string"), ("allo:poseSource", "string"),
    ("allo:poseSourceSha256", "string"), ("allo:positionSigma", "double"), ("allo:angleSigma", "double"))

# ---------------------------------------------------------------- AlloEclipseAPI (sun lamps)
LIT_FRACTION, ECLIPSE_STATE, ECLIPSE_BODY, IRRADIANCE_UNOCCLUDED, SUN_DISTANCE = ECLIPSE = _group(
    "AlloEclipseAPI", SUN_LAMPS,
    ("allo:litFraction", "double"), ("allo:eclipseState", "token"), ("allo:eclipseBody", "token"),
    ("allo:irradianceUnoccluded", "double"), ("allo:sunDistance", "double"))

# ---------------------------------------------------------------- AlloRayVisibilityAPI (bodies)
(RAY_VISIBILITY,) = RAY = _group("AlloRayVisibilityAPI", BODIES, ("allo:rayVisibility", "token"))

# ---------------------------------------------------------------- AlloRenderQualityAPI (render settings)
# `field`: the RenderSpec / RenderDesc field each records.
(RENDER_PRESET, RENDER_SAMPLES, RENDER_ADAPTIVE_THRESHOLD, RENDER_DENOISE, RENDER_DENOISE_PREFILTER,
 RENDER_DENOISE_QUALITY, RENDER_MAX_BOUNCES, RENDER_SEED, RENDER_THREADS, RENDER_TARGET_PSNR,
 RENDER_TIME_LIMIT) = RENDER_QUALITY = _group(
    "AlloRenderQualityAPI", layout.RENDER_SETTINGS,
    ("allo:render:preset", "token", "preset"), ("allo:render:samples", "int", "samples"),
    ("allo:render:adaptiveThreshold", "float", "adaptive_threshold"), ("allo:render:denoise", "bool", "denoise"),
    ("allo:render:denoisePrefilter", "token", "denoise_prefilter"),
    ("allo:render:denoiseQuality", "token", "denoise_quality"), ("allo:render:maxBounces", "int", "max_bounces"),
    ("allo:render:seed", "int", "seed"), ("allo:render:threads", "int", "threads"),
    # the target mode, authored only when > 0 (a layer without them renders fixed samples, as before)
    ("allo:render:targetPsnr", "float", "target_psnr"), ("allo:render:timeLimit", "float", "time_limit"))
# The film exposure is not here: it is the render camera's standard UsdGeom.Camera exposure attributes
# (exposure, exposure:fStop/time/iso/responsivity), read by read.camera_exposure.

# ---------------------------------------------------------------- AlloEffectsAPI (render settings)
# `field`: the EffectsSpec / EffectsDesc field, or for allo:effects:sensor:* the SensorParams field.
SENSOR_PREFIX = "allo:effects:sensor:"
SENSOR = _group(
    "AlloEffectsAPI", layout.RENDER_SETTINGS,
    (SENSOR_PREFIX + "quantumEfficiency", "double", "quantum_efficiency"),
    (SENSOR_PREFIX + "fullWell", "double", "full_well_e"),
    (SENSOR_PREFIX + "readNoise", "double", "read_noise_e"),
    (SENSOR_PREFIX + "darkCurrent", "double", "dark_current_e_s"),
    (SENSOR_PREFIX + "bitDepth", "int", "bits"),
    (SENSOR_PREFIX + "gain", "double", "gain_dn_per_e"),
    (SENSOR_PREFIX + "prnu", "double", "prnu"),
    (SENSOR_PREFIX + "dsnu", "double", "dsnu_e"),
    (SENSOR_PREFIX + "seed", "int64", "seed"),
    (SENSOR_PREFIX + "exposureTime", "double", "exposure_time_s"),
    (SENSOR_PREFIX + "fNumber", "double", "f_number"),
    (SENSOR_PREFIX + "pixelPitch", "double", "pixel_pitch_m"),
    (SENSOR_PREFIX + "transmission", "double", "transmission"))
EFFECTS_SENSOR_NOISE, EFFECTS_GLARE, EFFECTS_INSPECTION_LIGHT, EFFECTS_BODY_SHINE = EFFECT_FLAGS = _group(
    "AlloEffectsAPI", layout.RENDER_SETTINGS,
    ("allo:effects:sensorNoise", "bool", "sensor_noise"), ("allo:effects:glare", "bool", "glare"),
    ("allo:effects:inspectionLight", "bool", "inspection_light"), ("allo:effects:bodyShine", "bool", "body_shine"))
EFFECTS = EFFECT_FLAGS + SENSOR

# SensorParams field -> (attribute on the render settings prim, Sdf value type); author and reader share it.
SENSOR_ATTRIBUTES = {a.field: (a.name, a.sdf_type) for a in SENSOR}

# ---------------------------------------------------------------- AlloAnomalyAPI (anomaly prim)
(ANOMALY_ASSET, ANOMALY_ASSET_VARIANT, ANOMALY_DEPTH_INDEX, ANOMALY_DEPTH_OFFSET, ANOMALY_ATTEMPTS,
 ANOMALY_PREDICTED_AREA_FRACTION) = ANOMALY = _group(
    "AlloAnomalyAPI", layout.ANOMALY,
    ("allo:anomaly:asset", "string"), ("allo:anomaly:assetVariant", "string"), ("allo:anomaly:depthIndex", "int"),
    ("allo:anomaly:depthOffset", "double"), ("allo:anomaly:attempts", "int"),
    ("allo:anomaly:predictedAreaFraction", "double"))
ANOMALY_PREFIX = "allo:anomaly:"

# ---------------------------------------------------------------- AlloCameraPoseAPI (rig poses)
# A base pose is an Xform, not a UsdGeom.Camera (a composed scene offers outside tools one camera, the
# render camera): its transform is the pose, and these record the lens its view was chosen through, in
# UsdGeom.Camera's units (tenths of a scene unit; clipping range in metres).
(POSE_INDEX, POSE_SPLIT, POSE_FOCAL_LENGTH, POSE_HORIZONTAL_APERTURE, POSE_VERTICAL_APERTURE,
 POSE_HORIZONTAL_APERTURE_OFFSET, POSE_VERTICAL_APERTURE_OFFSET, POSE_CLIPPING_RANGE) = CAMERA_POSE = _group(
    "AlloCameraPoseAPI", RIG_POSES, ("allo:pose:index", "int"), ("allo:pose:split", "token"),
    ("allo:pose:focalLength", "float"), ("allo:pose:horizontalAperture", "float"),
    ("allo:pose:verticalAperture", "float"), ("allo:pose:horizontalApertureOffset", "float"),
    ("allo:pose:verticalApertureOffset", "float"), ("allo:pose:clippingRange", "float2"))
POSE_LENS = CAMERA_POSE[2:]

# ---------------------------------------------------------------- AlloJointAPI (station joints)
# An articulated joint of the procedural station (an Xform whose one named xformOp, e.g.
# xformOp:rotateY:alpha, is the joint angle): its axis, limits in degrees and the body it tracks.
STATION_JOINTS = f"{layout.STATION}/Geom/*"
JOINT_AXIS, JOINT_LOWER_LIMIT, JOINT_UPPER_LIMIT, JOINT_TRACKS = JOINT = _group(
    "AlloJointAPI", STATION_JOINTS, ("allo:joint:axis", "token"), ("allo:joint:lowerLimit", "double"),
    ("allo:joint:upperLimit", "double"), ("allo:joint:tracks", "token"))

# Every attribute, by API schema (schema order).
BY_SCHEMA: dict[str, tuple[AlloAttribute, ...]] = {
    "AlloSceneAPI": SCENE + SKY_RECORD + POSE_RECORD, "AlloEclipseAPI": ECLIPSE, "AlloRayVisibilityAPI": RAY,
    "AlloRenderQualityAPI": RENDER_QUALITY, "AlloEffectsAPI": EFFECTS, "AlloAnomalyAPI": ANOMALY,
    "AlloCameraPoseAPI": CAMERA_POSE, "AlloJointAPI": JOINT,
}
ALL: tuple[AlloAttribute, ...] = tuple(a for group in BY_SCHEMA.values() for a in group)
BY_NAME: dict[str, AlloAttribute] = {a.name: a for a in ALL}
NAMESPACE = "allo:"

# Not an attribute: the UsdRender.Var sourceName of the class mask output, in the same namespace.
CLASS_MASK_SOURCE = NAMESPACE + "classMask"
