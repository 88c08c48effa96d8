"""Inspect and compare scene layers from the USD alone (pxr only; no plan, no bpy, no renders).

A layer is the record of a scene, so these tools answer "what is this image?" and "what
differs between these two images?" without any other file: `describe` reads a composed stage
into plain, JSON-able values; `diff` lists the composed values that differ between two stages.

Why `diff` is fast but still correct: two scene layers usually share most of their layer stack
(the base stage, maybe a day layer). A layer present in BOTH stacks (same real path) carries the
same opinions in both, so it cannot create a difference on its own: every differing composed
value must have an opinion in a layer that is in only one stack, or be reached through a
composition arc (reference, payload, variant selection, inherit, specialize, activation)
authored in such a layer. `diff` therefore compares
  - every property that has a spec in a non-shared layer of either stack,
  - prim-level state (type, active, applied schemas, variant selections) of every prim with a
    spec in such a layer, and the whole composed subtree of a prim whose spec there authors a
    composition arc or `active`,
  - the layer stacks themselves (sublayers below the root; two entries match if they are the
    same file or have the same path relative to their root layer) and the root layers'
    customLayerData.
A day layer that differs between two scenes is a non-shared layer, so its opinions are compared.
`full=True` compares every prim under /World and /Render instead (slow; the tests use it to
check the fast path). Attribute values are compared at the default time code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from allo_usd.core import fixedmath as fm
from allo_usd.core.errors import LayerError
from allo_usd.usd import attributes as A
from allo_usd.usd import layout
from allo_usd.usd.layout import STATION_SUN
from allo_usd.usd.read import camera_exposure, open_stage
from allo_usd.usd.read_labels import anomaly_prims, composed_asset, composed_labels, composed_variant
from allo_usd.usd.read_lights import sun_irradiance
from allo_usd.usd.reader_bounds import world_matrix

ROOTS = (layout.WORLD, layout.RENDER)
ABSENT = "<absent>"
PRIM = "(prim)"
STACK = "(layer stack)"


# ----------------------------------------------------------------------------- plain values

def _plain(v):
    """A USD value as plain Python (tuples for vectors, nested lists for matrices)."""
    if v is None or isinstance(v, (bool, int, str)):
        return v
    if isinstance(v, float):
        return float(v)
    if hasattr(v, "GetReal") and hasattr(v, "GetImaginary"):  # Gf.Quat*
        return (float(v.GetReal()), *map(float, v.GetImaginary()))
    if hasattr(v, "path") and hasattr(v, "resolvedPath"):  # Sdf.AssetPath
        return v.path
    if type(v).__name__.startswith("Matrix"):
        return [list(map(float, row)) for row in v]
    if hasattr(v, "__len__") and not isinstance(v, dict):
        return tuple(_plain(x) for x in v)
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if hasattr(v, "pathString"):
        return v.pathString
    return v.item() if isinstance(v, np.generic) else v


def _comparable(v):
    """A raw USD value in a form `_same` compares quickly: numeric arrays stay numpy (no tuples)."""
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    if hasattr(v, "GetReal") and hasattr(v, "GetImaginary"):
        return np.array([v.GetReal(), *v.GetImaginary()], dtype=np.float64)
    try:
        arr = np.asarray(v)
        if arr.dtype.kind in "biuf":
            return arr.astype(np.float64)
    except (TypeError, ValueError):
        pass
    return _plain(v)


def _same(a, b, rtol: float = 1e-9, atol: float = 1e-12) -> bool:
    """Equality with a tolerance for floats: |a-b|max <= atol + rtol*|b|max, per value/array."""
    a, b = _comparable(a), _comparable(b)
    if isinstance(a, (str, type(None))) or isinstance(b, (str, type(None))):
        return a == b
    if isinstance(a, dict) or isinstance(b, dict):
        return isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys() and \
            all(_same(a[k], b[k], rtol, atol) for k in a)
    try:
        x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    except (TypeError, ValueError):
        return a == b
    if x.shape != y.shape:
        return False
    if x.size == 0:
        return True
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        return bool(np.array_equal(x, y, equal_nan=True))
    return float(np.abs(x - y).max()) <= atol + rtol * float(np.abs(y).max())


def _rel(path: str, start: Path) -> str:
    """core.files.relpath, keeping an empty path (an anonymous layer) empty."""
    from allo_usd.core.files import relpath

    return relpath(path, start) if path else path


def _stack(stage) -> list:
    return [l for l in stage.GetLayerStack(includeSessionLayers=False)]


# ----------------------------------------------------------------------------- describe

def _attr(prim, name, default=None):
    if not prim:
        return default
    attr = prim.GetAttribute(name)
    value = attr.Get() if attr else None
    return default if value is None else _plain(value)


def _source_text(src: dict) -> str:
    if src["kind"] == "user":
        return (f"from {src['file']} (your hazard: sha256 {str(src['sha256'])[:12]}, {src['format']}, unit {src['unit']}, "
                f"up axis {src['up_axis']}; converted to {src['layer']})")
    return f"built-in ({src['layer']})"


def _asset_source(aprim, start: Path) -> dict:
    """Where the anomaly's asset came from: a plan's own hazard (its conversion record: file, sha256,
    unit, up axis) or a built-in asset of the base stage; `layer` is the asset's interface layer,
    relative to `start` (the scene layer's folder)."""
    from allo_usd.usd.hazard import hazard_provenance

    interface = None
    for spec in aprim.GetPrimStack():
        hazard = hazard_provenance(spec.layer)
        if hazard:
            return {"kind": "user", "file": hazard.get("source"), "sha256": hazard.get("sha256"),
                    "format": hazard.get("format"), "unit": hazard.get("unit"), "up_axis": hazard.get("upAxis"),
                    "layer": _rel(spec.layer.realPath, start)}
        if spec.layer.realPath.endswith(".usda") and spec.path.pathString.count("/") == 1:
            interface = interface or spec.layer.realPath   # the asset root's interface layer (not the scene's)
    return {"kind": "built-in", "layer": _rel(interface, start) if interface else None}


def _lens_source(attr, stack) -> str:
    """Which layer holds the lens's strongest opinion: the scene's own layers (a plan's [camera]) or the
    base stage (the bottom of the stack: the paper's Table I camera)."""
    specs = attr.GetPropertyStack()
    if not specs:
        return "schema fallback"
    layer = specs[0].layer
    name = Path(layer.realPath).name if layer.realPath else layer.identifier
    if stack and layer.identifier == stack[-1].identifier:
        return f"base stage {name} (Table I default)"
    return f"scene layer {name} (plan camera)"


def describe(layer: str | Path) -> dict:
    """What the scene is, read from the USD alone: identity, anomaly, sky, camera, render, stack.
    A layer this project did not author (no AlloSceneAPI on its default prim) is a LayerError that
    says so, rather than a table of None."""
    from pxr import Usd, UsdGeom, UsdLux, UsdRender

    from allo_usd.core.geometry import matrix_to_quat

    layer = Path(layer)
    stage = open_stage(layer)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    world = stage.GetDefaultPrim() or stage.GetPrimAtPath(layout.WORLD)
    scene_api = A.SCENE_ID.api_schema
    if not world or not world.HasAPI(scene_api):
        why = (f"its default prim {world.GetPath()} has no {scene_api} (no {A.SCENE_ID.name})" if world else
               f"it has no default prim and no {layout.WORLD}")
        raise LayerError(f"{layer} is not a scene layer authored by allo-usd: {why}; `allo-usd inspect` describes "
                         "the scene layers that `allo-usd author` writes (fix the path; for other USD files use "
                         "usdcat or usdview)")
    provenance = dict(stage.GetRootLayer().customLayerData.get("allo", {}))
    root = stage.GetRootLayer()
    start = Path(root.realPath).parent if root.realPath else Path.cwd()
    a = lambda attr, default=None: _attr(world, attr.name, default)  # noqa: E731

    anomaly = None
    aprim = stage.GetPrimAtPath(layout.ANOMALY)
    if aprim and aprim.IsActive():
        m = world_matrix(cache, aprim)
        composed = composed_labels(aprim, check=True)   # what is referenced and selected (read_labels)
        anomaly = {"asset": composed["asset"], "variant": composed["assetVariant"],
                   "variant_selection": aprim.GetVariantSets().GetAllVariantSelections().get("variant"),
                   "depth_index": _attr(aprim, A.ANOMALY_DEPTH_INDEX.name),
                   "depth_offset": _attr(aprim, A.ANOMALY_DEPTH_OFFSET.name),
                   "predicted_area_fraction": _attr(aprim, A.ANOMALY_PREDICTED_AREA_FRACTION.name),
                   "attempts": _attr(aprim, A.ANOMALY_ATTEMPTS.name), "position": tuple(map(float, m[:3, 3])),
                   "source": _asset_source(aprim, start)}
    objects = [{"path": str(p.GetPath()), "asset": composed_asset(p), "variant": composed_variant(p)}
               for p in anomaly_prims(stage)]

    settings_path = stage.GetMetadata("renderSettingsPrimPath") or layout.RENDER_SETTINGS
    sp = stage.GetPrimAtPath(settings_path)
    r = lambda attr, default=None: _attr(sp, attr.name, default)  # noqa: E731
    render = {"settings": settings_path, "resolution": _attr(sp, "resolution"), "preset": r(A.RENDER_PRESET),
              "samples": r(A.RENDER_SAMPLES), "seed": r(A.RENDER_SEED),
              "denoise": r(A.RENDER_DENOISE), "max_bounces": r(A.RENDER_MAX_BOUNCES),
              "adaptive_threshold": r(A.RENDER_ADAPTIVE_THRESHOLD),
              "denoise_prefilter": r(A.RENDER_DENOISE_PREFILTER), "denoise_quality": r(A.RENDER_DENOISE_QUALITY)}
    for attr in (A.RENDER_TARGET_PSNR, A.RENDER_TIME_LIMIT):   # the target mode: shown where a layer has it
        if r(attr) is not None:
            render[attr.field] = r(attr)
    effects = {e.short: r(e) for e in A.EFFECT_FLAGS}
    sensor = ({a.GetName().rsplit(":", 1)[1]: _attr(sp, a.GetName()) for a in sp.GetAttributes()
               if a.GetName().startswith(A.SENSOR_PREFIX)} if effects[A.EFFECTS_SENSOR_NOISE.short] else None)

    def lamp(prim) -> dict:
        m = world_matrix(cache, prim)
        d = m[:3, 2] / fm.norm(m[:3, 2])  # light travels along -Z: +Z points at the Sun
        link = UsdLux.LightAPI(prim).GetLightLinkCollectionAPI()
        normalize = bool(_attr(prim, "inputs:normalize", False))
        intensity, angle = _attr(prim, "inputs:intensity", 50000.0), _attr(prim, "inputs:angle", 0.53)
        exposure = _attr(prim, "inputs:exposure", 0.0)
        return {"path": str(prim.GetPath()), "intensity": intensity, "exposure": exposure, "normalize": normalize,
                "irradiance": sun_irradiance(intensity * fm.exp2(exposure), angle, normalize),
                "irradiance_unoccluded": _attr(prim, A.IRRADIANCE_UNOCCLUDED.name),
                "lit_fraction": _attr(prim, A.LIT_FRACTION.name),
                "eclipse_state": _attr(prim, A.ECLIPSE_STATE.name), "eclipse_body": _attr(prim, A.ECLIPSE_BODY.name),
                "angular_diameter_deg": _attr(prim, "inputs:angle"), "distance_m": _attr(prim, A.SUN_DISTANCE.name),
                "direction": tuple(map(float, d)),
                "light_link": {"include_root": bool(link.GetIncludeRootAttr().Get()),
                               "includes": [str(t) for t in link.GetIncludesRel().GetTargets()],
                               "excludes": [str(t) for t in link.GetExcludesRel().GetTargets()]}}

    sky = stage.GetPrimAtPath(layout.SKY)
    lamps = [lamp(p) for p in sky.GetChildren() if p.IsA(UsdLux.DistantLight)] if sky else []
    sun = next((s for s in lamps if s["path"] == STATION_SUN), lamps[0] if lamps else None)
    body_suns = [s for s in lamps if s is not sun]
    others = [{"path": str(p.GetPath()), "type": p.GetTypeName(), "intensity": _attr(p, "inputs:intensity"),
               "exposure": _attr(p, "inputs:exposure", 0.0)}
              for p in stage.Traverse() if (p.IsA(UsdLux.BoundableLightBase) or p.IsA(UsdLux.NonboundableLightBase))
              and not p.GetPath().HasPrefix(layout.SKY)]  # the inspection light and a user's own lights

    camera = None
    targets = UsdRender.Settings(sp).GetCameraRel().GetForwardedTargets() if sp else []
    cam_prim = stage.GetPrimAtPath(targets[0]) if targets else stage.GetPrimAtPath(layout.CAMERA)
    if cam_prim:
        m = world_matrix(cache, cam_prim)
        scale, values = camera_exposure(cam_prim)
        lens = UsdGeom.Camera(cam_prim)
        mm = lambda attr: None if attr.Get() is None else float(attr.Get()) * 100.0  # noqa: E731 (tenths of a metre)
        camera = {"path": str(cam_prim.GetPath()), "position": tuple(map(float, m[:3, 3])),
                  "orientation_wxyz": tuple(map(float, matrix_to_quat(m[:3, :3]))),
                  "forward": tuple(map(float, -m[:3, 2])), "up": tuple(map(float, m[:3, 1])),
                  "focal_length_mm": mm(lens.GetFocalLengthAttr()),
                  "sensor_mm": (mm(lens.GetHorizontalApertureAttr()), mm(lens.GetVerticalApertureAttr())),
                  "aperture_offset_mm": (mm(lens.GetHorizontalApertureOffsetAttr()) or 0.0,
                                         mm(lens.GetVerticalApertureOffsetAttr()) or 0.0),
                  "lens_from": _lens_source(lens.GetFocalLengthAttr(), _stack(stage)),
                  "exposure": {"ev": values["exposure"], "f_stop": values["exposure:fStop"],
                               "time_s": values["exposure:time"], "iso": values["exposure:iso"],
                               "responsivity": values["exposure:responsivity"], "linear_scale": scale}}
        render["exposure"] = scale  # the film exposure the renderer applies (the camera's linear scale)

    joints = _joints(stage, start)
    return {
        "layer": str(layer),
        "scene_id": a(A.SCENE_ID, provenance.get("sceneId")), "epoch": a(A.EPOCH),
        "perilune_epoch": a(A.PERILUNE_EPOCH), "day": a(A.DAY), "pose": a(A.POSE), "split": a(A.SPLIT),
        "variant": a(A.VARIANT), "seed": a(A.SEED, provenance.get("seed")),
        "seed_path": a(A.SEED_PATH, provenance.get("seedPath")),
        "package_version": provenance.get("packageVersion"),
        "camera_perturbation": {"convention": a(A.PERTURBATION), "offset_position": a(A.CAMERA_OFFSET_POSITION),
                                "offset_rotation": a(A.CAMERA_OFFSET_ROTATION), "attempts": a(A.CAMERA_ATTEMPTS),
                                "position_sigma_m": a(A.POSITION_SIGMA), "angle_sigma_rad": a(A.ANGLE_SIGMA),
                                "sigmas_authored": bool(world and world.GetAttribute(A.POSITION_SIGMA.name)
                                                        and world.GetAttribute(A.POSITION_SIGMA.name).HasAuthoredValue())},
        "pose_file": ({"name": a(A.POSE_NAME), "source": a(A.POSE_SOURCE), "sha256": a(A.POSE_SOURCE_SHA256)}
                      if a(A.POSE_NAME) else None),
        "anomaly": anomaly, "anomaly_objects": objects, "effects": effects, "sensor": sensor, "render": render,
        "sun": sun, "body_suns": body_suns, "lights": others,
        "camera": camera, "joints": joints,
        "layer_stack": {"sublayers": list(root.subLayerPaths),
                        "layers": [_rel(l.realPath, start) or l.identifier for l in _stack(stage)]},
    }


def _joints(stage, start: Path) -> dict:
    """The procedural station's joints as the scene composes them: {name: {angle (degrees), lower,
    upper, from (the layer holding the angle: the sky layer when the plan tracks the Sun)}}."""
    from allo_usd.usd.stage_geometry import joint_op, station_joints

    out = {}
    for name, prim in station_joints(stage).items():
        op = joint_op(prim)
        specs = op.GetAttr().GetPropertyStack()
        source = specs[0].layer if specs else None
        out[name] = {"angle": float(op.Get()), "lower": _attr(prim, A.JOINT_LOWER_LIMIT.name),
                     "upper": _attr(prim, A.JOINT_UPPER_LIMIT.name),
                     "from": (_rel(source.realPath, start) or source.identifier) if source else None}
    return out


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, tuple):
        return "(" + ", ".join(_fmt(x) for x in v) + ")"
    return str(v)


def _lights(link: dict) -> str:
    """A lamp's lightLink collection in words."""
    if link["include_root"]:
        return "all but " + ", ".join(link["excludes"]) if link["excludes"] else "all"
    return "only " + ", ".join(link["includes"]) if link["includes"] else "nothing"


def format_description(d: dict) -> str:
    """The description for humans: one topic per line."""
    lines = [f"scene    {d['scene_id']}  ({d['split']}, {d['variant']})  layer {d['layer']}",
             f"time     epoch {d['epoch']}  day {d['day']}  perilune {d['perilune_epoch']}",
             f"seed     {d['seed']}  path {d['seed_path']}  package {d['package_version']}"]
    cam, cp = d["camera"] or {}, d["camera_perturbation"]
    lines.append(f"camera   pose {d['pose']}  position {_fmt(cam.get('position'))} m  "
                 f"orientation(wxyz) {_fmt(cam.get('orientation_wxyz'))}  forward {_fmt(cam.get('forward'))}")
    lines.append(f"         perturbation {cp['convention']}  offset {_fmt(cp['offset_position'])} m  "
                 f"rot {_fmt(cp['offset_rotation'])}  attempts {cp['attempts']}"
                 + (f"  sigma {_fmt(cp['position_sigma_m'])} m, {_fmt(cp['angle_sigma_rad'])} rad"
                    if cp.get("sigmas_authored") else ""))
    if d.get("pose_file"):
        pf = d["pose_file"]
        lines.append(f"         pose file: {pf['name']} from {pf['source']}  sha256 {pf['sha256']}")
    if cam.get("exposure"):
        e, sensor = cam["exposure"], cam["sensor_mm"]
        lines.append(f"lens     focal length {_fmt(cam['focal_length_mm'])} mm  aperture {_fmt(sensor[0])} x "
                     f"{_fmt(sensor[1])} mm  exposure {_fmt(e['ev'])} EV (f/{_fmt(e['f_stop'])}, {_fmt(e['time_s'])} s, "
                     f"ISO {_fmt(e['iso'])}, responsivity {_fmt(e['responsivity'])}) = linear x{_fmt(e['linear_scale'])}")
        lines.append(f"         aperture offset {_fmt(cam['aperture_offset_mm'])} mm  from {cam['lens_from']}")
    for s in ([d["sun"]] if d["sun"] else []) + d.get("body_suns", []):
        name = "sun" if s is d["sun"] else s["path"].rsplit("/", 1)[-1]
        lines.append(f"{name:<8} {_fmt(s['irradiance'])} W/m2 (intensity {_fmt(s['intensity'])}, normalize "
                     f"{s['normalize']}; unoccluded {_fmt(s['irradiance_unoccluded'])}, lit "
                     f"{_fmt(s['lit_fraction'])})  eclipse {s['eclipse_state']}/{s['eclipse_body']}  "
                     f"direction {_fmt(s['direction'])}  lights {_lights(s['light_link'])}")
    for x in d.get("lights", []):
        lines.append(f"light    {x['path']}  {x['type']}  intensity {_fmt(x['intensity'])}  exposure {_fmt(x['exposure'])}")
    an = d["anomaly"]
    lines.append("anomaly  none" if an is None else
                 f"anomaly  {an['asset']}/{an['variant']}  depth {an['depth_index']} ({_fmt(an['depth_offset'])} m)  "
                 f"predicted area {_fmt(an['predicted_area_fraction'])}  at {_fmt(an['position'])}  "
                 + _source_text(an["source"]))
    objects = d.get("anomaly_objects") or []
    if [o["path"] for o in objects] not in ([], [layout.ANOMALY]):   # more than the anomaly line says
        lines.append("objects  " + "  ".join(f"{o['path']} {o['asset']}/{o['variant']}" for o in objects))
    r = d["render"]
    res = r["resolution"] or ("?", "?")
    lines.append(f"render   {res[0]}x{res[1]}  {r['samples']} spp  preset {r['preset']}  seed {r['seed']}  "
                 f"denoise {r['denoise']}" + _target_text(r))
    lines.append("effects  " + "  ".join(f"{k}={v}" for k, v in d["effects"].items()))
    if d.get("sensor"):
        lines.append("sensor   " + "  ".join(f"{k}={_fmt(v)}" for k, v in sorted(d["sensor"].items())))
    if d.get("joints"):
        sources = sorted({str(j["from"]) for j in d["joints"].values()})
        lines.append("joints   " + "  ".join(f"{k} {_fmt(j['angle'])}" for k, j in d["joints"].items())
                     + f"  (degrees; from {', '.join(sources)})")
    lines.append("stack    " + " -> ".join(d["layer_stack"]["layers"]))
    return "\n".join(lines)


def _target_text(render: dict) -> str:
    """The render line's target mode: "  target 40 dB (cap 256 spp, 60 s)", or "" for fixed samples."""
    target, limit = render.get("target_psnr"), render.get("time_limit")
    if not target:
        return ""
    return (f"  target {_fmt(target)} dB (cap {render['samples']} spp"
            + (f", {_fmt(limit)} s" if limit else "") + ")")


# ----------------------------------------------------------------------------- diff

def _prim_state(prim) -> dict:
    return {"typeName": str(prim.GetTypeName()), "active": prim.IsActive(),
            "apiSchemas": tuple(prim.GetAppliedSchemas()),
            **{f"variant:{k}": v for k, v in prim.GetVariantSets().GetAllVariantSelections().items()}}


def _prop_value(prop):
    from pxr import Usd

    if isinstance(prop, Usd.Relationship):
        return tuple(str(t) for t in prop.GetTargets())
    return prop.Get()


def _props(prim, names=None) -> dict:
    if not prim:
        return {}
    if names is None:
        return {p.GetName(): _prop_value(p) for p in prim.GetProperties()}
    out = {}
    for n in names:
        p = prim.GetProperty(n)
        if p:
            out[n] = _prop_value(p)
    return out


def _in_roots(path) -> bool:
    return any(path.HasPrefix(r) for r in ROOTS)


def _opinions(layers) -> tuple[set, dict, set]:
    """Prim paths with specs, {prim path: property names with specs}, and arc-carrying prims."""
    from pxr import Sdf

    prims, props, arcs = set(), {}, set()
    for layer in layers:
        def visit(path, layer=layer):
            if path.IsTargetPath() or path.IsMapperPath() or path.IsExpressionPath():
                return
            plain = path.StripAllVariantSelections()
            if path.IsPropertyPath():
                props.setdefault(plain.GetPrimPath(), set()).add(plain.name)
                return
            if not (path.IsPrimPath() or path.IsPrimVariantSelectionPath()) or path == Sdf.Path.absoluteRootPath:
                return
            prims.add(plain)
            spec = layer.GetPrimAtPath(path)
            if spec and (spec.hasReferences or spec.hasPayloads or spec.hasInheritPaths or spec.hasSpecializes
                         or len(spec.variantSelections) or len(spec.variantSets) or spec.HasInfo("active")
                         or spec.HasInfo("instanceable")):
                arcs.add(plain)
        layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return prims, props, arcs


def _subtree(stage, path) -> set:
    from pxr import Usd

    prim = stage.GetPrimAtPath(path)
    return {p.GetPath() for p in Usd.PrimRange(prim, Usd.PrimAllPrimsPredicate)} if prim else set()


def diff(a: str | Path, b: str | Path, full: bool = False, rtol: float = 1e-9, atol: float = 1e-12) -> list:
    """[(prim path, property, value_a, value_b)] of composed values that differ; see module doc."""
    sa, sb = open_stage(a), open_stage(b)
    out = []
    la, lb = _stack(sa), _stack(sb)
    key = lambda l: l.realPath or l.identifier  # noqa: E731
    start_a, start_b = Path(key(la[0])).parent, Path(key(lb[0])).parent
    rel_a = [_rel(key(l), start_a) for l in la[1:]]
    rel_b = [_rel(key(l), start_b) for l in lb[1:]]
    same_stack = len(la) == len(lb) and all(key(x) == key(y) or rx == ry
                                              for x, y, rx, ry in zip(la[1:], lb[1:], rel_a, rel_b))
    if not same_stack:  # a layer is the same if it is the same file, or at the same relative path
        out.append(("/", STACK, tuple(rel_a), tuple(rel_b)))
    ca, cb = dict(la[0].customLayerData), dict(lb[0].customLayerData)
    if not _same(_plain(ca), _plain(cb), rtol, atol):
        out.append(("/", "customLayerData", _plain(ca), _plain(cb)))

    if full:
        paths = set().union(*(_subtree(s, r) for s in (sa, sb) for r in ROOTS))
        names, full_props = {}, set()
    else:
        shared = {key(l) for l in la} & {key(l) for l in lb}
        prims, names, arcs = _opinions([l for l in la + lb if key(l) not in shared])
        paths = set(prims)
        for p in arcs:
            paths |= _subtree(sa, p) | _subtree(sb, p)
        paths |= {p for p in names}
        full_props = {q for p in arcs for q in paths if q.HasPrefix(p)}
    for path in sorted(p for p in paths if _in_roots(p)):
        pa, pb = sa.GetPrimAtPath(path), sb.GetPrimAtPath(path)
        if not pa and not pb:
            continue
        if not pa or not pb:
            out.append((str(path), PRIM, str(pa.GetTypeName()) if pa else ABSENT,
                        str(pb.GetTypeName()) if pb else ABSENT))
            continue
        sta, stb = _prim_state(pa), _prim_state(pb)
        for k in sorted(set(sta) | set(stb)):
            if not _same(sta.get(k, ABSENT), stb.get(k, ABSENT), rtol, atol):
                out.append((str(path), k, sta.get(k, ABSENT), stb.get(k, ABSENT)))
        want = None if full or path in full_props else names.get(path, set())
        va, vb = _props(pa, want), _props(pb, want)
        for k in sorted(set(va) | set(vb)):
            x, y = va.get(k, ABSENT), vb.get(k, ABSENT)
            if not _same(x, y, rtol, atol):
                out.append((str(path), k, _plain(x), _plain(y)))
    return out


def format_diff(rows: list, width: int = 100) -> str:
    """One line per difference; long values are shortened."""
    def short(v):
        s = _fmt(v) if not isinstance(v, (list, tuple)) or len(v) <= 8 else f"<{len(v)} values>"
        return s if len(s) <= width else s[: width - 3] + "..."
    if not rows:
        return "no differences"
    return "\n".join(f"{path} {prop}: {short(x)} -> {short(y)}" for path, prop, x, y in rows)
