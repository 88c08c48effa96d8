"""Accuracy vs time of Cycles settings on one demo view; picks presets from the Pareto front.

    .venv/bin/python scripts/bench_accuracy.py [--phase all|reference|sweep|presets|report]
        [--layer out/demo/layers/d045_p42_power_drill_z0.usda] [--ref-samples 2048] [--out docs]
        [--cache out/bench]

Renders a reference (no denoise, its own seed) cached as out/bench/reference_<spp>.exr, then a
sweep (samples x denoiser, adaptive threshold, max bounces, half resolution) and the presets of
allo_usd.plan.settings (3 rounds, interleaved, median per preset, all in one process). Rows are cached in
out/bench/accuracy_rows.json so phases can be re-run separately; `report` writes
docs/bench_accuracy.csv, .md and .png.

Time = CPU seconds of the render call (`time.process_time()` around it: Cycles' and OIDN's threads
all run in this process), the cost a dedicated core pays; wall seconds of the same call are kept
beside it. CPU time hardly moves when other processes share the machine (about 1%, against 20% and
more for wall time), so the ratios between settings hold on a busy machine. PSNR on the 8-bit sRGB image
(write.linear_to_srgb8) and on linear values clipped to [0, 1]; SSIM on luminance, gaussian
window sigma 1.5 (Wang et al. 2004 constants). The half-resolution renders are compared with the
reference box-averaged 2x2. The OIDN prefilter/quality go through RenderDesc like any layer's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if __name__ == "__main__":  # run from a checkout; importing this file (tests) changes nothing
    sys.path.insert(0, str(ROOT))

from allo_usd.plan.settings import PRESETS
from allo_usd.output.writers import linear_to_srgb8

BENCH = ROOT / "out" / "bench"
ROWS = BENCH / "accuracy_rows.json"
# name -> (denoise, OIDN prefilter, OIDN quality). "clean": no prefilter of the albedo/normal passes
# (at 128 spp and up they are already nearly noise-free), full-quality network.
DENOISERS = {"off": (False, "FAST", "BALANCED"), "fast": (True, "FAST", "BALANCED"),
             "accurate": (True, "ACCURATE", "HIGH"), "clean": (True, "NONE", "HIGH")}
DENOISER_LABEL = {"off": "no denoise", "fast": "OIDN fast/balanced", "accurate": "OIDN accurate/high",
                  "clean": "OIDN no prefilter/high"}


# ----------------------------------------------------------------------------- metrics
def _gauss(img: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(img, sigma, mode="reflect", truncate=3.5)


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Mean SSIM of two 2-D images, gaussian window (sigma 1.5), K1 0.01, K2 0.03."""
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_a, mu_b = _gauss(a), _gauss(b)
    saa = _gauss(a * a) - mu_a**2
    sbb = _gauss(b * b) - mu_b**2
    sab = _gauss(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
    return float(s.mean())


def psnr(a: np.ndarray, b: np.ndarray, peak: float) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def metrics(rgb: np.ndarray, ref: np.ndarray) -> dict:
    if rgb.shape != ref.shape:
        fy, fx = ref.shape[0] // rgb.shape[0], ref.shape[1] // rgb.shape[1]
        ref = ref[: rgb.shape[0] * fy, : rgb.shape[1] * fx].reshape(rgb.shape[0], fy, rgb.shape[1], fx, 3).mean(axis=(1, 3))
    s8, r8 = linear_to_srgb8(rgb), linear_to_srgb8(ref)
    lin, rlin = np.clip(np.nan_to_num(rgb), 0, 1), np.clip(np.nan_to_num(ref), 0, 1)
    return {
        "psnr_srgb8": psnr(s8, r8, 255.0),
        "psnr_linear": psnr(lin, rlin, 1.0),
        "ssim_srgb8": ssim(luminance(s8 / 255.0), luminance(r8 / 255.0)),
    }


# ----------------------------------------------------------------------------- rendering
def render(desc, samples, denoiser="off", adaptive=0.0, bounces=8, scale=1.0, seed=0):
    """Render `desc` with the given settings; returns (rgb, cpu seconds, wall seconds) of the render call."""
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current

    denoise, prefilter, quality = DENOISERS[denoiser]
    w, h = desc.render.resolution
    r = dataclasses.replace(desc.render, samples=int(samples), denoise=denoise, adaptive_threshold=float(adaptive),
                            max_bounces=int(bounces), seed=int(seed), resolution=(round(w * scale), round(h * scale)),
                            denoise_prefilter=prefilter, denoise_quality=quality)
    d = dataclasses.replace(desc, render=r)
    build_scene(d)
    cpu0 = time.process_time()
    res = render_current(d)
    return res.rgb, time.process_time() - cpu0, res.seconds


def load_rows() -> dict:
    return json.loads(ROWS.read_text()) if ROWS.is_file() else {}


def save_rows(rows: dict) -> None:
    BENCH.mkdir(parents=True, exist_ok=True)
    tmp = ROWS.with_suffix(".tmp")
    tmp.write_text(json.dumps(rows, indent=1))
    tmp.replace(ROWS)


def reference(desc, spp: int) -> np.ndarray:
    """The reference image, cached as out/bench/reference_<spp>.exr (float32 R, G, B)."""
    import OpenEXR

    from allo_usd.output.writers import write_exr

    path = BENCH / f"reference_{spp}.exr"
    if path.is_file():
        with OpenEXR.File(str(path), separate_channels=True) as f:
            ch = {n: np.asarray(c.pixels) for n, c in f.parts[0].channels.items()}
        return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1).astype(np.float32)
    BENCH.mkdir(parents=True, exist_ok=True)
    la = os.getloadavg()[0]
    rgb, _, sec = render(desc, spp, "off", 0.0, 12, 1.0, seed=977)
    write_exr(path, {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2]}, half=False)
    (BENCH / f"reference_{spp}.json").write_text(json.dumps({"seconds": sec, "loadavg": la, "samples": spp}))
    print(f"reference {spp} spp: {sec:.1f} s (load {la:.2f})", flush=True)
    return rgb


def sweep_configs():
    cfg = []
    for spp in (4, 16, 32, 64, 128, 256):
        for dn in ("off", "fast", "accurate"):
            cfg.append(dict(samples=spp, denoiser=dn))
    for spp in (64, 128, 256):
        for ad in (0.01, 0.05):
            cfg.append(dict(samples=spp, denoiser="fast", adaptive=ad))
    cfg.append(dict(samples=256, denoiser="accurate", adaptive=0.01))
    cfg.append(dict(samples=256, denoiser="fast", adaptive=0.02))
    for b in (2, 4, 12):  # 8 is in the samples grid
        cfg.append(dict(samples=64, denoiser="fast", bounces=b))
    for b in (2, 4, 12):
        cfg.append(dict(samples=256, denoiser="accurate", bounces=b))
    for spp in (64, 256):
        for dn in ("fast", "accurate"):
            cfg.append(dict(samples=spp, denoiser=dn, scale=0.5))
    for spp in (96, 160, 192):
        for dn in ("fast", "accurate"):
            cfg.append(dict(samples=spp, denoiser=dn))
    for spp, ad in ((192, 0.01), (224, 0.01), (256, 0.0125), (256, 0.015)):  # around the `final` choice
        cfg.append(dict(samples=spp, denoiser="accurate", adaptive=ad))
    for spp, ad in ((128, 0.01), (160, 0.01), (176, 0.01), (192, 0.01), (224, 0.01), (256, 0.01), (256, 0.0),
                    (288, 0.01), (256, 0.008)):
        cfg.append(dict(samples=spp, denoiser="clean", adaptive=ad))
    for spp in (48, 96):  # around `preview`: adaptive 0.05 caps near 48 spp
        cfg.append(dict(samples=spp, denoiser="fast", adaptive=0.05))
    return cfg


def key_of(c: dict) -> str:
    c = {"adaptive": 0.0, "bounces": 8, "scale": 1.0, **c}
    return f"s{c['samples']}_{c['denoiser']}_a{c['adaptive']}_b{c['bounces']}_x{c['scale']}"


def preset_config(name: str) -> dict:
    p = PRESETS[name]
    if not p["denoise"]:
        dn = "off"
    else:
        pair = (p.get("denoise_prefilter"), p.get("denoise_quality"))
        dn = next((k for k, v in DENOISERS.items() if v[0] and v[1:] == pair), None)
        if dn is None:
            raise SystemExit(f"preset {name}: prefilter/quality pair {pair} not in {DENOISERS}")
    return dict(samples=p["samples"], denoiser=dn, adaptive=p["adaptive_threshold"], bounces=p["max_bounces"])


def run_one(desc, ref, c: dict, runs: int = 1, group: str = "sweep", name: str = "") -> dict:
    cpus, walls, loads = [], [], []
    for _ in range(runs):
        loads.append(os.getloadavg()[0])
        rgb, cpu, wall = render(desc, c["samples"], c["denoiser"], c.get("adaptive", 0.0), c.get("bounces", 8), c.get("scale", 1.0))
        cpus.append(cpu)
        walls.append(wall)
    row = {"group": group, "preset": name, "samples": c["samples"], "denoiser": c["denoiser"],
           "adaptive": c.get("adaptive", 0.0), "bounces": c.get("bounces", 8), "scale": c.get("scale", 1.0),
           "seconds": statistics.median(cpus), "runs": cpus, "wall": statistics.median(walls), "wall_runs": walls,
           "loadavg": loads, **metrics(rgb, ref)}
    print(f"{group:7s} {name:8s} {key_of(c):32s} cpu {row['seconds']:7.2f} s  wall {row['wall']:6.2f} s  "
          f"{row['psnr_srgb8']:6.2f} dB  ssim {row['ssim_srgb8']:.4f}  load {loads[0]:.2f}", flush=True)
    return row


def run_presets(desc, ref, rounds: int = 3) -> dict:
    """Every preset `rounds` times, interleaved (paper, final, ... then again), so drift hits all alike."""
    runs: dict[str, list[dict]] = {name: [] for name in PRESETS}
    for _ in range(rounds):
        for name in PRESETS:
            runs[name].append(run_one(desc, ref, preset_config(name), group="preset", name=name))
    rows = {}
    for name, rs in runs.items():
        row = dict(rs[-1])
        row["runs"] = [r["seconds"] for r in rs]
        row["wall_runs"] = [r["wall"] for r in rs]
        row["loadavg"] = [r["loadavg"][0] for r in rs]
        row["seconds"] = statistics.median(row["runs"])
        row["wall"] = statistics.median(row["wall_runs"])
        rows[f"preset_{name}"] = row
    return rows


# ----------------------------------------------------------------------------- report
NOTES = """## Notes

- **Why CPU seconds.** Wall time of the same render moved by up to 2x between rounds while other
  work shared the 2 cores (paper: 36-59 s wall); its CPU time moved by 1.5% (61.4-62.2 s). The
  ratios between settings are what the targets are about, and CPU time keeps them.
- **`final` sits on the target's edge, not inside it.** No measured setting is both within 1 dB
  of `paper` and at or under 0.6x its CPU time: 176 spp adaptive 0.01 (OIDN without prefilter) is
  at 0.60x but -1.07 dB; 192 spp is -0.84 dB at 0.61-0.64x (`final`, the cheapest point within
  1 dB); 224 spp is -0.48 dB at 0.70x; 288 spp beats `paper` (+0.01 dB) at 0.88x. On the previous
  rig's view of the same scene (mostly empty sky, 2048 spp reference), `final` at 256 spp was
  -0.82 dB at 0.67x and 224 spp -1.10 dB at 0.64x. The 0.6x bar sits inside the last 5% of what
  adaptive sampling and the denoiser buy here.
- **Adaptive sampling** with threshold 0.05 caps at about 12.5 s / 40.7 dB whatever the sample
  count (it stops near 48 spp); 0.01 keeps the quality and saves 13-17% at 192-256 spp on this
  view (35% on a view with more empty sky: black pixels converge at once). It is exposure-aware
  (Cycles' convergence test scales by `film.exposure`), so the physical 1361 W/m^2 scale does not
  distort it.
- **OIDN prefilter.** At 128 spp and up, NONE (no prefilter of the albedo and normal passes) gives
  the same PSNR as ACCURATE to 0.01 dB and saves 1.1-1.8 CPU s: the auxiliary passes are already
  clean. Below 32 spp the ACCURATE prefilter buys 0.5-0.7 dB over FAST.
- **Bounces.** Max bounces 4, 8 and 12 give the same image and time (Cycles' default diffuse and
  glossy limits of 4 bind first); 2 loses 1.1-2.5 dB. Not a speed lever on this scene.
- **Half resolution** (compared with the 2x2 box-averaged reference) is never on the front.
- **Other Cycles levers tried** on the previous view (`final` then 256 spp adaptive 0.01 OIDN
  accurate, wall time): light tree off -2.3 dB for 3% less time; adaptive min samples 8 -0.2 dB;
  blue-noise pattern: same; path guiding +44% time and -0.25 dB; BVH spatial splits and compact
  BVH: the same image, time within noise (a final render already builds Embree's static BVH);
  automatic scrambling distance 1.7x slower on CPU; indirect clamp 500/2000: no change (no
  fireflies to clip); caustics off -9 dB and Filter Glossy 0 -5.5 dB (both bias against the
  reference); OIDN quality BALANCED -0.26 dB for 5% less time; albedo-only denoise inputs
  -0.12 dB; light sampling threshold 0: no change.
- **The paper's setting.** Upstream ALLO sets only `cycles.samples = 256` and denoises in the
  compositor, on a GPU; its .blend files' other settings are not published. `paper` follows
  docs/physics.md section 9: 256 spp without adaptive sampling, OIDN ACCURATE/HIGH (Blender's defaults), max
  bounces 12. Blender's factory default would also turn adaptive sampling on at 0.01: that is
  the 256-spp adaptive row above (0.79x, -0.16 dB).
"""


def pareto(rows: list[dict]) -> list[dict]:
    """Rows not beaten by any other row in both seconds (lower) and sRGB PSNR (higher); full res only."""
    pts = sorted((r for r in rows if r["scale"] == 1.0), key=lambda r: (r["seconds"], -r["psnr_srgb8"]))
    front, best = [], -np.inf
    for r in pts:
        if r["psnr_srgb8"] > best:
            front.append(r)
            best = r["psnr_srgb8"]
    return front


def setting(r: dict) -> str:
    dn = DENOISER_LABEL[r["denoiser"]]
    s = f"{r['samples']} spp, {dn}"
    if r["adaptive"]:
        s += f", adaptive {r['adaptive']:g}"
    s += f", bounces {r['bounces']}"
    if r["scale"] != 1.0:
        s += f", {r['scale']:g}x res"
    return s


def report(rows: dict, out: Path, meta: dict) -> None:
    import csv

    allrows = list(rows.values())
    sweep = [r for r in allrows if r["group"] == "sweep"]
    presets = {r["preset"]: r for r in allrows if r["group"] == "preset"}
    out.mkdir(parents=True, exist_ok=True)
    cols = ["group", "preset", "samples", "denoiser", "adaptive", "bounces", "scale", "seconds", "wall", "psnr_srgb8",
            "psnr_linear", "ssim_srgb8", "loadavg"]
    with open(out / "bench_accuracy.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in sorted(allrows, key=lambda r: (r["group"], r["scale"], r["seconds"])):
            w.writerow([r.get(c, "") if not isinstance(r.get(c), float) else f"{r[c]:.4f}" for c in cols[:-1]]
                       + [f"{r['loadavg'][0]:.2f}"])
    front = pareto(sweep + list(presets.values()))
    front_ids = {id(r) for r in front}
    L = ["# Render accuracy vs time (scripts/bench_accuracy.py)", ""]
    L.append(f"Scene `{meta['layer']}` at {meta['resolution'][0]}x{meta['resolution'][1]}; reference "
             f"{meta['ref_samples']} spp, no denoise, another seed ({meta.get('ref_seconds', float('nan')):.0f} s). "
             f"{meta['machine']}. Seconds = CPU seconds of the render call (all of Cycles' and OIDN's threads; "
             "wall seconds of the same call beside them in the preset table and the CSV); sweep rows 1 run, presets "
             "median of 3 interleaved rounds, all in one process. PSNR on the 8-bit sRGB image and on linear clipped [0,1]; SSIM on "
             "luminance of the sRGB image, gaussian window sigma 1.5. Half-resolution rows are compared with the "
             "reference box-averaged 2x2 (and are left out of the front: they answer a different question). "
             "Load average (1 min) per row is in the CSV.")
    L.append("")
    if presets:
        paper = presets.get("paper")
        L += ["## Presets", "", "| preset | setting | CPU s | x paper | wall s | x paper (wall) | PSNR sRGB (dB) | "
              "PSNR linear (dB) | SSIM | load |", "|---|---|---|---|---|---|---|---|---|---|"]
        for name in PRESETS:
            r = presets.get(name)
            if r is None:
                continue
            ratio = r["seconds"] / paper["seconds"] if paper else float("nan")
            wratio = r["wall"] / paper["wall"] if paper else float("nan")
            L.append(f"| {name} | {setting(r)} | {r['seconds']:.2f} | {ratio:.2f} | {r['wall']:.2f} | {wratio:.2f} | "
                     f"{r['psnr_srgb8']:.2f} | {r['psnr_linear']:.2f} | {r['ssim_srgb8']:.4f} | "
                     f"{max(r['loadavg']):.2f} |")
        L.append("")
        if paper and "preview" in presets and "final" in presets:
            pv, fi = presets["preview"], presets["final"]
            t1 = pv["psnr_srgb8"] >= 40.0 and pv["seconds"] <= 0.25 * paper["seconds"]
            t2 = fi["psnr_srgb8"] >= paper["psnr_srgb8"] - 1.0 and fi["seconds"] <= 0.6 * paper["seconds"]
            L.append(f"- Target 1, `preview` >= 40 dB in <= 0.25x paper time: **{'met' if t1 else 'NOT met'}** "
                     f"({pv['psnr_srgb8']:.2f} dB, {pv['seconds'] / paper['seconds']:.2f}x).")
            L.append(f"- Target 2, `final` within 1 dB of paper ({paper['psnr_srgb8']:.2f} dB) in <= 0.6x paper time: "
                     f"**{'met' if t2 else 'NOT met'}** ({fi['psnr_srgb8']:.2f} dB, {fi['seconds'] / paper['seconds']:.2f}x).")
            L.append("")
    L += ["## Pareto front (sRGB PSNR vs seconds, full resolution)", "", "| setting | seconds | PSNR sRGB | PSNR linear | SSIM |", "|---|---|---|---|---|"]
    for r in front:
        tag = f" (preset `{r['preset']}`)" if r["group"] == "preset" else ""
        L.append(f"| {setting(r)}{tag} | {r['seconds']:.2f} | {r['psnr_srgb8']:.2f} | {r['psnr_linear']:.2f} | {r['ssim_srgb8']:.4f} |")
    L += ["", NOTES]
    L += ["", "## All sweep rows", "", "| setting | seconds | PSNR sRGB | PSNR linear | SSIM | front |", "|---|---|---|---|---|---|"]
    for r in sorted(sweep, key=lambda r: (r["scale"], r["seconds"])):
        L.append(f"| {setting(r)} | {r['seconds']:.2f} | {r['psnr_srgb8']:.2f} | {r['psnr_linear']:.2f} | "
                 f"{r['ssim_srgb8']:.4f} | {'*' if id(r) in front_ids else ''} |")
    (out / "bench_accuracy.md").write_text("\n".join(L) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    colors = {"off": "tab:gray", "fast": "tab:blue", "accurate": "tab:orange", "clean": "tab:purple"}
    for dn, c in colors.items():
        pts = [r for r in sweep if r["denoiser"] == dn and r["scale"] == 1.0]
        ax.scatter([r["seconds"] for r in pts], [r["psnr_srgb8"] for r in pts], c=c, s=18, label=f"denoise {dn}")
    half = [r for r in sweep if r["scale"] != 1.0]
    ax.scatter([r["seconds"] for r in half], [r["psnr_srgb8"] for r in half], marker="x", c="k", s=22, label="0.5x resolution")
    ax.plot([r["seconds"] for r in front], [r["psnr_srgb8"] for r in front], "g-", lw=1.5, label="Pareto front")
    for name, r in presets.items():
        ax.scatter([r["seconds"]], [r["psnr_srgb8"]], marker="*", s=160, c="red", zorder=5)
        ax.annotate(name, (r["seconds"], r["psnr_srgb8"]), textcoords="offset points", xytext=(6, -12), color="red")
    if "paper" in presets:
        p = presets["paper"]
        ax.axvline(0.25 * p["seconds"], color="red", ls=":", lw=0.8)
        ax.axvline(0.6 * p["seconds"], color="red", ls="--", lw=0.8)
        ax.axhline(40.0, color="gray", ls=":", lw=0.8)
        ax.axhline(p["psnr_srgb8"] - 1.0, color="gray", ls="--", lw=0.8)
    if sweep or presets:  # a log axis needs points: a reference alone leaves the plot empty
        ax.set_xscale("log")
    else:
        ax.text(0.5, 0.5, "no sweep or preset rows yet", transform=ax.transAxes, ha="center", color="gray")
    ax.set_xlabel("render CPU seconds (log)")
    ax.set_ylabel("PSNR vs reference, 8-bit sRGB (dB)")
    ax.set_title(f"Cycles CPU, {meta['resolution'][0]}x{meta['resolution'][1]}, reference {meta['ref_samples']} spp")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "bench_accuracy.png", dpi=110)
    print(f"wrote {out}/bench_accuracy.csv, .md, .png")


def main(argv=None) -> int:
    global BENCH, ROWS
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--phase", default="all", choices=["all", "reference", "sweep", "presets", "report"])
    ap.add_argument("--layer", default=str(ROOT / "out/demo/layers/d045_p42_power_drill_z0.usda"))
    ap.add_argument("--ref-samples", type=int, default=4096)
    ap.add_argument("--out", default=str(ROOT / "docs"))
    ap.add_argument("--redo", action="store_true", help="re-render sweep rows already cached")
    ap.add_argument("--cache", default=str(BENCH), help="where the reference and the rows are cached (default out/bench)")
    args = ap.parse_args(argv)
    BENCH = Path(args.cache)
    ROWS = BENCH / "accuracy_rows.json"

    from allo_usd.usd.read import read_scene

    desc = read_scene(args.layer)
    meta = {"layer": os.path.relpath(args.layer, ROOT), "resolution": desc.render.resolution, "ref_samples": args.ref_samples,
            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs"}
    refmeta = BENCH / f"reference_{args.ref_samples}.json"
    rows = load_rows()
    if args.phase != "report":
        ref = reference(desc, args.ref_samples)
        if args.phase in ("all", "sweep"):
            for c in sweep_configs():
                k = key_of(c)
                if k in rows and not args.redo:
                    continue
                rows[k] = run_one(desc, ref, c)
                save_rows(rows)
        if args.phase in ("all", "presets"):
            for k in [k for k, r in rows.items() if r["group"] == "preset"]:
                del rows[k]
            rows.update(run_presets(desc, ref))
            save_rows(rows)
    if refmeta.is_file():
        meta["ref_seconds"] = json.loads(refmeta.read_text())["seconds"]
    report(rows, Path(args.out), meta)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
