"""Author a whole plan: resolve every scene, write shared layers once and scene layers atomically.

The unit of work is one camera sample (a normal scene, or the depths of one anomaly placement):
its perturbation and its ray-cast placement are resolved once and shared by its scenes. The sky
is computed once for all plan days (one vectorised `compute_sky`). Samples go to a local process
pool (2 workers by default for large plans) in chunks. Authoring resumes: a scene whose layer
exists, or that skipped.csv already lists, is not redone. Ctrl-C stops at the next file boundary;
every file is written under a temporary name and renamed, so no partial file is left.
"""

from __future__ import annotations

import csv
from contextlib import contextmanager
import io
import os
import signal
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from itertools import groupby
from pathlib import Path

from .author.compose import (pose_layer_path, scene_layer_path, sky_layer_path, write_composed_scene,
                             write_pose_layer, write_sky_layer)
from .author.scene import write_text_atomic
from .errors import PlacementError, PlanError
from .plan import Plan, SceneKey, enumerate_scenes, save_plan
from .spec import EffectsSpec, RenderSpec

SKIPPED_FIELDS = ("scene_id", "seed", "day", "pose", "asset", "variant", "depth_index", "reason")
CHUNK_SAMPLES = 48

_ctx = None  # the per-process authoring context (set by _init)


class _Context:
    """What every worker needs, built once per process: the world (base stage, station BVH) and sky."""

    def __init__(self, plan: Plan, out_dir: Path, sky, stop=None):
        from .scenes import EXPOSURE, World, sun_and_bodies

        self.plan, self.out_dir, self.stop = plan, Path(out_dir), stop
        self.base_stage = plan.resolve_base_stage()
        self.world = World(self.base_stage, sky, plan.perilune_epoch.strftime("%Y-%m-%dT%H:%M:%SZ"))
        q = plan.quality
        self.render = RenderSpec(resolution=tuple(q.resolution), preset=q.preset, samples=q.samples,
                                 adaptive_threshold=q.adaptive_threshold, denoise=q.denoise,
                                 denoise_prefilter=q.denoise_prefilter, denoise_quality=q.denoise_quality,
                                 max_bounces=q.max_bounces, exposure=EXPOSURE)
        self.effects = EffectsSpec(**plan.effects.model_dump())
        self._sky_cache: dict[int, tuple] = {}
        self._sun_and_bodies = sun_and_bodies

    def sky(self, day: int):
        if day not in self._sky_cache:
            self._sky_cache[day] = self._sun_and_bodies(self.world.sky, day)
        return self._sky_cache[day]


def _init(plan_json: str, out_dir: str, sky, stop) -> None:
    global _ctx
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and tells us through `stop`
    _ctx = _Context(Plan.model_validate_json(plan_json), Path(out_dir), sky, stop)


def _skip_row(key: SceneKey, reason: str) -> dict:
    return {"scene_id": key.scene_id, "seed": key.seed, "day": key.day, "pose": key.pose, "asset": key.asset,
            "variant": key.variant, "depth_index": key.depth_index, "reason": reason}


def author_sample(ctx: _Context, keys: list[SceneKey]) -> tuple[int, list[dict]]:
    """Resolve one camera sample and write its pose layer and its scenes' layers.
    Returns (scenes handled, skipped rows)."""
    from .scenes import build_spec, resolve_camera, resolve_placements

    k0 = keys[0]
    anomaly = None if k0.asset is None else (k0.asset, k0.variant)
    camera, rng, seed, seed_path = resolve_camera(ctx.world, day=k0.day, pose=k0.pose, plan_seed=k0.seed,
                                                  anomaly=anomaly)
    specs: dict[int, object] = {k.depth_index: None for k in keys}
    if anomaly is not None:
        try:
            specs = dict(enumerate(resolve_placements(ctx.world, camera, rng, anomaly, ctx.render.resolution)))
        except PlacementError as exc:
            return len(keys), [_skip_row(k, f"no initial placement: {exc}") for k in keys]
    pose_path = pose_layer_path(ctx.out_dir, k0.seed, k0.sample_id)
    if not pose_path.exists():
        write_pose_layer(pose_path, pose=k0.pose, camera=camera, seed=seed, seed_path=seed_path,
                         sample_id=k0.sample_id)
    skipped = []
    for key in keys:
        a = specs[key.depth_index]
        if isinstance(a, str):
            skipped.append(_skip_row(key, a))
            continue
        path = scene_layer_path(ctx.out_dir, key.split, key.kind, key.scene_id)
        if path.exists():
            continue
        spec = build_spec(ctx.world, scene_id=key.scene_id, day=key.day, pose=key.pose, seed=seed,
                          seed_path=seed_path, camera=camera, render=ctx.render, effects=ctx.effects,
                          anomaly=a, sky=ctx.sky(key.day))
        write_composed_scene(spec, path, pose_layer=pose_path, sky_layer=sky_layer_path(ctx.out_dir, key.day),
                             base_stage=ctx.base_stage, root=ctx.out_dir)
    return len(keys), skipped


def _run_chunk(samples: list[list[SceneKey]]) -> tuple[int, list[dict], bool]:
    done, skipped = 0, []
    for keys in samples:
        if _ctx.stop is not None and _ctx.stop.is_set():
            return done, skipped, True
        n, s = author_sample(_ctx, keys)
        done, skipped = done + n, skipped + s
    return done, skipped, False


def read_skipped(path: Path) -> dict[str, dict]:
    if not path.is_file():
        return {}
    with open(path, newline="") as fh:
        return {row["scene_id"]: row for row in csv.DictReader(fh)}


def write_skipped(path: Path, rows: dict[str, dict]) -> Path:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=SKIPPED_FIELDS, lineterminator="\n")
    writer.writeheader()
    for sid in sorted(rows):
        writer.writerow({k: ("" if rows[sid].get(k) is None else rows[sid][k]) for k in SKIPPED_FIELDS})
    return write_text_atomic(path, buf.getvalue())


def _existing(out_dir: Path) -> set[str]:
    root = out_dir / "scenes"
    found = set()
    for split in ("train", "test"):
        for kind in ("normal", "anomaly"):
            d = root / split / kind
            if d.is_dir():
                found.update(e.name[:-5] for e in os.scandir(d) if e.name.endswith(".usda"))
    return found


def with_tree_stage(plan: Plan, out_dir: Path) -> Plan:
    """The plan, pointed at the output tree's own base stage `out_dir/stages/base.usda`, made before
    any worker starts. A procedural station's tree gets a byte copy of the plan's base stage and its
    assets; a station that is a model file gets a base stage built from it (into a temporary
    directory, then renamed). Scene layers then refer only to files inside the tree, so the tree
    can be moved or copied as a whole and re-authoring elsewhere gives the same bytes."""
    from .author.compose import copy_base_stage, tree_base_stage

    base = tree_base_stage(out_dir)
    if plan.station.source == "procedural":
        copy_base_stage(plan.resolve_base_stage(), out_dir)
    elif not base.is_file():
        import shutil
        import uuid

        from .author.build_stage import build_base_stage

        source = Path(plan.station.source)
        if not source.is_file():
            raise PlanError(f"station.source: {source} does not exist; fix: give the path of a glTF/OBJ/STL "
                            "model, or 'procedural'")
        tmp = base.parent.with_name(f".{base.parent.name}.{uuid.uuid4().hex}.tmp")
        try:
            build_base_stage(tmp, str(source), plan.station.units)
            if base.parent.exists():  # an incomplete build of an older version: replace it
                shutil.rmtree(base.parent)
            os.replace(tmp, base.parent)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return plan.model_copy(update={"base_stage": str(base.resolve())})


class AuthoringInterrupted(PlanError):
    """Ctrl-C stopped authoring; finished layers are kept (the CLI exits 130)."""


def author_plan(plan: Plan, out_dir: Path, limit: int | None = None, progress: bool = True,
                workers: int | None = None) -> list[Path]:
    """Author the plan's scenes (the first `limit` of them) under `out_dir`; returns their layer paths
    (skipped depths excluded; they are listed in `out_dir/skipped.csv` with the reason). The tree
    is self-contained (allo_usd.author.compose): its own base stage in `out_dir/stages`, shared
    `sky/` and `poses/` layers, `scenes/`, and `plan.toml` (the plan as given)."""
    from tqdm import tqdm

    from .sky import Orbit, compute_sky

    out_dir = Path(out_dir)
    keys = enumerate_scenes(plan)[: limit if limit is not None else None]
    out_dir.mkdir(parents=True, exist_ok=True)
    given, plan = plan, with_tree_stage(plan, out_dir)
    save_plan(given, out_dir / "plan.toml")  # as given: the tree's record, and its root for allo_usd.safety
    sky = compute_sky(plan.dates.epochs(), Orbit(perilune_epoch=plan.perilune_epoch))
    ctx = _Context(plan, out_dir, sky)
    for day in sorted({k.day for k in keys}):
        path = sky_layer_path(out_dir, day)
        if not path.exists():
            sun, bodies = ctx.sky(day)
            write_sky_layer(path, day=day, epoch=sky.epochs[day], perilune_epoch=ctx.world.perilune_epoch,
                            sun=sun, bodies=bodies)

    skipped_path = out_dir / "skipped.csv"
    skipped = read_skipped(skipped_path)
    done = _existing(out_dir) | set(skipped)
    samples = [list(g) for _, g in groupby(keys, key=lambda k: (k.sample_id, k.split))]
    todo = [s for s in samples if any(k.scene_id not in done for k in s)]
    n_todo = sum(len(s) for s in todo)
    if workers is None:
        workers = 2 if n_todo > 2000 else 1
    bar = tqdm(total=n_todo, unit="scene", disable=not progress, desc=f"authoring {plan.name}",
               initial=0, smoothing=0.05)
    interrupted = False
    t0 = time.perf_counter()
    try:
        if workers <= 1:
            try:
                for s in todo:
                    n, rows = author_sample(ctx, s)
                    skipped.update({r["scene_id"]: r for r in rows})
                    bar.update(n)
                    bar.set_postfix(skipped=len(skipped), refresh=False)
            except KeyboardInterrupt:
                interrupted = True
        else:
            interrupted = _run_pool(plan, out_dir, sky, todo, workers, skipped, bar)
    finally:
        bar.close()
        write_skipped(skipped_path, skipped)
    if interrupted:
        raise AuthoringInterrupted(f"interrupted after {bar.n} of {n_todo} scenes ({time.perf_counter() - t0:.0f} s); "
                        f"finished layers are kept and no partial file is left; fix: re-run the same command "
                        f"to resume")
    return [scene_layer_path(out_dir, k.split, k.kind, k.scene_id) for k in keys if k.scene_id not in skipped]


_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


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


def _run_pool(plan: Plan, out_dir: Path, sky, todo, workers: int, skipped: dict, bar) -> bool:
    """Run the samples on a spawn-based process pool; True if Ctrl-C stopped it."""
    import multiprocessing as mp

    mpctx = mp.get_context("spawn")
    stop = mpctx.Event()
    chunks = [todo[i:i + CHUNK_SAMPLES] for i in range(0, len(todo), CHUNK_SAMPLES)]
    interrupted = False
    with _single_threaded_numerics(), \
            ProcessPoolExecutor(workers, mp_context=mpctx, initializer=_init,
                                initargs=(plan.model_dump_json(), str(out_dir), sky, stop)) as pool:
        pending = {pool.submit(_run_chunk, c) for c in chunks}
        while pending:
            try:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            except KeyboardInterrupt:
                interrupted = True
                stop.set()
                for f in pending:
                    f.cancel()
                continue
            for f in finished:
                if f.cancelled():
                    continue
                n, rows, _ = f.result()
                skipped.update({r["scene_id"]: r for r in rows})
                bar.update(n)
                bar.set_postfix(skipped=len(skipped), refresh=False)
    return interrupted
