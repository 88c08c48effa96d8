"""A user's own layer over a demo scene, rendered tiny: the tests of docs/usd/what_renders.md.

`demo_layers(root)` authors the demo's four scene layers (the default station, as `allo-usd demo`
writes them, without rendering) into root/layers. `override(scene, path, body)` writes a layer of
one's own that sublayers a scene layer, holds `body` (prim specs in .usda text, under `over "World"`
or anything else) and renders at RESOLUTION with SAMPLES samples. `render(layer, out)` renders it in
this process and reads back what the render wrote: colour, class mask, instance ids and the render
JSON. The same override minus the edit is the baseline a row's test compares with.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

RESOLUTION = (96, 54)
SAMPLES = 8
DEMO_ANOMALY = "d045_p42_power_drill_z0"   # the demo's anomalous scene with the drill (test pose 42)
DEMO_NORMAL = "d120_p44"                   # a sunlit normal scene


def demo_layers(root: Path) -> Path:
    """root/layers: the demo's scene layers (DEMO_SCENES) over the package's own base stage, at the
    demo's settings (they are overridden by `override`)."""
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.core.timefmt import format_utc
    from allo_usd.run.demo import DEMO_SCENES, DEMO_TRACK_SUN, demo_spec, write_demo_layer
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.usd.compose import copy_base_stage, copy_schema
    from allo_usd.usd.stage_geometry import scene_inputs

    tree = Path(root) / "layers"
    tree.mkdir(parents=True, exist_ok=True)
    stage = copy_base_stage(BASE_STAGE, tree)
    copy_schema(tree)
    orbit = Orbit()
    inputs = scene_inputs(stage, compute_sky(default_epochs(), orbit), format_utc(orbit.perilune_epoch),
                          track_sun=DEMO_TRACK_SUN)
    for i in range(len(DEMO_SCENES)):
        write_demo_layer(demo_spec(inputs, i), tree, stage)
    return tree


SETTINGS = """
over "Render"
{{
    over "Settings"
    {{
        int allo:render:samples = {samples}
        uniform int2 resolution = ({w}, {h})
    }}
}}
"""


def override(scene: Path, path: Path, body: str = "", resolution=RESOLUTION, samples: int = SAMPLES,
             metadata: str = "") -> Path:
    """A layer of one's own at `path` over the scene layer `scene`: `body` (usda prim specs) and
    render settings for a tiny render. `metadata`: more layer metadata lines (e.g. customLayerData)."""
    import os

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rel = os.path.relpath(scene, path.parent)
    text = (f'#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Z"\n{metadata}'
            f'    subLayers = [\n        @{rel}@\n    ]\n)\n\n{body}\n'
            + SETTINGS.format(samples=samples, w=resolution[0], h=resolution[1]))
    path.write_text(text)
    return path


@dataclass
class Rendered:
    rgb: np.ndarray          # (H, W, 3) uint8, the delivered PNG
    mask: np.ndarray         # (H, W) uint8: 0 background, 1 station and bodies, 2 anomaly
    record: dict             # the render JSON
    out: Path                # the folder the render wrote into

    def file(self, key: str) -> Path:
        return self.out / self.record["files"][key]


def render(layer: Path, out: Path, **options) -> Rendered:
    """Render `layer` in this process into `out` (allo_usd.run.job.render_record) and read it back."""
    from allo_usd.run.job import render_record
    from allo_usd.run.options import JobOptions

    meta = render_record(Path(layer), Path(out), JobOptions(**options))
    record = json.loads((Path(out) / meta.files["meta"]).read_text())
    rgb = np.asarray(Image.open(Path(out) / meta.files["rgb"]).convert("RGB"))
    mask = np.asarray(Image.open(Path(out) / meta.files["mask"]))
    return Rendered(rgb, mask, record, Path(out))
