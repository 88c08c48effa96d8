"""The base stage: station, bodies, camera rig, inspection light, render settings, labels.

Everything a scene does not change lives here, once. Scene layers sublayer `stages/base.usda`
and override only camera, sky, anomaly, effects and render settings.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from allo_usd.core.camera_model import CLIPPING_RANGE_M, DEFAULT_CAMERA, CameraModel
from allo_usd.core.constants import EXPOSURE, FOCAL_LENGTH_MM, SENSOR_HEIGHT_MM, SENSOR_WIDTH_MM
from allo_usd.core.geometry import matrix_to_quat
from allo_usd.assets.mesh import Asset
from allo_usd.usd import schema
from allo_usd.core.constants import EARTH_RADIUS_M, MOON_RADIUS_M, SOLAR_CONSTANT, SUN_COLOR, SUN_RADIUS_M
from allo_usd.sky import model as sky
from allo_usd.usd import attributes as A
from allo_usd.usd.attributes import CLASS_MASK_SOURCE
from allo_usd.plan.settings import DEFAULT_PASSES, PASSES
from allo_usd.usd import layout
from allo_usd.usd.layout import STATION_SUN, body_sun_path
from allo_usd.usd.asset import commit_layer, new_layer, stage_metadata, write_asset, write_variant_asset
from allo_usd.scene.spec import CameraPose
from allo_usd.core import fixedmath as fm
from allo_usd.usd.tree import BASE_STAGE_FILE

# UsdGeom.Camera lens values are tenths of a scene unit (docs/physics.md section 6).
FOCAL_LENGTH = FOCAL_LENGTH_MM / 100.0
H_APERTURE = SENSOR_WIDTH_MM / 100.0
V_APERTURE = SENSOR_HEIGHT_MM / 100.0
CLIPPING_RANGE = CLIPPING_RANGE_M  # far plane beyond the Sun at 1.5e11 m (core.camera_model: Table I)

# Inspection light: a 5 cm sphere emitting radiance L (UsdLux: an un-normalised SphereLight's intensity is
# the radiance of its surface; this project is radiometric, so W/m^2/sr), shaped to a 35-degree half-angle
# cone. Its radiant power is 4 pi^2 r^2 L (see blender/build.py).
SPOT_RADIUS_M = 0.05
SPOT_INTENSITY = 20_000.0
SPOT_CONE_DEG = 35.0
SPOT_SOFTNESS = 0.3
SPOT_OFFSET_M = (0.25, -0.12, 0.0)  # beside the lens, in the camera frame

DEFAULT_RESOLUTION = (1920, 1080)

# Sun lamps (docs/physics.md sections 5, 7, 10): DistantLights with inputs:normalize = true, so that, as
# UsdLux defines it, inputs:intensity is the irradiance at normal incidence (W/m^2; the project is
# radiometric) and inputs:angle the Sun's angular diameter. The station's lamp lights everything. On an
# eclipse day (the station's, the Earth's and the Moon's lit fractions differ) the day's layer links
# light: the station's lamp then excludes the Earth and the Moon, and each of those gets a lamp of its
# own (inactive here) that lights only it, with the Sun as seen from its centre and its own eclipse.
LIT_BODIES = tuple(name.capitalize() for name in sky.LIT_BODIES)  # prim names of the bodies with a lamp


def set_pose(prim, position, rotation) -> None:
    """Author translate (double3) + orient (quatd), replacing any earlier op order."""
    from pxr import Gf, UsdGeom

    xf = UsdGeom.Xformable(prim)
    xf.ClearXformOpOrder()
    xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, position)))
    xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(gf_quatd(rotation))


def gf_quatd(rotation):
    """A rotation matrix as the Gf.Quatd of an xformOp:orient (the one conversion authoring uses)."""
    from pxr import Gf

    q = matrix_to_quat(np.asarray(rotation, dtype=np.float64))
    return Gf.Quatd(float(q[0]), Gf.Vec3d(*map(float, q[1:])))


def camera_ev(film_exposure: float) -> float:
    """A linear film exposure as UsdGeom.Camera `exposure` (EV, log2), rounded to the float it is stored as."""
    return float(np.float32(fm.log2(film_exposure)))


def define_camera(stage, path: str):
    from pxr import Gf, UsdGeom

    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    cam.CreateFocalLengthAttr(FOCAL_LENGTH)
    cam.CreateHorizontalApertureAttr(H_APERTURE)
    cam.CreateVerticalApertureAttr(V_APERTURE)
    cam.CreateClippingRangeAttr(Gf.Vec2f(*CLIPPING_RANGE))
    return cam


def write_base_stage(stages_dir: Path, station: Asset, bodies: dict[str, Asset],
                     anomalies: dict[str, dict[str, Asset]], poses: list[CameraPose],
                     station_doc: str = "", lens: CameraModel = DEFAULT_CAMERA,
                     size: tuple[int, int] | None = None) -> Path:
    """Write every asset and `base.usda` into `stages_dir`; returns the base stage path. `lens`, `size`:
    the camera and image size the rig's views were chosen through, recorded on each pose (define_rig)."""
    from pxr import Usd

    schema.register()
    stages_dir = Path(stages_dir)
    write_assets(stages_dir, station, bodies, anomalies, station_doc)
    path = stages_dir / BASE_STAGE_FILE
    layer, tmp = new_layer(path)
    layer.documentation = ("allo-usd base stage: a station in lunar orbit (station frame: +Z zenith away "
                           "from the Moon, +X flight direction), the Sun, Earth and Moon at true scale, "
                           "50 base camera poses, the inspection light and render settings. "
                           "Generated by scripts/make_base_stage.py; do not edit by hand.")
    stage = Usd.Stage.Open(layer)
    define_world(stage)
    define_sky(stage, bodies)
    define_rig(stage, poses, lens, size)
    define_render_camera(stage, poses[0])
    define_render_settings(stage)
    commit_layer(layer, tmp, path)
    return path


def write_assets(stages_dir: Path, station: Asset, bodies: dict[str, Asset],
                 anomalies: dict[str, dict[str, Asset]], station_doc: str) -> None:
    """The station, body and anomaly asset files the base stage references."""
    write_asset(station, stages_dir / "station", "station", root=layout.STATION_ROOT, doc=station_doc)
    for name, body in bodies.items():
        write_asset(body, stages_dir / "bodies", "celestial_body", root=name)
    for name, variants in anomalies.items():
        write_variant_asset(variants, stages_dir / "anomalies", name, "anomaly")


def define_world(stage) -> None:
    """The default prim (an assembly) and the station referenced under it."""
    from pxr import Kind, Usd, UsdGeom

    world = UsdGeom.Xform.Define(stage, layout.WORLD).GetPrim()
    Usd.ModelAPI(world).SetKind(Kind.Tokens.assembly)
    stage_metadata(stage, layout.WORLD_NAME)
    station_prim = stage.DefinePrim(layout.STATION)
    station_prim.GetReferences().AddReference("./station/Station.usda")


def _define_sun(stage, path: str, doc: str):
    """A sun DistantLight at 1 AU, unposed, intensity = irradiance (normalised); returns its light-link
    collection."""
    from pxr import Gf, UsdLux

    lamp = UsdLux.DistantLight.Define(stage, path)
    lamp.CreateIntensityAttr(SOLAR_CONSTANT)
    lamp.CreateNormalizeAttr(True)
    lamp.CreateAngleAttr(0.533)
    lamp.CreateColorAttr(Gf.Vec3f(*SUN_COLOR))  # the Sun's colour, once (docs/physics.md, Sun colour)
    schema.apply(lamp.GetPrim(), "AlloEclipseAPI")
    set_pose(lamp.GetPrim(), (0, 0, 0), np.eye(3))
    lamp.GetPrim().SetDocumentation(doc)
    return UsdLux.LightAPI(lamp).GetLightLinkCollectionAPI()


def define_sky(stage, bodies: dict[str, Asset]) -> None:
    """The sky group: the station's sun lamp, each lit body's own lamp, then the bodies."""
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom

    sky_prim = UsdGeom.Xform.Define(stage, layout.SKY).GetPrim()
    Usd.ModelAPI(sky_prim).SetKind(Kind.Tokens.group)
    lit_bodies = [name for name in LIT_BODIES if name in bodies]
    _define_sun(stage, STATION_SUN, "The Sun as the station sees it, times the station's lit fraction (off in "
                "umbra); intensity is the irradiance (normalize), angle the Sun's angular diameter. Lights "
                "everything, except on an eclipse day, when the Earth and the Moon have lamps of their own.")
    for name in lit_bodies:
        link = _define_sun(stage, body_sun_path(name), f"The Sun as the {name} sees it, times the {name}'s own "
                           f"lit fraction (off in total eclipse). Lights only the {name}; active only on an "
                           "eclipse day, when the lit fractions differ.")
        link.CreateIncludeRootAttr(False)
        link.CreateIncludesRel().SetTargets([Sdf.Path(layout.body_path(name))])
        link.GetPrim().SetActive(False)
    default_body_pos = {"Sun": (1.495978707e11, 0, 0), "Earth": (0, 3.844e8, 0), "Moon": (0, 0, -7.0e7)}
    default_body_radius = {"Sun": SUN_RADIUS_M, "Earth": EARTH_RADIUS_M, "Moon": MOON_RADIUS_M}
    for name in bodies:
        prim = UsdGeom.Xform.Define(stage, layout.body_path(name)).GetPrim()
        prim.GetReferences().AddReference(f"./bodies/{name}.usda")
        xf = UsdGeom.Xformable(prim)
        xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*default_body_pos[name]))
        xf.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*[default_body_radius[name]] * 3))
        # The Sun's sphere is fully transparent (its material's opacity is 0): the station's DistantLight
        # draws the disc and lights the scene, the sphere only labels the disc's pixels in the class mask
        # (and here is seen by camera rays only). Moon and Earth cast no shadow on the lamps' rays, since
        # each lamp's intensity already holds its eclipse.
        schema.apply(prim, "AlloRayVisibilityAPI")
        prim.GetAttribute(A.RAY_VISIBILITY.name).Set("cameraOnly" if name == "Sun" else "noShadow")


def rig_lens_values(lens: CameraModel = DEFAULT_CAMERA, size: tuple[int, int] | None = None) -> list:
    """[(AlloCameraPoseAPI lens attribute, value)] of `lens`, in UsdGeom.Camera's units (tenths of a scene
    unit); the aperture offsets only when the principal point is off centre (they need the image width)."""
    from pxr import Gf

    values = [(A.POSE_FOCAL_LENGTH, lens.focal_length_mm / 100.0),
              (A.POSE_HORIZONTAL_APERTURE, lens.sensor_width_mm / 100.0),
              (A.POSE_VERTICAL_APERTURE, lens.sensor_height_mm / 100.0),
              (A.POSE_CLIPPING_RANGE, Gf.Vec2f(*map(float, lens.clipping_range_m)))]
    if tuple(lens.principal_point_offset_px) != (0.0, 0.0) and size is not None:
        h_off, v_off = lens.aperture_offsets_mm(size[0])
        values += [(A.POSE_HORIZONTAL_APERTURE_OFFSET, h_off / 100.0), (A.POSE_VERTICAL_APERTURE_OFFSET, v_off / 100.0)]
    return values


def define_rig(stage, poses: list[CameraPose], lens: CameraModel = DEFAULT_CAMERA,
               size: tuple[int, int] | None = None) -> None:
    """The base camera poses: one Xform each (not a UsdGeom.Camera: a composed scene offers outside tools
    one camera, /World/Camera), its transform the pose, AlloCameraPoseAPI recording index, split and the
    lens the views were chosen through."""
    from pxr import UsdGeom

    rig = UsdGeom.Scope.Define(stage, layout.RIG)
    rig.GetPrim().SetDocumentation("Base camera poses: 1-40 train, 41-50 test (paper Table II). Each is an Xform "
                                   "(the camera looks down its -Z, +Y up) whose AlloCameraPoseAPI records the lens; "
                                   "the scene's one camera is /World/Camera.")
    lens_values = rig_lens_values(lens, size)
    for pose in poses:
        prim = UsdGeom.Xform.Define(stage, layout.rig_pose_path(pose.index)).GetPrim()
        set_pose(prim, pose.position, pose.rotation)
        schema.apply(prim, "AlloCameraPoseAPI")
        prim.GetAttribute(A.POSE_INDEX.name).Set(pose.index)
        prim.GetAttribute(A.POSE_SPLIT.name).Set(pose.split)
        for attr, value in lens_values:
            prim.GetAttribute(attr.name).Set(value)


def define_render_camera(stage, first: CameraPose) -> None:
    """The render camera at the first pose, with the inspection light beside its lens."""
    from pxr import Gf, UsdLux

    camera = define_camera(stage, layout.CAMERA)
    camera.CreateExposureAttr(camera_ev(EXPOSURE))  # the linear film exposure is 2^exposure (fStop 1, time 1, iso 100)
    set_pose(camera.GetPrim(), first.position, first.rotation)
    spot = UsdLux.SphereLight.Define(stage, layout.INSPECTION_LIGHT)
    spot.CreateRadiusAttr(SPOT_RADIUS_M)
    spot.CreateIntensityAttr(SPOT_INTENSITY)
    spot.CreateColorAttr(Gf.Vec3f(1.0, 0.95, 0.88))
    shaping = UsdLux.ShapingAPI.Apply(spot.GetPrim())
    shaping.CreateShapingConeAngleAttr(SPOT_CONE_DEG)
    shaping.CreateShapingConeSoftnessAttr(SPOT_SOFTNESS)
    set_pose(spot.GetPrim(), SPOT_OFFSET_M, np.eye(3))


# Render vars: prim name -> (pass, source, data type, doc), one per pass of allo_usd.plan.settings.PASSES, in
# that order. Source names follow Hydra's AOV names where one exists (color, depth, normal, primId). The
# base product orders the default passes; a scene layer that asks for others orders its own.
RENDER_VARS = {
    "Color": ("rgb", "color", "color3f", "Written as 8-bit sRGB PNG (STEM.png): linear scene-referred radiance "
              "(W/m^2/sr) times the camera's linear exposure scale (UsdGeom.Camera exposure attributes), clipped."),
    "LinearColor": ("exr", "color", "color3f", "Written as linear half EXR (STEM.exr): the same radiance as Color, "
                    "unclipped."),
    "ClassMask": ("mask", CLASS_MASK_SOURCE, "uchar", "0 background, 1 station and celestial bodies, 2 anomaly "
                  "(STEM_mask.png)."),
    "Depth": ("depth", "depth", "float", "Camera depth in metres along the view axis, float32 EXR "
              "(STEM_depth.exr); written only when a product orders it."),
    "Normal": ("normal", "normal", "normal3f", "World-space unit surface normal (Cycles' Normal pass), float32 EXR "
               "X, Y, Z (STEM_normal.exr), 0 where nothing is hit; written only when a product orders it."),
    "PrimId": ("instance", "primId", "int", "Object id, 1 + the index of the object's path among the scene's "
               "sorted object paths (a station or body mesh prim; the anomaly as one object), 0 background; uint16 PNG (STEM_instance.png), id -> prim path in the JSON; "
               "written only when a product orders it."),
    "AmodalMask": ("amodal", A.NAMESPACE + "amodalMask", "uchar", "0 background, 2 anomaly: the anomaly's full "
                   "silhouette, the station and bodies invisible to camera rays (a second, 1-sample mask-only "
                   "render), uint8 PNG (STEM_amodal.png); written only when a product orders it."),
}
PASS_VARS = {p: name for name, (p, _, _, _) in RENDER_VARS.items()}   # pass -> var prim name


def product_vars(passes) -> list[str]:
    """The render var prim paths a product orders for `passes` (in PASSES order)."""
    return [layout.render_var(PASS_VARS[p]) for p in PASSES if p in passes]


def define_render_settings(stage) -> None:
    """Render settings (with the quality and effects schemas), the image product and its vars."""
    from pxr import Gf, Sdf, UsdGeom, UsdRender

    UsdGeom.Scope.Define(stage, layout.RENDER)
    settings = UsdRender.Settings.Define(stage, layout.RENDER_SETTINGS)
    settings.CreateResolutionAttr(Gf.Vec2i(*DEFAULT_RESOLUTION))
    settings.CreatePixelAspectRatioAttr(1.0)
    settings.CreateCameraRel().SetTargets([Sdf.Path(layout.CAMERA)])
    settings.CreateProductsRel().SetTargets([Sdf.Path(layout.IMAGE_PRODUCT)])
    settings.CreateIncludedPurposesAttr([UsdGeom.Tokens.default_, UsdGeom.Tokens.render])
    schema.apply(settings.GetPrim(), "AlloRenderQualityAPI")
    schema.apply(settings.GetPrim(), "AlloEffectsAPI")
    UsdGeom.Scope.Define(stage, layout.PRODUCTS)
    product = UsdRender.Product.Define(stage, layout.IMAGE_PRODUCT)
    product.CreateProductNameAttr("image")
    UsdGeom.Scope.Define(stage, layout.VARS)
    for name, (_, source, dtype, doc) in RENDER_VARS.items():
        var = UsdRender.Var.Define(stage, layout.render_var(name))
        var.CreateSourceNameAttr(source)
        var.CreateDataTypeAttr(dtype)
        var.GetPrim().SetDocumentation(doc)
    product.CreateOrderedVarsRel().SetTargets([Sdf.Path(p) for p in product_vars(DEFAULT_PASSES)])
    stage.SetMetadata("renderSettingsPrimPath", layout.RENDER_SETTINGS)
