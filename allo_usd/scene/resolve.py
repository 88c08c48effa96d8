"""Resolve scenes: sky for a day + perturbed pose + (optional) placed anomaly -> SceneSpec.

Everything random happens here, from an explicit numpy Generator seeded per scene, before
anything is authored. Station and anomaly geometry for the checks is read from the base
stage, so the checks see exactly what the renderer will see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol

import numpy as np

from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.labels import STATION
from allo_usd.core.errors import PlacementError
from allo_usd.scene.placement import anomaly_scene, place
from allo_usd.scene.raycast import RayScene
from allo_usd.scene.rig import ANGLE_SIGMA_RAD, PERTURBATION, POSITION_SIGMA_M, perturb
from allo_usd.scene.spec import AnomalySpec, BodySpec, CameraPose, CameraSpec, SceneSpec, SunSpec
from allo_usd.plan.settings import EffectsSpec, RenderSpec
from allo_usd.core.seeds import scene_seed
from allo_usd.core import fixedmath as fm


DAY_SCENES_KEPT = 4   # posed station BVHs SceneInputs keeps (~0.1 s to build each)


class StationGeometry(Protocol):
    """Where the base stage's geometry comes from: allo_usd.usd.stage_geometry.StageGeometry reads it from a
    base stage; anything else that answers these three calls will do (the scene layer reads no USD)."""

    def poses(self) -> list: ...                                        # CameraPose, pose numbers 1..50

    # (points, triangles), world frame; `angles` {joint name: degrees} poses the station's joints (rest if None)
    def station_triangles(self, angles: dict[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]: ...

    def anomaly_triangles(self, asset: str, variant: str) -> tuple[np.ndarray, np.ndarray]: ...  # asset frame


@dataclass
class SceneInputs:
    """What resolving a scene needs, loaded once and shared by every scene of a run: the base
    poses, the station's ray-casting BVH, each anomaly's mesh and BVH, and the sky. With `track_sun`
    (the plan's station.track_sun) the station's arrays face each day's Sun: `station_scene_on(day)`
    is then that day's posed station (the camera rig's base poses were chosen at rest)."""

    geometry: StationGeometry
    sky: object                 # allo_usd.sky.model.Sky
    perilune_epoch: str
    track_sun: bool = False
    _anomaly_cache: dict = field(default_factory=dict)
    extra_poses: list = field(default_factory=list)   # a plan's pose-file poses (CameraPose, numbers 51, ...)
    sigmas: tuple[float, float] = (POSITION_SIGMA_M, ANGLE_SIGMA_RAD)   # the plan's perturbation
    _day_scenes: dict = field(default_factory=dict)
    lens: CameraModel = DEFAULT_CAMERA   # the plan's camera: placement's visibility checks look through it

    @cached_property
    def poses(self):
        return {p.index: p for p in [*self.geometry.poses(), *self.extra_poses]}

    @cached_property
    def station_parts(self):
        pts, tris = self.geometry.station_triangles()
        return [(pts, tris, STATION)]

    @cached_property
    def station_scene(self) -> RayScene:
        return RayScene(self.station_parts)

    def joint_angles(self, day: int) -> dict[str, float] | None:
        """The station's joint angles on `day` (degrees, allo_usd.scene.tracking), or None (rest) when
        the plan does not track the Sun."""
        if not self.track_sun:
            return None
        from allo_usd.scene.tracking import sun_tracking_angles

        return sun_tracking_angles(sun_and_bodies(self.sky, day)[0].direction)

    def station_scene_on(self, day: int | None) -> RayScene:
        """The station's BVH as it is posed on `day` (the rest pose without tracking or day); the last
        few days' are kept (a day's scenes are authored together)."""
        angles = None if day is None else self.joint_angles(day)
        if angles is None:
            return self.station_scene
        if day not in self._day_scenes:
            while len(self._day_scenes) >= DAY_SCENES_KEPT:
                self._day_scenes.pop(next(iter(self._day_scenes)))
            pts, tris = self.geometry.station_triangles(angles)
            self._day_scenes[day] = RayScene([(pts, tris, STATION)])
        return self._day_scenes[day]

    def anomaly_geometry(self, asset: str, variant: str):
        key = (asset, variant)
        if key not in self._anomaly_cache:
            self._anomaly_cache[key] = self.geometry.anomaly_triangles(asset, variant)
        return self._anomaly_cache[key]

    def anomaly_scene(self, asset: str, variant: str):
        """(centred points, triangles, centre, BVH in the object's own frame), built once per asset variant."""
        key = ("scene", asset, variant)
        if key not in self._anomaly_cache:
            pts, tris = self.anomaly_geometry(asset, variant)
            centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
            self._anomaly_cache[key] = (pts - centre, tris, centre, anomaly_scene(pts - centre, tris))
        return self._anomaly_cache[key]


def file_camera_poses(pose_file, numbered) -> list[CameraPose]:
    """The scene layer's CameraPoses of a plan's pose file (allo_usd.plan.posefile.PoseFile) and its
    (pose number, UserPose) pairs (allo_usd.plan.model.Poses.file_poses)."""
    return [CameraPose(n, p.split, np.array(p.position, dtype=np.float64), p.rotation(), p.name,
                       pose_file.source(p), pose_file.sha256) for n, p in numbered]


def sun_and_bodies(sky, day: int) -> tuple[SunSpec, dict[str, BodySpec]]:
    """The station's sun lamp, and each body with its place and (Earth, Moon) its own sun lamp."""
    from allo_usd.sky.model import body_placement, body_sun_light, sun_light

    at = sky.at(day)
    light = sun_light(at)
    sun = SunSpec(tuple(map(float, light["direction_to_sun"])), float(light["irradiance_w_m2"]),
                  float(at.sun_irradiance_w_m2), math.degrees(float(light["angular_diameter_rad"])),
                  float(at.distance_m["sun"]), float(light["lit_fraction"]), str(light["state"]),
                  str(at.eclipse_body or "none"))
    lamps = {name: SunSpec(tuple(map(float, b["direction_to_sun"])), float(b["irradiance_w_m2"]),
                           float(b["irradiance_unoccluded_w_m2"]), math.degrees(b["angular_diameter_rad"]),
                           float(b["distance_m"]), float(b["lit_fraction"]), str(b["state"]),
                           str(b["eclipse_body"] or "none"))
             for name, b in body_sun_light(at).items()}
    bodies = {name.capitalize(): BodySpec(tuple(map(float, pos)), float(radius), lamps.get(name),
                                          tuple(map(float, at.geometric_direction[name])))
              for name, (pos, radius) in body_placement(at).items()}
    return sun, bodies


def resolve_camera(inputs: SceneInputs, *, day: int, pose: int, plan_seed: int,
                   anomaly: tuple[str, str] | None = None, reserve: int = 0):
    """The perturbed camera of one pose sample: (CameraSpec, the Generator after the draw, seed,
    seed path). Every scene of the sample (the five depths of a placement) shares it. `reserve`
    k >= 1: the k-th reserve group of the plan's top-up (allo_usd.plan.enumeration.reserve_group), a draw of its own."""
    base = inputs.poses[pose]
    key = (day, pose) if anomaly is None else (day, pose, *anomaly)
    if reserve:
        key = (*key, f"r{reserve}")
    seed, seed_path = scene_seed(plan_seed, *key)
    rng = np.random.default_rng(seed)
    try:
        pos, rot, dpos, dang, attempts = perturb(base, rng, inputs.station_scene_on(day),
                                                 position_sigma_m=inputs.sigmas[0], angle_sigma_rad=inputs.sigmas[1])
    except PlacementError as exc:   # say which day, and why a pose that was clear may not be on it
        where = f"; it is {base.name!r} of the pose file {base.source}" if base.source else ""
        turning = (" with the solar arrays turned to that day's Sun (station.track_sun): a wing may sweep through "
                   "the pose; move it, or set a position sigma above 0") if inputs.track_sun else ""
        raise PlacementError(f"day {day}: {exc}{where}{turning}") from None
    sigmas = None if tuple(inputs.sigmas) == (POSITION_SIGMA_M, ANGLE_SIGMA_RAD) else tuple(map(float, inputs.sigmas))
    camera = CameraSpec(tuple(map(float, pos)), rot, tuple(map(float, dpos)), tuple(map(float, dang)),
                        PERTURBATION, attempts, sigmas, base.name, base.source, base.source_sha256)
    return camera, rng, seed, seed_path


def resolve_placements(inputs: SceneInputs, camera: CameraSpec, rng: np.random.Generator, anomaly: tuple[str, str],
                       resolution: tuple[int, int], day: int | None = None) -> list[AnomalySpec | str]:
    """All five depths of one placement from one ray-cast search (`placement.place`: candidates are
    redrawn until all five depths pass, screened at 480 px wide and confirmed at `resolution`): an
    AnomalySpec per depth, with the fraction of the image it covers at `resolution`, or the reason
    that depth was skipped. Raises PlacementError when no initial placement is found.
    `day`: the station as posed that day (SceneInputs.station_scene_on; None: at rest)."""
    pts, tris, centre, scene = inputs.anomaly_scene(*anomaly)
    pos = np.asarray(camera.position, dtype=np.float64)
    placements = place(inputs.station_scene_on(day), pts, tris, pos, camera.rotation, rng, resolution[0], resolution[1],
                       anomaly=scene, lens=inputs.lens)
    out = []
    for p in placements:
        if p.position is None:
            out.append(f"depth {p.depth_index} ({p.depth_offset:+.0f} m) was skipped: {p.skipped_reason}")
            continue
        # The asset's own origin is its bounding-box centre, so the placed centre is the prim position.
        out.append(AnomalySpec(anomaly[0], anomaly[1], tuple(map(float, p.position - fm.matmul(p.rotation, centre))),
                               p.rotation, p.depth_index, p.depth_offset, p.attempts, p.area_fraction))
    return out


def build_spec(inputs: SceneInputs, *, scene_id: str, day: int, pose: int, seed: int, seed_path: str,
               camera: CameraSpec, render: RenderSpec, effects: EffectsSpec,
               anomaly: AnomalySpec | None = None, sky: tuple | None = None) -> SceneSpec:
    """Assemble a SceneSpec from resolved parts (`sky`: a precomputed sun_and_bodies result)."""
    sun, bodies = sky if sky is not None else sun_and_bodies(inputs.sky, day)
    render = RenderSpec(**{**render.__dict__, "seed": seed % (2 ** 31)})
    return SceneSpec(scene_id, inputs.sky.epochs[day], inputs.perilune_epoch, day, pose, inputs.poses[pose].split,
                     seed, seed_path, camera, sun, bodies, render, effects, anomaly, lens=inputs.lens)


def resolve_scene(inputs: SceneInputs, *, scene_id: str, day: int, pose: int, plan_seed: int,
                  render: RenderSpec, effects: EffectsSpec = EffectsSpec(),
                  anomaly: tuple[str, str] | None = None, depth_index: int = 0, reserve: int = 0) -> SceneSpec:
    """One fully resolved scene. With an anomaly, its five depths share the same draw, so depth k of
    the same (day, pose, anomaly) differs only by the offset along the view ray."""
    camera, rng, seed, seed_path = resolve_camera(inputs, day=day, pose=pose, plan_seed=plan_seed, anomaly=anomaly,
                                                  reserve=reserve)
    anomaly_spec = None
    if anomaly is not None:
        chosen = resolve_placements(inputs, camera, rng, anomaly, render.resolution, day=day)[depth_index]
        if isinstance(chosen, str):
            raise PlacementError(f"scene {scene_id}: {chosen}")
        anomaly_spec = chosen
    return build_spec(inputs, scene_id=scene_id, day=day, pose=pose, seed=seed, seed_path=seed_path,
                      camera=camera, render=render, effects=effects, anomaly=anomaly_spec)
