"""Write one scene as a small USD layer over the base stage.

The layer sublayers the base stage by a relative path and holds only this scene's opinions:
camera, sky, anomaly, effects and render settings, plus the seed and package version. It
carries its own defaultPrim, upAxis and metersPerUnit, so it is a valid stage on its own.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .. import __version__, schema
from ..errors import LayerError
from ..geometry import check_finite, matrix_to_quat
from ..spec import SceneSpec
from .asset import commit_layer, new_layer


def _relpath(target: Path, start: Path) -> str:
    rel = os.path.relpath(Path(target).resolve(), Path(start).resolve())
    return rel if rel.startswith(".") else f"./{rel}"


def _quatd(rotation):
    from pxr import Gf

    q = matrix_to_quat(np.asarray(rotation, dtype=np.float64))
    return Gf.Quatd(float(q[0]), Gf.Vec3d(*map(float, q[1:])))


def validate_spec(spec: SceneSpec) -> None:
    """Check every number before authoring, so a bad spec writes nothing (validate, then author)."""
    check_finite("camera position", spec.camera.position)
    check_finite("camera rotation", spec.camera.rotation)
    check_finite("sun direction", spec.sun.direction)
    for name, body in spec.bodies.items():
        check_finite(f"{name} position", body.position)
        if not body.radius > 0:
            raise LayerError(f"{name} radius must be positive, got {body.radius}")
    if spec.anomaly is not None:
        check_finite("anomaly position", spec.anomaly.position)
        check_finite("anomaly rotation", spec.anomaly.rotation)
    w, h = spec.render.resolution
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise LayerError(f"resolution {w}x{h} is outside 1..16384 per side; choose a real image size")
    if not 1 <= spec.render.samples <= 65536:
        raise LayerError(f"samples={spec.render.samples} is outside 1..65536")
    if spec.split not in ("train", "test"):
        raise LayerError(f"split must be 'train' or 'test', got {spec.split!r}")


def write_scene_layer(spec: SceneSpec, path: Path, base_stage: Path) -> Path:
    """Author `spec` to `path` (atomically) over `base_stage`; returns the path."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender

    schema.register()
    validate_spec(spec)
    path = Path(path)
    base_stage = Path(base_stage)
    if not base_stage.is_file():
        raise LayerError(f"base stage {base_stage} does not exist; run scripts/make_base_stage.py or "
                         "pass the path of stages/base.usda")
    layer, tmp = new_layer(path)
    layer.subLayerPaths.append(_relpath(base_stage, path.parent))
    layer.defaultPrim = "World"
    layer.customLayerData = {
        "allo": {"packageVersion": __version__, "seed": int(spec.seed), "seedPath": spec.seed_path,
                 "sceneId": spec.scene_id},
    }
    layer.documentation = f"allo-usd scene {spec.scene_id}"
    stage = Usd.Stage.Open(layer)
    stage.SetEditTarget(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)

    world = stage.OverridePrim("/World")
    schema.apply(world, "AlloSceneAPI")
    values = {
        "allo:sceneId": spec.scene_id, "allo:epoch": spec.epoch, "allo:periluneEpoch": spec.perilune_epoch,
        "allo:day": int(spec.day), "allo:pose": int(spec.pose), "allo:split": spec.split,
        "allo:variant": spec.variant, "allo:seed": int(spec.seed), "allo:seedPath": spec.seed_path,
        "allo:perturbation": spec.camera.perturbation,
        "allo:cameraOffsetPosition": Gf.Vec3d(*map(float, spec.camera.offset_position)),
        "allo:cameraOffsetRotation": Gf.Vec3d(*map(float, spec.camera.offset_rotation)),
        "allo:cameraAttempts": int(spec.camera.attempts),
    }
    for name, value in values.items():
        world.GetAttribute(name).Set(value)

    camera = stage.OverridePrim("/World/Camera")
    camera.GetAttribute("xformOp:translate").Set(Gf.Vec3d(*map(float, spec.camera.position)))
    camera.GetAttribute("xformOp:orient").Set(_quatd(spec.camera.rotation))

    sun = stage.OverridePrim("/World/Sky/SunLight")
    light = UsdLux.DistantLight(sun)
    from ..geometry import rotation_towards
    sun.GetAttribute("xformOp:orient").Set(_quatd(rotation_towards(spec.sun.direction)))
    light.GetIntensityAttr().Set(float(spec.sun.irradiance))
    light.GetAngleAttr().Set(float(spec.sun.angular_diameter_deg))
    for name, value in {"allo:litFraction": float(spec.sun.lit_fraction), "allo:eclipseState": spec.sun.eclipse_state,
                        "allo:eclipseBody": spec.sun.eclipse_body,
                        "allo:irradianceUnoccluded": float(spec.sun.irradiance_unoccluded),
                        "allo:sunDistance": float(spec.sun.distance_m)}.items():
        sun.GetAttribute(name).Set(value)
    for name, body in spec.bodies.items():
        prim = stage.OverridePrim(f"/World/Sky/{name}")
        prim.GetAttribute("xformOp:translate").Set(Gf.Vec3d(*map(float, body.position)))
        prim.GetAttribute("xformOp:scale").Set(Gf.Vec3d(*[float(body.radius)] * 3))

    if not spec.effects.inspection_light:
        stage.OverridePrim("/World/Camera/InspectionLight").SetActive(False)

    if spec.anomaly is not None:
        a = spec.anomaly
        prim = UsdGeom.Xform.Define(stage, "/World/Anomaly").GetPrim()
        asset = Path(base_stage).parent / "anomalies" / f"{a.asset}.usda"
        if not asset.is_file():
            raise LayerError(f"anomaly asset {a.asset!r} has no file {asset}; choose one of the "
                             f"assets in {asset.parent}")
        prim.GetReferences().AddReference(_relpath(asset, path.parent))
        prim.GetVariantSets().GetVariantSet("variant").SetVariantSelection(a.variant)
        xf = UsdGeom.Xformable(prim)
        xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, a.position)))
        xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(_quatd(a.rotation))
        schema.apply(prim, "AlloAnomalyAPI")
        for name, value in {"allo:anomaly:asset": a.asset, "allo:anomaly:assetVariant": a.variant,
                            "allo:anomaly:depthIndex": int(a.depth_index),
                            "allo:anomaly:depthOffset": float(a.depth_offset),
                            "allo:anomaly:attempts": int(a.attempts),
                            "allo:anomaly:predictedAreaFraction": float(a.predicted_area_fraction)}.items():
            prim.GetAttribute(name).Set(value)

    settings = stage.OverridePrim("/Render/Settings")
    UsdRender.Settings(settings).GetResolutionAttr().Set(Gf.Vec2i(*map(int, spec.render.resolution)))
    r, e = spec.render, spec.effects
    for name, value in {"allo:render:preset": r.preset, "allo:render:samples": int(r.samples),
                        "allo:render:adaptiveThreshold": float(r.adaptive_threshold),
                        "allo:render:denoise": bool(r.denoise), "allo:render:maxBounces": int(r.max_bounces),
                        "allo:render:seed": int(r.seed), "allo:render:exposure": float(r.exposure),
                        "allo:render:threads": int(r.threads),
                        "allo:effects:sensorNoise": bool(e.sensor_noise), "allo:effects:glare": bool(e.glare),
                        "allo:effects:inspectionLight": bool(e.inspection_light),
                        "allo:effects:bodyShine": bool(e.body_shine)}.items():
        attr = settings.GetAttribute(name)
        if not attr:
            raise LayerError(f"render settings have no {name}; the base stage is out of date, regenerate it")
        attr.Set(value)
    commit_layer(layer, tmp, path)
    return path
