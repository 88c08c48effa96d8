"""What a spec-following USD client sees: a scene layer imported by Blender's own USD importer.

Blender 5.0's `bpy.ops.wm.usd_import` reads a scene layer as any outside tool would. This script
imports an authored layer into a fresh Blender scene (in a child process: the project's renderer
keeps its own scene in this one), applies only the spec-level mapping a user would apply by hand
(the camera's exposure, from the standard `UsdGeom.Camera` exposure attributes through usd-core's
`ComputeLinearExposureScale`; lens and aperture units the importer converts itself), renders it
with Cycles, and compares it with the project's own render of the same layer:

- the view: both cameras project the same 3D points to the same normalised image coordinates;
- the mean linear radiance (EXR, both sides: scene-linear times the exposure, no view transform
  or 8-bit rounding in the way) of the station's pixels: the project mask's class-1 pixels that
  the imported scene's own object-index pass puts on the station (not on a celestial body).

Run as a benchmark, it measures what the importer's departures from the spec (light linking and
`allo:rayVisibility` ignored, the DistantLight intensity factor, ...) cost on a normal day and on
eclipse days, and writes docs/benchmarks/bench_light_linking.md and .png (or into --out).
tests/system/test_outside_client.py imports this module for the same functions.

    python -m scripts.bench_light_linking [--size 96x54] [--samples 16]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scripts import benchinfo

ROOT = Path(__file__).resolve().parents[1]

# Object indices the child gives the imported objects, by the USD prim their object came from.
STATION_INDEX, BODY_INDEX, ANOMALY_INDEX = 1, 3, 2

# Departures of Blender 5.0's importer from the UsdLux specification that a client can undo after
# the import, each named by the importer's code (blender/blender source/blender/io/usd/intern/
# usd_reader_light.cc). Light linking and allo:rayVisibility, which the importer ignores, cannot be
# undone this way: the benchmark measures what they cost.
DEPARTURES = {
    "distant_light_x4": "every DistantLight is imported with 4 x its intensity (`blight->energy = intensity * 4.0f`, "
                        "'approximately matches Karma'); a normalized DistantLight's intensity is its illuminance",
    "distant_light_angle_x2": "`inputs:angle` is imported doubled (`sun_angle = DEG2RADF(angle * 2.0f)`); UsdLux's "
                              "angle is the light's angular size (the Sun: about 0.53 degrees)",
}

# Days of 2030 (tests/blender/test_render_sky.py): a normal day, the station's umbra (the Earth and Moon
# stay sunlit), the lunar eclipse (the Moon's lamp dims, the station in sunlight).
DAYS = {"normal (day 0)": 0, "umbra (2030-09-27)": 269, "lunar eclipse (2030-12-10)": 343}


# ------------------------------------------------------------------- the child (bpy, importer)

def _child(args: dict) -> None:
    """Inside the child: import the layer with Blender's USD importer (default options), set the
    camera's exposure scale and the render quality, render, write an EXR and the camera as JSON."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    result = bpy.ops.wm.usd_import(filepath=args["layer"])
    assert "FINISHED" in result, result
    scene = bpy.context.scene
    cams = [o for o in scene.objects if o.type == "CAMERA" and o.name == args["camera_name"]]
    assert len(cams) == 1, [o.name for o in scene.objects if o.type == "CAMERA"]
    scene.camera = cams[0]

    def origin(obj) -> str:  # the top-level prim under the default prim an object came from
        names = []
        while obj is not None:
            names.append(obj.name)
            obj = obj.parent
        return "/".join(reversed(names))

    for obj in scene.objects:
        path = origin(obj)
        obj.pass_index = (STATION_INDEX if f"/{args['station_name']}" in f"/{path}/" else
                          ANOMALY_INDEX if f"/{args['anomaly_name']}" in f"/{path}/" else
                          BODY_INDEX if any(f"/{b}/" in f"/{path}/" for b in args["body_names"]) else 0)
    for obj in scene.objects:  # undo the named importer departures asked for (DEPARTURES)
        if obj.type == "LIGHT" and obj.data.type == "SUN":
            if "distant_light_x4" in args["undo"]:
                obj.data.energy /= 4.0
            if "distant_light_angle_x2" in args["undo"]:
                obj.data.angle /= 2.0
    # The spec-level mapping: the camera's exposure (UsdGeom.Camera exposure attributes), which
    # the importer does not read, as Cycles' linear film exposure. Everything else is the import's.
    scene.render.engine = "CYCLES"
    scene.cycles.film_exposure = args["exposure_scale"]
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    # Render quality (not scene meaning): the same as the project's render of this layer.
    scene.cycles.device = "CPU"
    scene.render.resolution_x, scene.render.resolution_y = args["resolution"]
    scene.render.resolution_percentage = 100
    q = args["quality"]
    scene.cycles.samples = q["samples"]
    scene.cycles.seed = q["seed"]
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = q["max_bounces"]
    scene.cycles.diffuse_bounces = min(4, q["max_bounces"])
    scene.cycles.sample_clamp_direct = scene.cycles.sample_clamp_indirect = 0.0
    if scene.world is not None:  # no dome light authored: space is black on both sides
        scene.world.color = (0.0, 0.0, 0.0)
    layer = scene.view_layers[0]
    layer.use_pass_object_index = True
    scene.render.use_compositing = False
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = args["exr"]
    assert "FINISHED" in bpy.ops.render.render(write_still=True)
    cam = scene.camera
    lights = {o.name: {"type": o.data.type, "energy": o.data.energy, "normalize": o.data.normalize,
                       "exposure": o.data.exposure} for o in scene.objects if o.type == "LIGHT"}
    Path(args["json"]).write_text(json.dumps({
        "matrix_world": [list(r) for r in cam.matrix_world], "lens": cam.data.lens,
        "sensor_width": cam.data.sensor_width, "sensor_height": cam.data.sensor_height,
        "sensor_fit": cam.data.sensor_fit, "shift": [cam.data.shift_x, cam.data.shift_y],
        "clip": [cam.data.clip_start, cam.data.clip_end], "dof": cam.data.dof.use_dof, "lights": lights}))


# ------------------------------------------------------------------- the parent (usd-core)

@dataclass(frozen=True)
class Imported:
    rgb: np.ndarray        # (H, W, 3) linear, times the exposure scale
    index: np.ndarray      # (H, W) object index: STATION_INDEX, BODY_INDEX, ANOMALY_INDEX, 0
    camera: dict           # the imported camera (matrix_world, lens, sensor_*), its lights
    exposure_scale: float


def exposure_scale(layer: Path) -> float:
    """The render camera's linear exposure scale under the standard: usd-core's
    UsdGeom.Camera.ComputeLinearExposureScale (2^exposure * time*iso/100 / fStop^2 * responsivity)."""
    from pxr import Usd, UsdGeom

    from allo_usd.usd import layout

    stage = Usd.Stage.Open(str(layer))
    return float(UsdGeom.Camera(stage.GetPrimAtPath(layout.CAMERA)).ComputeLinearExposureScale())


def read_exr(path: Path) -> dict:
    """Every channel of every part (Blender 5.0 writes a multilayer EXR as one part per pass)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {name: np.asarray(ch.pixels) for part in f.parts for name, ch in part.channels.items()}


def import_render(layer: Path, out_dir: Path, quality: dict, resolution: tuple[int, int],
                  undo: tuple[str, ...] = ()) -> Imported:
    """Import `layer` with Blender's USD importer in a fresh Blender (a child process) and render it,
    undoing the named importer departures `undo` (keys of DEPARTURES)."""
    from allo_usd.usd import layout

    out_dir.mkdir(parents=True, exist_ok=True)
    scale = exposure_scale(layer)
    args = {"layer": str(layer), "exr": str(out_dir / "import.exr"), "json": str(out_dir / "import.json"),
            "camera_name": layout.CAMERA.rsplit("/", 1)[1], "station_name": layout.STATION.rsplit("/", 1)[1],
            "anomaly_name": layout.ANOMALY.rsplit("/", 1)[1], "body_names": ["Sun", "Earth", "Moon"],
            "exposure_scale": scale, "quality": quality, "resolution": list(resolution),
            "undo": list(undo)}
    if set(undo) - set(DEPARTURES):
        raise ValueError(f"unknown importer departures {sorted(set(undo) - set(DEPARTURES))}; known: {sorted(DEPARTURES)}")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(ROOT)   # the checkout: this package and allo_usd
    r = subprocess.run([sys.executable, "-m", "scripts.bench_light_linking", "--child", json.dumps(args)],
                       capture_output=True, text=True, env=env, cwd=out_dir, timeout=900)
    if r.returncode != 0:
        raise RuntimeError(f"Blender import render of {layer} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    ch = read_exr(out_dir / "import.exr")
    rgb = np.stack([ch[f"ViewLayer.Combined.{c}"] for c in "RGB"], -1).astype(np.float64)
    index = np.rint(next(ch[k] for k in ("ViewLayer.IndexOB.X", "ViewLayer.Object Index.X") if k in ch)).astype(int)
    return Imported(rgb, index, json.loads((out_dir / "import.json").read_text()), scale)


def project_render(layer: Path, out_dir: Path) -> tuple[np.ndarray, np.ndarray, object]:
    """The project's own render of `layer`: linear EXR (times the layer's exposure), mask, description."""
    from PIL import Image

    from allo_usd import read_scene
    from allo_usd.run.job import render_layer

    meta = render_layer(layer, out_dir, force=True)
    ch = read_exr(out_dir / meta["files"]["exr"])
    rgb = np.stack([ch[c] for c in "RGB"], -1).astype(np.float64)
    mask = np.asarray(Image.open(out_dir / meta["files"]["mask"]))
    return rgb, mask, read_scene(layer)


def project_points(matrix_world: np.ndarray, lens_mm: float, sensor_w_mm: float, points: np.ndarray) -> np.ndarray:
    """Pinhole projection with a horizontal sensor fit: image coordinates normalised by the image
    width (x right, y up, the centre at 0). matrix_world is the camera's column-vector 4x4 (Blender's
    convention; the camera looks down its local -Z)."""
    inv = np.linalg.inv(matrix_world)
    local = (inv[:3, :3] @ points.T).T + inv[:3, 3]
    return lens_mm / sensor_w_mm * local[:, :2] / -local[:, 2:3]


def view_error(desc, imported: Imported, points: np.ndarray) -> float:
    """Largest difference, in image widths, between the project's camera and the imported one
    projecting `points` (plus the difference of their sensor heights' share, i.e. the vertical fov)."""
    cam = imported.camera
    assert cam["sensor_fit"] == "HORIZONTAL" and cam["shift"] == [0.0, 0.0]
    ours = project_points(np.asarray(desc.camera.matrix, float), desc.camera.focal_length_mm,
                          desc.camera.sensor_width_mm, points)
    theirs = project_points(np.asarray(cam["matrix_world"], float), cam["lens"], cam["sensor_width"], points)
    aspect = abs(desc.camera.sensor_height_mm / desc.camera.sensor_width_mm - cam["sensor_height"] / cam["sensor_width"])
    return float(max(np.abs(ours - theirs).max(), aspect))


def station_pixels(mask: np.ndarray, imported: Imported) -> np.ndarray:
    """The project's class-1 pixels that are the station (the import's object index says which
    class-1 pixels are celestial bodies)."""
    return (mask == 1) & (imported.index == STATION_INDEX)


def compare(layer: Path, work: Path, undo: tuple[str, ...] = tuple(DEPARTURES)) -> dict:
    """Render `layer` both ways at its own resolution (the import undoing the departures `undo`);
    the view error and the station's brightness ratio (import / ours)."""
    return compare_all(layer, work, (undo,))[0]


def compare_all(layer: Path, work: Path, undo_sets) -> list[dict]:
    """One project render of `layer`, one import render per set of departures to undo; a row each.
    `ratio` compares the images as rendered (each side with its own exposure), `radiance_ratio`
    the radiance (each divided by its exposure), which does not depend on how exposure is authored."""
    rgb, mask, desc = project_render(layer, work / "ours")
    r = desc.render
    quality = {"samples": int(r.samples), "seed": int(r.seed), "max_bounces": int(r.max_bounces)}
    rng = np.random.default_rng(0)
    # points in front of the project's camera, 2-200 m away, spread over the view
    m = np.asarray(desc.camera.matrix, float)
    d = rng.uniform(2, 200, 64)
    dirs = np.column_stack([rng.uniform(-0.4, 0.4, 64), rng.uniform(-0.2, 0.2, 64), -np.ones(64)])
    points = (m[:3, :3] @ (dirs * d[:, None]).T).T + m[:3, 3]
    rows = []
    for undo in undo_sets:
        imported = import_render(layer, work / ("import_" + "_".join(undo) if undo else "import"), quality,
                                 tuple(r.resolution), tuple(undo))
        station = station_pixels(mask, imported)
        ours = float(rgb[station].mean()) if station.any() else float("nan")
        theirs = float(imported.rgb[station].mean()) if station.any() else float("nan")
        ratio = theirs / ours if ours > 0 else float("inf")
        rows.append({"layer": layer.name, "undo": list(undo), "view_error": view_error(desc, imported, points),
                     "station_pixels": int(station.sum()), "ours": ours, "import": theirs, "ratio": ratio,
                     "radiance_ratio": ratio * float(r.exposure) / imported.exposure_scale,
                     "exposure_scale": imported.exposure_scale, "project_exposure": float(r.exposure),
                     "mask_agreement": float(((mask == 1) == np.isin(imported.index, (STATION_INDEX, BODY_INDEX))).mean()),
                     "lights": imported.camera["lights"], "dof": imported.camera["dof"]})
    return rows


_SKY: dict = {}  # the year's sky, computed once per process


def demo_layer(tree: Path, day: int, pose: int = 3, resolution=(96, 54), samples: int = 16) -> Path:
    """A demo scene (allo_usd.run.demo's authoring: sky, pose and scene layers over the tree's copy of
    the committed base stage) for `day` of 2030, no anomaly, denoising off (so means are unbiased)."""
    from allo_usd.core.constants import EXPOSURE
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.core.timefmt import format_utc
    from allo_usd.plan.settings import RenderSpec
    from allo_usd.run.demo import DEMO_SEED, write_demo_layer
    from allo_usd.scene.resolve import resolve_scene
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.usd.compose import copy_base_stage
    from allo_usd.usd.stage_geometry import scene_inputs

    tree.mkdir(parents=True, exist_ok=True)
    stage = copy_base_stage(BASE_STAGE, tree)
    orbit = Orbit()
    if "sky" not in _SKY:
        _SKY["sky"] = compute_sky(default_epochs(), orbit)
    inputs = scene_inputs(stage, _SKY["sky"], format_utc(orbit.perilune_epoch))
    render = RenderSpec(resolution=tuple(resolution), preset="demo", samples=samples, exposure=EXPOSURE, seed=1,
                        denoise=False)
    spec = resolve_scene(inputs, scene_id=f"d{day:03d}_p{pose:02d}", day=day, pose=pose, plan_seed=DEMO_SEED,
                         render=render, anomaly=None)
    return write_demo_layer(spec, tree, stage)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--size", default="96x54", help="render size WxH (default 96x54)")
    p.add_argument("--samples", type=int, default=16, help="Cycles samples, both renders (default 16)")
    p.add_argument("--poses", default="3,17", help="demo camera poses, comma-separated (default 3,17)")
    p.add_argument("--work", type=Path, default=ROOT / "out" / "bench_light_linking", help="scratch folder")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks", help="where bench_light_linking.md/.png go (default docs)")
    a = p.parse_args(argv)
    if a.child:
        return _child(json.loads(a.child))
    w, h = (int(v) for v in a.size.split("x"))
    run = benchinfo.start()
    rows = []
    for label, day in DAYS.items():
        for pose in (int(v) for v in a.poses.split(",")):
            layer = demo_layer(a.work / "layers", day, pose, (w, h), a.samples)
            for row in compare_all(layer, a.work / layer.stem, ((), tuple(DEPARTURES))):
                row.update(case=label, day=day, pose=pose)
                rows.append(row)
                print(json.dumps({k: v for k, v in row.items() if k != "lights"}), flush=True)
    write_report(rows, (w, h), a.samples, a.out, benchinfo.finish(run))


def write_report(rows: list[dict], size, samples: int, docs: Path = ROOT / "docs" / "benchmarks", run: dict | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    docs.mkdir(parents=True, exist_ok=True)
    raw = [r for r in rows if not r["undo"]]
    fixed = {(r["day"], r["pose"]): r for r in rows if r["undo"]}
    lines = ["# What an outside USD client sees: Blender 5.0.1's own importer vs allo-usd's render",
             "",
             benchinfo.header(run or benchinfo.finish(benchinfo.start())),
             "",
             f"`python -m scripts.bench_light_linking`: demo scenes (committed base stage, demo seed, no anomaly) at "
             f"{size[0]}x{size[1]}, {samples} samples, no denoising, rendered by allo-usd and, after "
             "`bpy.ops.wm.usd_import` into a fresh Blender with only the camera exposure applied (usd-core "
             "`ComputeLinearExposureScale` -> Cycles film exposure), by Cycles with the same samples, seed and "
             "bounces. Station pixels: the allo-usd mask's class 1 minus what the import's object index puts on a "
             "celestial body. Ratios are of the station's mean linear radiance (EXR divided by each side's exposure), "
             "import / allo-usd: *as imported* takes the import as it is; *undone* divides every imported SUN lamp's "
             "energy by 4 and halves its angle (the importer's two DistantLight departures, `DEPARTURES` in the script). "
             "What remains is what the importer ignores: light linking (`collection:lightLink`), "
             "`allo:rayVisibility`.",
             "",
             "| case | pose | station px | allo-usd radiance | ratio as imported | ratio undone | as rendered (undone) | view error | imported lamps (W/m², W) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in raw:
        f = fixed[(r["day"], r["pose"])]
        lamps = ", ".join(f"{n} {v['energy']:.4g}" for n, v in sorted(r["lights"].items()))
        lines.append(f"| {r['case']} | {r['pose']} | {r['station_pixels']} | {r['ours'] / r['project_exposure']:.4g} | "
                     f"{r['radiance_ratio']:.3g} | {f['radiance_ratio']:.3g} | {f['ratio']:.3g} | "
                     f"{r['view_error']:.1e} | {lamps} |")
    (docs / "bench_light_linking.md").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(7, 3.4))
    x = np.arange(len(raw))
    ax.bar(x - 0.2, [r["radiance_ratio"] for r in raw], 0.4, label="as imported", color="#b5654a")
    ax.bar(x + 0.2, [fixed[(r["day"], r["pose"])]["radiance_ratio"] for r in raw], 0.4,
           label="x4 and angle undone", color="#4a7ab5")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{r['case'].split(' (')[0]}\np{r['pose']}" for r in raw], fontsize=7)
    ax.set_ylabel("station radiance, import / allo-usd")
    ax.set_title(f"Blender 5.0.1's USD import vs allo-usd's render ({size[0]}x{size[1]})", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(docs / "bench_light_linking.png", dpi=120)


if __name__ == "__main__":
    main()
