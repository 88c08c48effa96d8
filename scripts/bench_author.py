"""Benchmark authoring the paper plan (51,409 scenes) and write docs/bench_author.md.

By default a scaled subset is authored in one process (normal scenes and anomaly placements
timed separately, since placement ray casting dominates) and the full plan is extrapolated for
2 workers; `--full` authors the whole plan through `author_plan` (2 workers) instead.

    python scripts/bench_author.py [--normal 1500] [--placements 40] [--full] [--out docs/bench_author.md]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from itertools import groupby
from pathlib import Path

from allo_usd.authoring import _Context, author_plan, author_sample
from allo_usd.author.compose import sky_layer_path, write_sky_layer
from allo_usd.plan import enumerate_scenes, paper_plan
from allo_usd.sky import Orbit, compute_sky

ROOT = Path(__file__).resolve().parent.parent


def sizes(paths) -> str:
    s = [p.stat().st_size for p in paths]
    if not s:
        return "-"
    return f"{len(s)} files, min {min(s)} B, median {int(statistics.median(s))} B, max {max(s)} B"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--normal", type=int, default=1500)
    ap.add_argument("--placements", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench_author.md")
    args = ap.parse_args()

    plan = paper_plan()
    t = time.perf_counter()
    keys = enumerate_scenes(plan)
    t_enum = time.perf_counter() - t
    samples = [list(g) for _, g in groupby(keys, key=lambda k: (k.sample_id, k.split))]
    normal = [s for s in samples if s[0].kind == "normal"]
    placements = [s for s in samples if s[0].kind == "anomaly"]
    lines = ["# Authoring benchmark: the paper plan", "",
             f"Plan: {len(keys):,} scenes ({sum(len(s) for s in normal):,} normal, "
             f"{sum(len(s) for s in placements):,} anomalous in {len(placements):,} placements), "
             f"{len(samples):,} camera samples, {plan.dates.days} days. "
             f"`enumerate_scenes`: {t_enum * 1000:.0f} ms.", ""]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        if args.full:
            t = time.perf_counter()
            paths = author_plan(plan, out, progress=True, workers=args.workers)
            total = time.perf_counter() - t
            lines += [f"Full run, {args.workers} workers: {len(paths):,} scene layers in {total:.0f} s "
                      f"({len(paths) / total:.0f} scenes/s).", ""]
        else:
            t = time.perf_counter()
            sky = compute_sky(plan.dates.epochs(), Orbit(perilune_epoch=plan.perilune_epoch))
            ctx = _Context(plan, out, sky)
            ctx.world.station_scene
            for day in range(plan.dates.days):
                sun, bodies = ctx.sky(day)
                write_sky_layer(sky_layer_path(out, day), day=day, epoch=sky.epochs[day],
                                perilune_epoch=ctx.world.perilune_epoch, sun=sun, bodies=bodies)
            t_setup = time.perf_counter() - t
            step = max(1, len(normal) // args.normal)
            sub_n = normal[::step][: args.normal]
            t = time.perf_counter()
            for s in sub_n:
                author_sample(ctx, s)
            per_normal = (time.perf_counter() - t) / len(sub_n)
            step = max(1, len(placements) // args.placements)
            sub_p = placements[::step][: args.placements]
            t = time.perf_counter()
            skipped = sum(len(author_sample(ctx, s)[1]) for s in sub_p)
            per_place = (time.perf_counter() - t) / len(sub_p)
            n_normal = sum(len(s) for s in normal)
            t_normal, t_anom = n_normal * per_normal, len(placements) * per_place
            est = t_setup + (t_normal + t_anom) / args.workers
            lines += [
                f"Measured in one process on a subset ({len(sub_n)} normal scenes, {len(sub_p)} placements, "
                f"strided over the plan), extrapolated to {args.workers} workers:", "",
                "| part | per unit | full plan, 1 core |", "|---|---|---|",
                f"| setup: sky for 365 days (one vectorised call), station BVH, 365 sky layers | - | {t_setup:.1f} s |",
                f"| normal scene (perturb camera, pose layer, scene layer) | {per_normal * 1000:.2f} ms | "
                f"{t_normal:.0f} s |",
                f"| anomaly placement (5 depths: ray-cast placement, pose layer, 5 scene layers) | "
                f"{per_place * 1000:.0f} ms | {t_anom:.0f} s |", "",
                f"Estimated total with {args.workers} workers: **{est:.0f} s** "
                f"({len(keys) / est:.0f} scenes/s). Skipped depths in the subset: {skipped} of "
                f"{sum(len(s) for s in sub_p)}.", ""]
        lines += ["Layer sizes:", "",
                  f"- scene layers: {sizes(list((out / 'scenes').rglob('*.usda')))}",
                  f"- pose layers: {sizes(list((out / 'poses').rglob('*.usda')))}",
                  f"- sky layers: {sizes(list((out / 'sky').rglob('*.usda')))}", ""]
    lines += [
        "What dominates: since issue 6, normal scenes (~60% of the CPU time: two Sdf layer writes, "
        "file creation, the camera clearance test). Anomaly placement went from ~110 ms to ~22 ms a "
        "placement: `raycast.Scene` calls embree directly (trimesh's per-call hashing dominated small "
        "batches; distances are computed operation for operation as trimesh did), the anomaly's BVH is "
        "built once per asset variant in its own frame and the rays are moved into it, and pixel rays "
        "are computed only inside the anomaly's exact image-space bounding box. Results are unchanged "
        "except for last-bit differences in some positions (see docs/bench_author.md).", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
