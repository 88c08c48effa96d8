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

The S1/P1 thermal radiators turn about their beam (station +Y) by theta, edge-on to the Sun (the Sun
then heats them least): their panels span Y and r(theta) = Ry(theta) r0, r0 = (-sin 35, 0, -cos 35)
(down and aft at rest), so they are edge-on when r(theta) is parallel to d's projection on the XZ
plane. With psi(v) = atan2(v_x, v_z), the two solutions are theta = psi(d) - psi(r0) and that + 180
degrees; the one inside the joint's limits with the smaller turn is taken, else the limit nearer to
a solution (the panels then meet the Sun at the excess angle). A Sun along +-Y is edge-on at any
theta: the radiators stay at rest.
"""

from __future__ import annotations

import math

import numpy as np

from allo_usd.assets.station import (ALPHA_JOINTS, RADIATOR_JOINTS, RADIATOR_PHI, WINGS, beta_joint_name,
                                     station_joints)
from allo_usd.core import fixedmath as fm


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def sun_tracking_angles(direction) -> dict[str, float]:
    """{joint name: angle in degrees} pointing every wing's cells at the Sun along `direction`
    (station frame), within each joint's limits; joints listed in station_joints() order."""
    d = np.asarray(direction, dtype=np.float64)
    norm = float(fm.norm(d))
    if not norm > 0.0 or not np.isfinite(d).all():
        raise ValueError(f"sun direction {tuple(d)} is not a finite non-zero vector")
    d = d / norm
    alpha = _wrap(math.degrees(fm.arctan2(-d[2], d[0])))
    elevation = math.degrees(fm.arcsin(min(1.0, max(-1.0, d[1]))))
    limits = {j.name: (j.lower, j.upper) for j in station_joints()}
    out: dict[str, float] = {}
    for name in ALPHA_JOINTS.values():
        out[name] = alpha
    for wing in WINGS:
        s = 1.0 if wing.endswith("a") else -1.0
        name = beta_joint_name(wing)
        lo, hi = limits[name]
        out[name] = float(min(hi, max(lo, s * elevation)))
    theta = radiator_angle(d, limits[RADIATOR_JOINTS[1]])
    for name in RADIATOR_JOINTS.values():
        out[name] = theta
    return {j.name: out[j.name] for j in station_joints()}


def radiator_angle(d: np.ndarray, limits: tuple[float, float]) -> float:
    """The radiator joint angle (degrees) turning the panels edge-on to the unit Sun direction `d`."""
    if fm.hypot(d[0], d[2]) < 1e-9:
        return 0.0
    psi_d = math.degrees(fm.arctan2(d[0], d[2]))
    psi_r = math.degrees(fm.arctan2(-fm.sin(RADIATOR_PHI), -fm.cos(RADIATOR_PHI)))
    lo, hi = limits
    best = None
    for theta in (_wrap(psi_d - psi_r), _wrap(psi_d - psi_r + 180.0)):
        clamped = min(hi, max(lo, theta))
        key = (abs(clamped - theta), abs(clamped))
        if best is None or key < best[0]:
            best = (key, clamped)
    return float(best[1])


def radiator_normal(angles: dict[str, float], side: int = 1) -> np.ndarray:
    """The unit normal of the S1 (side 1) or P1 (-1) radiator panels in the station frame at `angles`."""
    t = math.radians(angles[RADIATOR_JOINTS[side]])
    r0 = np.array([-fm.sin(RADIATOR_PHI), 0.0, -fm.cos(RADIATOR_PHI)])
    r = np.array([fm.cos(t) * r0[0] + fm.sin(t) * r0[2], 0.0, -fm.sin(t) * r0[0] + fm.cos(t) * r0[2]])
    return np.cross(r, [0.0, 1.0, 0.0])


def cell_normal(angles: dict[str, float], wing: str) -> np.ndarray:
    """The unit cell-side normal of `wing` (e.g. "S4a") in the station frame at `angles` (degrees)."""
    a = math.radians(angles[ALPHA_JOINTS[1 if wing[0] == "S" else -1]])
    b = math.radians(angles[beta_joint_name(wing)])
    s = 1.0 if wing.endswith("a") else -1.0
    return np.array([fm.cos(a) * fm.cos(b), s * fm.sin(b), -fm.sin(a) * fm.cos(b)])
