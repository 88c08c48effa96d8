"""Physical constants and the paper's camera (docs/physics.md sections 5-6): one place for every number the
pipeline shares."""

from __future__ import annotations

import math


SOLAR_CONSTANT = 1361.0  # W/m^2 at 1 AU


AU_M = 149_597_870_700.0


SUN_RADIUS_M = 696_340e3


EARTH_RADIUS_M = 6_371e3


MOON_RADIUS_M = 1_737.4e3


GM_SUN_M3_S2 = 1.32712440041e20  # the Sun's gravitational parameter


SECONDS_PER_DAY = 86_400.0


# Standard view transform, linear 1.0 = white: a white Lambertian surface facing a 1361 W/m^2 Sun
# renders at 1361/pi, so this exposure puts it at 0.9 (near, but below, white).
EXPOSURE = 0.9 * math.pi / SOLAR_CONSTANT


# 25 mm lens on a 36 x 20.25 mm back (16:9 crop of the paper's 36 x 24 mm), docs/physics.md section 6.
FOCAL_LENGTH_MM = 25.0


SENSOR_WIDTH_MM = 36.0


SENSOR_HEIGHT_MM = 20.25
