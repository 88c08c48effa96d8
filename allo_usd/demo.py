"""The small real dataset `make run` renders: 2 normal and 2 anomalous scenes, plus a contact sheet."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from .author.scene import write_scene_layer
from .errors import PlacementError
from .paths import BASE_STAGE
from .scenes import EXPOSURE, World, resolve_scene
from .spec import RenderSpec
from .write import linear_to_srgb8, mask_overlay, write_png

DEMO_SCENES = (  # (day, pose, anomaly or None)
    (0, 3, None),
    (120, 17, None),
    (45, 42, ("power_drill", None)),
    (200, 47, ("mli_blanket", None)),
)


def demo_specs(world: World, resolution=(480, 270), samples: int = 32, seed: int = 2030) -> list:
    from .assets.anomalies import ANOMALY_VARIANTS

    render = RenderSpec(resolution=tuple(resolution), preset="demo", samples=samples, exposure=EXPOSURE)
    specs = []
    for day, pose, anomaly in DEMO_SCENES:
        if anomaly is not None:
            name = anomaly[0] if anomaly[0] in ANOMALY_VARIANTS else sorted(ANOMALY_VARIANTS)[len(specs)]
            anomaly = (name, anomaly[1] or ANOMALY_VARIANTS[name][0])
        scene_id = f"d{day:03d}_p{pose:02d}" + ("" if anomaly is None else f"_{anomaly[0]}_z0")
        for shift in range(12):  # a pose whose view shows no nearby structure gets the next day's draw
            try:
                specs.append(resolve_scene(world, scene_id=scene_id, day=day + shift, pose=pose, plan_seed=seed,
                                           render=render, anomaly=anomaly))
                break
            except PlacementError:
                continue
        else:
            raise PlacementError(f"demo scene {scene_id}: no valid anomaly placement in 12 days")
    return specs


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


def run_demo(out_dir: Path, resolution=(480, 270), samples: int = 32, base_stage: Path = BASE_STAGE) -> Path:
    from .job import render_layer
    from .sky import Orbit, compute_sky, default_epochs

    out_dir = Path(out_dir)
    orbit = Orbit()
    sky = compute_sky(default_epochs(), orbit)
    world = World(Path(base_stage), sky, orbit.perilune_epoch.strftime("%Y-%m-%dT%H:%M:%SZ"))
    rows = []
    for spec in demo_specs(world, resolution, samples):
        layer = write_scene_layer(spec, out_dir / "layers" / f"{spec.scene_id}.usda", base_stage)
        meta = render_layer(layer, out_dir / "renders")
        print(f"{spec.scene_id}: {meta['render_seconds']:.1f} s, anomaly {meta['anomaly_fraction']:.3%}, "
              f"sun {spec.sun.eclipse_state}")
        rgb = np.asarray(Image.open(out_dir / "renders" / meta["files"]["rgb"]))
        mask = np.asarray(Image.open(out_dir / "renders" / meta["files"]["mask"]))
        rows.append((spec.scene_id, rgb, mask))
    return contact_sheet(rows, out_dir / "contact_sheet.png")
