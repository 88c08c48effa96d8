"""Images per hour: 1 worker x all threads, 1 worker x 1 thread, N workers x 1 thread (local pool).

    .venv/bin/python -m scripts.bench_workers [--scenes 24] [--width 320 --height 180 --samples 32]

Authors `--scenes` layers over the committed base stage (camera circling the station), renders
them once per configuration into a fresh directory (full renders, then mask-only renders), and
writes docs/benchmarks/bench_workers.md and docs/benchmarks/bench_workers.png. Other processes on the machine load
the CPU too: the report records the load average before and after each run.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scripts import benchinfo

ROOT = Path(__file__).resolve().parent.parent


def make_layers(root: Path, n: int, resolution, samples: int, mask_only: bool = False) -> list[Path]:
    from allo_usd.usd.scene_layer import write_scene_layer
    from allo_usd.core.geometry import look_at
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.scene.spec import BodySpec, CameraSpec, SceneSpec, SunSpec
    from allo_usd.plan.settings import DEFAULT_PASSES, RenderSpec

    sun = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    bodies = {"Sun": BodySpec(tuple(sun * 1.496e11), 6.9634e8), "Moon": BodySpec((0.0, 0.0, -7.0e6), 1.7374e6),
              "Earth": BodySpec((-3.0e8, 2.0e8, 0.0), 6.371e6)}
    layers = []
    for i in range(n):
        a = 2 * math.pi * i / n
        pos = np.array([30 * math.cos(a), 30 * math.sin(a), 8.0])
        spec = SceneSpec(scene_id=f"bench_{i:02d}", epoch="2030-01-01T00:00:00Z", perilune_epoch="2030-01-01T00:00:00Z",
                         day=0, pose=1, split="train", seed=i, seed_path=f"bench/{i}",
                         camera=CameraSpec(tuple(pos), look_at(pos, [0, 0, 0])),
                         sun=SunSpec(tuple(sun), 1361.0, 1361.0, 0.533, 1.496e11), bodies=bodies,
                         render=RenderSpec(tuple(resolution), preset="bench", samples=samples,
                                           exposure=0.9 * math.pi / 1361.0, seed=1, denoise=False,
                                           passes=("mask",) if mask_only else DEFAULT_PASSES))
        layers.append(write_scene_layer(spec, root / f"bench_{i:02d}.usda", BASE_STAGE))
    return layers


def run_configs(layers: list[Path], configs, tmp: Path, tag: str, first_file: str) -> tuple[list[dict], bool]:
    """Render `layers` once per (workers, threads); images per hour and whether outputs agree."""
    import allo_usd

    results = []
    for workers, threads in configs:
        load0 = os.getloadavg()[0]
        out = tmp / f"{tag}_{workers}x{threads}"
        t0 = time.perf_counter()
        summary = allo_usd.render(layers, out, workers=workers, threads=threads, progress=False)
        seconds = time.perf_counter() - t0
        if summary.failed:
            sys.exit(f"failed: {summary.failed}")
        results.append({"workload": tag, "workers": workers, "threads": threads, "seconds": seconds,
                        "per_hour": len(layers) / seconds * 3600, "load": (load0, os.getloadavg()[0])})
        print(f"{tag}: {workers} worker(s) x {threads} thread(s): {seconds:.1f} s, "
              f"{results[-1]['per_hour']:.0f} images/hour", flush=True)
    first = tmp / f"{tag}_{configs[0][0]}x{configs[0][1]}"
    same = all((tmp / f"{tag}_{w}x{t}" / first_file.format(stem=p.stem)).read_bytes()
               == (first / first_file.format(stem=p.stem)).read_bytes() for w, t in configs for p in layers)
    return results, same


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    args = ap.parse_args()
    run = benchinfo.start()

    cores = os.cpu_count() or 1
    configs = [(1, cores), (1, 1), (cores, 1)] if cores > 1 else [(1, 1)]
    tmp = Path(tempfile.mkdtemp(prefix="bench-workers-"))
    try:
        full, same_full = run_configs(make_layers(tmp / "layers", args.scenes, (args.width, args.height), args.samples),
                                      configs, tmp, "full", "{stem}.png")
        masks, same_masks = run_configs(make_layers(tmp / "mask_layers", args.scenes, (args.width, args.height),
                                                    args.samples, mask_only=True),
                                        [configs[0], configs[-1]], tmp, "mask", "{stem}_mask.png")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    def rate(rows, w, t):
        return next(r["per_hour"] for r in rows if (r["workers"], r["threads"]) == (w, t))

    many = (cores, 1)
    vs_all_threads = rate(full, *many) / rate(full, 1, cores)
    vs_one_thread = rate(full, *many) / rate(full, 1, 1)
    mask_ratio = rate(masks, *many) / rate(masks, 1, cores)
    args.out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3))
    for ax, rows, title in ((axes[0], full, f"{args.samples} spp renders"), (axes[1], masks, "mask-only renders")):
        ax.bar([f"{r['workers']}w x {r['threads']}t" for r in rows], [r["per_hour"] for r in rows],
               color=["#888", "#bbb", "#3a7"][: len(rows)] if len(rows) == 3 else ["#888", "#3a7"])
        ax.set_ylabel("images / hour")
        ax.set_title(f"{title}, {args.width}x{args.height}", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out / "bench_workers.png", dpi=120)
    rows = "\n".join(f"| {r['workload']} | {r['workers']} | {r['threads']} | {r['seconds']:.1f} | {r['per_hour']:.0f} | "
                     f"{r['load'][0]:.1f} -> {r['load'][1]:.1f} |" for r in full + masks)
    (args.out / "bench_workers.md").write_text(f"""# Workers vs threads (scripts/bench_workers.py)

{benchinfo.header(benchinfo.finish(run))}

{args.scenes} scene layers over the committed base stage, {args.width}x{args.height}, rendered with
`allo_usd.run.dispatch` (local pool) on this machine ({cores} cores): full renders at {args.samples} samples
without denoising, and mask-only renders (one sample, no lights). Each configuration starts its own
warm workers (bpy import included in the time).

| workload | workers | Cycles threads each | seconds | images/hour | load average before -> after |
|---|---|---|---|---|---|
{rows}

- {cores} workers x 1 thread vs 1 worker x 1 thread (render threads per worker matched), full renders:
  **x{vs_one_thread:.2f}** (target >= 1.7).
- {cores} workers x 1 thread vs 1 worker x {cores} threads, full renders: **x{vs_all_threads:.2f}**. One worker with
  every thread is already x{rate(full, 1, cores) / rate(full, 1, 1):.2f} of one thread, so no split of the same cores can do much better.
- {cores} workers x 1 thread vs 1 worker x {cores} threads, mask-only renders: **x{mask_ratio:.2f}**.
- Outputs byte-identical across configurations: full {same_full}, masks {same_masks}.

Workers are pinned to cores of their own when their threads fit (allo_usd.run.dispatch.core_sets).
Unpinned, each 1-thread worker's TBB pool keeps a second thread spinning in sched_yield through
the whole render, so two 1-thread workers fight over the cores with four busy threads (measured
before pinning: x0.72-0.91 against 1 worker x {cores} threads, x1.35 against 1 worker x 1 thread).
Pinned, N workers x 1 thread scale with N. They still cannot beat one worker using every core for
full renders, because Cycles already scales with threads and the serial part of a scene (read,
update, write) is about 0.15 s. They win where that serial part is large (mask-only renders), on
many-core nodes, and with one worker per GPU.

![images per hour](bench_workers.png)
""")
    print(f"x{vs_one_thread:.2f} / x{vs_all_threads:.2f} / masks x{mask_ratio:.2f}; wrote {args.out / 'bench_workers.md'}")


if __name__ == "__main__":
    main()
