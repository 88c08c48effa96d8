"""Render time of the quality presets on a GPU (when Cycles finds one) and on the CPU, for reference.

    .venv/bin/python -m scripts.bench_gpu [--layer LAYER] [--size 480x270] [--cpu-size 160x90]
        [--presets draft,preview,final,paper] [--out docs]

The scene is the demo's anomalous view (authored into out/bench/gpu/layers when --layer is not
given). Each preset of allo_usd.plan.settings is rendered twice per device and size, in one
process, through the same builder as every render (allo_usd.blender.build with the device of
allo_usd.blender.device):
- CPU at --cpu-size (small: the reference rows, so the script runs in a few minutes anywhere);
- GPU (the first backend `--device auto` picks: OptiX, CUDA, HIP, oneAPI, Metal) at --cpu-size
  and at --size, when there is one.
Columns: wall seconds of the render call (the second run: the first pays kernel loading and, on
a GPU, kernel compilation; both are in the CSV), whether the second render is byte-identical to
the first (the determinism that docs/guide/dispatch.md, "GPU rendering", states, measured), and for GPU rows at the
CPU's size the PSNR (8-bit sRGB) of the GPU image against the CPU image of the same seed and
settings (inf = identical). Writes OUT/bench_gpu.md, .csv and .png; without a GPU the table
says so and holds the CPU rows only.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import platform
import time
from pathlib import Path

import numpy as np

from scripts import benchinfo

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "out" / "bench" / "gpu"
PRESET_ORDER = ("draft", "preview", "final", "paper")


def size(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    return int(w), int(h)


def demo_layer() -> Path:
    """The demo's first anomalous scene, authored as the demo does (cached under out/bench/gpu)."""
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.run.demo import DEMO_SCENES, demo_spec, write_demo_layer
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.usd.compose import copy_base_stage, copy_schema
    from allo_usd.usd.stage_geometry import scene_inputs

    tree = BENCH / "layers"
    found = sorted(tree.glob("*.usda")) if tree.is_dir() else []
    if found:
        return found[0]
    tree.mkdir(parents=True, exist_ok=True)
    stage = copy_base_stage(BASE_STAGE, tree)
    copy_schema(tree)
    orbit = Orbit()
    inputs = scene_inputs(stage, compute_sky(default_epochs(), orbit), orbit.perilune_epoch.strftime("%Y-%m-%dT%H:%M:%SZ"))
    index = next(i for i, scene in enumerate(DEMO_SCENES) if scene[-1] is not None)
    return write_demo_layer(demo_spec(inputs, index), tree, stage)


def render(desc, preset: str, resolution: tuple[int, int], device) -> tuple[np.ndarray, float]:
    """One render of `desc` with preset `preset`'s settings at `resolution` on `device`: (rgb, wall s)."""
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current
    from allo_usd.plan.settings import preset_fields

    r = dataclasses.replace(desc.render, resolution=tuple(resolution), **preset_fields(preset))
    d = dataclasses.replace(desc, render=r)
    build_scene(d, device)
    res = render_current(d)
    return res.rgb, res.seconds


def run(desc, presets, device, resolution, reference: dict | None = None) -> list[dict]:
    from allo_usd.output.writers import linear_to_srgb8
    from allo_usd.plan.settings import preset_fields
    from scripts.bench_accuracy import psnr

    rows = []
    for preset in presets:
        first, s1 = render(desc, preset, resolution, device)
        second, s2 = render(desc, preset, resolution, device)
        row = {"device": device.label, "kind": device.kind, "preset": preset, "size": f"{resolution[0]}x{resolution[1]}",
               "samples": preset_fields(preset)["samples"],
               "seconds_first": round(s1, 3), "seconds": round(s2, 3),
               "rerender_identical": bool(np.array_equal(first.view(np.uint32), second.view(np.uint32)))}
        ref = (reference or {}).get(preset)
        if ref is not None and ref[0].shape == second.shape:
            row["psnr_vs_cpu"] = round(psnr(linear_to_srgb8(second), linear_to_srgb8(ref[0]), 255.0), 2)
            row["speedup_vs_cpu"] = round(ref[1] / max(s2, 1e-9), 2)
        rows.append(row)
        row["_rgb"] = second
        print(f"{row['device']:<40} {preset:<8} {row['size']:>9} {s2:8.2f} s  identical re-render: "
              f"{row['rerender_identical']}" + (f"  PSNR vs CPU {row['psnr_vs_cpu']} dB" if "psnr_vs_cpu" in row else ""),
              flush=True)
    return rows


def report(rows: list[dict], out: Path, meta: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    cols = ["device", "preset", "size", "samples", "seconds", "seconds_first", "rerender_identical", "psnr_vs_cpu",
            "speedup_vs_cpu"]
    with open(out / "bench_gpu.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, cols, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    gpu = meta["gpu"]
    lines = ["# GPU rendering: time per preset (scripts/bench_gpu.py)", "", benchinfo.header(meta["run"]), "",
             f"Scene `{meta['layer']}`; Blender {meta['blender']['version']} ({meta['blender']['build_hash']}); "
             f"CPU {meta['cpu']}, {meta['cores']} cores usable, load average {meta['load']} (1 min, at the end: "
             "other processes may share the cores, so the seconds are upper bounds); "
             f"{meta['date']}.", ""]
    if gpu is None:
        lines += [f"**No GPU found**: Cycles lists no OptiX, CUDA, HIP, oneAPI or Metal device on this machine "
                  f"(it lists: {meta['found']}), so `--device auto` renders on the CPU and `--device gpu` is an error. "
                  "Only the CPU reference rows below were measured; run the script on a GPU machine to add GPU rows.", ""]
    else:
        lines += [f"GPU: {gpu}.", ""]
    lines += ["Seconds: wall time of the render call, second of two runs (the first, with kernel loading, is in "
              "the CSV). *Identical*: the second render's linear float image equals the first bit for bit. "
              "*PSNR vs CPU*: 8-bit sRGB, GPU image against the CPU image of the same seed and settings.", "",
              "| device | preset | size | spp | seconds | identical re-render | PSNR vs CPU (dB) | speed-up vs CPU |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['device']} | {r['preset']} | {r['size']} | {r['samples']} | {r['seconds']:.2f} | "
                     f"{'yes' if r['rerender_identical'] else 'NO'} | {r.get('psnr_vs_cpu', '')} | "
                     f"{r.get('speedup_vs_cpu', '')} |")
    lines += ["", "![seconds per preset](bench_gpu.png)", ""]
    (out / "bench_gpu.md").write_text("\n".join(lines))

    fig, ax = plt.subplots(figsize=(7, 3.5))
    groups = sorted({(r["device"], r["size"]) for r in rows}, key=lambda g: (g[0].startswith("GPU"), g[1]))
    width = 0.8 / max(len(groups), 1)
    presets = [p for p in PRESET_ORDER if any(r["preset"] == p for r in rows)]
    for k, g in enumerate(groups):
        ys = [next((r["seconds"] for r in rows if (r["device"], r["size"]) == g and r["preset"] == p), 0) for p in presets]
        ax.bar(np.arange(len(presets)) + k * width, ys, width, label=f"{g[0]}, {g[1]}")
    ax.set_xticks(np.arange(len(presets)) + width * (len(groups) - 1) / 2, presets)
    ax.set_yscale("log")
    ax.set_ylabel("seconds per render")
    ax.set_title("Cycles render time per preset" + ("" if gpu else " (no GPU found: CPU only)"))
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "bench_gpu.png", dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--layer", default=None, help="scene layer (default: the demo's anomalous view, authored here)")
    ap.add_argument("--size", type=size, default=(480, 270), help="GPU render size")
    ap.add_argument("--cpu-size", type=size, default=(160, 90), help="CPU reference size (GPU rows too)")
    ap.add_argument("--presets", default=",".join(PRESET_ORDER))
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks"))
    args = ap.parse_args(argv)
    bench_run = benchinfo.start()

    from allo_usd import read_scene
    from allo_usd.blender import device as dev

    layer = Path(args.layer) if args.layer else demo_layer()
    desc = read_scene(layer)
    presets = [p.strip() for p in args.presets.split(",") if p.strip()]
    found = dev.probe()
    auto = dev.choose("auto", found)
    gpu = auto if auto.kind == "GPU" else None
    rows = run(desc, presets, dev.CPU, args.cpu_size)
    reference = {r["preset"]: (r["_rgb"], r["seconds"]) for r in rows}
    if gpu is not None:
        rows += run(desc, presets, gpu, args.cpu_size, reference)
        if tuple(args.size) != tuple(args.cpu_size):
            rows += run(desc, presets, gpu, args.size)
    meta = {"layer": os.path.relpath(layer, ROOT), "blender": dev.blender_version(), "cpu": dev.cpu_model(),
            "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
            "gpu": None if gpu is None else gpu.label, "date": time.strftime("%Y-%m-%d"),
            "found": ", ".join(f"{n} ({k})" for n, k, _ in found) or "nothing",
            "machine": platform.machine(), "load": f"{os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else "?",
            "run": benchinfo.finish(bench_run)}
    report(rows, Path(args.out), meta)
    print(f"wrote {Path(args.out) / 'bench_gpu.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
