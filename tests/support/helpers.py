"""Test helpers shared by the test modules (`from helpers import ...`): a tiny station and
anomaly set, scene specs over the tiny base stage that conftest.py's `tiny_base` builds, and the
command line run as a user runs it (`sandboxed_cli`, `one_line_error`)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from allo_usd.assets.primitives import box, cylinder, transform
from allo_usd.core.geometry import rot_y
from allo_usd.core.geometry import look_at
from allo_usd.assets.mesh import Asset, Material
from allo_usd.scene.spec import AnomalySpec, BodySpec, CameraSpec, SceneSpec, SunSpec
from allo_usd.plan.settings import RenderSpec

EXPOSURE = 0.9 * math.pi / 1361.0


def tiny_station() -> Asset:
    return Asset("Station", (box("Truss", (2, 60, 2), "metal"),
                             cylinder("Module", 2.1, 20, "white", matrix=transform((-10, 0, 0), rot_y(np.pi / 2)))),
                 (Material("metal", (0.6, 0.6, 0.62), 1.0, 0.35), Material("white", (0.8, 0.8, 0.8), 0.0, 0.6)))


def tiny_anomalies() -> dict:
    red = Asset("Crate", (box("Body", (0.6, 0.4, 0.3), "paint"),), (Material("paint", (0.8, 0.05, 0.05)),))
    blue = Asset("Crate", (box("Body", (0.6, 0.4, 0.3), "paint"),), (Material("paint", (0.05, 0.05, 0.8)),))
    return {"Crate": {"red": red, "blue": blue}}


CAM_POS = np.array([15.0, 8.0, 5.0])


def make_spec(anomaly: bool = False, resolution=(64, 36), samples=4, seed=7, **kw) -> SceneSpec:
    sun_dir = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    bodies = {"Sun": BodySpec(tuple(sun_dir * 1.496e11), 6.9634e8),
              "Moon": BodySpec((0.0, 0.0, -7.0e6), 1.7374e6),
              "Earth": BodySpec((-3.0e8, 2.0e8, 0.0), 6.371e6)}
    spec = SceneSpec(
        scene_id="test_scene", epoch="2030-01-01T00:00:00Z", perilune_epoch="2030-01-01T00:00:00Z",
        day=0, pose=1, split="train", seed=seed, seed_path=f"1/0/1/{seed}",
        camera=CameraSpec(tuple(CAM_POS), look_at(CAM_POS, [0, 0, 0])),
        sun=SunSpec(tuple(sun_dir), 1361.0, 1361.0, 0.533, 1.496e11),
        bodies=bodies,
        render=RenderSpec(resolution, samples=samples, exposure=EXPOSURE, seed=1, denoise=False),
        anomaly=AnomalySpec("Crate", "blue", (8.0, 4.0, 2.5), np.eye(3)) if anomaly else None,
    )
    return spec if not kw else SceneSpec(**{**spec.__dict__, **kw})


ROOT = Path(__file__).resolve().parents[2]


def sandboxed_cli(*args, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """`allo-usd ARGS` in a subprocess without ALLO_ASSET_ROOTS (conftest sets it to pytest's whole
    temp dir): a layer reaches only what it is granted."""
    from allo_usd.usd.safety import ENV_ROOTS

    env = {**{k: v for k, v in os.environ.items() if k != ENV_ROOTS}, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", "from allo_usd.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=600)


def one_line_error(r: subprocess.CompletedProcess, *words: str, hidden: str) -> str:
    """The command failed with exit 2 and one `error: ...` line holding `words`, and never printed
    the text `hidden` (a file outside the sandbox)."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert hidden not in r.stdout + r.stderr
    return lines[0]

