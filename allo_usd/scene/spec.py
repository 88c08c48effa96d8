"""A scene spec: every value one scene layer records, fully resolved (nothing random left).

Planning code (sky, rig, placement) fills it; `author.scene.write_scene_layer` writes it.
Plain dataclasses so it can be built and tested without pxr.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.plan.settings import EffectsSpec, RenderSpec


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
    # Unit vector to the body's geometric (no light time, no aberration) centre, station frame, for the
    # record; `position` is along the apparent direction (docs/physics.md section 11). None: not recorded.
    geometric_direction: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class CameraSpec:
    position: tuple[float, float, float]
    rotation: np.ndarray                     # (3, 3) camera-to-station
    offset_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    perturbation: str = "euler-zyx"
    attempts: int = 1
    sigmas: tuple[float, float] | None = None   # (position m, angle rad) when the plan's are not the paper's
    pose_name: str = ""                          # a pose file's pose: its name, 'FILE:LINE', the file's sha256
    pose_source: str = ""
    pose_source_sha256: str = ""


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
    lens: CameraModel = DEFAULT_CAMERA       # the plan's camera; authored on the camera only when not the default

    @property
    def variant(self) -> str:
        return "normal" if self.anomaly is None else "anomaly"


@dataclass(frozen=True)
class CameraPose:
    index: int            # 1-based, as in the paper's Table II
    split: str            # "train" (1-40) or "test" (41-50)
    position: np.ndarray  # (3,) metres, station frame
    rotation: np.ndarray  # (3, 3) camera-to-station, camera looks down its -Z
    name: str = ""        # a pose file's pose (allo_usd.plan.posefile): its name,
    source: str = ""      # where it came from, 'FILE:LINE',
    source_sha256: str = ""  # and the file's sha256; "" for the built-in rig
