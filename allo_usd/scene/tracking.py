"""Sun tracking of the procedural station's solar arrays: the alpha and beta joint angles that point
each wing's cell side at the Sun (numpy only; docs/physics.md "Sun-tracking arrays").

The joints (allo_usd.assets.station.station_joints): each side's outboard truss turns by alpha about
the truss axis (station +Y); each wing turns by beta about its mast (its frame's Z) under it. A wing's
cells face +X of its own frame, so with the "b" wings (below the truss) mounted turned 180 degrees
about X, the cell normal in the station frame is

    n = Ry(alpha) Rx(flip) Rz(beta) x = (cos(alpha) cos(beta), s sin(beta), -sin(alpha) cos(beta)),

s = +1 for an "a" wing and -1 for a "b" wing. For the unit direction to the Sun d (station frame):

    alpha = atan2(-d_z, d_x)        (the SARJ turns continuously: wrapped into [-180, 180))
    beta  = s asin(d_y)             (clamped to the gimbal's limits, +-BETA_LIMIT degrees)

so n = d exactly while |asin(d_y)| (the Sun's elevation out of the station's orbital XZ plane, its
beta angle) is within the limit; beyond it the wing stops at the limit and misses the Sun by the
excess. The direction is the apparent one (SunSpec.direction), the one the Sun lamp shines along.
"""

from __future__ import annotations

import math

import numpy as np

from allo_usd.assets.station import ALPHA_JOINTS, WINGS, beta_joint_name, station_joints


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def sun_tracking_angles(direction) -> dict[str, float]:
    """{joint name: angle in degrees} pointing every wing's cells at the Sun along `direction`
    (station frame), within each joint's limits; joints listed in station_joints() order."""
    d = np.asarray(direction, dtype=np.float64)
    norm = float(np.linalg.norm(d))
    if not norm > 0.0 or not np.isfinite(d).all():
        raise ValueError(f"sun direction {tuple(d)} is not a finite non-zero vector")
    d = d / norm
    alpha = _wrap(math.degrees(math.atan2(-d[2], d[0])))
    elevation = math.degrees(math.asin(min(1.0, max(-1.0, d[1]))))
    limits = {j.name: (j.lower, j.upper) for j in station_joints()}
    out: dict[str, float] = {}
    for name in ALPHA_JOINTS.values():
        out[name] = alpha
    for wing in WINGS:
        s = 1.0 if wing.endswith("a") else -1.0
        name = beta_joint_name(wing)
        lo, hi = limits[name]
        out[name] = float(min(hi, max(lo, s * elevation)))
    return {j.name: out[j.name] for j in station_joints()}


def cell_normal(angles: dict[str, float], wing: str) -> np.ndarray:
    """The unit cell-side normal of `wing` (e.g. "S4a") in the station frame at `angles` (degrees)."""
    a = math.radians(angles[ALPHA_JOINTS[1 if wing[0] == "S" else -1]])
    b = math.radians(angles[beta_joint_name(wing)])
    s = 1.0 if wing.endswith("a") else -1.0
    return np.array([math.cos(a) * math.cos(b), s * math.sin(b), -math.sin(a) * math.cos(b)])
