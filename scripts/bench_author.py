"""Benchmark authoring the paper plan (51,409 scenes) and write docs/benchmarks/bench_author.md.

By default a scaled subset is authored in one process and the full plan is extrapolated for
2 workers: normal scenes, planned anomaly placements (strided over the plan) and the top-up of
their skipped depths (the reserve groups of the same (seed, asset, variant)s, decided as
`allo_usd.run.author` does, for the subset's shortfalls) are timed separately. `--sample DAYS`
authors the paper plan scaled down to DAYS days (the same poses, seeds, quality and proportions)
end to end through `author` with `--workers` processes, as `allo-usd author` does. `--full`
authors the whole plan that way. Both report planned vs authored counts and the top-up.
Numerics run single-threaded (OPENBLAS/OMP/MKL_NUM_THREADS=1), as in authoring's workers, and
the subset is timed in CPU seconds of this process (`time.process_time`), so other load on the
machine inflates the estimate less than wall-clock time would. `--sample` and `--full` report wall
seconds, the CPU seconds (user + system) of this process and its workers together, and the time of
a second run with nothing left to do (a resume).

    python -m scripts.bench_author [--normal 1500] [--placements 300] [--sample DAYS | --full] [--out FILE]
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # before numpy loads: authoring's workers run like this; importing changes nothing
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from itertools import groupby  # noqa: E402
from pathlib import Path  # noqa: E402

from allo_usd import author_plan, enumerate_scenes, paper_plan
from allo_usd.run.author import drive
from allo_usd.run.author_pool import InlineRunner
from allo_usd.run.author_tree import with_tree_stage
from allo_usd.run.ledgers import summary_lines
from allo_usd.run.samples import AuthorContext, author_sample, ensure_sky_layer
from allo_usd.usd.tree import POSE_DIR, SCENE_DIR, SKY_DIR
from allo_usd.sky.model import compute_sky
from allo_usd.sky.orbit import Orbit
from scripts import benchinfo

ROOT = Path(__file__).resolve().parent.parent


def sizes(paths) -> str:
    s = [p.stat().st_size for p in paths]
    if not s:
        return "-"
    return f"{len(s)} files, min {min(s)} B, median {int(statistics.median(s))} B, max {max(s)} B"


class _Quiet:
    """A stand-in for the progress bar."""
    total = n = 0

    def update(self, n=1):
        pass

    def refresh(self):
        pass

    def set_postfix(self, **kw):
        pass


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its finished (joined) children: the pool's workers."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def scaled_plan(plan, days: int):
    """The paper plan over its first `days` days, with its counts scaled by days/365."""
    from allo_usd.plan.model import Counts, Dates

    f = days / plan.dates.days
    c = plan.counts
    return plan.model_copy(update={
        "name": f"{plan.name}-{days}d", "dates": Dates(start=plan.dates.start, days=days, step_days=1),
        "counts": Counts(normal_train=round(c.normal_train * f), normal_test=round(c.normal_test * f),
                         anomalous_test=round(c.anomalous_test * f))})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--normal", type=int, default=1500, help="normal camera samples to time")
    ap.add_argument("--placements", type=int, default=300, help="planned anomaly placements to time")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--sample", type=int, metavar="DAYS", help="author the plan scaled to DAYS days instead")
    ap.add_argument("--full", action="store_true", help="author the whole plan instead")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "bench_author.md")
    args = ap.parse_args()
    run = benchinfo.start()

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
        if args.full or args.sample:
            authored = plan if args.full else scaled_plan(plan, args.sample)
            n_run = len(enumerate_scenes(authored))
            t, c = time.perf_counter(), cpu_seconds()
            done = author_plan(authored, out, progress=True, workers=args.workers)
            total, cpu = time.perf_counter() - t, cpu_seconds() - c
            t = time.perf_counter()
            again = author_plan(authored, out, progress=False)   # a resume with nothing to do, as the CLI runs it
            noop = time.perf_counter() - t
            assert again.paths == done.paths
            what = "Full run" if args.full else f"The plan scaled to {args.sample} days ({n_run:,} scenes)"
            lines += [f"{what}, {args.workers} workers: {len(done.paths):,} scene layers in **{total:.1f} s** wall, "
                      f"{cpu:.1f} CPU s (user + system, all processes) ({n_run / total:.0f} plan scenes/s); "
                      f"{done.reserve_resolved} reserve groups resolved. A resume with nothing to do: {noop:.1f} s.",
                      ""]
            if not args.full:
                lines += [f"Scaled by scenes to the full plan: **{total * len(keys) / n_run:.0f} s** wall, "
                          f"{cpu * len(keys) / n_run:.0f} CPU s.", ""]
            lines += [*[f"- {s}" for s in summary_lines(done.counts)], "",
                      "| asset | planned | skipped | skipped % | reserve groups | topped up | short |",
                      "|---|---|---|---|---|---|---|"]
            for r in done.counts:
                if r["kind"] == "anomaly":
                    lines.append(f"| {r['asset'] or 'all'} | {r['planned']} | {r['skipped']} | "
                                 f"{100 * int(r['skipped']) / max(1, int(r['planned'])):.1f} | {r['reserve_groups']} | "
                                 f"{r['from_reserve']} | {r['short']} |")
            lines.append("")
        else:
            t = time.perf_counter()
            plan = with_tree_stage(plan, out)
            sky = compute_sky(plan.dates.epochs(), Orbit(perilune_epoch=plan.perilune_epoch))
            ctx = AuthorContext(plan, out, sky)
            ctx.inputs.station_scene
            for day in range(plan.dates.days):
                ensure_sky_layer(ctx, day)
            t_setup = time.perf_counter() - t
            step = max(1, len(normal) // args.normal)
            sub_n = normal[::step][: args.normal]
            t = time.process_time()
            for s in sub_n:
                author_sample(ctx, s)
            per_normal = (time.process_time() - t) / len(sub_n)
            step = max(1, len(placements) // args.placements)
            sub_p = placements[::step][: args.placements]
            skipped: dict = {}
            t = time.process_time()
            for s in sub_p:
                skipped.update({r["scene_id"]: r for r in author_sample(ctx, s)[1]})
            per_place = (time.process_time() - t) / len(sub_p)
            # The top-up of the subset's shortfalls, decided exactly as authoring does.
            t = time.process_time()
            topup, _ = drive(InlineRunner(ctx), ctx, [k for s in sub_p for k in s], [], skipped, {}, _Quiet())
            t_topup = time.process_time() - t
            n_normal = sum(len(s) for s in normal)
            scale = len(placements) / len(sub_p)
            t_normal, t_anom, t_res = n_normal * per_normal, len(placements) * per_place, t_topup * scale
            est = t_setup + (t_normal + t_anom + t_res) / args.workers
            sub_keys = [k for s in sub_p for k in s]
            lost = Counter(k.asset for k in sub_keys if k.scene_id in skipped)
            planned = Counter(k.asset for k in sub_keys)
            groups = Counter(sav[1] for sav, w in topup.walks.items() for _ in w.entries)
            filled = Counter(sav[1] for sav, w in topup.walks.items() for _ in w.authored)
            n_groups = sum(groups.values())
            lines += [
                f"Measured in one process on a subset ({len(sub_n)} normal scenes, {len(sub_p)} placements, "
                f"strided over the plan, and the top-up of their skipped depths), extrapolated to "
                f"{args.workers} workers:", "",
                "| part | per unit | full plan, 1 core |", "|---|---|---|",
                f"| setup: sky for 365 days (one vectorised call), station BVH, 365 sky layers | - | {t_setup:.1f} s |",
                f"| normal scene (perturb camera, pose layer, scene layer) | {per_normal * 1000:.2f} ms | "
                f"{t_normal:.0f} s |",
                f"| planned anomaly placement (5 depths: ray-cast placement, pose layer, 5 scene layers) | "
                f"{per_place * 1000:.0f} ms | {t_anom:.0f} s |",
                f"| top-up: {n_groups} reserve groups for {sum(lost.values())} skipped depths (per planned "
                f"placement) | {t_topup / len(sub_p) * 1000:.0f} ms | {t_res:.0f} s |", "",
                f"Estimated total with {args.workers} workers: **{est:.0f} s** "
                f"({len(keys) / est:.0f} scenes/s).", "",
                "Skipped planned depths and the top-up, per asset (subset):", "",
                "| asset | planned depths | skipped | skipped % | reserve groups | topped up | short |",
                "|---|---|---|---|---|---|---|"]
            for asset in planned:
                lines.append(f"| {asset} | {planned[asset]} | {lost[asset]} | {100 * lost[asset] / planned[asset]:.1f} | "
                             f"{groups[asset]} | {filled[asset]} | {lost[asset] - filled[asset]} |")
            lines += [f"| all | {sum(planned.values())} | {sum(lost.values())} | "
                      f"{100 * sum(lost.values()) / sum(planned.values()):.1f} | {n_groups} | "
                      f"{sum(filled.values())} | {sum(lost.values()) - sum(filled.values())} |", ""]
        lines += ["Layer sizes:", "",
                  f"- scene layers: {sizes(list((out / SCENE_DIR).rglob('*.usda')))}",
                  f"- pose layers: {sizes(list((out / POSE_DIR).rglob('*.usda')))}",
                  f"- sky layers: {sizes(list((out / SKY_DIR).rglob('*.usda')))}", ""]
    lines[2:2] = [benchinfo.header(benchinfo.finish(run)), ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
