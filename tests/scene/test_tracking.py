"""Sun-tracking arrays (allo_usd.scene.tracking): each day's sky layer turns the procedural station's
alpha and beta joints so every wing's cell side faces that day's Sun, within the joints' limits; the
composed stage (pxr) shows it, a plan without tracking writes no joint opinion, and ray casting of
the day's station agrees with Cycles' class mask."""

from __future__ import annotations

import math

import numpy as np
import pytest

from allo_usd.core.paths import BASE_STAGE

DAYS = (0, 9, 45, 90, 120, 200)     # sun elevations out of the orbit plane 42, -63, -26, 8, 31, 61 degrees
CLAMPED_DAY = 10                    # elevation -85 degrees: beyond the beta gimbals' +-75 degree limit
RENDER_DAY = 120                    # alpha -166 (rest 25), beta +-31: far from the rest pose


@pytest.fixture(scope="module")
def sky():
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky

    return compute_sky(default_epochs())


def _day(sky, day):
    from allo_usd.scene.resolve import sun_and_bodies
    from allo_usd.scene.tracking import sun_tracking_angles

    sun, bodies = sun_and_bodies(sky, day)
    return sun, bodies, sun_tracking_angles(sun.direction)


def _write_sky(path, sky, day, joints):
    from allo_usd.usd.compose import write_sky_layer

    sun, bodies = _day(sky, day)[:2]
    return write_sky_layer(path, day=day, epoch=sky.epochs[day], perilune_epoch="2030-01-01T00:00:00Z", sun=sun,
                           bodies=bodies, joints=joints)


def _composed(sky_layer):
    """The sky layer over the base stage, composed by pxr (no allo_usd reader involved)."""
    from pxr import Sdf, Usd

    from allo_usd.usd import schema

    schema.register()
    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths = [str(sky_layer), str(BASE_STAGE)]
    return Usd.Stage.Open(root)


def _face_normals(stage, name_of) -> dict[str, np.ndarray]:
    """{name_of(mesh name): world-space unit normal of the mesh's first face} for every station mesh that
    name_of names (returns a key, or None to skip it)."""
    from pxr import Usd, UsdGeom

    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    out = {}
    for prim in Usd.PrimRange(stage.GetPrimAtPath("/World/Station")):
        key = name_of(prim.GetName()) if prim.IsA(UsdGeom.Mesh) else None
        if key is None:
            continue
        mesh = UsdGeom.Mesh(prim)
        pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
        idx = np.array(mesh.GetFaceVertexIndicesAttr().Get())[:3]
        m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64).T
        p = pts[idx] @ m[:3, :3].T
        n = np.cross(p[1] - p[0], p[2] - p[0])
        out[key] = n / np.linalg.norm(n)
    return out


def _cell_normals(stage) -> dict[str, np.ndarray]:
    """{wing: world-space unit normal of its cell side}, from the solar_wing_<wing> meshes' first face."""
    return _face_normals(stage, lambda name: name.removeprefix("solar_wing_")
                         if name.startswith("solar_wing_") and name != "solar_wing_backs" else None)


def _angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


@pytest.mark.parametrize("day", DAYS)
def test_every_wing_faces_the_sun(sky, tmp_path, day):
    sun, _, angles = _day(sky, day)
    normals = _cell_normals(_composed(_write_sky(tmp_path / "sky.usda", sky, day, angles)))
    assert sorted(normals) == sorted(["S4a", "S4b", "S6a", "S6b", "P4a", "P4b", "P6a", "P6b"])
    for wing, n in normals.items():
        assert _angle_deg(n, sun.direction) < 1.0, (day, wing, _angle_deg(n, sun.direction))


def test_at_the_beta_limit_a_wing_stops_there(sky, tmp_path):
    from allo_usd.assets.station import BETA_LIMIT

    sun, _, angles = _day(sky, CLAMPED_DAY)
    elevation = math.degrees(math.asin(sun.direction[1]))
    assert abs(elevation) > BETA_LIMIT + 5
    assert all(abs(angles[f"Beta{w}"]) == BETA_LIMIT for w in ("S4a", "S4b", "P6a", "P6b"))
    normals = _cell_normals(_composed(_write_sky(tmp_path / "sky.usda", sky, CLAMPED_DAY, angles)))
    for wing, n in normals.items():   # it misses the Sun by exactly the excess over the limit
        assert _angle_deg(n, sun.direction) == pytest.approx(abs(elevation) - BETA_LIMIT, abs=0.05), wing


def test_joint_limits_respected_all_year(sky):
    from allo_usd.usd.stage_geometry import read_joint_angles

    joints = read_joint_angles(BASE_STAGE)
    assert sorted(joints) == sorted(["AlphaS", "AlphaP", "RadiatorS", "RadiatorP"]
                                    + [f"Beta{w}" for w in ("S4a", "S4b", "S6a", "S6b", "P4a", "P4b", "P6a", "P6b")])
    assert joints["AlphaS"]["op"] == "xformOp:rotateY:alpha" and joints["BetaS4a"]["op"] == "xformOp:rotateZ:beta"
    assert joints["RadiatorS"]["op"] == "xformOp:rotateY:trrj" and joints["RadiatorP"]["angle"] == pytest.approx(0.0)
    assert joints["AlphaS"]["angle"] == pytest.approx(25.0) and joints["BetaP4b"]["angle"] == pytest.approx(-9.0)
    assert all(j["tracks"] == ("SunEdgeOn" if n.startswith("Radiator") else "Sun") for n, j in joints.items())
    for day in range(len(sky.epochs)):
        for name, angle in _day(sky, day)[2].items():
            assert joints[name]["lower"] <= angle <= joints[name]["upper"], (day, name, angle)


@pytest.mark.slow
def test_rest_pose_is_the_static_station():
    """The articulated station at rest is the flat one the camera rig was chosen on, triangle for triangle."""
    from allo_usd.assets.station import build_station, station_triangles

    art = build_station()
    assert art.joints and any(p.joint for p in art.parts)
    pts, tris = art.triangle_soup()
    flat_pts, flat_tris = station_triangles()
    assert len(tris) == len(flat_tris)
    np.testing.assert_allclose(np.sort(pts, axis=0), np.sort(flat_pts, axis=0), atol=1e-9)
    moved, _ = station_triangles({"AlphaS": 100.0})
    assert np.abs(np.sort(moved, axis=0) - np.sort(flat_pts, axis=0)).max() > 1.0


def test_no_tracking_writes_no_joint_opinions(sky, tmp_path):
    from pxr import Sdf

    off = _write_sky(tmp_path / "off.usda", sky, 0, None)
    on = _write_sky(tmp_path / "on.usda", sky, 0, _day(sky, 0)[2])

    def station_specs(path):
        layer = Sdf.Layer.FindOrOpen(str(path))
        found = []
        layer.Traverse(Sdf.Path("/World"), lambda p: found.append(p) if str(p).startswith("/World/Station") else None)
        return found

    assert station_specs(off) == []
    assert len([p for p in station_specs(on) if p.IsPropertyPath()]) == 12   # 2 alpha, 8 beta, 2 radiator
    assert "Station" not in off.read_text() and "xformOp:rotateY:alpha" in on.read_text()


def test_model_station_cannot_track(tmp_path):
    from allo_usd.core.errors import PlanError
    from allo_usd.plan.io import load_plan
    from allo_usd.plan.model import demo_plan, paper_plan

    assert paper_plan().station.track_sun is False and demo_plan().station.track_sun is True
    plan = tmp_path / "p.toml"
    plan.write_text('name = "x"\n[station]\nsource = "iss.glb"\ntrack_sun = true\n')
    with pytest.raises(PlanError, match="track_sun"):
        load_plan(plan)


@pytest.mark.slow
def test_scene_inputs_pose_the_station_per_day(sky):
    from allo_usd.usd.stage_geometry import scene_inputs

    inputs = scene_inputs(BASE_STAGE, sky, "2030-01-01T00:00:00Z", track_sun=True)
    rest = scene_inputs(BASE_STAGE, sky, "2030-01-01T00:00:00Z")
    assert rest.station_scene_on(RENDER_DAY) is rest.station_scene
    assert inputs.station_scene_on(RENDER_DAY) is inputs.station_scene_on(RENDER_DAY)   # cached
    assert inputs.station_scene_on(RENDER_DAY) is not inputs.station_scene


def _array_view():
    """A camera 80 m forward of the starboard arrays, level (the Moon stays below the frame)."""
    from allo_usd.core.geometry import look_at

    pos = np.array([80.0, 45.0, 5.0])
    return pos, look_at(pos, [0.0, 45.0, 5.0])


def _tracking_layer(sky, tmp_path, resolution=(64, 36)):
    """A scene layer of RENDER_DAY with tracking, composed as a plan authors it: (layer, inputs, pos, rot)."""
    from allo_usd.core.constants import EXPOSURE
    from allo_usd.plan.settings import EffectsSpec, RenderSpec
    from allo_usd.scene.resolve import build_spec
    from allo_usd.scene.spec import CameraSpec
    from allo_usd.usd.compose import write_composed_scene, write_pose_layer
    from allo_usd.usd.stage_geometry import scene_inputs

    inputs = scene_inputs(BASE_STAGE, sky, "2030-01-01T00:00:00Z", track_sun=True)
    pos, rot = _array_view()
    camera = CameraSpec(tuple(pos), rot)
    spec = build_spec(inputs, scene_id="tracking", day=RENDER_DAY, pose=1, seed=1, seed_path="test", camera=camera,
                      render=RenderSpec(resolution, samples=1, exposure=EXPOSURE, seed=1, denoise=False),
                      effects=EffectsSpec())
    sky_layer = _write_sky(tmp_path / "sky.usda", sky, RENDER_DAY, inputs.joint_angles(RENDER_DAY))
    pose_layer = write_pose_layer(tmp_path / "pose.usda", pose=1, camera=camera, seed=1, seed_path="test",
                                  sample_id="tracking")
    layer = write_composed_scene(spec, tmp_path / "tracking.usda", pose_layer=pose_layer, sky_layer=sky_layer,
                                 base_stage=BASE_STAGE)
    return layer, inputs, pos, rot


def test_inspect_shows_the_joint_angles_and_their_layer(sky, tmp_path):
    from allo_usd.usd.inspect import describe, format_description

    layer, inputs, _, _ = _tracking_layer(sky, tmp_path)
    d = describe(layer)
    angles = inputs.joint_angles(RENDER_DAY)
    assert {k: j["angle"] for k, j in d["joints"].items()} == pytest.approx(angles)
    assert {j["from"] for j in d["joints"].values()} == {"./sky.usda"}
    assert d["joints"]["BetaS4a"]["upper"] == 75.0
    assert "joints   AlphaS -165.98" in format_description(d)


@pytest.mark.slow
def test_articulated_budget():
    from allo_usd.assets.station import build_station

    station = build_station()
    assert len(station.parts) <= 100 and sum(len(p.triangles()) for p in station.parts) <= 150_000
    assert len(station.joints) == 12
    under = {p.joint for p in station.parts}
    assert under >= {"AlphaS", "AlphaP", "BetaS4a", "BetaP6b"}
    wings = [p for p in station.parts if p.name.startswith("solar_wing_") and p.material == "solar_cells"]
    assert len(wings) == 8 and all(p.joint == "Beta" + p.name.removeprefix("solar_wing_") for p in wings)


@pytest.mark.render
def test_raycast_of_the_day_matches_cycles(sky, tmp_path):
    """The day's ray-cast station agrees with Cycles' 64x36 class mask; the rest pose clearly does not."""
    from PIL import Image

    from allo_usd.run.job import render_layer
    from allo_usd.scene.raycast import class_image

    w, h = 64, 36
    layer, inputs, pos, rot = _tracking_layer(sky, tmp_path, (w, h))
    render_layer(layer, tmp_path / "renders")
    mask = np.array(Image.open(tmp_path / "renders" / "tracking_mask.png")) == 1
    tracked = class_image(inputs.station_scene_on(RENDER_DAY), pos, rot, w, h) > 0
    rest = class_image(inputs.station_scene, pos, rot, w, h) > 0
    assert 0.1 < mask.mean() < 0.9       # the arrays fill part of the frame
    agree, agree_rest = (tracked == mask).mean(), (rest == mask).mean()
    assert agree >= 0.98, agree
    assert agree_rest < agree - 0.03, (agree_rest, agree)


@pytest.mark.slow
def test_a_file_pose_a_wing_sweeps_through_fails_naming_the_day_the_pose_and_the_fix(sky, tmp_path):
    """A pose-file pose clear of the rest-pose station but inside a wing as turned on the plan's first
    day: with sigma 0 no camera can be drawn there, and the error says which day, which pose line,
    and that the arrays turned (nothing half-written is left: the error comes before that scene)."""
    from allo_usd.core.errors import PlacementError
    from allo_usd.plan.model import Anomalies, Counts, Dates, Plan, Poses, Station
    from allo_usd.run.author import author_plan
    from allo_usd.scene.raycast import RayScene
    from allo_usd.scene.rig import too_close
    from allo_usd.usd.stage_geometry import StageGeometry

    day = RENDER_DAY
    geometry = StageGeometry(BASE_STAGE)
    rest = RayScene([(*geometry.station_triangles(), 1)])
    pts, tris = geometry.station_triangles(_day(sky, day)[2])
    turned = RayScene([(pts, tris, 1)])
    # a point just off a turned wing's blanket that the rest pose leaves clear
    centres = pts[tris].mean(axis=1)
    far_from_rest = [c for c in centres[:: max(1, len(centres) // 4000)]
                     if abs(c[1]) > 40 and not too_close(rest, c, 1.0)]
    assert far_from_rest, "no turned wing point clear of the rest pose"
    spot = far_from_rest[0]
    assert too_close(turned, spot) and not too_close(rest, spot)
    (tmp_path / "poses.csv").write_text("name,split,x,y,z,qw,qx,qy,qz\n"
                                        f"in_the_sweep,train,{spot[0]},{spot[1]},{spot[2]},1,0,0,0\n")
    from datetime import date, timedelta

    plan = Plan(name="sweep", dates=Dates(start=date(2030, 1, 1) + timedelta(days=day), days=1),
                poses=Poses(train=[], test=[], file=str(tmp_path / "poses.csv"), position_sigma_m=0.0,
                            angle_sigma_rad=0.0),
                anomalies=Anomalies(assets=[]), counts=Counts(), station=Station(track_sun=True),
                base_stage=str(BASE_STAGE))
    with pytest.raises(PlacementError) as e:
        author_plan(plan, tmp_path / "tree", progress=False)
    text = str(e.value)
    assert "day 0" in text and "in_the_sweep" in text and "poses.csv:2" in text and "track_sun" in text



def _radiator_normals(stage) -> dict[str, np.ndarray]:
    """{side: world-space unit normal of the S1/P1 radiator panels}, from the radiator_*_panels meshes."""
    return _face_normals(stage, lambda name: name[9:11] if name in ("radiator_S1_panels", "radiator_P1_panels")
                         else None)


@pytest.mark.parametrize("day", DAYS + (CLAMPED_DAY,))
def test_the_radiators_turn_edge_on_to_the_sun(sky, tmp_path, day):
    """The S1/P1 thermal radiators (TRRJ) turn so the Sun grazes them: their panels' normal is at 90
    degrees to the Sun within 1 degree, or, where the edge-on angle lies past the joint's +-85 degree
    limit, at most the 5 degrees that leaves (the two edge-on angles are 180 degrees apart)."""
    from allo_usd.assets.station import RADIATOR_LIMITS
    from allo_usd.scene.tracking import radiator_normal

    sun, _, angles = _day(sky, day)
    normals = _radiator_normals(_composed(_write_sky(tmp_path / "sky.usda", sky, day, angles)))
    assert sorted(normals) == ["P1", "S1"]
    at_limit = angles["RadiatorS"] in RADIATOR_LIMITS
    for side, n in normals.items():
        grazing = 90.0 - _angle_deg(n, sun.direction) if _angle_deg(n, sun.direction) <= 90 else \
            _angle_deg(n, sun.direction) - 90.0
        assert grazing <= (5.0 if at_limit else 1.0), (day, side, grazing, angles["RadiatorS"])
        np.testing.assert_allclose(abs(n @ radiator_normal(angles)), 1.0, atol=1e-9)


@pytest.mark.slow
def test_the_radiators_sweep_clear_of_the_station():
    """Across the radiator joints' whole range (every 5 degrees), no radiator panel, rail or hinge
    member crosses any other part of the station, nor any station edge a radiator part: a joint angle
    inside the limits never puts a panel through the truss or a module. (Past -97 degrees they would.)"""
    from allo_usd.assets.mesh import Asset
    from allo_usd.assets.station import RADIATOR_BEAM, RADIATOR_JOINTS, RADIATOR_LIMITS, TRUSS_Z, build_station
    from allo_usd.scene.raycast import RayScene

    station = build_station()
    moving = set(RADIATOR_JOINTS.values())
    rest = Asset("rest", tuple(p for p in station.parts if p.joint not in moving), station.materials,
                 station.textures, station.joints)
    radiators = Asset("radiators", tuple(p for p in station.parts if p.joint in moving), station.materials,
                      station.textures, station.joints)
    axis = np.array([RADIATOR_BEAM[0], RADIATOR_BEAM[2] + TRUSS_Z])

    def away_from_hinge(t):   # the panels' rails start on the beam they turn about: leave the hinge out
        return t[(np.linalg.norm(t[:, :, [0, 2]] - axis, axis=2) > 1.0).all(axis=1)]

    def crossings(scene, t) -> int:
        n = 0
        for i, j in ((0, 1), (1, 2), (2, 0)):
            d = t[:, j] - t[:, i]
            length = np.linalg.norm(d, axis=1)
            ok = length > 1e-9
            n += int(scene.occluded(t[ok, i], d[ok] / length[ok, None], length[ok]).sum())
        return n

    spts, stris = rest.triangle_soup()
    static, static_tris = RayScene([(spts, stris, 1)]), away_from_hinge(spts[stris])
    lo, hi = RADIATOR_LIMITS
    for theta in [*np.arange(lo, hi, 5.0), hi]:
        pts, tris = radiators.triangle_soup({name: theta for name in moving})
        assert crossings(static, away_from_hinge(pts[tris])) == 0, theta
        assert crossings(RayScene([(pts, tris, 2)]), static_tris) == 0, theta
    pts, tris = radiators.triangle_soup({name: -105.0 for name in moving})   # the check can fail
    assert crossings(static, away_from_hinge(pts[tris])) > 0
