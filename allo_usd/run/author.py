"""Author a whole plan: resolve every scene, write shared layers once and scene layers atomically.

The unit of work is one camera sample (a normal scene, or the depths of one anomaly placement):
its perturbation and its ray-cast placement are resolved once and shared by its scenes. The sky
is computed once for all plan days (one vectorised `compute_sky`). Samples go to a local process
pool (2 workers by default for large plans) in chunks. Authoring resumes: a scene whose layer
exists, or that skipped.csv already lists, is not redone. Ctrl-C stops at the next file boundary;
every file is written under a temporary name and renamed, so no partial file is left.

Top-up. Each (plan seed, asset, variant) must reach its planned number of anomalous images (its
quota), so every hazard class keeps its share when the placement check skips depths. Once the
planned placements are authored, each shortfall is filled from reserve groups of the same asset
and variant (`allo_usd.plan.enumeration.reserve_group`), taken strictly in order k = 1, 2, ...: a reserve
group's depths are used in depth order while images are still missing, a depth that fails is
listed in skipped.csv (with its reserve number), and depths not needed are neither authored nor
listed. Reserve placements are computed on the pool in batches, ahead of need (some are computed
and thrown away), but decided in order in the parent, so the tree is a function of the plan
alone: not of the worker count, the chunking, or interruptions. A (seed, asset, variant) draws
at most `plan.reserve_cap` groups; what is still missing then is reported (counts.csv, the CLI
summary). reserves.csv records each used reserve group's decided depths, so a resumed run reuses
them instead of recomputing.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import time
from collections import Counter, deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager, suppress
from dataclasses import asdict, dataclass, field
from itertools import groupby, islice
from pathlib import Path

from allo_usd.usd.compose import TreeLinks, write_composed_scene, write_pose_layer, write_sky_layer
from allo_usd.usd.tree import (BASE_STAGE_FILE, COUNTS_CSV, LAYER_DIRS, POSE_INPUTS, RESERVES_CSV, SKIPPED_CSV,
                               STAGE_DIR, STATION_MARKER, TREE_ENTRIES, TREE_LOCK, TREE_PLAN, existing_scene_ids,
                               hazard_asset_path, pose_layer_path, scene_layer_path, sky_layer_path, tree_base_stage)
from allo_usd.core.camera_model import DEFAULT_CAMERA
from allo_usd.core.files import atomic_directory, file_problem, write_text_atomic
from allo_usd.core.provenance import record_tree_versions
from allo_usd.core.errors import AlloError, DiskFullError, LayerError, PlacementError, PlanError
from allo_usd.core.timefmt import format_utc
from allo_usd.plan.model import Plan
from allo_usd.plan.enumeration import (SceneKey, anomaly_quotas, iter_scenes, reserve_cap,
                                       reserve_group)
from allo_usd.plan.io import save_plan
from allo_usd.plan.settings import EffectsSpec, RenderSpec, quality_of

SKIPPED_FIELDS = ("scene_id", "seed", "day", "pose", "asset", "variant", "depth_index", "reserve", "reason")
RESERVE_FIELDS = ("seed", "asset", "variant", "reserve", "day", "pose", "authored", "skipped")
COUNT_FIELDS = ("split", "kind", "asset", "planned", "authored", "skipped", "reserve_groups", "from_reserve",
                "short")
CHUNK_SAMPLES = 48         # planned anomaly placements per pool task
CHUNK_NORMAL = 256         # normal camera samples per pool task
CHUNK_RESERVE = 1          # reserve groups per pool task (each walk decides as soon as one is back)

_ctx = None  # the per-process authoring context (set by _init)


class AuthorContext:
    """What every worker needs, built once per process: the scene inputs (base stage, station BVH) and sky."""

    def __init__(self, plan: Plan, out_dir: Path, sky, stop=None):
        from allo_usd.core.constants import EXPOSURE
        from allo_usd.scene.resolve import sun_and_bodies
        from allo_usd.usd.read import scene_inputs

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


def _init(plan_json: str, out_dir: str, sky, stop) -> None:
    global _ctx
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and tells us through `stop`
    _ctx = AuthorContext(Plan.model_validate_json(plan_json), Path(out_dir), sky, stop)


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


# ---------------------------------------------------------------------------------------------
# One camera sample: resolve (all randomness, ray casting), then write


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


def _author_samples(ctx: AuthorContext, samples: list[list[SceneKey]]) -> tuple[int, list[dict]]:
    """A pool task: author planned samples (stops early when the parent asks)."""
    done, skipped = 0, []
    for keys in samples:
        if ctx.stopped():
            break
        n, s = author_sample(ctx, keys)
        done, skipped = done + n, skipped + s
    return done, skipped


def _resolve_groups(ctx: AuthorContext, groups: list[tuple[tuple, int, list[SceneKey]]]) -> list[tuple]:
    """A pool task: resolve reserve groups without writing; [(sav, k, Resolved)] (a prefix when stopped)."""
    out = []
    for sav, k, keys in groups:
        if ctx.stopped():
            break
        out.append((sav, k, resolve_sample(ctx, keys)))
    return out


def _in_worker(fn, *args):
    return fn(_ctx, *args)


# ---------------------------------------------------------------------------------------------
# Records: skipped.csv, reserves.csv, counts.csv


def _write_csv(path: Path, fields: tuple, rows: list[dict]) -> Path:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row[k]) for k in fields})
    return write_text_atomic(path, buf.getvalue())


def read_skipped(path: Path) -> dict[str, dict]:
    if not path.is_file():
        return {}
    with open(path, newline="") as fh:
        return {row["scene_id"]: row for row in csv.DictReader(fh)}


def write_skipped(path: Path, rows: dict[str, dict]) -> Path:
    return _write_csv(path, SKIPPED_FIELDS, [rows[sid] for sid in sorted(rows)])


def _depth_list(text: str) -> tuple[int, ...]:
    return tuple(int(z) for z in str(text or "").split())


def read_reserves(path: Path) -> dict[tuple, dict]:
    """reserves.csv by (seed, asset, variant, k): the group's (day, pose) and its decided depths."""
    if not path.is_file():
        return {}
    out = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            out[(int(row["seed"]), row["asset"], row["variant"], int(row["reserve"]))] = {
                "day": int(row["day"]), "pose": int(row["pose"]),
                "authored": _depth_list(row["authored"]), "skipped": _depth_list(row["skipped"])}
    return out


def write_reserves(path: Path, entries: dict[tuple, dict]) -> Path:
    rows = [{"seed": s, "asset": a, "variant": v, "reserve": k, "day": e["day"], "pose": e["pose"],
             "authored": " ".join(map(str, e["authored"])), "skipped": " ".join(map(str, e["skipped"]))}
            for (s, a, v, k), e in entries.items()]
    return _write_csv(path, RESERVE_FIELDS, rows)


def read_counts(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


# ---------------------------------------------------------------------------------------------
# The top-up


@dataclass
class _Walk:
    """The reserve groups of one (seed, asset, variant), decided strictly in order."""

    sav: tuple
    need: int                 # images still missing
    cap: int                  # reserve groups it may use
    next_k: int = 1           # the next group to decide
    ahead: int = 0            # the highest group asked of the pool (or found in reserves.csv)
    inflight: set = field(default_factory=set)      # groups asked of the pool, not back yet
    results: dict = field(default_factory=dict)     # k -> Resolved, computed and not yet decided
    entries: dict = field(default_factory=dict)     # k -> {"day", "pose", "authored", "skipped"}: decided
    authored: list = field(default_factory=list)    # SceneKeys authored from reserves

    @property
    def open(self) -> bool:
        return self.need > 0 and self.next_k <= self.cap


class _TopUp:
    """Every (seed, asset, variant)'s walk. `advance` decides every group it can (computed, or
    recorded in reserves.csv and present on disk) and writes its layers; `next_task` names the
    groups the pool should resolve next. Decisions depend only on each walk's groups in order, so
    how far ahead the pool computes, or which task finishes first, changes nothing written."""

    def __init__(self, ctx: AuthorContext, keys: list[SceneKey], skipped: dict, ledger: dict, bar):
        self.ctx, self.plan, self.skipped, self.ledger, self.bar = ctx, ctx.plan, skipped, ledger, bar
        self.depths = list(self.plan.anomalies.depths)
        self.quotas = anomaly_quotas(keys)
        anomalous = [k for k in keys if k.kind == "anomaly"]
        lost = Counter((k.seed, k.asset, k.variant) for k in anomalous if k.scene_id in skipped)
        self.walks = {sav: _Walk(sav, lost[sav], reserve_cap(self.plan, lost[sav])) for sav in self.quotas}
        # The expected images per reserve group, from the planned groups' yield of the same asset:
        # how many groups to compute ahead (a guess; it changes only how much work is thrown away).
        planned, passed = Counter(), Counter()
        for k in anomalous:
            planned[k.asset] += 1
            passed[k.asset] += k.scene_id not in skipped
        self.per_group = {a: max(1.0, len(self.depths) * passed[a] / planned[a]) for a in planned}
        self._turn = 0
        self.resolved = 0     # reserve groups resolved by the pool in this run (used or not)

    def _keys(self, walk: _Walk, k: int) -> list[SceneKey]:
        return reserve_group(self.plan, *walk.sav, k)

    def _from_ledger(self, walk: _Walk, keys: list[SceneKey]):
        """The decided depths of group k from reserves.csv, if they settle it with everything they
        authored on disk and everything they skipped in skipped.csv; else None (compute it)."""
        entry = self.ledger.get((*walk.sav, keys[0].reserve))
        if entry is None or (entry["day"], entry["pose"]) != (keys[0].day, keys[0].pose):
            return None
        outcome = {**{z: True for z in entry["authored"]}, **{z: False for z in entry["skipped"]}}
        need, used = walk.need, []
        for key in keys:
            if need == 0:
                break
            if key.depth_index not in outcome:
                return None
            ok = outcome[key.depth_index]
            if ok and not scene_layer_path(self.ctx.out_dir, key.split, key.kind, key.scene_id).exists():
                return None
            if not ok and key.scene_id not in self.skipped:
                return None
            used.append((key, ok))
            need -= ok
        return used

    def _decide(self, walk: _Walk, keys: list[SceneKey], used: list[tuple[SceneKey, bool]]) -> None:
        authored = [key for key, ok in used if ok]
        walk.need -= len(authored)
        walk.authored += authored
        walk.entries[keys[0].reserve] = {"day": keys[0].day, "pose": keys[0].pose,
                                        "authored": tuple(k.depth_index for k in authored),
                                        "skipped": tuple(k.depth_index for k, ok in used if not ok)}
        self.bar.update(len(authored))

    def advance(self) -> None:
        for walk in self.walks.values():
            while walk.open:
                keys = self._keys(walk, walk.next_k)
                resolved = walk.results.pop(walk.next_k, None)
                if resolved is not None:
                    used, need = [], walk.need
                    for key in keys:
                        if need == 0:
                            break
                        ok = not isinstance(resolved.results[key.depth_index], str)
                        used.append((key, ok))
                        need -= ok
                    ensure_sky_layer(self.ctx, keys[0].day)   # a reserve may fall on a day the plan's
                    rows = write_sample(self.ctx, [key for key, _ in used], resolved)  # scenes do not use
                    self.skipped.update({r["scene_id"]: r for r in rows})
                else:
                    used = self._from_ledger(walk, keys)
                    if used is None:
                        break
                self._decide(walk, keys, used)
                walk.next_k += 1
            if not walk.open:
                walk.results.clear()

    def next_task(self, chunk: int) -> list[tuple] | None:
        """Up to `chunk` groups for the pool to resolve, or None: the walks take turns, and each asks
        for the group it waits on and for more only while the groups it has in hand are not expected,
        at its asset's planned yield, to cover what it still misses (so few are thrown away)."""
        walks = [w for w in self.walks.values() if w.open]
        for i in range(len(walks)):
            walk = walks[(self._turn + i) % len(walks)]
            ks = self._more(walk, chunk)
            if ks:
                self._turn = (self._turn + i + 1) % len(walks)
                walk.inflight.update(ks)
                return [(walk.sav, k, self._keys(walk, k)) for k in ks]
        return None

    def _more(self, walk: _Walk, chunk: int) -> list[int]:
        ks = []
        walk.ahead = max(walk.ahead, walk.next_k - 1)
        if walk.next_k not in walk.results and walk.next_k not in walk.inflight:
            ks.append(walk.next_k)                   # the group it waits on (not settled by reserves.csv)
            walk.ahead = max(walk.ahead, walk.next_k)
        per_group = self.per_group[walk.sav[1]]
        while len(ks) < chunk and walk.ahead < walk.cap and \
                (len(walk.inflight) + len(walk.results) + len(ks)) * per_group < walk.need:
            walk.ahead += 1
            if (*walk.sav, walk.ahead) not in self.ledger:   # recorded groups are most likely settled
                ks.append(walk.ahead)
        return ks

    def receive(self, results: list[tuple]) -> None:
        self.resolved += len(results)
        for sav, k, resolved in results:
            walk = self.walks[sav]
            walk.inflight.discard(k)
            if walk.open and k >= walk.next_k:
                walk.results[k] = resolved

    @property
    def need(self) -> int:
        return sum(w.need for w in self.walks.values())

    def entries(self) -> dict[tuple, dict]:
        return {(*sav, k): e for sav, w in self.walks.items() for k, e in sorted(w.entries.items())}

    def authored(self) -> list[SceneKey]:
        return [key for w in self.walks.values() for key in w.authored]


def count_rows(plan: Plan, keys: list[SceneKey], skipped: dict, topup: _TopUp | None) -> list[dict]:
    """counts.csv: planned vs authored scenes per (split, kind), and per anomaly asset."""
    walks = topup.walks if topup is not None else {}
    rows = []
    for split, kind in (("train", "normal"), ("test", "normal"), ("test", "anomaly")):
        mine = [k for k in keys if (k.split, k.kind) == (split, kind)]
        lost = sum(k.scene_id in skipped for k in mine)
        groups = sum(len(w.entries) for w in walks.values()) if kind == "anomaly" else 0
        extra = sum(len(w.authored) for w in walks.values()) if kind == "anomaly" else 0
        rows.append({"split": split, "kind": kind, "asset": "", "planned": len(mine),
                     "authored": len(mine) - lost + extra, "skipped": lost, "reserve_groups": groups,
                     "from_reserve": extra, "short": len(mine) - (len(mine) - lost + extra)})
    per_asset: dict[str, Counter] = {}
    for k in keys:
        if k.kind == "anomaly":
            c = per_asset.setdefault(k.asset, Counter())
            c["planned"] += 1
            c["skipped"] += k.scene_id in skipped
    for (_, asset, _), w in walks.items():
        per_asset[asset]["reserve_groups"] += len(w.entries)
        per_asset[asset]["from_reserve"] += len(w.authored)
    for asset, c in per_asset.items():
        authored = c["planned"] - c["skipped"] + c["from_reserve"]
        rows.append({"split": "test", "kind": "anomaly", "asset": asset, "planned": c["planned"],
                     "authored": authored, "skipped": c["skipped"], "reserve_groups": c["reserve_groups"],
                     "from_reserve": c["from_reserve"], "short": c["planned"] - authored})
    return rows


def summary_lines(counts: list[dict], topup: bool = True) -> list[str]:
    """Planned vs authored, one line per (split, kind), and a line per asset left short (SHORT when
    the top-up ran out of reserve groups; a plain note when the plan turned the top-up off)."""
    lines = []
    for r in counts:
        if r["asset"]:
            continue
        line = f"{r['split']}/{r['kind']}: {int(r['authored']):,} of {int(r['planned']):,} planned authored"
        if r["kind"] == "anomaly":
            line += (f" ({int(r['skipped']):,} planned depths skipped, {int(r['from_reserve']):,} topped up from "
                     f"{int(r['reserve_groups']):,} reserve groups)")
        lines.append(line)
    short = [r for r in counts if r["asset"] and int(r["short"]) > 0]
    for r in short:
        if not topup:
            lines.append(f"{r['asset']}: {int(r['authored']):,} of {int(r['planned']):,} ({int(r['short']):,} skipped "
                         "depths not replaced: the plan turns the top-up off, anomalies.reserve_groups_per_slot = 0)")
            continue
        lines.append(f"SHORT: {r['asset']}: {int(r['authored']):,} of {int(r['planned']):,} "
                     f"({int(r['short']):,} missing: it used every reserve group the top-up bound allows, "
                     f"{int(r['reserve_groups']):,}, see {RESERVES_CSV}; fix: raise anomalies.reserve_groups_per_slot, "
                     f"or leave this asset out of the plan)")
    return lines


# ---------------------------------------------------------------------------------------------
# Authoring a plan


def rig_notes(ctx: AuthorContext) -> list[str]:
    """One line per base pose the plan uses whose view does not qualify (rig.view_quality) under the
    plan's camera: the built-in rig was chosen for the paper's Table I camera. Empty for that camera."""
    from allo_usd.scene.rig import view_quality

    lens = ctx.inputs.lens
    if lens == DEFAULT_CAMERA:
        return []
    out = []
    for index in (*ctx.plan.poses.train, *ctx.plan.poses.test):
        pose = ctx.inputs.poses[index]
        q = view_quality(ctx.inputs.station_scene, pose.position, pose.rotation, lens=lens, size=ctx.size)
        if not q.ok:
            out.append(f"base pose {index}'s view does not qualify under the plan's camera "
                       f"({lens.focal_length_mm:g} mm on {lens.sensor_width_mm:g} mm): optical axis meets structure "
                       f"at {q.centre_m:.3g} m, {q.coverage:.0%} of the frame shows structure, {q.in_range:.0%} of "
                       f"it 5-40 m away, {q.near:.0%} nearer than 5 m (the rig was chosen for Table I)")
    return out


def with_tree_stage(plan: Plan, out_dir: Path) -> Plan:
    """The plan, pointed at the output tree's own base stage `out_dir/stages/base.usda`, made before
    any worker starts. A procedural station's tree gets a byte copy of the plan's base stage and its
    assets; a station that is a model file gets a base stage built from it (into a temporary
    directory, then renamed, with `stages/station_source.json` naming the file and its sha256; a tree
    built from another station is refused). Scene layers then refer only to files inside the tree,
    so the tree can be moved or copied as a whole and re-authoring elsewhere gives the same bytes
    (for a model-built stage, on machines whose OpenBLAS rounds alike: scripts/make_base_stage.py
    pins that kernel for the committed stage)."""
    from allo_usd.usd.compose import copy_base_stage

    base = tree_base_stage(out_dir)
    if plan.station.source == "procedural":
        copy_base_stage(plan.resolve_base_stage(), out_dir)
        return plan.model_copy(update={"base_stage": str(base.resolve())})
    source = Path(plan.station.source)
    problem = file_problem(source, 1 << 40)   # missing, unreadable, a name too long, not a regular file
    if problem:
        raise PlanError(f"station.source: {str(source)[:200]} {problem}; fix: give the path of a glTF/OBJ/STL "
                        "model, or 'procedural'")
    from allo_usd.core.files import sha256_file

    made_from = {"source": source.name, "sha256": sha256_file(source), "units": plan.station.units,
                 "up_axis": plan.station.up_axis}
    lens, size = plan.camera_model()   # the rig scores its views through the plan's camera
    if lens != DEFAULT_CAMERA:
        made_from["camera"] = {**asdict(lens), "resolution": list(size)}
    marker = base.parent / STATION_MARKER
    if base.is_file():
        recorded = json.loads(marker.read_text()) if marker.is_file() else None
        if recorded != made_from:
            raise PlanError(f"{base.parent} was built from {recorded or 'another station'}, not from {made_from}; "
                            f"fix: author this plan into a new output directory (or delete that {STAGE_DIR}/ folder)")
    else:
        from allo_usd.usd.build_stage import build_base_stage

        with atomic_directory(base.parent) as tmp:  # replaces an incomplete build of an older version
            build_base_stage(tmp, str(source), plan.station.units, plan.station.up_axis, lens, size)
            (tmp / STATION_MARKER).write_text(json.dumps(made_from, indent=1, sort_keys=True) + "\n")
    return plan.model_copy(update={"base_stage": str(base.resolve())})


class AuthoringInterrupted(PlanError):
    """Ctrl-C stopped authoring; finished layers are kept (the CLI exits 130)."""


@dataclass(frozen=True)
class Authored:
    """What `author` made: the scene layers (planned ones first, then the reserves in order) and the
    planned vs authored counts written to counts.csv."""

    paths: list[Path]
    counts: list[dict]
    reserve_resolved: int = 0   # reserve groups resolved in this run, including any not needed in the end

    @property
    def short(self) -> dict[str, int]:
        """Images still missing per anomaly asset (empty when every quota was met)."""
        return {r["asset"]: int(r["short"]) for r in self.counts if r["asset"] and int(r["short"]) > 0}


# ---------------------------------------------------------------------------------------------
# The tree: one writer at a time, the plan it was made from, a readable base stage

_TRASH = re.compile(r"^\.replaced\.[a-z0-9_]{8}$")   # a replace's trash (mkdtemp), left if the run was killed
# Plan fields the tree checks by content, not by name: the base stage's path and the station's
# source (stages/ must be a byte copy of the plan's stage, or built from the same model file).
# `render.device` is not compared at all: it says how to render, not what (plan.model.Render);
# any other field of `render` is compared like the rest.
UNCOMPARED = {"base_stage": True, "station": True, "render": {"device"}}


@contextmanager
def tree_lock(out_dir: Path):
    """Hold the tree's lock (RunLock on `TREE_LOCK`) for the block. The holder writes its pid into
    the lock file and empties it on release (so a finished tree's bytes do not depend on who
    wrote it); a second run is refused with one line naming the holder."""
    from allo_usd.core.errors import AlloError
    from allo_usd.core.files import RunLock

    lock = RunLock(out_dir, TREE_LOCK, "author")
    try:
        lock.__enter__()
    except AlloError:
        holder = ""
        try:
            holder = lock.path.read_text().strip()
        except OSError:
            pass
        raise AlloError(f"another author run{f' ({holder})' if holder else ''} is writing to {Path(out_dir)}; "
                        f"wait for it to finish, then re-run to resume (or stop it), or author into "
                        f"another --out") from None
    try:
        os.ftruncate(lock.fd, 0)
        os.pwrite(lock.fd, f"pid {os.getpid()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode(), 0)
        yield
    finally:
        try:
            os.ftruncate(lock.fd, 0)
        finally:
            lock.__exit__(None, None, None)


def plan_fields(plan: Plan) -> dict:
    """The plan as flat `section.field` -> value (JSON types), the fields a tree compares."""
    flat = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict):
            for k in sorted(value):
                walk(f"{prefix}.{k}" if prefix else k, value[k])
        else:
            flat[prefix] = value

    walk("", plan.model_dump(mode="json", exclude=UNCOMPARED))
    return flat


def _shown(field: str, value) -> str:
    if field == "quality.resolution" and isinstance(value, list) and len(value) == 2:
        return f"{value[0]}x{value[1]}"
    return json.dumps(value, separators=(",", ":"))


def plan_differences(recorded: Plan, given: Plan) -> list[str]:
    """'field RECORDED in the tree, GIVEN in this plan' for each field where the plans differ (the
    validated models, so formatting, field order and omitted defaults do not count)."""
    a, b = plan_fields(recorded), plan_fields(given)
    return [f"{k} {_shown(k, a.get(k))} in the tree, {_shown(k, b.get(k))} in the plan given"
            for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def _refuse(out_dir: Path, why: str) -> PlanError:
    return PlanError(f"{out_dir} {why}; fix: author into a fresh --out, or pass --replace (replace=True) to "
                     f"delete this tree's layers and author the plan given")


def check_tree_plan(plan: Plan, out_dir: Path) -> bool:
    """Refuse to author `plan` into a tree made from another plan; True if the tree already records
    this plan (then plan.toml is kept as first written). `--limit` is not part of the plan, so the
    same plan with another limit resumes."""
    from allo_usd.plan.io import load_plan

    record = out_dir / TREE_PLAN
    if not record.is_file():
        found = [n for n in LAYER_DIRS if (out_dir / n).is_dir()]
        if found:
            raise _refuse(out_dir, f"holds authored layers ({', '.join(found)}/) but no {TREE_PLAN}, so the plan "
                                   "they were made from is unknown")
        return False
    try:
        recorded = load_plan(record)
    except PlanError as exc:
        raise _refuse(out_dir, f"records its plan in {record}, which cannot be read "
                               f"({str(exc).splitlines()[0]})") from None
    diff = plan_differences(recorded, plan)
    if diff:
        more = f" (and {len(diff) - 1} more: {'; '.join(diff[1:4])}{'; ...' if len(diff) > 4 else ''})" \
            if len(diff) > 1 else ""
        raise _refuse(out_dir, f"was authored from another plan: {diff[0]}{more}")
    return True


def replace_tree(out_dir: Path) -> list[str]:
    """Remove what authoring wrote under `out_dir` (TREE_ENTRIES; plan.toml is rewritten after),
    nothing else: each entry is renamed into one hidden trash directory (a symlink moves as a
    link, its target untouched), which is then deleted. Only a folder that is a tree (plan.toml or
    stages/base.usda at its top) is touched. Returns the names removed."""
    out_dir = Path(out_dir)
    for stale in out_dir.iterdir():   # a replace killed before it emptied its trash
        if _TRASH.match(stale.name) and stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
    present = [n for n in TREE_ENTRIES if os.path.lexists(out_dir / n)]
    if not present:
        return []
    if not (out_dir / TREE_PLAN).is_file() and not tree_base_stage(out_dir).is_file():
        raise PlanError(f"{out_dir} holds {', '.join(present)} but is not an authored tree (no {TREE_PLAN}, no "
                        f"{STAGE_DIR}/{BASE_STAGE_FILE}), so --replace leaves it alone; fix: author into a fresh "
                        "--out, or remove those entries yourself")
    trash = Path(tempfile.mkdtemp(dir=out_dir, prefix=".replaced."))
    for name in present:
        os.rename(out_dir / name, trash / name)
    shutil.rmtree(trash)
    return present


def with_tree_poses(plan: Plan, out_dir: Path) -> tuple[Plan, Path | None]:
    """The plan pointed at the tree's byte copy of its pose file, `out_dir/inputs/<name>` (written
    atomically if missing), and the copy if this call wrote it (else None). A tree whose copy differs
    from the plan's pose file (sha256) is refused, so pose layers of old poses never mix with new ones."""
    if plan.poses.file is None:
        return plan, None
    from allo_usd.core.files import read_user_bytes, sha256_file, write_bytes_atomic
    from allo_usd.plan.posefile import MAX_POSE_FILE_BYTES

    src = Path(plan.poses.file)
    pose_file = plan.poses.pose_file()   # read and checked (PlanError naming FILE:LINE)
    data = read_user_bytes(src, MAX_POSE_FILE_BYTES, "pose file", "re-run when it is no longer replaced",
                           error=PlanError)   # the gate again: a file swapped for a FIFO since is refused, not read
    now = hashlib.sha256(data).hexdigest()
    if now != pose_file.sha256:
        raise PlanError(f"pose file {src} changed while it was read; fix: re-run when it is no longer edited")
    dest = Path(out_dir) / POSE_INPUTS / src.name
    wrote = None
    if dest.is_file():
        had = sha256_file(dest)
        if had != now:
            raise PlanError(f"pose file {src} changed since {out_dir} was authored from it (sha256 {had[:12]}... in "
                            f"the tree's copy {dest}, {now[:12]}... now); its pose layers were made from the old "
                            "poses; fix: restore the pose file (the tree's copy is the old one), or author into a "
                            "fresh --out, or pass --replace")
    else:
        write_bytes_atomic(dest, data)
        wrote = dest
    return plan.model_copy(update={"poses": plan.poses.model_copy(update={"file": str(dest.resolve())})}), wrote


def _broken_stage(stage: Path, exc: BaseException, copy: Path | None = None) -> LayerError:
    """The one error for a base stage that cannot be read (pxr's own message reduced to its last line)."""
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[-1].strip()
    also = f", and delete the tree's copy {copy} (or author with --replace)" if copy is not None else ""
    return LayerError(f"base stage {stage} cannot be read ({first[:300]}); fix: regenerate it (`make stage`, "
                      f"i.e. scripts/make_base_stage.py) or restore stages/ (git checkout stages){also}, then re-run")


def _stage_source(plan: Plan) -> Path:
    return plan.resolve_base_stage() if plan.station.source == "procedural" else Path(plan.station.source)


@contextmanager
def open_tree(plan: Plan, out_dir: Path, replace: bool = False):
    """Hold `out_dir` (tree_lock) as a tree for `plan` and yield the authoring context over it: the
    plan must be the one the tree records (check_tree_plan; `replace` first removes the tree's
    layers: replace_tree); the tree's own base stage (with_tree_stage), read whole before any
    scene (its rig, the station and the plan's anomaly assets: a broken stage is one LayerError
    naming it and the fix); `plan.toml` (the tree's record, and its root for allo_usd.usd.safety)
    and the sky of every plan day. `author` and `author_scene` start here."""
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.usd.compose import copy_schema
    from allo_usd.usd.hazard import write_hazards

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tree_lock(out_dir):
        if replace:
            replace_tree(out_dir)   # plan.toml is rewritten below
        same = not replace and check_tree_plan(plan, out_dir)
        source, stages = _stage_source(plan), tree_base_stage(out_dir).parent
        had_stages = stages.exists()
        given = plan
        try:
            plan = with_tree_stage(plan, out_dir)
            write_hazards(plan, out_dir)   # the plan's own hazards, converted into OUT/hazards
        except (AlloError, KeyboardInterrupt):
            raise
        except Exception as exc:  # pxr's Tf.ErrorException (a RuntimeError) and the like
            raise _broken_stage(source, exc) from None
        plan, new_copy = with_tree_poses(plan, out_dir)
        ctx = AuthorContext(plan, out_dir, compute_sky(plan.dates.epochs(), Orbit(perilune_epoch=plan.perilune_epoch)))
        try:
            ctx.read_stage()
        except (DiskFullError, KeyboardInterrupt):
            raise
        except PlanError:   # a pose-file pose inside the station: nothing is kept of this run
            if new_copy is not None:
                new_copy.unlink()
                with suppress(OSError):
                    new_copy.parent.rmdir()   # if this run made it
            raise
        except Exception as exc:  # LayerError "re-author it" is a scene layer's fix, not a stage's
            if not had_stages:    # the copy this run made from a broken stage: do not keep it
                shutil.rmtree(stages, ignore_errors=True)
            raise _broken_stage(source, exc, stages if had_stages else None) from None
        copy_schema(out_dir)   # for other USD tools (allo_usd.usd.compose); this process uses the package's
        if not same:
            save_plan(given, out_dir / TREE_PLAN)
        record_tree_versions(out_dir)   # versions.json: the library versions of each run (never in a layer)
        yield ctx


def author(plan: Plan, out_dir: Path, limit: int | None = None, progress: bool = True,
           workers: int | None = None, replace: bool = False) -> Authored:
    """Author the plan's scenes (the first `limit` of them) under `out_dir`, then top up the anomalous
    depths the placement check skipped (see the module doc). With `limit`, the quotas are those of
    the anomalous scenes among the first `limit`, and their shortfalls are topped up too (so the
    tree may hold scenes beyond the first `limit`: their reserves).

    The tree is self-contained (allo_usd.usd.compose): its own base stage in `out_dir/stages`,
    shared `sky/` and `poses/` layers, `scenes/`, `plan.toml` (the plan as given), `versions.json` (the
    library versions of each authoring run: allo_usd.core.provenance), `skipped.csv`
    (every skipped depth and why; a reserve depth carries its group number in `reserve`),
    `reserves.csv` (per reserve group used: its (day, pose) and the depths authored and skipped)
    and, once finished, `counts.csv`: per split/kind and per anomaly asset, `planned`, `authored`,
    `skipped` (planned depths skipped), `reserve_groups` and `from_reserve` (the top-up) and
    `short` (planned - authored; above 0 only where the top-up bound was reached).

    The tree remembers its plan: authoring another plan into it is refused (PlanError naming the
    fields that differ) unless `replace`, which first removes the tree's layers; the same plan,
    with any `limit`, resumes. One author run at a time per tree (`TREE_LOCK`)."""
    if limit is not None and limit < 0:
        raise PlanError(f"limit {limit} is negative; fix: give the number of scenes to author, 0 or more")
    keys = list(islice(iter_scenes(plan), limit))   # lazily: --limit N builds N scenes, not the plan
    with open_tree(plan, out_dir, replace) as ctx:
        return _author_tree(ctx, keys, progress, workers)


def _author_tree(ctx: AuthorContext, keys: list[SceneKey], progress: bool, workers: int | None) -> Authored:
    """`author` over an open tree (its lock held)."""
    from tqdm import tqdm

    plan, sky, out_dir = ctx.plan, ctx.inputs.sky, ctx.out_dir
    for line in rig_notes(ctx):
        print(f"note: {line}", file=sys.stderr)
    for day in sorted({k.day for k in keys}):
        ensure_sky_layer(ctx, day)

    skipped_path, reserves_path = out_dir / SKIPPED_CSV, out_dir / RESERVES_CSV
    skipped = read_skipped(skipped_path)
    ledger = read_reserves(reserves_path)
    done = existing_scene_ids(out_dir) | set(skipped)
    samples = [list(g) for _, g in groupby(keys, key=lambda k: (k.sample_id, k.split))]
    todo = [s for s in samples if any(k.scene_id not in done for k in s)]
    n_todo = sum(len(s) for s in todo)
    if workers is None:
        workers = 2 if n_todo > 2000 else 1
    bar = tqdm(total=n_todo, unit="scene", disable=not progress, desc=f"authoring {plan.name}",
               initial=0, smoothing=0.05)
    t0 = time.perf_counter()
    topup = None
    interrupted = False
    finished = False
    try:
        with _runner(ctx, plan, out_dir, sky, workers) as runner:
            topup, interrupted = drive(runner, ctx, keys, todo, skipped, ledger, bar)
        finished = not interrupted
    finally:
        bar.close()
        write_skipped(skipped_path, skipped)
        if topup is not None:
            entries = topup.entries()
            # A finished run's entries are exactly the groups it used (ledger entries it reused
            # included); a run cut short by Ctrl-C or an error keeps what earlier runs recorded too.
            write_reserves(reserves_path, entries if finished else {**ledger, **entries})
    if interrupted:
        raise AuthoringInterrupted(f"interrupted after {bar.n} scenes ({time.perf_counter() - t0:.0f} s); "
                                   f"finished layers are kept and no partial file is left; fix: re-run the "
                                   f"same command to resume")
    counts = count_rows(plan, keys, skipped, topup)
    _write_csv(out_dir / COUNTS_CSV, COUNT_FIELDS, counts)
    reserves = topup.authored() if topup is not None else []
    paths = [scene_layer_path(out_dir, k.split, k.kind, k.scene_id) for k in [*keys, *reserves]
             if k.scene_id not in skipped]
    return Authored(paths, counts, topup.resolved if topup is not None else 0)


def author_plan(plan: Plan, out_dir: Path, limit: int | None = None, progress: bool = True,
                workers: int | None = None, replace: bool = False) -> list[Path]:
    """Author the plan (see `author`); returns the scene layer paths: the planned scenes that were
    not skipped, then the reserve scenes that top up the skipped ones. Skipped depths are listed
    in `out_dir/skipped.csv` with the reason, and planned vs authored counts in `out_dir/counts.csv`."""
    return author(plan, out_dir, limit=limit, progress=progress, workers=workers, replace=replace).paths


def drive(runner, ctx: AuthorContext, keys: list[SceneKey], todo: list[list[SceneKey]], skipped: dict,
           ledger: dict, bar) -> tuple[_TopUp | None, bool]:
    """Run the planned samples (anomaly placements first, then normal scenes) and the top-up on
    `runner`, keeping a few tasks in flight: reserve groups go before normal scenes, and normal
    scenes fill the pool while the walks wait for their groups. Returns (top-up, interrupted)."""
    n_anomalous, n_normal, n_reserve = runner.chunks
    anomalous = [s for s in todo if s[0].kind == "anomaly"]
    normal = [s for s in todo if s[0].kind != "anomaly"]
    main = deque(anomalous[i:i + n_anomalous] for i in range(0, len(anomalous), n_anomalous))
    fillers = deque(normal[i:i + n_normal] for i in range(0, len(normal), n_normal))
    anomalous_left = len(main)
    pending: dict[Future, str] = {}
    topup, interrupted = None, False

    def next_task():
        if main:
            return "anomalous", main.popleft()
        groups = topup.next_task(n_reserve) if topup is not None else None
        if groups:
            return "reserve", groups
        if fillers:
            return "normal", fillers.popleft()
        return None

    while True:
        try:
            if not interrupted:
                if topup is None and anomalous_left == 0:
                    topup = _TopUp(ctx, keys, skipped, ledger, bar)
                    bar.total += topup.need
                    bar.refresh()
                if topup is not None:
                    topup.advance()
                while len(pending) < runner.in_flight and (task := next_task()) is not None:
                    kind, payload = task
                    fn = _resolve_groups if kind == "reserve" else _author_samples
                    pending[runner.submit(fn, payload)] = kind
            if not pending:
                break
            finished, _ = wait(list(pending), return_when=FIRST_COMPLETED)
            for f in finished:
                kind = pending.pop(f)
                if f.cancelled():
                    continue
                if kind == "reserve":
                    if not interrupted:
                        topup.receive(f.result())
                    continue
                n, rows = f.result()
                skipped.update({r["scene_id"]: r for r in rows})
                bar.update(n)
                bar.set_postfix(skipped=len(skipped), refresh=False)
                anomalous_left -= kind == "anomalous"
        except KeyboardInterrupt:
            interrupted = True
            runner.stop()
            for f in pending:
                f.cancel()
    return topup, interrupted


class InlineRunner:
    """Runs each task at once in this process (one worker)."""

    in_flight = 1
    chunks = (1, 1, 1)  # (planned placements, normal samples, reserve groups) per task

    def __init__(self, ctx: AuthorContext):
        self.ctx = ctx

    def submit(self, fn, *args) -> Future:
        f = Future()
        f.set_result(fn(self.ctx, *args))
        return f

    def stop(self) -> None:
        pass


class _Pool:
    """A spawn-based process pool; each worker builds its own `AuthorContext` once."""

    chunks = (CHUNK_SAMPLES, CHUNK_NORMAL, CHUNK_RESERVE)

    def __init__(self, pool: ProcessPoolExecutor, stop, workers: int):
        self.pool, self._stop, self.in_flight = pool, stop, 2 * workers

    def submit(self, fn, *args) -> Future:
        return self.pool.submit(_in_worker, fn, *args)

    def stop(self) -> None:
        self._stop.set()


@contextmanager
def _runner(ctx: AuthorContext, plan: Plan, out_dir: Path, sky, workers: int):
    if workers <= 1:
        yield InlineRunner(ctx)
        return
    import multiprocessing as mp

    mpctx = mp.get_context("spawn")
    stop = mpctx.Event()
    with _single_threaded_numerics(), _caller_main_hidden(), \
            ProcessPoolExecutor(workers, mp_context=mpctx, initializer=_init,
                                initargs=(plan.model_dump_json(), str(out_dir), sky, stop)) as pool:
        try:
            yield _Pool(pool, stop, workers)
        except BaseException:  # a failed task or Ctrl-C: stop the workers now, not after their queued chunks
            stop.set()
            pool.shutdown(wait=True, cancel_futures=True)
            raise


_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextmanager
def _caller_main_hidden():
    """While the pool lives, spawned workers do not run the caller's script. multiprocessing's spawn
    re-imports `__main__` in every child (from its __spec__ name or its __file__), so a script without
    an `if __name__ == "__main__":` guard would author again in each worker, recursively. The workers
    need nothing from it (their functions and initializer live here), so the two attributes spawn
    reads are hidden while workers start, and put back after."""
    import sys

    main = sys.modules.get("__main__")
    saved = {k: main.__dict__[k] for k in ("__spec__", "__file__") if main is not None and k in main.__dict__}
    if main is not None:
        main.__dict__.pop("__file__", None)
        if "__spec__" in saved:
            main.__spec__ = None
    try:
        yield
    finally:
        if main is not None:
            main.__dict__.update(saved)


@contextmanager
def _single_threaded_numerics():
    """One BLAS thread per worker process. Each worker multiplies large ray arrays; with BLAS's
    default of one thread per core, 2 workers on 2 cores oversubscribe and the paper plan takes
    146 s instead of 73 s (measured). Spawned workers inherit the environment when they start,
    which happens inside this block; a value the user set is kept."""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    for k in _THREAD_VARS:
        os.environ.setdefault(k, "1")
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def author_scene(plan: Plan, scene_id: str, out_dir: Path, replace: bool = False) -> Path:
    """One scene of `plan`, by id, into the tree at `out_dir` with the sky and pose layers it stacks:
    the same bytes that authoring the whole plan gives it (its camera sample is resolved whole, so
    the random draws match; only this scene's layer is written). Raises PlacementError if the
    placement check skips it (authoring the plan would top it up from a reserve group). Like `author`,
    it refuses a tree made from another plan unless `replace`."""
    key, sample, example = None, [], None
    for _, group in groupby(iter_scenes(plan), key=lambda k: (k.sample_id, k.split)):  # lazily, one sample at a time
        sample = list(group)
        example = example or sample[0].scene_id
        key = next((k for k in sample if k.scene_id == scene_id), None)
        if key is not None:
            break
    if key is None:
        raise PlanError(f"plan {plan.name!r} has no scene {scene_id!r}; fix: pick an id from "
                        f"allo_usd.enumerate_scenes(plan) (e.g. {example})")
    out_dir = Path(out_dir)
    with open_tree(plan, out_dir, replace) as ctx:
        ensure_sky_layer(ctx, key.day)
        skipped = write_sample(ctx, [key], resolve_sample(ctx, sample))
    if skipped:
        raise PlacementError(f"scene {scene_id} was skipped: {skipped[0]['reason']}; fix: author the whole plan, "
                             "which tops skipped depths up from reserve groups")
    return scene_layer_path(out_dir, key.split, key.kind, key.scene_id)
