"""The small real dataset `make run` renders: 2 normal and 2 anomalous scenes, plus a contact sheet.

One normal scene has a training pose (1-40), the other normal and the two anomalous scenes test
poses (41-50), so the assembled dataset has every folder an anomaly detector reads: train/good,
test/good and one test/<defect>/ per anomaly asset.

The demo authors exactly as a plan does (allo_usd.usd.compose), into a self-contained tree:

    OUT/layers/NAME.usda            scene layers (only their own opinions, under 4 KB)
    OUT/layers/sky/, poses/         the shared day and camera-sample layers they stack
    OUT/layers/stages/              the tree's own byte copy of the base stage and its assets
    OUT/layers/schema/              the Allo*API schemas' plugin, for PXR_PLUGINPATH_NAME
    OUT/layers/versions.json        the library versions of each run that authored it (core.provenance)
    OUT/renders/                    PNG, EXR, mask, depth, instance ids and JSON per scene (demo_passes)
    OUT/contact_sheet.png
    OUT/dataset/                    the renders as an MVTec AD tree, with COCO, BOP, depth/ and instance/
                                    (allo_usd.output.dataset)
    OUT/logs/demo.log               what Blender printed while rendering

Every path in a layer is relative and stays inside OUT/layers, the directory a scene layer lies
in (an allowed root of allo_usd.usd.safety), so OUT/layers can be moved, copied or opened in any USD
tool on its own.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from allo_usd.usd.compose import copy_base_stage, write_composed_scene, write_pose_layer, write_sky_layer
from allo_usd.usd.tree import pose_layer_path, sky_layer_path
from allo_usd.core.errors import PlacementError
from allo_usd.core.paths import BASE_STAGE
from allo_usd.core.constants import EXPOSURE
from allo_usd.core.timefmt import format_utc
from allo_usd.scene.resolve import SceneInputs, resolve_scene
from allo_usd.scene.tracking import sun_tracking_angles
from allo_usd.usd.stage_geometry import scene_inputs
from allo_usd.plan.settings import RenderSpec
from allo_usd.scene.spec import SceneSpec
from allo_usd.output.writers import linear_to_srgb8, mask_overlay, write_png

DEMO_SCENES = (  # (day, pose, anomaly or None); poses 1-40 are the train split, 41-50 the test split
    (0, 3, None),
    (120, 44, None),
    (45, 42, ("power_drill", None)),
    (200, 47, ("mli_blanket", None)),
)
DEMO_SEED = 2030
DEMO_TRACK_SUN = True   # as demo_plan: the arrays face each day's Sun (allo_usd.scene.tracking)


def demo_passes() -> tuple[str, ...]:
    """The demo's render passes: colour and mask, plus depth and instance ids (and the anomaly's
    amodal mask where the renderer has that pass), so that the demo dataset shows depth/, instance/,
    instances.json and BOP's depth PNGs and masks. Depth and instance ids come from the same Cycles
    render (no extra samples); the amodal pass is one mask-only sample of the anomaly alone."""
    from allo_usd.output.render_outputs import PASS_FILES

    return ("rgb", "exr", "mask", "depth", "instance") + (("amodal",) if "amodal" in PASS_FILES else ())


def demo_spec(inputs: SceneInputs, index: int, resolution=(480, 270), samples: int = 32, seed: int = DEMO_SEED,
              target_psnr: float = 0.0, time_limit: float = 0.0) -> SceneSpec:
    """Demo scene `index` of DEMO_SCENES, fully resolved; with `target_psnr` (and `time_limit`) its layer
    asks for the target mode (samples: the cap)."""
    from allo_usd.assets.catalogue import ANOMALY_VARIANTS

    render = RenderSpec(resolution=tuple(resolution), preset="demo", samples=samples, exposure=EXPOSURE,
                        passes=demo_passes(), target_psnr=float(target_psnr), time_limit=float(time_limit))
    day, pose, anomaly = DEMO_SCENES[index]
    if anomaly is not None:
        name = anomaly[0] if anomaly[0] in ANOMALY_VARIANTS else sorted(ANOMALY_VARIANTS)[index]
        anomaly = (name, anomaly[1] or ANOMALY_VARIANTS[name][0])
    scene_id = f"d{day:03d}_p{pose:02d}" + ("" if anomaly is None else f"_{anomaly[0]}_z0")
    for shift in range(12):  # a pose whose view shows no nearby structure gets the next day's draw
        try:
            return resolve_scene(inputs, scene_id=scene_id, day=day + shift, pose=pose, plan_seed=seed,
                                 render=render, anomaly=anomaly)
        except PlacementError:
            continue
    raise PlacementError(f"demo scene {scene_id}: no valid anomaly placement in 12 days")


def write_demo_layer(spec: SceneSpec, tree: Path, base_stage: Path, seed: int = DEMO_SEED) -> Path:
    """Author one demo scene by composition into `tree`: its day's sky layer, its camera-sample
    layer (each written once) and the scene layer `tree/SCENE_ID.usda` over them."""
    sky = sky_layer_path(tree, spec.day)
    if not sky.is_file():
        joints = sun_tracking_angles(spec.sun.direction) if DEMO_TRACK_SUN else None
        write_sky_layer(sky, day=spec.day, epoch=spec.epoch, perilune_epoch=spec.perilune_epoch,
                        sun=spec.sun, bodies=spec.bodies, joints=joints)
    sample_id = f"s{seed}_d{spec.day:03d}_p{spec.pose:02d}" + (
        "" if spec.anomaly is None else f"_{spec.anomaly.asset}-{spec.anomaly.variant}")
    pose = pose_layer_path(tree, seed, sample_id)
    if not pose.is_file():
        write_pose_layer(pose, pose=spec.pose, camera=spec.camera, seed=spec.seed, seed_path=spec.seed_path,
                         sample_id=sample_id)
    return write_composed_scene(spec, Path(tree) / f"{spec.scene_id}.usda", pose_layer=pose, sky_layer=sky,
                                base_stage=base_stage, root=tree)


def contact_sheet(rows: list[tuple[str, np.ndarray, np.ndarray]], path: Path) -> Path:
    """Each row: the image beside its mask overlay, with the scene name."""
    h, w = rows[0][1].shape[:2]
    label_h = 18
    sheet = Image.new("RGB", (2 * w + 12, len(rows) * (h + label_h + 6) + 6), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    for i, (name, rgb, mask) in enumerate(rows):
        y = 6 + i * (h + label_h + 6)
        img8 = linear_to_srgb8(rgb) if rgb.dtype != np.uint8 else rgb
        draw.text((4, y), f"{name}   (right: mask overlay, blue = station/bodies, red = anomaly)",
                  fill=(230, 230, 230))
        sheet.paste(Image.fromarray(img8), (4, y + label_h))
        sheet.paste(Image.fromarray(mask_overlay(img8, mask)), (8 + w, y + label_h))
    write_png(path, np.asarray(sheet))
    return path


def demo_dataset(renders: Path, dataset: Path, resolution) -> Path:
    """Assemble the demo renders into `dataset`; returns its manifest. A dataset holds one image
    size, so one assembled at another resolution (an earlier run's) is removed and made anew."""
    import shutil

    from allo_usd.output.dataset import MANIFEST, assemble, read_manifest, read_pixels

    rows = read_manifest(dataset / MANIFEST)
    if rows:
        first = dataset / rows[0]["image"]
        if not first.is_file() or read_pixels(first).shape[1::-1] != tuple(resolution):
            shutil.rmtree(dataset)
    return assemble([renders], dataset)


def run_demo(out_dir: Path, resolution=(480, 270), samples: int = 32, base_stage: Path = BASE_STAGE,
             progress: bool = True, device: str = "auto", target_psnr: float = 0.0, time_limit: float = 0.0) -> Path:
    """Author, render and contact-sheet the demo scenes under `out_dir`, and assemble them into an
    MVTec AD tree in `out_dir/dataset` (hard links); returns the sheet's path.
    A progress bar (counts and ETA) runs over the scenes; Ctrl-C raises KeyboardInterrupt between
    atomic file writes, so finished scenes are kept and a re-run renders only what is missing.
    `device` is the Cycles device (allo_usd.blender.device: auto, cpu, gpu). `target_psnr` and
    `time_limit` (allo_usd.plan.settings.target_problem; 0: fixed samples) go into the layers."""
    from tqdm import tqdm

    from allo_usd.core.provenance import record_tree_versions
    from allo_usd.output.dataset import read_pixels
    from allo_usd.run.job import render_record
    from allo_usd.run.options import JobOptions
    from allo_usd.run.worker import output_to
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.usd.compose import copy_schema

    out_dir = Path(out_dir)
    tree = out_dir / "layers"
    tree.mkdir(parents=True, exist_ok=True)
    stage = copy_base_stage(base_stage, tree)
    copy_schema(tree)
    record_tree_versions(tree)   # the library versions of this run, beside the layers (never in them)
    orbit = Orbit()
    sky = compute_sky(default_epochs(), orbit)
    inputs = scene_inputs(stage, sky, format_utc(orbit.perilune_epoch), track_sun=DEMO_TRACK_SUN)
    rows = []
    with tqdm(total=len(DEMO_SCENES), unit="scene", desc="demo", disable=not progress) as bar:
        for i in range(len(DEMO_SCENES)):
            spec = demo_spec(inputs, i, resolution, samples, target_psnr=target_psnr, time_limit=time_limit)
            layer = write_demo_layer(spec, tree, stage)
            with output_to(out_dir / "logs" / "demo.log"):  # Blender's own prints stay out of the bar
                # skipped when done for these very layer bytes (allo_usd.run.render_index.is_done); a
                # changed layer, e.g. another resolution, renders again
                meta = render_record(layer, out_dir / "renders", JobOptions(device=device))
            bar.write(f"{spec.scene_id}: {meta.render_seconds:.1f} s, anomaly {meta.anomaly_fraction:.3%}, "
                      f"sun {spec.sun.eclipse_state}")
            rgb = read_pixels(out_dir / "renders" / meta.files["rgb"])
            mask = read_pixels(out_dir / "renders" / meta.files["mask"])
            rows.append((spec.scene_id, rgb, mask))
            bar.update(1)
    manifest = demo_dataset(out_dir / "renders", out_dir / "dataset", resolution)
    if progress:
        tqdm.write(f"dataset: {manifest.parent / 'allo'} (train/good, test/good, test/<defect>), {manifest}")
    return contact_sheet(rows, out_dir / "contact_sheet.png")
