"""What a re-render on another machine's CPU kernel changes: the same layers rendered with Cycles'
default CPU kernel choice twice and with a lower kernel forced, each run in a fresh process.

    .venv/bin/python -m scripts.bench_rerender LAYER_OR_DIR [...] [--size 480x270] [--samples N]
        [--limit N] [--threads N] [--out out/bench/rerender] [--docs docs]

LAYER_OR_DIR: scene layers, or directories: a demo (`allo-usd demo --out DIR`: DIR/layers/*.usda),
an authored tree (DIR/scenes/**/*.usda) or any folder of layers (*.usda). Each layer is rendered
through the real job (allo_usd.run.job.render_layer, --device cpu: PNG, EXR, mask, JSON) from a
small layer of our own that sublayers it and sets only the resolution (--size) and, with
--samples, the samples (docs/guide/layering.md); the scene's seed, denoiser and
everything else are the layer's. Three runs, each a separate process:
- `run1`, `run2`: the kernel Cycles picks on this machine (AVX2 on any x86-64 CPU with AVX2);
- `forced`: CYCLES_CPU_NO_AVX2=1, Cycles' switch for its "default" kernel (x86-64-v2, no FMA):
  what a CPU without AVX2 renders with. Embree and OpenImageDenoise choose their own code paths
  from the CPU and are not affected by it.
Each run's JSON records the kernel Cycles really used (`cycles_cpu`, read back from Cycles), so
the table shows what was compared. Per scene and pair: are the PNG, EXR and mask bytes identical;
the max and mean absolute difference of the linear (half float) EXR and the fraction of its
pixels that differ; the PSNR and the largest difference of the 8-bit sRGB PNG; how many mask
pixels changed class. Writes DOCS/bench_rerender.md and DOCS/bench_rerender.png (bar chart of the
per-scene max and mean EXR difference between the kernels).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from scripts import benchinfo

ROOT = Path(__file__).resolve().parents[1]

NO_AVX2_ENV = "CYCLES_CPU_NO_AVX2"   # allo_usd.blender.device.NO_AVX2_ENV (not imported: that module is bpy's side)
RUNS = (("run1", {}), ("run2", {}), ("forced", {NO_AVX2_ENV: "1"}))
PAIRS = (("run1", "run2", "same kernel, again"), ("run1", "forced", "other kernel"))
COLUMNS = ("scene", "pair", "kernels", "PNG identical", "EXR identical", "mask identical", "EXR max abs diff",
           "EXR mean abs diff", "EXR pixels differing", "PNG PSNR (dB)", "PNG max diff (levels)",
           "PNG pixels differing", "mask pixels differing")


def size(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    return int(w), int(h)


def find_layers(items: list[str], limit: int | None) -> list[Path]:
    """Scene layers named by `items` (files, or demo / tree / plain directories), in order, no repeats."""
    from allo_usd.usd.tree import SCENE_DIR

    found: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_file():
            layers = [p]
        elif (p / "layers").is_dir():
            layers = sorted((p / "layers").glob("*.usda"))
        elif (p / SCENE_DIR).is_dir():
            layers = sorted((p / SCENE_DIR).rglob("*.usda"))
        elif p.is_dir():
            layers = sorted(p.glob("*.usda"))
        else:
            raise SystemExit(f"{item}: no such layer or directory")
        if not layers:
            raise SystemExit(f"{item}: no scene layers (*.usda) there; author a demo with `allo-usd demo --out DIR`")
        found += [layer.resolve() for layer in layers if layer.resolve() not in found]
    return found[:limit] if limit else found


def write_override(layer: Path, out_dir: Path, resolution: tuple[int, int], samples: int | None) -> Path:
    """A layer that sublayers `layer` and sets the resolution (and samples): our own layer on top."""
    from pxr import Sdf

    src = Sdf.Layer.FindOrOpen(str(layer))
    if src is None:
        raise SystemExit(f"{layer}: USD cannot open it")
    root = src.pseudoRoot
    meta = []
    if src.defaultPrim:
        meta.append(f'defaultPrim = "{src.defaultPrim}"')
    for key in ("metersPerUnit", "upAxis"):
        if root.HasInfo(key):
            v = root.GetInfo(key)
            meta.append(f'{key} = "{v}"' if isinstance(v, str) else f"{key} = {v}")
    rel = os.path.relpath(layer, out_dir)
    lines = ["#usda 1.0", "(", *(f"    {m}" for m in meta), f"    subLayers = [@{rel}@]", ")", "",
             'over "Render"', "{", '    over "Settings"', "    {",
             f"        uniform int2 resolution = ({resolution[0]}, {resolution[1]})"]
    if samples is not None:
        lines.append(f"        int allo:render:samples = {int(samples)}")
    lines += ["    }", "}", ""]
    out = out_dir / layer.name
    out.write_text("\n".join(lines))
    return out


# ---------------------------------------------------------------- one run (a child process)

def child(run_dir: Path, layers: list[Path], threads: int | None) -> None:
    from allo_usd.run.job import render_layer

    run_dir.mkdir(parents=True, exist_ok=True)
    for layer in layers:
        render_layer(layer, run_dir, force=True, threads=threads, device="cpu")


def run(name: str, env_extra: dict, out: Path, layers: list[Path], threads: int | None, roots: list[str]) -> float:
    """Render `layers` into OUT/runs/NAME in a fresh process with `env_extra`; Blender's output to its log."""
    from allo_usd.usd.safety import ENV_ROOTS

    run_dir = out / "runs" / name
    run_dir.mkdir(parents=True, exist_ok=True)
    env = {k: v for k, v in os.environ.items() if k != NO_AVX2_ENV}
    env.update(env_extra)
    prior = env.get(ENV_ROOTS)
    env[ENV_ROOTS] = os.pathsep.join([*roots, *([prior] if prior else [])])
    cmd = [sys.executable, "-m", "scripts.bench_rerender", "--child", str(run_dir),
           *(["--threads", str(threads)] if threads else []), *map(str, layers)]
    t0 = time.perf_counter()
    with open(run_dir / "log.txt", "w") as log:
        done = subprocess.run(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    if done.returncode != 0:
        raise SystemExit(f"run {name} failed (exit {done.returncode}); see {run_dir / 'log.txt'}")
    return time.perf_counter() - t0


# ---------------------------------------------------------------- comparing

def read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.parts[0].channels
        return np.stack([np.asarray(ch[c].pixels) for c in "RGB"], axis=-1).astype(np.float64)


def read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im).astype(np.int32)


def compare(a_dir: Path, b_dir: Path, stem: str) -> dict:
    """The measures of one scene between two runs (files named as allo_usd.output.render_outputs.output_paths)."""
    files = {"png": f"{stem}.png", "exr": f"{stem}.exr", "mask": f"{stem}_mask.png"}
    row: dict = {}
    for key, name in files.items():
        a, b = a_dir / name, b_dir / name
        row[f"{key}_identical"] = a.read_bytes() == b.read_bytes() if a.is_file() and b.is_file() else None
    if row["exr_identical"] is not None:
        ea, eb = read_exr(a_dir / files["exr"]), read_exr(b_dir / files["exr"])
        d = np.abs(ea - eb)
        row.update(exr_max=float(d.max()), exr_mean=float(d.mean()), exr_value_mean=float(np.abs(ea).mean()),
                   exr_pixels=float(np.any(d > 0, axis=-1).mean()))
    if row["png_identical"] is not None:
        pa, pb = read_png(a_dir / files["png"]), read_png(b_dir / files["png"])
        mse = float(np.mean((pa - pb) ** 2))
        row.update(png_psnr=float("inf") if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse)),
                   png_max=int(np.abs(pa - pb).max()), png_pixels=float(np.any(pa != pb, axis=-1).mean()))
    if row["mask_identical"] is not None:
        row["mask_pixels"] = int(np.count_nonzero(read_png(a_dir / files["mask"]) != read_png(b_dir / files["mask"])))
        row["mask_total"] = int(read_png(a_dir / files["mask"]).size)
    return row


def fmt(v, kind: str = "") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "**no**"
    if kind == "psnr":
        return "inf" if v == float("inf") else f"{v:.1f}"
    if kind == "frac":
        return f"{v:.2%}"
    if isinstance(v, float):
        return "0" if v == 0 else f"{v:.3g}"
    return str(v)


def commit() -> str:
    def git(*args: str) -> str:
        r = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
        return r.stdout.strip() if r.returncode == 0 else ""

    head = git("rev-parse", "--short=12", "HEAD") or "unknown"
    return head + (" (working tree with uncommitted changes)" if git("status", "--porcelain", "--untracked-files=no")
                   else "")


def report(rows: list[dict], kernels: dict, seconds: dict, render_s: dict, args, layers: list[Path],
           docs: Path, command: str, date: str, bench_run: dict | None = None) -> None:
    from allo_usd.blender.device import cpu_model   # plain Python: reads /proc/cpuinfo

    flags = kernels.get("_flags", [])
    other = [r for r in rows if r["pair"] == "other kernel"]
    same = [r for r in rows if r["pair"] == "same kernel, again"]
    forced_ok = kernels["run1"] != kernels["forced"]
    lines = [
        "# Re-render on another CPU kernel",
        "",
        benchinfo.header(bench_run) if bench_run else
        f"{benchinfo.HEADER_START}: the runs' commit, CPU and load were not recorded (runs made before the header); "
        "re-run without --no-render to record them",
        "",
        f"- machine: {cpu_model()}, {os.cpu_count()} cores, {platform.system()} {platform.machine()}; "
        f"CPU flags {', '.join(flags) or '-'}",
        f"- Blender (bpy) {kernels.get('_blender', '?')}; Cycles' default kernel is built for "
        f"{kernels.get('_march') or '?'}",
        f"- commit: {commit()}",
        f"- date: {date}",
        f"- command: {command}",
        f"- scenes: {len(layers)} at {args.size[0]}x{args.size[1]}, "
        + ("the layers' own samples" if args.samples is None else f"{args.samples} samples") + " (layers: "
        + f"{', '.join(p.name for p in layers)})"
        + ("; a demo directory is authored by `allo-usd demo --out DIR`" if any(
            Path(a, "layers").is_dir() for a in args.layers) else ""),
        "",
        "Three runs of the same layers, each in a fresh process through the real job (`render_layer`, "
        "`--device cpu`): `run1` and `run2` with the CPU kernel Cycles picks here, `forced` with "
        f"`{NO_AVX2_ENV}=1` (Cycles' switch for its `default` kernel: what a CPU without AVX2 renders "
        "with). The kernels are those each render's JSON records (`cycles_cpu.kernel`, read back from "
        "Cycles): " + ", ".join(f"{k} = {v}" for k, v in kernels.items() if not k.startswith("_")) + ". "
        "Embree (ray intersection) and OpenImageDenoise choose their own code paths from the CPU and "
        "are the same in all three runs; a real pre-AVX2 CPU would change them too.",
        "",
    ]
    if not forced_ok:
        lines += [f"**{NO_AVX2_ENV} did not change the kernel here ({kernels['run1']} in both runs): this "
                  "CPU has no AVX2, so Cycles already renders with its default kernel; the 'other kernel' "
                  "rows compare two runs of the same kernel.**", ""]
    lines += ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        cells = [r["scene"], r["pair"], r["kernels"], fmt(r["png_identical"]), fmt(r["exr_identical"]),
                 fmt(r["mask_identical"]), fmt(r.get("exr_max")), fmt(r.get("exr_mean")),
                 fmt(r.get("exr_pixels"), "frac"), fmt(r.get("png_psnr"), "psnr"), fmt(r.get("png_max")),
                 fmt(r.get("png_pixels"), "frac"), fmt(r.get("mask_pixels"))]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")

    def worst(key, rs, f=max):
        vals = [r[key] for r in rs if r.get(key) is not None]
        return f(vals) if vals else None

    identical = all(r["png_identical"] is not False and r["exr_identical"] is not False
                    and r["mask_identical"] is not False for r in same)
    lines += [
        "Summary:",
        "",
        "- same kernel, separate processes: " + ("byte-identical PNG, EXR and mask for every scene." if identical
                                                 else "**not byte-identical** (see the rows)."),
    ]
    if other:
        lines.append(
            f"- {kernels['run1']} against {kernels['forced']}: EXR max abs diff {fmt(worst('exr_max', other))} "
            f"(linear, mean pixel value {fmt(worst('exr_value_mean', other, lambda v: sum(v) / len(v)))}), "
            f"mean abs diff at most {fmt(worst('exr_mean', other))}; up to {fmt(worst('exr_pixels', other), 'frac')} "
            f"of the EXR pixels differ; PNG PSNR at least {fmt(worst('png_psnr', other, min), 'psnr')} dB, "
            f"largest PNG difference {fmt(worst('png_max', other))} of 255 levels, in at most "
            f"{fmt(worst('png_pixels', other), 'frac')} of the PNG pixels; "
            f"mask pixels changing class: at most {fmt(worst('mask_pixels', other))} "
            f"(of {fmt(worst('mask_total', other))}).")
    lines += [
        "- render seconds per run (sum over scenes, from the JSONs): "
        + ", ".join(f"{k} ({kernels[k]}) {render_s[k]:.1f} s" for k in render_s)
        + "; wall seconds per run including Blender's start-up: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items())
        + " (one run after the other on a machine others may use: not a speed benchmark).",
        "",
        "Columns: EXR = the linear half-float EXR the job writes; PSNR on the 8-bit sRGB PNG (peak 255, "
        "inf = identical); mask = the 3-class mask (pixels whose class differs).",
        "",
        "![per-scene difference between the kernels](bench_rerender.png)",
        "",
    ]
    docs.mkdir(parents=True, exist_ok=True)
    (docs / "bench_rerender.md").write_text("\n".join(lines))
    plot(other, kernels, docs / "bench_rerender.png")


def plot(rows: list[dict], kernels: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["scene"] for r in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(5.0, 1.3 * len(rows) + 2), 3.6))
    floor = 1e-12   # zero differences drawn at the axis floor (log scale)
    for off, key, label in ((-0.2, "exr_max", "max abs diff"), (0.2, "exr_mean", "mean abs diff")):
        vals = [max(r.get(key) or 0.0, floor) for r in rows]
        ax.bar(x + off, vals, width=0.4, label=label)
    ax.set_yscale("log")
    ax.set_xticks(x, names, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("linear EXR difference")
    ax.set_title(f"Cycles CPU kernel {kernels['run1']} vs {kernels['forced']} (same kernel twice: 0)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("layers", nargs="+", help="scene layers, or a demo / tree / folder of layers")
    ap.add_argument("--size", type=size, default=(480, 270), help="WxH (default 480x270)")
    ap.add_argument("--samples", type=int, default=None, help="samples per pixel (default: the layer's own)")
    ap.add_argument("--limit", type=int, default=None, help="at most this many scenes")
    ap.add_argument("--threads", type=int, default=None, help="Cycles threads (default: the layer's, 0 = all cores)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "rerender", help="work directory")
    ap.add_argument("--docs", type=Path, default=ROOT / "docs" / "benchmarks", help="where bench_rerender.md/.png go")
    ap.add_argument("--no-render", action="store_true",
                    help="compare the runs already in OUT/runs (same layers and --out) and rewrite the report")
    ap.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        child(args.child, [Path(p) for p in args.layers], args.threads)
        return
    given = argv if argv is not None else sys.argv[1:]
    command = benchinfo.command_line([__file__, *given])

    from allo_usd.usd.safety import allowed_roots

    layers = find_layers(args.layers, args.limit)
    names = [layer.name for layer in layers]
    if len(set(names)) != len(names):
        raise SystemExit(f"two layers share a file name ({sorted({n for n in names if names.count(n) > 1})}); "
                         "their outputs would collide: pass them in separate runs")
    out = args.out.resolve()
    (out / "layers").mkdir(parents=True, exist_ok=True)
    overrides = [write_override(layer, out / "layers", args.size, args.samples) for layer in layers]
    roots = sorted({str(r) for layer in layers for r in allowed_roots(layer)})  # what each layer may read itself
    record_file = out / "runs" / "runs.json"   # how and when the runs were made, for --no-render
    runs = {"seconds": {}, "command": command, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "bench_run": benchinfo.start([__file__, *given])}
    if args.no_render:
        if not record_file.is_file():
            raise SystemExit(f"--no-render: no runs in {out / 'runs'}; run without --no-render first")
        runs = json.loads(record_file.read_text())
    seconds = runs["seconds"]
    for name, env in RUNS if not args.no_render else ():
        print(f"{name}: rendering {len(overrides)} scene(s){' with ' + NO_AVX2_ENV + '=1' if env else ''} ...",
              flush=True)
        seconds[name] = run(name, env, out, overrides, args.threads, roots)
        benchinfo.finish(runs["bench_run"])
        record_file.write_text(json.dumps(runs))
    kernels, render_s, first = {}, {}, None
    for name, _ in RUNS:
        metas = [json.loads((out / "runs" / name / f"{o.stem}.json").read_text()) for o in overrides]
        got = {m["cycles_cpu"]["kernel"] for m in metas}
        kernels[name] = "/".join(sorted(got))
        render_s[name] = sum(m["render_seconds"] for m in metas)
        first = first or metas[0]
    kernels["_flags"] = first["cycles_cpu"].get("cpu_flags", [])
    kernels["_march"] = first["cycles_cpu"].get("build_march")
    kernels["_blender"] = first["device"]["blender"]["version"]
    rows = []
    for o in overrides:
        for a, b, label in PAIRS:
            row = compare(out / "runs" / a, out / "runs" / b, o.stem)
            row.update(scene=o.stem, pair=label, kernels=f"{kernels[a]} / {kernels[b]}")
            rows.append(row)
    shown = f"`{runs['command']}`" + (f" (report rewritten from its runs by `{command}`)" if args.no_render else "")
    report(rows, kernels, seconds, render_s, args, layers, args.docs, shown, runs["date"], runs.get("bench_run"))
    print(f"wrote {args.docs / 'bench_rerender.md'} and {args.docs / 'bench_rerender.png'}")
    for r in rows:
        print(f"  {r['scene']:40s} {r['pair']:20s} {r['kernels']:18s} png={fmt(r['png_identical'])} "
              f"exr={fmt(r['exr_identical'])} mask={fmt(r['mask_identical'])} max={fmt(r.get('exr_max'))} "
              f"mean={fmt(r.get('exr_mean'))} psnr={fmt(r.get('png_psnr'), 'psnr')} maskpx={fmt(r.get('mask_pixels'))}")


if __name__ == "__main__":
    main()
