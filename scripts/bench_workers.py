"""Images per hour: 1 worker x all threads vs N workers x 1 thread (allo_usd.dispatch, local pool).

    .venv/bin/python scripts/bench_workers.py [--scenes 8] [--width 320 --height 180 --samples 32]

Authors `--scenes` layers over the committed base stage (camera circling the station), renders
them once per configuration into a fresh directory, and writes docs/bench_workers.md and
docs/bench_workers.png. Other processes on the machine load the CPU too: read the figure with
that in mind (the report records the load average before and after).
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

ROOT = Path(__file__).resolve().parent.parent


def make_layers(root: Path, n: int, resolution, samples: int) -> list[Path]:
    from allo_usd.author.scene import write_scene_layer
    from allo_usd.geometry import look_at
    from allo_usd.paths import BASE_STAGE
    from allo_usd.spec import BodySpec, CameraSpec, RenderSpec, SceneSpec, SunSpec

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
                                           exposure=0.9 * math.pi / 1361.0, seed=1, denoise=False))
        layers.append(write_scene_layer(spec, root / f"bench_{i:02d}.usda", BASE_STAGE))
    return layers


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()

    from allo_usd.dispatch import dispatch

    cores = os.cpu_count() or 1
    configs = [(1, cores), (cores, 1)] if cores > 1 else [(1, 1)]
    tmp = Path(tempfile.mkdtemp(prefix="bench-workers-"))
    results = []
    try:
        layers = make_layers(tmp / "layers", args.scenes, (args.width, args.height), args.samples)
        for workers, threads in configs:
            load0 = os.getloadavg()[0]
            out = tmp / f"out_{workers}x{threads}"
            t0 = time.perf_counter()
            summary = dispatch(layers, out, workers=workers, threads=threads, progress=False)
            seconds = time.perf_counter() - t0
            if summary.failed:
                sys.exit(f"failed: {summary.failed}")
            results.append({"workers": workers, "threads": threads, "seconds": seconds,
                            "per_hour": len(layers) / seconds * 3600, "load": (load0, os.getloadavg()[0])})
            print(f"{workers} worker(s) x {threads} thread(s): {seconds:.1f} s, "
                  f"{results[-1]['per_hour']:.0f} images/hour", flush=True)
        same = all((tmp / f"out_{w}x{t}" / f"{p.stem}.png").read_bytes()
                   == (tmp / f"out_{configs[0][0]}x{configs[0][1]}" / f"{p.stem}.png").read_bytes()
                   for w, t in configs for p in layers)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    speedup = results[-1]["per_hour"] / results[0]["per_hour"]
    args.out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3))
    labels = [f"{r['workers']} worker x {r['threads']} thr" for r in results]
    ax.bar(labels, [r["per_hour"] for r in results], color=["#888", "#3a7"][: len(results)])
    ax.set_ylabel("images / hour")
    ax.set_title(f"{args.scenes} scenes, {args.width}x{args.height}, {args.samples} spp: x{speedup:.2f}")
    fig.tight_layout()
    fig.savefig(args.out / "bench_workers.png", dpi=120)
    rows = "\n".join(f"| {r['workers']} | {r['threads']} | {r['seconds']:.1f} | {r['per_hour']:.0f} | "
                     f"{r['load'][0]:.1f} -> {r['load'][1]:.1f} |" for r in results)
    (args.out / "bench_workers.md").write_text(f"""# Workers vs threads (scripts/bench_workers.py)

{args.scenes} scene layers over the committed base stage, {args.width}x{args.height}, {args.samples} samples,
no denoising, rendered with `allo_usd.dispatch` on this machine ({cores} cores). Each configuration
starts its own warm workers (bpy import included in the time).

| workers | Cycles threads each | seconds | images/hour | load average before -> after |
|---|---|---|---|---|
{rows}

**Speed-up of {results[-1]['workers']} workers x {results[-1]['threads']} thread over 1 worker x {results[0]['threads']} threads: x{speedup:.2f}**
(target >= 1.7). Images identical across configurations: {same}.

Other engineers' processes were using the same CPU while this ran (see the load averages). With a
load average above the core count, both configurations got about one core between them, and
neither the rates nor the ratio show what an idle machine would do. Re-run this on an idle machine
before drawing conclusions.

![images per hour](bench_workers.png)
""")
    print(f"speed-up x{speedup:.2f}; wrote {args.out / 'bench_workers.md'}")


if __name__ == "__main__":
    main()
