"""The camera's lens and sensor (numpy only): one `CameraModel`, its pinhole K, its UsdGeom.Camera values.

`DEFAULT_CAMERA` is the paper's Table I camera (25 mm lens on a 36 x 20.25 mm back, the 16:9 crop of
36 x 24 mm; clipping 0.05 m .. 1e12 m), which the base stage authors. A plan's `[camera]` gives another.

Pixels are square and the sensor fit is horizontal (Blender's HORIZONTAL, UsdGeom.Camera's aperture):
fx = fy = focal_length_mm / sensor_width_mm * W for a W x H image.

Principal point offset (dx, dy): pixels from the image centre, x right, y down. The principal point
(where the optical axis meets the image) is then at the centre + (dx, dy).

UsdGeom.Camera (docs/physics.md, "Camera units"): the view window on the film, in the aperture's units,
is [-hAp/2 + hOff, hAp/2 + hOff] x [-vAp/2 + vOff, vAp/2 + vOff] (film x right, y up; GfCamera's
frustum). The optical axis (film 0, 0) therefore sits at u = W/2 - hOff * W / hAp from the left edge
and v = H/2 + vOff * H / vAp from the top, so with square pixels (mm per pixel = sensor_width / W):

    horizontalApertureOffset = -dx * sensor_width_mm / W        (mm)
    verticalApertureOffset   = +dy * sensor_width_mm / W        (mm; = dy * sensor_height / H)

and Blender's lens shift (fractions of the sensor width under the horizontal fit, shift_x moving the
view right, shift_y up) is shift_x = hOff / hAp, shift_y = vOff / hAp.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from allo_usd.core.constants import FOCAL_LENGTH_MM, SENSOR_HEIGHT_MM, SENSOR_WIDTH_MM

# What the layer reader (usd/reader_bounds.py) lets through to Blender, and so what a plan's [camera] may ask for.
# Each lies inside the hard limits of the bpy RNA property the value ends in (tests/usd/test_reader_bounds.py).
LENS_MM = (1.0, 100_000.0)        # Camera.lens (Blender's hard minimum is 1 mm)
SENSOR_MM = (1.0, 10_000.0)       # Camera.sensor_width / sensor_height (hard minimum 1 mm)
CLIP_M = (1e-5, 1e13)             # Camera.clip_start / clip_end (hard minimum 1e-6 m); the Sun is 1.5e11 m away
# |aperture offset| / aperture, per axis: the principal point stays inside the image (|dx| <= W/2,
# |dy| <= H/2), so Blender's |shift_x|, |shift_y| <= 0.5, well inside its hard limits of 10.
MAX_SHIFT = 0.5

CLIPPING_RANGE_M = (0.05, 1.0e12)   # far plane beyond the Sun at 1.5e11 m (scheme C, true scale)


@dataclass(frozen=True)
class CameraModel:
    focal_length_mm: float = FOCAL_LENGTH_MM
    sensor_width_mm: float = SENSOR_WIDTH_MM
    sensor_height_mm: float = SENSOR_HEIGHT_MM
    clipping_range_m: tuple[float, float] = CLIPPING_RANGE_M
    principal_point_offset_px: tuple[float, float] = (0.0, 0.0)   # (dx right, dy down) from the image centre

    def focal_px(self, width: int) -> float:
        return self.focal_length_mm / self.sensor_width_mm * width

    def principal_point(self, width: int, height: int) -> tuple[float, float]:
        """(cx, cy) in pixel-corner coordinates: the image spans [0, W] x [0, H], pixel (c, r)'s centre
        is at (c + 0.5, r + 0.5) (core.geometry.camera_intrinsics, placement, ray casting)."""
        dx, dy = self.principal_point_offset_px
        return width / 2.0 + dx, height / 2.0 + dy

    def intrinsics(self, width: int, height: int) -> np.ndarray:
        """3x3 K, pixel-corner convention (see `principal_point`)."""
        f = self.focal_px(width)
        cx, cy = self.principal_point(width, height)
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])

    def intrinsics_opencv(self, width: int, height: int) -> np.ndarray:
        """3x3 K, OpenCV pixel centres (pixel (c, r)'s centre at (c, r)): the corner K shifted by -0.5."""
        k = self.intrinsics(width, height)
        k[0, 2] -= 0.5
        k[1, 2] -= 0.5
        return k

    def aperture_offsets_mm(self, width: int) -> tuple[float, float]:
        """(horizontalApertureOffset, verticalApertureOffset) in mm for a `width`-pixel image (module doc)."""
        dx, dy = self.principal_point_offset_px
        mm_per_px = self.sensor_width_mm / width
        return float(-dx * mm_per_px) + 0.0, float(dy * mm_per_px) + 0.0   # + 0.0: no -0.0

    def scaled(self, factor: float) -> "CameraModel":
        """The same lens for an image `factor` times as wide (and high): the offset in pixels scales."""
        dx, dy = self.principal_point_offset_px
        return replace(self, principal_point_offset_px=(dx * factor, dy * factor))

    def half_tangents(self) -> tuple[float, float]:
        """tan of the half field of view across x and y (centred principal point)."""
        return self.sensor_width_mm / 2 / self.focal_length_mm, self.sensor_height_mm / 2 / self.focal_length_mm

    def window_centre(self, width: int) -> tuple[float, float]:
        """The image centre's direction as (x/-z, y/-z) in the camera frame (USD axes: x right, y up):
        (-dx / f, dy / f), f the focal length in pixels of a `width`-pixel image."""
        f = self.focal_px(width)
        dx, dy = self.principal_point_offset_px
        return -dx / f + 0.0, dy / f + 0.0


DEFAULT_CAMERA = CameraModel()


def sensor_height_for(sensor_width_mm: float, width: int, height: int) -> float:
    """The sensor height square pixels give a `width` x `height` image on a `sensor_width_mm` back."""
    return sensor_width_mm * height / width
