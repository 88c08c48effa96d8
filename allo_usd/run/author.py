"""Author a whole plan: resolve every scene, write shared layers once and scene layers atomically.

The unit of work is one camera sample (a normal scene, or the depths of one anomaly placement):
its perturbation and its ray-cast placement are resolved once and shared by its scenes. The sky
is computed once for all plan days (one vectorised `compute_sky`). Samples go to a local process
pool (2 workers by default for large plans) in chunks. Authoring resumes: a scene whose layer
exists, or that skipped.csv already lists, is not redone. Ctrl-C stops at the next file boundary;
every file is written under a temporary name and renamed, so no partial file is left. Once the
planned placements are authored, the top-up fills each (seed, asset, variant)'s skipped depths
from reserve groups (allo_usd.run.topup).

This module drives a run (`drive`) and holds the public `author`, `author_plan` and
`author_scene`; the parts it drives each have their own module: allo_usd.run.author_tree (the
tree: its lock, its plan, its base stage), allo_usd.run.samples (one camera sample, resolved and
written), allo_usd.run.topup, allo_usd.run.ledgers (skipped.csv, reserves.csv, counts.csv) and
allo_usd.run.author_pool (this process or a process pool).
"""

from __future__ import annotations

import sys
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass
from itertools import groupby, islice
from pathlib import Path

from allo_usd.core.camera_model import DEFAULT_CAMERA
from allo_usd.core.errors import PlacementError, PlanError
from allo_usd.plan.enumeration import SceneKey, iter_scenes
from allo_usd.plan.model import Plan
from allo_usd.run.author_pool import open_runner
from allo_usd.run.author_tree import open_tree
from allo_usd.run.ledgers import (count_rows, read_reserves, read_skipped, write_counts, write_reserves,
                                  write_skipped)
from allo_usd.run.samples import (AuthorContext, author_samples, ensure_sky_layer, resolve_groups, resolve_sample,
                                  write_sample)
from allo_usd.run.topup import TopUp
from allo_usd.usd.tree import COUNTS_CSV, RESERVES_CSV, SKIPPED_CSV, existing_scene_ids, scene_layer_path


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
        with open_runner(ctx, plan, out_dir, sky, workers) as runner:
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
    write_counts(out_dir / COUNTS_CSV, counts)
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
           ledger: dict, bar) -> tuple[TopUp | None, bool]:
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
                    topup = TopUp(ctx, keys, skipped, ledger, bar)
                    bar.total += topup.need
                    bar.refresh()
                if topup is not None:
                    topup.advance()
                while len(pending) < runner.in_flight and (task := next_task()) is not None:
                    kind, payload = task
                    fn = resolve_groups if kind == "reserve" else author_samples
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
