"""The plain scene description that crosses from `read` (pxr) to `blender` (bpy).

Frozen dataclasses of numbers, strings and numpy arrays: nothing here imports pxr or bpy, so
it can cross a process boundary (pickle) and be compared for incremental scene updates.
Matrices are 4x4 float64, column-vector convention (p' = M @ [p, 1]).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from allo_usd.core.sensor import SensorParams
from allo_usd.plan.settings import EffectFlags, QualitySettings
from allo_usd.usd.layout import CAMERA, INSPECTION_LIGHT, STATION_SUN

DISPLAY_COLOR_ATTRIBUTE = "displayColor"   # the per-corner colour attribute MeshDesc.colors is built into


@dataclass(frozen=True, eq=False)
class MeshDesc:
    path: str
    points: np.ndarray          # (N, 3) float32, local
    face_counts: np.ndarray     # (F,) int32
    face_indices: np.ndarray    # (sum,) int32
    uv: np.ndarray | None       # (len(face_indices), 2) float32, face-varying
    smooth: bool
    material: str               # key into SceneDescription.materials
    matrix: np.ndarray          # local-to-world
    class_id: int
    ray_visibility: str = "all"  # all | cameraOnly (the Sun's disc) | noShadow (Moon, Earth)
    object: str = ""            # the object it is part of (its instance id): an anomaly-class mesh's anomaly
                                # object (the prim its class label is applied on); "" = the mesh itself
    colors: np.ndarray | None = None  # (len(face_indices), 4) float32 linear RGBA per face vertex: the display
                                      # colour and opacity (read by a material with color_attribute), or None
    subsets: tuple = ()               # ((material key, (K,) int32 face indices), ...): faces bound to other
                                      # materials than `material` (GeomSubsets of the materialBind family)

    @property
    def object_path(self) -> str:
        return self.object or self.path


@dataclass(frozen=True)
class MaterialDesc:
    path: str
    base_color: tuple[float, float, float]
    metallic: float
    roughness: float
    base_color_texture: str | None = None      # absolute, resolved file path
    emissive_color: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ior: float = 1.5                           # UsdPreviewSurface ior; 1.0 = no specular layer
    opacity: float = 1.0                       # UsdPreviewSurface opacity; 0 = fully transparent (the Sun's sphere)
    color_attribute: str | None = None         # base colour and alpha from this per-corner colour attribute
                                               # (MeshDesc.colors), not base_color and opacity


@dataclass(frozen=True, eq=False)
class CameraDesc:
    matrix: np.ndarray
    focal_length_mm: float
    sensor_width_mm: float
    sensor_height_mm: float
    clip: tuple[float, float]
    path: str = CAMERA                     # the UsdGeom.Camera prim (the Blender object's name)
    horizontal_offset_mm: float = 0.0      # horizontalApertureOffset, verticalApertureOffset in mm (the
    vertical_offset_mm: float = 0.0        # principal point: core.camera_model; Blender's lens shift)
    f_stop: float = 0.0                    # UsdGeom.Camera fStop: 0 no depth of field (Blender dof.use_dof off)
    focus_distance_m: float = 0.0          # UsdGeom.Camera focusDistance (m), read when f_stop > 0


@dataclass(frozen=True)
class LightLink:
    """Which meshes a light lights, resolved by the reader from the light's USD `lightLink`
    collection: every mesh except `paths` (exclude=True), or only `paths` (exclude=False)."""
    exclude: bool
    paths: tuple[str, ...]                 # MeshDesc paths


@dataclass(frozen=True)
class LampRays:
    """What a lamp lights and whether it casts shadows: UsdLux inputs:diffuse / inputs:specular (1 or 0:
    Cycles' per-lamp diffuse / glossy ray visibility) and ShadowAPI inputs:shadow:enable (Cycles' use_shadow)."""
    diffuse: bool = True
    specular: bool = True
    shadow: bool = True


@dataclass(frozen=True)
class SunDesc:
    direction: tuple[float, float, float]  # unit, towards the Sun
    irradiance: float                      # W/m^2 at normal incidence, as UsdLux defines it (inputs:normalize
                                           # honoured); > 0: a lamp at 0 is left out of the description
    angle_deg: float                       # angular diameter
    color: tuple[float, float, float]
    path: str = STATION_SUN                # the UsdLux.DistantLight prim
    link: LightLink | None = None          # None: lights every mesh
    camera_visible: bool = False           # its disc is drawn in camera rays (a lamp not restricted to named
                                           # objects: the Sun itself, not a body's own lamp)
    rays: LampRays | None = None           # None: every ray type and shadows (LampRays())


@dataclass(frozen=True, eq=False)
class SpotDesc:
    matrix: np.ndarray
    radius: float
    intensity: float                       # surface radiance, W/m^2/sr (UsdLux intensity, normalize honoured)
    color: tuple[float, float, float]
    cone_angle_deg: float                  # half angle
    softness: float
    path: str = INSPECTION_LIGHT           # the UsdLux.SphereLight prim (the Blender object's name)
    shaped: bool = True                    # ShapingAPI applied: a spot lamp; else a point lamp (all directions)
    link: LightLink | None = None          # None: lights every mesh
    rays: LampRays | None = None           # None: LampRays()


@dataclass(frozen=True, eq=False)
class AreaDesc:
    """A UsdLux RectLight (shape RECTANGLE, size = width, height) or DiskLight (shape DISK, size = the
    diameter twice): one-sided, emitting along its local -Z, as a Blender area lamp."""
    path: str
    matrix: np.ndarray
    shape: str                             # RECTANGLE | DISK
    size: tuple[float, float]              # local, m (Blender's size, size_y)
    radiance: float                        # W/m^2/sr (UsdLux intensity x 2^exposure, normalize honoured)
    power: float                           # W: radiance x world-space area x pi (a Lambertian one-sided emitter)
    color: tuple[float, float, float]
    texture: str | None = None             # RectLight inputs:texture:file, absolute
    link: LightLink | None = None
    rays: LampRays | None = None


@dataclass(frozen=True, eq=False)
class CylinderDesc:
    """A UsdLux CylinderLight (its axis the local X, no end caps) as an emission-only cylinder mesh."""
    path: str
    matrix: np.ndarray
    radius: float
    length: float
    radiance: float                        # W/m^2/sr: the Emission shader's strength
    color: tuple[float, float, float]
    link: LightLink | None = None
    rays: LampRays | None = None


@dataclass(frozen=True, eq=False)
class DomeDesc:
    """A UsdLux DomeLight as the world background: radiance color x intensity x 2^exposure (W/m^2/sr),
    optionally times a lat-long texture turned by `rotation` (3x3, dome local -> world)."""
    path: str
    color: tuple[float, float, float]
    strength: float
    texture: str | None = None
    rotation: np.ndarray | None = None
    rays: LampRays | None = None


@dataclass(frozen=True)
class RenderDesc(QualitySettings):
    """The quality settings (allo:render:*, declared once in QualitySettings) and the rest of the
    render settings prim."""
    resolution: tuple[int, int]
    preset: str
    seed: int
    exposure: float                        # linear film exposure: the camera's UsdGeom exposure scale
    threads: int
    outputs: tuple[str, ...]               # passes (plan.settings.PASSES) of the render vars the product orders
    estimate: bool = False                 # a fixed render also estimates its error (one more render, not authored:
                                           # `allo-usd render --estimate`, blender.target.estimate_fixed)


@dataclass(frozen=True)
class EffectsDesc(EffectFlags):
    """The effect switches (allo:effects:*, declared once in EffectFlags) and the sensor."""
    sensor: SensorParams | None = None     # the layer's allo:effects:sensor:* (when sensor_noise)


@dataclass(frozen=True, eq=False)
class SceneDescription:
    layer: str
    meshes: tuple[MeshDesc, ...]
    materials: dict[str, MaterialDesc]
    camera: CameraDesc
    suns: tuple[SunDesc, ...]              # sun lamps that are on, in stage order (station's, bodies')
    spot: SpotDesc | None                  # the inspection light (layout.INSPECTION_LIGHT)
    render: RenderDesc
    effects: EffectsDesc
    meta: dict = field(default_factory=dict)  # scene identity and provenance (epoch, pose, seed, ...)
    lights: tuple = ()                     # every other local lamp, in stage order: SpotDesc (sphere lights
                                           # other than the inspection light), AreaDesc, CylinderDesc
    dome: DomeDesc | None = None           # the one DomeLight (the world background), if any

    @property
    def sun(self) -> SunDesc | None:
        """The station's sun lamp (/World/Sky/SunLight), None when it is off (umbra)."""
        return next((s for s in self.suns if s.path == STATION_SUN), None)
