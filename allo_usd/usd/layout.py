"""Prim paths of the base stage and scene layers: one layout that author, read, inspect and the
Blender builder share (no pxr here, so blender/ may import it)."""

from __future__ import annotations


WORLD_NAME = "World"                    # the default prim of the base stage and every scene layer
WORLD = f"/{WORLD_NAME}"                # scene identity (AlloSceneAPI)
STATION = f"{WORLD}/Station"            # references ./station/Station.usda
SKY = f"{WORLD}/Sky"                    # the bodies and their sun lamps
STATION_SUN = f"{SKY}/SunLight"         # the sun lamp that lights the station (not the bodies)
RIG = f"{WORLD}/Rig"                    # base camera poses (Xforms: a scene has one camera, CAMERA)
CAMERA = f"{WORLD}/Camera"              # the render camera
INSPECTION_LIGHT = f"{CAMERA}/InspectionLight"
ANOMALY = f"{WORLD}/Anomaly"

RENDER = "/Render"
RENDER_SETTINGS = f"{RENDER}/Settings"
PRODUCTS = f"{RENDER}/Products"
IMAGE_PRODUCT = f"{PRODUCTS}/Image"
VARS = f"{RENDER}/Vars"


def body_path(body: str) -> str:
    """A celestial body's prim (e.g. /World/Sky/Moon)."""
    return f"{SKY}/{body}"


def body_sun_path(body: str) -> str:
    """The prim path of the sun lamp that lights only `body` (e.g. /World/Sky/EarthSunLight)."""
    return f"{SKY}/{body}SunLight"


def rig_pose_path(index: int) -> str:
    """A base camera pose's prim (e.g. /World/Rig/Pose07): an Xform with AlloCameraPoseAPI, not a camera."""
    return f"{RIG}/Pose{index:02d}"


def render_var(name: str) -> str:
    """A render var's prim (Color, ClassMask, Depth)."""
    return f"{VARS}/{name}"


# Inside an asset file (stages/station, bodies, anomalies): /<root>, its materials under
# /<root>/Looks and its meshes under /<root>/Geom. The station asset's root is STATION_ROOT.
STATION_ROOT = "Station"


def asset_root(root: str) -> str:
    return f"/{root}"


def asset_looks(root: str) -> str:
    return f"/{root}/Looks"


def asset_geom(root: str) -> str:
    return f"/{root}/Geom"


def asset_joint(root: str, chain) -> str:
    """A joint's Xform inside an asset: /<root>/Geom/<joint>/<child joint>... (`chain`: root joint first)."""
    return "/".join((asset_geom(root), *chain))


def station_joint(chain) -> str:
    """A station joint's prim in the base stage and scene layers (e.g. /World/Station/Geom/AlphaS/BetaS4a)."""
    return "/".join((STATION, "Geom", *chain))
