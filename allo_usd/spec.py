"""A scene spec: every value one scene layer records, fully resolved (nothing random left).

Planning code (sky, rig, placement) fills it; `author.scene.write_scene_layer` writes it.
Plain dataclasses so it can be built and tested without pxr.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .effects.noise import SensorParams

# The largest image a scene may ask for: per side, and in all (8192 x 4608 fits; 8192 x 8192 would take
# about 1 GB per pass). One bound for plans, authoring and the reader, so nothing authors what cannot render.
MAX_SIDE_PX = 8192
MAX_PIXELS = 40_000_000


def resolution_problem(width: int, height: int) -> str | None:
    """Why (width, height) is not a renderable image size, or None if it is."""
    if not (1 <= width <= MAX_SIDE_PX and 1 <= height <= MAX_SIDE_PX) or width * height > MAX_PIXELS:
        return (f"resolution {width}x{height} is outside 1..{MAX_SIDE_PX} per side or above {MAX_PIXELS:,} "
                "pixels in all; choose a real image size, e.g. 1920x1080")
    return None


@dataclass(frozen=True)
class SunSpec:
    """A sun lamp: the Sun as seen from where the lamp's light lands (the station, or one body)."""
    direction: tuple[float, float, float]   # unit vector towards the Sun, station frame
    irradiance: float                        # W/m^2 there, times lit fraction (0 in umbra: lamp off)
    irradiance_unoccluded: float
    angular_diameter_deg: float
    distance_m: float                        # to the Sun
    lit_fraction: float = 1.0
    eclipse_state: str = "lit"
    eclipse_body: str = "none"


@dataclass(frozen=True)
class BodySpec:
    position: tuple[float, float, float]    # metres, station frame (true scale, scheme C)
    radius: float
    # The lamp that lights only this body (Earth, Moon): the Sun seen from the body's centre, times
    # the body's own lit fraction. None: the author lights it with the station sun, unoccluded.
    light: SunSpec | None = None


@dataclass(frozen=True)
class CameraSpec:
    position: tuple[float, float, float]
    rotation: np.ndarray                     # (3, 3) camera-to-station
    offset_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    perturbation: str = "euler-zyx"
    attempts: int = 1


@dataclass(frozen=True)
class AnomalySpec:
    asset: str
    variant: str
    position: tuple[float, float, float]
    rotation: np.ndarray                     # (3, 3) asset-to-station
    depth_index: int = 0
    depth_offset: float = 0.0
    attempts: int = 1
    predicted_area_fraction: float = 0.0


@dataclass(frozen=True)
class RenderSpec:
    resolution: tuple[int, int] = (1920, 1080)
    preset: str = "preview"
    samples: int = 64
    adaptive_threshold: float = 0.0
    denoise: bool = True
    max_bounces: int = 8
    seed: int = 0
    exposure: float = 1.0
    threads: int = 0
    depth: bool = False          # also write camera depth (metres, float32 EXR)
    mask_only: bool = False      # only the class mask: one sample, no lights, no path tracing
    denoise_prefilter: str = "FAST"      # OIDN prefilter: NONE, FAST, ACCURATE
    denoise_quality: str = "BALANCED"    # OIDN quality: FAST, BALANCED, HIGH


@dataclass(frozen=True)
class EffectsSpec:
    sensor_noise: bool = False
    glare: bool = False
    inspection_light: bool = True
    body_shine: bool = True
    # The camera's EMVA 1288 parameters and its own seed (fixed patterns); authored, resolved
    # against the render exposure, when sensor_noise is on.
    sensor: SensorParams = field(default_factory=SensorParams)


@dataclass(frozen=True)
class SceneSpec:
    scene_id: str
    epoch: str
    perilune_epoch: str
    day: int
    pose: int
    split: str
    seed: int
    seed_path: str
    camera: CameraSpec
    sun: SunSpec
    bodies: dict[str, BodySpec]
    render: RenderSpec = field(default_factory=RenderSpec)
    effects: EffectsSpec = field(default_factory=EffectsSpec)
    anomaly: AnomalySpec | None = None

    @property
    def variant(self) -> str:
        return "normal" if self.anomaly is None else "anomaly"
