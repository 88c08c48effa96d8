"""Write one scene as a small USD layer over the base stage.

A scene's opinions fall into three groups, each built here as plain data (`Prim` lists):
- `sky_prims`: what the day decides (the station's sun lamp, and on an eclipse day each body's
  own lamp with the light linking; true-scale bodies, eclipse states, epoch);
- `pose_prims`: what the perturbed camera sample decides (camera transform, offsets, attempts);
- `scene_prims`: what only this image decides (identity and seed, anomaly, effects, render, and
  the camera's exposure and, when the plan's camera is not the paper's, its lens: `lens_attrs`).

`write_scene_layer` writes all three into one self-contained layer over the base stage;
`author.compose` writes the first two once as shared layers and stacks them under a scene layer
that holds only the third. Both go through `write_layer`, which writes atomically the text Sdf's
ExportToString gives for the layer: written directly (`fast_layer_text`, issue 26) when it knows every
value, else authored with the Sdf API (`sdf_layer_text`; far cheaper than through Usd.Stage:
docs/bench_author.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


from allo_usd.core.version import __version__
from allo_usd.usd import schema
from allo_usd.sky import eclipse as sky_eclipse
from allo_usd.core.sensor import SensorParams
from allo_usd.core.errors import AlloError, LayerError
from allo_usd.core.camera_model import CLIP_M, DEFAULT_CAMERA, LENS_MM, MAX_SHIFT, SENSOR_MM
from allo_usd.core.geometry import check_finite, rotation_towards
from allo_usd.scene.spec import AnomalySpec, BodySpec, CameraSpec, SceneSpec, SunSpec
from allo_usd.core.limits import resolution_problem
from allo_usd.usd import attributes as A
from allo_usd.usd import layout
from allo_usd.usd.attributes import SENSOR_ATTRIBUTES
from allo_usd.usd.base_stage import LIT_BODIES, camera_ev, gf_quatd, product_vars
from allo_usd.plan.settings import DEFAULT_PASSES, canonical_passes
from allo_usd.usd.layout import STATION_SUN, body_sun_path
from allo_usd.core.files import relpath, write_text_atomic


@dataclass
class Prim:
    """The opinions one layer holds on one prim: {attr: (Sdf type name, value)} plus metadata."""

    path: str
    attrs: dict = field(default_factory=dict)
    api: tuple[str, ...] = ()
    define: str = ""              # type name to `def` (e.g. "Xform"); empty = `over`
    reference: str = ""
    variants: dict = field(default_factory=dict)
    active: bool | None = None
    rels: dict = field(default_factory=dict)  # {relationship: [target paths]} (explicit targets)


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
    return 2.0 ** camera_ev(exposure)


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


_VALUE_TYPES: dict[str, tuple] = {}


def _value_type(type_name: str) -> tuple:
    """(Sdf value type, variability) of a Prim attribute's type name ("double3", "uniform token[]"),
    looked up once per name: a layer authors a few dozen attributes, a plan ~90,000 layers."""
    found = _VALUE_TYPES.get(type_name)
    if found is None:
        from pxr import Sdf

        uniform = type_name.startswith("uniform ")
        found = _VALUE_TYPES[type_name] = (Sdf.ValueTypeNames.Find(type_name.removeprefix("uniform ")),
                                           Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
    return found


def layer_text(prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> str:
    """The .usda text of a layer holding `prims`: written directly (`fast_layer_text`) when every
    value is of a kind whose text is known to be Sdf's, else through the Sdf API (`sdf_layer_text`).
    The two give the same bytes (tests/test_author_fast_layer.py); the direct writer costs about a third."""
    text = fast_layer_text(prims, sublayers, custom, doc)
    return sdf_layer_text(prims, sublayers, custom, doc) if text is None else text


def sdf_layer_text(prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> str:
    """The .usda text of a layer holding `prims` (Sdf API inside one change block): the reference
    the direct writer is held to, and the way any value it does not know is written."""
    from pxr import Sdf

    layer = Sdf.Layer.CreateAnonymous(".usda")
    with Sdf.ChangeBlock():
        layer.subLayerPaths[:] = list(sublayers)
        layer.defaultPrim = layout.WORLD_NAME
        layer.customLayerData = {"allo": {"packageVersion": __version__, **custom}}
        layer.documentation = doc
        layer.pseudoRoot.SetInfo("upAxis", "Z")
        layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
        for prim in prims:
            spec = Sdf.CreatePrimInLayer(layer, prim.path)
            if prim.define:
                spec.specifier = Sdf.SpecifierDef
                spec.typeName = prim.define
            if prim.api:
                spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=list(prim.api)))
            if prim.reference:
                spec.referenceList.Prepend(Sdf.Reference(prim.reference))
            for vset, choice in prim.variants.items():
                spec.variantSelections[vset] = choice
            if prim.active is not None:
                spec.active = prim.active
            for name, (type_name, value) in prim.attrs.items():
                vtype, variability = _value_type(type_name)
                Sdf.AttributeSpec(spec, name, vtype, variability).default = value
            for name, targets in prim.rels.items():
                rel = Sdf.RelationshipSpec(spec, name, custom=False)
                rel.targetPathList.explicitItems = [Sdf.Path(t) for t in targets]
    return layer.ExportToString()


# --- the direct .usda writer ------------------------------------------------------------------
# It knows exactly what layer_text authors and nothing more; anything else (a value of another
# Python type, a string needing quotes or escapes, a name or path outside the plain identifier
# syntax, a number that is not finite) makes it return None, and the layer goes through Sdf.

class _Unknown(Exception):
    """A value the direct writer does not know how to write as Sdf would."""


_INDENT = "    "
_INT32 = (-2 ** 31, 2 ** 31 - 1)
_INT64 = (-2 ** 63, 2 ** 63 - 1)


def _plain(s: str) -> bool:
    """Printable ASCII without quotes or backslashes: Sdf writes it between double quotes as is."""
    return type(s) is str and s.isascii() and s.isprintable() and '"' not in s and "'" not in s and "\\" not in s


def _quote(s) -> str:
    if not _plain(s):
        raise _Unknown(s)
    return f'"{s}"'


def _ident(s) -> bool:
    """A plain identifier (prim, property or namespace part name)."""
    return type(s) is str and s.isascii() and s.replace("_", "a").isalnum() and not s[0].isdigit()


_NAMES: set[str] = set()        # property names already checked (a plan authors a few dozen, ~90,000 layers)
_PRIM_NAMES: set[str] = set()   # prim names already checked (identifiers)


def _name(s) -> str:
    if s in _NAMES and type(s) is str:
        return s
    if not (type(s) is str and s and all(_ident(part) for part in s.split(":"))):
        raise _Unknown(s)
    _NAMES.add(s)
    return s


def _path(p) -> str:
    """An absolute prim path of plain identifiers, as Sdf writes a target: </A/B>."""
    if not (type(p) is str and p.startswith("/") and all(_ident(part) for part in p[1:].split("/"))):
        raise _Unknown(p)
    return f"<{p}>"


def _asset(p) -> str:
    if not (_plain(p) and p and "@" not in p):
        raise _Unknown(p)
    return f"@{p}@"


def _shortest(digits: str, exp: int) -> str:
    """Shortest round-trip digits (no leading or trailing zeros) and the decimal exponent of the first,
    laid out as Tf's double-conversion does (TfStringify: fixed notation for exponents -6..14, else
    d.ddde<exp> with no '+')."""
    if -6 <= exp < 15:
        if exp < 0:
            return "0." + "0" * (-exp - 1) + digits
        if len(digits) <= exp + 1:
            return digits + "0" * (exp + 1 - len(digits))
        return f"{digits[:exp + 1]}.{digits[exp + 1:]}"
    return (f"{digits[0]}.{digits[1:]}" if len(digits) > 1 else digits) + f"e{exp}"


def _digits(mantissa: str, exp: int) -> tuple[str, int]:
    """(digits, exponent of the first) of a decimal mantissa 'I.F' (or 'I') times 10**exp."""
    whole, _, frac = mantissa.partition(".")
    digits = (whole + frac).lstrip("0")
    exp += len(whole) - 1 - (len(whole + frac) - len(digits))
    return digits.rstrip("0"), exp


def _double(x) -> str:
    """A double as Sdf writes it: Python's repr holds the same shortest round-trip digits. From 1e-4 to
    1e15 (most of a layer's values) repr already lays them out as Tf does, in fixed notation, but for
    a whole number's ".0" (the digits and _shortest's layout agree there: exponents -4 to 14)."""
    if type(x) is not float or x != x or x in (_INF, -_INF):
        raise _Unknown(x)
    if 1e-4 <= abs(x) < 1e15:
        r = repr(x)
        return r[:-2] if r.endswith(".0") else r
    if x == 0.0:
        return "-0" if str(x)[0] == "-" else "0"
    r = repr(abs(x))
    mantissa, _, e = r.partition("e")
    digits, exp = _digits(mantissa, int(e) if e else 0)
    return ("-" if x < 0 else "") + _shortest(digits, exp)


def _float(x) -> str:
    """A double stored as a float attribute (rounded to float32, as Sdf's cast), written with the float's
    own shortest round-trip digits (numpy's unique Dragon4 for float32, as double-conversion's). Kept
    per value (a run writes the same exposures and render settings into thousands of layers); zero is
    not kept, since 0.0 and -0.0 are one key."""
    if type(x) is not float or not abs(x) < _FLOAT32_SAFE:   # nan, inf or past float32's range
        raise _Unknown(x)
    text = _FLOATS.get(x) if x else None
    if text is None:
        text = _float_text(x)
        if x:
            if len(_FLOATS) >= 4096:
                _FLOATS.clear()
            _FLOATS[x] = text
    return text


_FLOATS: dict[float, str] = {}


def _float_text(x: float) -> str:
    import numpy as np

    f = np.float32(x)
    if f == 0.0:
        return "-0" if np.signbit(f) else "0"
    mantissa, _, e = np.format_float_scientific(abs(f), unique=True, trim="-").partition("e")
    digits, exp = _digits(mantissa, int(e))
    return ("-" if f < 0 else "") + _shortest(digits, exp)


_INF = float("inf")
_FLOAT32_SAFE = 3.4e38   # under float32's largest finite value: the cast stays finite


def _int(v, bounds=_INT32) -> str:
    if type(v) is not int or not bounds[0] <= v <= bounds[1]:
        raise _Unknown(v)
    return str(v)


def _gf(value, cls_name: str, n: int) -> list:
    if type(value).__name__ != cls_name or type(value).__module__ != "pxr.Gf":
        raise _Unknown(value)
    return [value[i] for i in range(n)]


def _tuple(items) -> str:
    return "(" + ", ".join(items) + ")"


def _quat(q) -> str:
    if type(q).__name__ != "Quatd" or type(q).__module__ != "pxr.Gf":
        raise _Unknown(q)
    im = q.GetImaginary()
    return _tuple([_double(q.GetReal()), *(_double(im[i]) for i in range(3))])


def _token_array(v) -> str:
    if type(v) is not list or not v:
        raise _Unknown(v)
    return "[" + ", ".join(_quote(t) for t in v) + "]"


_WRITERS = {
    "bool": lambda v: ("1" if v else "0") if type(v) is bool else _raise(v),
    "int": _int,
    "int64": lambda v: _int(v, _INT64),
    "double": _double,
    "float": _float,
    "string": _quote,
    "token": _quote,
    "double3": lambda v: _tuple([_double(c) for c in _gf(v, "Vec3d", 3)]),
    "quatd": _quat,
    "int2": lambda v: _tuple([_int(c) for c in _gf(v, "Vec2i", 2)]),
    "float2": lambda v: _tuple([_float(c) for c in _gf(v, "Vec2f", 2)]),
    "token[]": _token_array,
}


def _raise(v):
    raise _Unknown(v)


def _attr_line(name: str, type_name: str, value) -> str:
    base = type_name.removeprefix("uniform ")
    writer = _WRITERS.get(base)
    if writer is None:
        raise _Unknown(type_name)
    return f"{type_name} {_name(name)} = {writer(value)}"


def _rel_lines(name: str, targets, indent: str) -> list[str]:
    if not isinstance(targets, (list, tuple)) or not targets:
        raise _Unknown(targets)
    if len(targets) == 1:
        return [f"{indent}rel {_name(name)} = {_path(targets[0])}"]
    return [f"{indent}rel {_name(name)} = [", *(f"{indent}{_INDENT}{_path(t)}," for t in targets), f"{indent}]"]


_ORDER: dict[tuple[str, ...], tuple[str, ...]] = {}


def _property_order(names: tuple[str, ...]) -> tuple[str, ...]:
    """The order Sdf writes a prim's properties in (TfDictionaryLessThan: case-folded, digit runs by
    value), taken from Sdf itself once per set of names: a plan authors a handful of sets."""
    found = _ORDER.get(names)
    if found is None:
        from pxr import Sdf

        layer = Sdf.Layer.CreateAnonymous(".usda")
        spec = Sdf.CreatePrimInLayer(layer, "/P")
        for name in names:
            Sdf.AttributeSpec(spec, name, Sdf.ValueTypeNames.Int).default = 0
        lines = layer.ExportToString().split("\n")
        found = tuple(line.strip().removeprefix("int ").removesuffix(" = 0") for line in lines
                      if line.startswith(_INDENT + "int "))
        if sorted(found) != sorted(names):
            raise _Unknown(names)
        _ORDER[names] = found
    return found


class _Node:
    """One prim spec of the layer being written: its Prim (None: an ancestor only) and children."""

    __slots__ = ("prim", "children")

    def __init__(self):
        self.prim: Prim | None = None
        self.children: dict[str, _Node] = {}


def _prim_lines(name: str, node: _Node, depth: int, out: list[str]) -> None:
    ind = _INDENT * depth
    prim = node.prim
    head = f'{ind}{"def" if prim is not None and prim.define else "over"} '
    if prim is not None and prim.define:
        head += f"{_name(prim.define)} "
    head += f'"{name}"'
    meta: list[str] = []
    props: dict[str, list[str]] = {}
    if prim is not None:
        inner = ind + _INDENT
        if prim.active is not None:
            if type(prim.active) is not bool:
                raise _Unknown(prim.active)
            meta.append(f"{inner}active = {'true' if prim.active else 'false'}")
        if prim.api:
            meta.append(f"{inner}prepend apiSchemas = [{', '.join(_quote(a) for a in prim.api)}]")
        if prim.reference:
            meta.append(f"{inner}prepend references = {_asset(prim.reference)}")
        if prim.variants:
            meta.append(f"{inner}variants = {{")
            for vset in sorted(prim.variants):
                choice = prim.variants[vset]
                if not _ident(choice):       # Sdf checks a variant name's syntax (and may refuse it)
                    raise _Unknown(choice)
                meta.append(f"{inner}{_INDENT}string {_name(vset)} = {_quote(choice)}")
            meta.append(f"{inner}}}")
        for attr, (type_name, value) in prim.attrs.items():
            props[attr] = [inner + _attr_line(attr, type_name, value)]
        for rel, targets in prim.rels.items():
            if rel in props:
                raise _Unknown(rel)
            props[rel] = _rel_lines(rel, targets, inner)
    if meta:
        out.append(head + " (")
        out += meta
        out.append(f"{ind})")
    else:
        out.append(head)
    out.append(ind + "{")
    for prop in _property_order(tuple(props)) if props else ():
        out += props[prop]
    for i, (child, sub) in enumerate(node.children.items()):
        if props or i:
            out.append("")
        _prim_lines(child, sub, depth + 1, out)
    out.append(ind + "}")


def _custom_lines(custom: dict) -> list[str]:
    """customLayerData's allo dictionary (std::map order: by bytes), ints as int or int64 as Vt keeps them."""
    out = []
    for key in sorted(custom):
        value = custom[key]
        if not _ident(key):
            raise _Unknown(key)
        if type(value) is str:
            out.append(f"string {key} = {_quote(value)}")
        elif type(value) is int and _INT32[0] <= value <= _INT32[1]:
            out.append(f"int {key} = {value}")
        elif type(value) is int and _INT64[0] <= value <= _INT64[1]:
            out.append(f"int64 {key} = {value}")
        else:
            raise _Unknown(value)
    return [_INDENT * 3 + line for line in out]


def fast_layer_text(prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> str | None:
    """`sdf_layer_text`'s bytes written directly, or None when something in the layer is outside what
    this writer knows (the caller then uses Sdf)."""
    try:
        if not doc:                          # Sdf writes no doc line for an empty one
            return None
        root = _Node()
        seen = set()
        for prim in prims:
            if prim.path in seen or not prim.path.startswith("/"):
                return None
            seen.add(prim.path)
            node = root
            for part in prim.path[1:].split("/"):
                if part not in _PRIM_NAMES:
                    if not _ident(part):
                        return None
                    _PRIM_NAMES.add(part)
                node = node.children.get(part) or node.children.setdefault(part, _Node())
            node.prim = prim
        out = ["#usda 1.0", "(", f"{_INDENT}customLayerData = {{", f"{_INDENT * 2}dictionary allo = {{",
               *_custom_lines({"packageVersion": __version__, **custom}), f"{_INDENT * 2}}}", f"{_INDENT}}}",
               f'{_INDENT}defaultPrim = {_quote(layout.WORLD_NAME)}', f"{_INDENT}doc = {_quote(doc)}",
               f"{_INDENT}metersPerUnit = 1"]
        if sublayers:
            out.append(f"{_INDENT}subLayers = [")
            out.append(",\n".join(f"{_INDENT * 2}{_asset(s)}" for s in sublayers))
            out.append(f"{_INDENT}]")
        out += [f'{_INDENT}upAxis = "Z"', ")", ""]
        for name, node in root.children.items():
            _prim_lines(name, node, 0, out)
            out.append("")
        return "\n".join(out) + "\n"
    except _Unknown:
        return None


def write_layer(path: Path, prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> Path:
    schema.register()
    return write_text_atomic(path, layer_text(prims, sublayers, custom, doc))


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
