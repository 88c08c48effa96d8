"""What the `amodal` pass costs against the RGB render, and how close its free stand-in is.

For each size, one anomalous scene renders in a warm Session (allo_usd.blender.session) with passes
rgb + mask (its RGB render: the layer's samples and denoiser), then again with amodal added; the
second render of the anomaly alone (blender.amodal: 1 sample, mask-only, the rest invisible to
camera rays) is timed on its own (RenderResult.amodal_seconds). The ray cast that stands in for the
pass when it is not asked for (output.annotations.amodal_raycast) is timed too, and its silhouette
compared with the pass's pixel for pixel.

By default the scene is the demo plan's first anomalous scene (authored into --work, as
tests/system/test_golden.py does) over the committed stages/; --layer renders another one.
Writes docs/benchmarks/bench_amodal.md and docs/benchmarks/bench_amodal.png. Usage:
    .venv/bin/python -m scripts.bench_amodal [--sizes 160x90,480x270,960x540] [--repeats 2] [--out docs]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from scripts import benchinfo

ROOT = Path(__file__).resolve().parents[1]

COLUMNS = ("size", "samples", "RGB render s", "amodal render s", "amodal / RGB", "ray cast s", "amodal px",
           "visible px", "pass vs ray cast: differing px")


def demo_layer(work: Path) -> Path:
    """The demo plan's first anomalous scene, authored into `work` (once)."""
    from allo_usd import author_plan, demo_plan
    from allo_usd.usd.tree import SCENE_DIR

    found = sorted((work / SCENE_DIR).rglob("*_z*.usda")) if (work / SCENE_DIR).is_dir() else []
    if not found:
        author_plan(demo_plan(), work, limit=7, progress=False, workers=1)
        found = sorted((work / SCENE_DIR).rglob("*_z*.usda"))
    if not found:
        raise SystemExit(f"the demo plan authored no anomalous scene into {work}; pass --layer")
    return found[0]


def measure(layer: Path, sizes: list[tuple[int, int]], repeats: int, samples: int | None, work: Path) -> list[dict]:
    from allo_usd import read_scene
    from allo_usd.blender.session import Session
    from allo_usd.core.labels import ANOMALY
    from allo_usd.output.annotations import amodal_raycast, camera_record

    base = read_scene(layer)
    session = Session()
    rows = []
    for w, h in sizes:
        render = dataclasses.replace(base.render, resolution=(w, h),
                                     **({} if samples is None else {"samples": samples}))
        plain = dataclasses.replace(base, render=dataclasses.replace(render, outputs=("rgb", "mask")))
        with_pass = dataclasses.replace(base, render=dataclasses.replace(render, outputs=("rgb", "mask", "amodal")))
        session.render(plain, work)   # warm-up: the scene is built, the size set
        rgb_s, amodal_s, cast_s = [], [], []
        for _ in range(repeats):
            rgb_s.append(session.render(plain, work).seconds)
            result = session.render(with_pass, work)
            amodal_s.append(result.amodal_seconds)
            cam = camera_record(base, w, h)
            t0 = time.perf_counter()
            cast = amodal_raycast(base, np.array(cam["K_px"]), np.array(cam["world_to_cam_opencv"]), w, h)
            cast_s.append(time.perf_counter() - t0)
        full = result.amodal == ANOMALY
        rgb, amodal = statistics.median(rgb_s), statistics.median(amodal_s)
        rows.append({"size": f"{w}x{h}", "samples": render.samples, "RGB render s": round(rgb, 3),
                     "amodal render s": round(amodal, 3), "amodal / RGB": round(amodal / rgb, 3),
                     "ray cast s": round(statistics.median(cast_s), 4), "amodal px": int(full.sum()),
                     "visible px": int((result.mask == ANOMALY).sum()),
                     "pass vs ray cast: differing px": int((full != cast).sum()), "pixels": w * h})
        print(rows[-1], flush=True)
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=100)
    px = [r["pixels"] for r in rows]
    for key, style in (("RGB render s", "o-"), ("amodal render s", "s-"), ("ray cast s", "^-")):
        ax.plot(px, [max(r[key], 1e-4) for r in rows], style, label=key.replace(" s", ""))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xticks(px, [r["size"] for r in rows])
    ax.set_xlabel("image size")
    ax.set_ylabel("seconds (median)")
    ax.set_title("amodal pass vs the RGB render")
    ax.legend()
    fig.tight_layout()
    from allo_usd.core.files import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def report(rows: list[dict], run: dict, layer: Path) -> str:
    lines = ["# The `amodal` pass: cost against the RGB render", "", benchinfo.header(run), "",
             f"Scene: `{layer.name}` (its own preset: samples and denoiser as the layer says, unless --samples). "
             "Median of the repeats, in a warm session; the amodal render is the second render of the scene "
             "with the station and bodies invisible to camera rays, 1 sample, mask-only (allo_usd/blender/amodal.py). "
             "The ray cast is what annotations use without the pass (visib_source \"raycast\"). "
             "Absolute seconds scale with the load the header records; the ratio amodal / RGB is the figure to keep.", "",
             "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(str(r[c]) for c in COLUMNS) + " |" for r in rows]
    lines += ["", "![seconds per size](bench_amodal.png)", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--layer", type=Path, help="an anomalous scene layer (default: the demo plan's first)")
    ap.add_argument("--sizes", default="160x90,480x270,960x540")
    ap.add_argument("--samples", type=int, help="override the layer's samples")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "bench_amodal")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    args = ap.parse_args(argv)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    args.work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    layer = args.layer or demo_layer(args.work / "tree")
    run = benchinfo.start()
    rows = measure(layer, sizes, args.repeats, args.samples, args.work)
    benchinfo.finish(run)
    from allo_usd.core.files import write_text_atomic

    write_text_atomic(args.out / "bench_amodal.md", report(rows, run, layer))
    plot(rows, args.out / "bench_amodal.png")
    print(args.out / "bench_amodal.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
