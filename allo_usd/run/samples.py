"""One camera sample of a plan, resolved and written: the unit of authoring work.

A camera sample is a normal scene, or the depths of one anomaly placement: its perturbation and
its ray-cast placement are resolved once and shared by its scenes. `AuthorContext` holds what that
takes (the plan's scene inputs: base stage, station BVH, sky), built once per process. The pool's
tasks (`author_samples`, `resolve_groups`), the top-up (allo_usd.run.topup) and `author_scene`
work through here. The top-up looks `write_sample` up in this module at each call, so a
replacement made here (a test that interrupts a run mid-sample) reaches every writer.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from allo_usd.core.errors import PlacementError, PlanError
from allo_usd.core.timefmt import format_utc
from allo_usd.plan.enumeration import SceneKey
from allo_usd.plan.model import Plan
from allo_usd.plan.settings import EffectsSpec, RenderSpec, quality_of
from allo_usd.usd.compose import TreeLinks, write_composed_scene, write_pose_layer, write_sky_layer
from allo_usd.usd.tree import hazard_asset_path, pose_layer_path, scene_layer_path, sky_layer_path


class AuthorContext:
    """What every worker needs, built once per process: the scene inputs (base stage, station BVH) and sky."""

    def __init__(self, plan: Plan, out_dir: Path, sky, stop=None):
        from allo_usd.core.constants import EXPOSURE
        from allo_usd.scene.resolve import sun_and_bodies
        from allo_usd.usd.stage_geometry import scene_inputs

        self.plan, self.out_dir, self.stop = plan, Path(out_dir), stop
        self.base_stage = plan.resolve_base_stage()
        # The plan's own hazards, converted into the tree by open_tree (allo_usd.usd.hazard.write_hazards).
        self.hazards = {c.id: hazard_asset_path(self.out_dir, c.id) for c in plan.anomalies.user_hazards()}
        self.inputs = scene_inputs(self.base_stage, sky, format_utc(plan.perilune_epoch), self.hazards,
                                   track_sun=plan.station.track_sun)
        self._add_file_poses(plan)
        self.inputs.lens, self.size = plan.camera_model()   # placement looks through the plan's camera
        q = plan.quality
        self.render = RenderSpec(resolution=tuple(q.resolution), preset=q.preset, exposure=EXPOSURE,
                                 passes=tuple(q.passes), **quality_of(q))
        self.effects = EffectsSpec(**plan.effects.model_dump())
        self._sky_cache: dict[int, tuple] = {}
        self._sun_and_bodies = sun_and_bodies
        self.links = TreeLinks()   # the relative paths written into scene layers, each directory resolved once

    def sky(self, day: int):
        if day not in self._sky_cache:
            self._sky_cache[day] = self._sun_and_bodies(self.inputs.sky, day)
        return self._sky_cache[day]

    def _add_file_poses(self, plan: Plan) -> None:
        """The plan's pose-file poses (numbers 51, ...) and perturbation sigmas, into the scene inputs."""
        from allo_usd.scene.resolve import file_camera_poses

        pose_file = plan.poses.pose_file()
        if pose_file is not None:
            self.inputs.extra_poses = file_camera_poses(pose_file, plan.poses.file_poses())
        self.inputs.sigmas = (plan.poses.position_sigma_m, plan.poses.angle_sigma_rad)

    def check_file_poses(self) -> None:
        """Refuse a pose-file pose inside the station or within rig.CLEARANCE_M of it (PlanError naming
        FILE:LINE, the pose and the fix), before anything is authored."""
        from allo_usd.scene.rig import CLEARANCE_M, too_close

        for p in self.inputs.extra_poses:
            if too_close(self.inputs.station_scene, p.position):
                x, y, z = (float(c) for c in p.position)
                raise PlanError(f"pose file {p.source}: pose {p.name!r} at ({x:g}, {y:g}, {z:g}) m is inside the "
                                f"station's geometry or within {CLEARANCE_M} m of it; fix: move it out into open "
                                "space (positions are metres in the stage frame, Z up)")

    def stopped(self) -> bool:
        return self.stop is not None and self.stop.is_set()

    def read_stage(self) -> None:
        """Read what scene resolution takes from the base stage now (its camera rig, the station's
        triangles, every anomaly asset variant of the plan), so a broken stage fails here, once,
        and not in the middle of a run or in a worker."""
        self.inputs.poses, self.inputs.station_parts  # noqa: B018 (cached properties, read now)
        for choice in self.plan.anomalies.assets:
            for asset, variant in choice.choices():
                self.inputs.anomaly_geometry(asset, variant)
        self.check_file_poses()


def ensure_sky_layer(ctx: AuthorContext, day: int) -> Path:
    """The shared sky layer of `day`, written if missing."""
    path = sky_layer_path(ctx.out_dir, day)
    if not path.exists():
        sun, bodies = ctx.sky(day)
        write_sky_layer(path, day=day, epoch=ctx.inputs.sky.epochs[day], perilune_epoch=ctx.inputs.perilune_epoch,
                        sun=sun, bodies=bodies, joints=ctx.inputs.joint_angles(day))
    return path


def _skip_row(key: SceneKey, reason: str) -> dict:
    return {"scene_id": key.scene_id, "seed": key.seed, "day": key.day, "pose": key.pose, "asset": key.asset,
            "variant": key.variant, "depth_index": key.depth_index, "reserve": key.reserve or None,
            "reason": reason}


@dataclass(frozen=True)
class Resolved:
    """One camera sample, resolved: its camera and seeds, and per depth index an AnomalySpec, the
    reason that depth is skipped (str), or None (a normal scene). Small enough to send between
    processes, so a reserve group is resolved in a worker and written by the parent."""

    camera: object
    seed: int
    seed_path: str
    results: dict


def resolve_sample(ctx: AuthorContext, keys: list[SceneKey]) -> Resolved:
    """Perturb the sample's camera and, for an anomaly, place the object at every depth."""
    from allo_usd.scene.resolve import resolve_camera, resolve_placements

    k0 = keys[0]
    anomaly = None if k0.asset is None else (k0.asset, k0.variant)
    camera, rng, seed, seed_path = resolve_camera(ctx.inputs, day=k0.day, pose=k0.pose, plan_seed=k0.seed,
                                                  anomaly=anomaly, reserve=k0.reserve)
    results: dict = {k.depth_index: None for k in keys}
    if anomaly is not None:
        try:
            results = dict(enumerate(resolve_placements(ctx.inputs, camera, rng, anomaly, ctx.render.resolution,
                                                            day=k0.day)))
        except PlacementError as exc:
            results = {k.depth_index: f"no initial placement: {exc}" for k in keys}
    return Resolved(camera, seed, seed_path, results)


def write_sample(ctx: AuthorContext, keys: list[SceneKey], resolved: Resolved) -> list[dict]:
    """Write the pose layer (once, if any of `keys` is authored) and the layers of `keys` that pass;
    returns the skipped rows of those that do not. Existing layers are kept (resume)."""
    from allo_usd.scene.resolve import build_spec

    rows, todo = [], []
    for key in keys:
        a = resolved.results[key.depth_index]
        if isinstance(a, str):
            rows.append(_skip_row(key, a))
        else:
            todo.append((key, a))
    if not todo:
        return rows
    k0 = keys[0]
    pose_path = pose_layer_path(ctx.out_dir, k0.seed, k0.sample_id)
    if not pose_path.exists():
        write_pose_layer(pose_path, pose=k0.pose, camera=resolved.camera, seed=resolved.seed,
                         seed_path=resolved.seed_path, sample_id=k0.sample_id)
    for key, a in todo:
        path = scene_layer_path(ctx.out_dir, key.split, key.kind, key.scene_id)
        if path.exists():
            continue
        spec = build_spec(ctx.inputs, scene_id=key.scene_id, day=key.day, pose=key.pose, seed=resolved.seed,
                          seed_path=resolved.seed_path, camera=resolved.camera, render=ctx.render,
                          effects=ctx.effects, anomaly=a, sky=ctx.sky(key.day))
        write_composed_scene(spec, path, pose_layer=pose_path, sky_layer=sky_layer_path(ctx.out_dir, key.day),
                             base_stage=ctx.base_stage, root=ctx.out_dir,
                             anomaly_asset=None if key.asset is None else ctx.hazards.get(key.asset), links=ctx.links)
    return rows


def author_sample(ctx: AuthorContext, keys: list[SceneKey]) -> tuple[int, list[dict]]:
    """Resolve one camera sample and write its pose layer and its scenes' layers.
    Returns (scenes handled, skipped rows)."""
    return len(keys), write_sample(ctx, keys, resolve_sample(ctx, keys))


def author_samples(ctx: AuthorContext, samples: list[list[SceneKey]]) -> tuple[int, list[dict]]:
    """A pool task: author planned samples (stops early when the parent asks)."""
    done, skipped = 0, []
    for keys in samples:
        if ctx.stopped():
            break
        n, s = author_sample(ctx, keys)
        done, skipped = done + n, skipped + s
    return done, skipped


def resolve_groups(ctx: AuthorContext, groups: list[tuple[tuple, int, list[SceneKey]]]) -> list[tuple]:
    """A pool task: resolve reserve groups without writing; [(sav, k, Resolved)] (a prefix when stopped)."""
    out = []
    for sav, k, keys in groups:
        if ctx.stopped():
            break
        out.append((sav, k, resolve_sample(ctx, keys)))
    return out
