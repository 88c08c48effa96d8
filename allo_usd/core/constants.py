"""Physical constants and the paper's camera (docs/physics.md sections 5-6): one place for every number the
pipeline shares."""

from __future__ import annotations

import math


SOLAR_CONSTANT = 1361.0  # W/m^2 at 1 AU: IAU 2015 Resolution B3, nominal total solar irradiance


AU_M = 149_597_870_700.0


# Radii (docs/physics.md, "Radii"): each body is a sphere of one radius, from a named source.
# The Sun: IAU 2015 Resolution B3, nominal solar radius.
SUN_RADIUS_M = 695_700e3


# The Earth: mean radius, IAU Working Group on Cartographic Coordinates and Rotational Elements
# (WGCCRE) report 2009 (Archinal et al. 2011), kept in the 2015 report; not the IAU 2015 B3 nominal
# equatorial radius 6,378.1 km: seen from near the Earth's equator plane (the station's sky) and as the
# shadow's cross-section, the mean radius is within 5.6e-4 of the oblate Earth's mean outline, the
# equatorial radius up to 1.7e-3 off.
EARTH_RADIUS_M = 6_371.0084e3


# The Moon: mean radius, WGCCRE reports 2009 and 2015.
MOON_RADIUS_M = 1_737.4e3


# Colour of the Sun's light (linear RGB, the lamps' inputs:color and so the disc they draw): white.
# The lamps' intensity is the total solar irradiance and the albedos are Bond (bolometric) albedos, so
# each channel carries the whole spectrum; the renderer's RGB is colour-neutral (docs/physics.md,
# "Sun colour").
SUN_COLOR = (1.0, 1.0, 1.0)


GM_SUN_M3_S2 = 1.32712440041e20  # the Sun's gravitational parameter


SECONDS_PER_DAY = 86_400.0


# Standard view transform, linear 1.0 = white: a white Lambertian surface facing a 1361 W/m^2 Sun
# renders at 1361/pi, so this exposure puts it at 0.9 (near, but below, white).
EXPOSURE = 0.9 * math.pi / SOLAR_CONSTANT


# 25 mm lens on a 36 x 20.25 mm back (16:9 crop of the paper's 36 x 24 mm), docs/physics.md section 6.
FOCAL_LENGTH_MM = 25.0


SENSOR_WIDTH_MM = 36.0


SENSOR_HEIGHT_MM = 20.25
