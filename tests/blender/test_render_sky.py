"""Hard cases of the sky that need Blender: float32 transforms, vertical cameras, the Sun in frame, umbra,
penumbra and a lunar eclipse (each body lit by its own sun lamp, the station by its own)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.blender.build import build_scene
from allo_usd.blender.render import render_scene
from allo_usd.core.geometry import camera_intrinsics, look_at, matrix_to_quat
from allo_usd.usd.read import read_scene
from allo_usd.scene.resolve import sun_and_bodies
from allo_usd.sky.ephemeris import default_epochs
from allo_usd.sky.model import compute_sky
from allo_usd.scene.spec import CameraSpec
from allo_usd.plan.settings import EffectsSpec

from tests.support.helpers import make_spec

pytestmark = pytest.mark.render

UMBRA_DAY = 269          # 2030-09-27 00:00: the station in the Moon's umbra, a full Earth overhead
LUNAR_ECLIPSE_DAY = 343  # 2030-12-10 00:00: the Moon in the Earth's penumbra, the station in sunlight


@pytest.fixture(scope="module")
def sky():
    return compute_sky(default_epochs())


def _blender_matrices() -> dict:
    import bpy

    return {o.name: np.array(o.matrix_world, dtype=np.float64) for o in bpy.context.scene.objects}


@pytest.mark.parametrize("day", [0, 3, 91, 269])  # perilune, apolune side, spring, the umbra day
def test_body_transforms_survive_float32_in_blender(sky, tiny_base, tmp_path, day):
    sun, bodies = sun_and_bodies(sky, day)
    spec = replace(make_spec(), sun=sun, bodies=bodies)
    desc = read_scene(write_scene_layer(spec, tmp_path / "s.usda", tiny_base))
    build_scene(desc)
    got = _blender_matrices()
    cams = np.random.default_rng(day).uniform(-100, 100, size=(64, 3))
    cams = cams / np.linalg.norm(cams, axis=1, keepdims=True) * np.linspace(0, 100, 64)[:, None]
    for name, body in bodies.items():
        m = got[f"/World/Sky/{name}/Geom/Surface"]
        true_pos, true_r = np.array(body.position), body.radius
        v_true = true_pos - cams
        v_got = m[:3, 3] - cams
        cosang = np.einsum("ij,ij->i", v_true, v_got) / np.linalg.norm(v_true, axis=1) / np.linalg.norm(v_got, axis=1)
        err = np.arctan2(np.linalg.norm(np.cross(v_true, v_got), axis=1), np.einsum("ij,ij->i", v_true, v_got))
        assert err.max() <= 1e-5, f"{name}: direction error {err.max():.2e} rad"
        r_got = np.linalg.norm(m[:3, 0])
        ang_true = np.arcsin(true_r / np.linalg.norm(v_true, axis=1))
        ang_got = np.arcsin(min(r_got, 0.999 * np.linalg.norm(v_got, axis=1).min()) / np.linalg.norm(v_got, axis=1))
        assert (np.abs(ang_got / ang_true - 1) <= 1e-4).all(), name
        assert cosang.min() > 0.999999


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_vertical_camera_round_trips_as_a_matrix(tiny_base, tmp_path, pitch):
    pos = np.array([12.0, 3.0, 4.0])
    target = pos + np.array([0.0, 0.0, math.copysign(10.0, pitch)])  # straight up or down
    rot = look_at(pos, target)
    spec = replace(make_spec(), camera=CameraSpec(tuple(pos), rot))
    desc = read_scene(write_scene_layer(spec, tmp_path / "s.usda", tiny_base))
    np.testing.assert_allclose(desc.camera.matrix[:3, :3], rot, atol=1e-12)
    build_scene(desc)
    import bpy

    assert {o.rotation_mode for o in bpy.context.scene.objects} == {"QUATERNION"}
    obj = bpy.context.scene.objects["/World/Camera"]
    q = np.array(obj.rotation_quaternion, dtype=np.float64)  # float32, as Blender keeps it
    np.testing.assert_allclose(q * np.sign(q[0] or 1.0), matrix_to_quat(rot), atol=1e-6)
    m = _blender_matrices()["/World/Camera"]
    np.testing.assert_allclose(m[:3, :3], rot, atol=1e-6)
    np.testing.assert_allclose(m[:3, 3], pos, atol=1e-5)
    forward = -m[:3, 2]
    assert forward[2] == pytest.approx(math.copysign(1.0, pitch), abs=1e-7)  # still straight up/down


def test_camera_looking_at_the_sun(sky, tiny_base, tmp_path):
    sun, bodies = sun_and_bodies(sky, 10)
    pos = np.array([0.0, 0.0, 30.0])  # above the station, nothing between camera and Sun
    d = np.array(sun.direction)
    spec = replace(make_spec(resolution=(320, 180), samples=1), sun=sun, bodies=bodies,
                   camera=CameraSpec(tuple(pos), look_at(pos, pos + d)))
    desc = read_scene(write_scene_layer(spec, tmp_path / "s.usda", tiny_base))
    result = render_scene(desc)
    assert np.isfinite(result.rgb).all()
    cy, cx = 90, 160  # the Sun sits at the image centre
    disc = result.rgb[cy - 2:cy + 2, cx - 2:cx + 2].max()
    assert disc > 1e3, "the solar disc should be far brighter than white (radiance 2e7 times exposure)"
    assert (result.mask[cy - 2:cy + 2, cx - 2:cx + 2] == 1).any()
    # Away from the disc the sky is black: the disc lights nothing and the world is empty.
    assert np.median(result.rgb) == 0.0


def test_umbra_scene_is_never_rendered_lit(sky, tiny_base, tmp_path):
    day = int(np.flatnonzero(np.asarray(sky.eclipse_state) == "umbra")[0])
    sun, bodies = sun_and_bodies(sky, day)
    assert sun.irradiance == 0.0 and sun.eclipse_state == "umbra"
    lit_sun = replace(sun, irradiance=sun.irradiance_unoccluded, lit_fraction=1.0, eclipse_state="lit",
                      eclipse_body="none")
    means = {}
    for name, s in (("umbra", sun), ("lit", lit_sun)):
        spec = replace(make_spec(resolution=(64, 36), samples=8), sun=s, bodies=bodies)
        desc = read_scene(write_scene_layer(spec, tmp_path / f"{name}.usda", tiny_base))
        assert (desc.sun is None) == (name == "umbra")
        r = render_scene(desc)
        means[name] = float(r.rgb[r.mask == 1].mean())
    assert means["umbra"] < 0.05 * means["lit"]


def _disc_pixels(camera: CameraSpec, resolution, direction, angular_radius: float, inner: float = 0.7) -> np.ndarray:
    """Pixels whose centre ray lies within `inner` x the angular radius of a body's centre direction."""
    w, h = resolution
    f = camera_intrinsics(w, h)[0, 0]
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(jj - w / 2) / f, -(ii - h / 2) / f, -np.ones_like(jj)], axis=-1) @ camera.rotation.T
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return np.arccos(np.clip(rays @ np.asarray(direction), -1, 1)) < inner * angular_radius


def _looking_at(direction, pos=(0.0, 0.0, 5.0)) -> CameraSpec:
    pos = np.asarray(pos, dtype=np.float64)
    return CameraSpec(tuple(pos), look_at(pos, pos + np.asarray(direction)))


def _render_spec(spec, base, path):
    desc = read_scene(write_scene_layer(spec, path, base))
    return desc, render_scene(desc)


def test_umbra_station_is_lit_by_earthshine_and_the_earth_stays_sunlit(sky, tiny_base, tmp_path):
    """The eclipsed scene: in the Moon's umbra, the spotlight off, the station gets only the
    light of the sunlit Earth (about 0.1 W/m^2: far below one 8-bit level, so linear values are checked)."""
    sun, bodies = sun_and_bodies(sky, UMBRA_DAY)
    assert sun.eclipse_state == "umbra" and sun.irradiance == 0.0
    earth_sun = bodies["Earth"].light
    assert earth_sun.eclipse_state == "lit" and earth_sun.irradiance > 1300.0
    e = np.asarray(sky.direction["earth"][UMBRA_DAY])
    dark = EffectsSpec(inspection_light=False)
    # The station seen from the Earth's side: every surface in view has the Earth above its horizon.
    pos = 30.0 * e
    above = replace(make_spec(resolution=(64, 36), samples=256), sun=sun, bodies=bodies, effects=dark,
                    camera=CameraSpec(tuple(pos), look_at(pos, np.zeros(3))))
    desc, shine = _render_spec(above, tiny_base, tmp_path / "shine.usda")
    assert desc.sun is None and [s.path for s in desc.suns] == ["/World/Sky/EarthSunLight", "/World/Sky/MoonSunLight"]
    _, no_shine = _render_spec(replace(above, effects=replace(dark, body_shine=False)), tiny_base,
                               tmp_path / "no_shine.usda")
    station = shine.mask == 1
    assert station.sum() > 100 and (no_shine.mask == shine.mask).all()
    assert no_shine.rgb[station].max() == 0.0  # no sun, no spot, no body shine: black
    radiance = shine.rgb[station].mean() / above.render.exposure  # W/m^2/sr
    assert 1e-3 < radiance < 0.2, f"earthshine radiance {radiance:.3g} W/m^2/sr"  # ~0.8 * 0.1 W/m^2 / pi
    assert shine.rgb[station].mean() < 255 ** -1  # below one 8-bit level at the default exposure
    # The Earth itself, seen from the station: its disc is sunlit, not black.
    cam = _looking_at(e)
    look = replace(above, camera=cam, render=replace(above.render, resolution=(192, 108), samples=4))
    _, r = _render_spec(look, tiny_base, tmp_path / "earth.usda")
    disc = _disc_pixels(cam, (192, 108), e, sky.angular_radius_rad["earth"][UMBRA_DAY])
    assert disc.sum() >= 6 and (r.mask[disc] == 1).all()
    assert r.rgb[disc].mean() > 0.05  # full Earth, albedo ~0.3: ~0.1-0.3 at the default exposure


def _penumbra_epoch() -> str:
    """The second of 2030-09-26T23:31 UTC when the station, entering the Moon's shadow, keeps about
    half of the Sun (a sub-day epoch: no day of 2030 at 00:00 falls in a penumbra)."""
    from datetime import datetime, timedelta, timezone

    start = datetime(2030, 9, 26, 23, 30, tzinfo=timezone.utc)
    span = compute_sky([start + timedelta(seconds=k) for k in range(180)])
    i = int(np.argmin(np.abs(np.asarray(span.lit_fraction) - 0.5)))
    return span.epochs[i]


def test_penumbra_dims_the_station_not_the_earth(tiny_base, tmp_path):
    sky = compute_sky([_penumbra_epoch()])
    sun, bodies = sun_and_bodies(sky, 0)
    assert sun.eclipse_state == "penumbra" and 0.3 < sun.lit_fraction < 0.7
    assert sun.irradiance == pytest.approx(sun.irradiance_unoccluded * sun.lit_fraction)
    assert bodies["Earth"].light.lit_fraction == 1.0
    full = replace(sun, irradiance=sun.irradiance_unoccluded, lit_fraction=1.0, eclipse_state="lit", eclipse_body="none")
    d_sun, e = np.asarray(sun.direction), np.asarray(sky.direction["earth"][0])
    spec = replace(make_spec(resolution=(64, 36), samples=16), bodies=bodies,
                   effects=EffectsSpec(inspection_light=False))
    pos = 30.0 * d_sun  # the station from the Sun's side
    station_cam = CameraSpec(tuple(pos), look_at(pos, np.zeros(3)))
    earth_cam = _looking_at(e)
    means = {}
    for name, s in (("penumbra", sun), ("full", full)):
        _, st = _render_spec(replace(spec, sun=s, camera=station_cam), tiny_base, tmp_path / f"st_{name}.usda")
        earth_spec = replace(spec, sun=s, camera=earth_cam, render=replace(spec.render, resolution=(192, 108), samples=4))
        _, ea = _render_spec(earth_spec, tiny_base, tmp_path / f"ea_{name}.usda")
        disc = _disc_pixels(earth_cam, (192, 108), e, sky.angular_radius_rad["earth"][0])
        assert disc.sum() >= 6
        means[name] = (st.rgb[st.mask == 1].mean(), ea.rgb[disc])
    ratio = means["penumbra"][0] / means["full"][0]
    assert ratio == pytest.approx(sun.lit_fraction, rel=0.02), "the station's light scales with its lit fraction"
    assert means["full"][1].mean() > 0.05
    # On the penumbra day the station's sun never lights the bodies: the Earth keeps its own lamp. The
    # uneclipsed copy is a normal day, whose one lamp is the Sun at the station (0.4% off the Earth's).
    ratio = bodies["Earth"].light.irradiance / sun.irradiance_unoccluded
    np.testing.assert_allclose(means["penumbra"][1], means["full"][1] * ratio, rtol=2e-3, atol=0)


def test_lunar_eclipse_day_darkens_the_moon_lamp(sky, tiny_base, tmp_path):
    sun, bodies = sun_and_bodies(sky, LUNAR_ECLIPSE_DAY)
    moon_sun = bodies["Moon"].light
    assert sun.eclipse_state == "lit" and sun.irradiance == pytest.approx(sun.irradiance_unoccluded)
    assert moon_sun.eclipse_state == "penumbra" and moon_sun.eclipse_body == "earth" and moon_sun.lit_fraction < 0.99
    assert moon_sun.irradiance == pytest.approx(moon_sun.irradiance_unoccluded * moon_sun.lit_fraction)
    m = np.asarray(sky.direction["moon"][LUNAR_ECLIPSE_DAY])
    cam = _looking_at(m, pos=(0.0, 0.0, -5.0))
    spec = replace(make_spec(resolution=(192, 108), samples=4), sun=sun, camera=cam,
                   effects=EffectsSpec(inspection_light=False))
    uneclipsed = replace(moon_sun, irradiance=moon_sun.irradiance_unoccluded, lit_fraction=1.0, eclipse_state="lit",
                         eclipse_body="none")
    disc = _disc_pixels(cam, (192, 108), m, sky.angular_radius_rad["moon"][LUNAR_ECLIPSE_DAY], inner=0.9)
    means = {}
    for name, light in (("eclipse", moon_sun), ("uneclipsed", uneclipsed)):
        s = replace(spec, bodies={**bodies, "Moon": replace(bodies["Moon"], light=light)})
        desc, r = _render_spec(s, tiny_base, tmp_path / f"{name}.usda")
        lamp = {x.path: x for x in desc.suns}["/World/Sky/MoonSunLight" if name == "eclipse" else "/World/Sky/SunLight"]
        assert lamp.irradiance == pytest.approx(light.irradiance if name == "eclipse" else sun.irradiance, rel=1e-6)
        lit = disc & (r.rgb.max(axis=-1) > 0)
        means[name] = r.rgb[disc].mean()
    assert lit.sum() >= 10  # the Moon is about half lit from the station that day
    # The uneclipsed copy is a normal day: one lamp, the Sun at the station, lights the Moon too.
    assert means["eclipse"] / means["uneclipsed"] == pytest.approx(moon_sun.irradiance / sun.irradiance, rel=0.01)

def _random_rotation(rng) -> np.ndarray:
    from allo_usd.core.geometry import quat_to_matrix

    return quat_to_matrix(rng.standard_normal(4))  # uniform on SO(3)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    """Rotation angle between two rotation matrices: ||A - B||_F = 2 sqrt(2) sin(angle / 2)."""
    return 2.0 * math.asin(min(1.0, np.linalg.norm(a - b) / (2.0 * math.sqrt(2.0))))


def _ulps32(x) -> float:
    """One float32 ulp at the magnitude of x (the spacing Blender stores a coordinate with)."""
    return float(np.spacing(np.float32(np.max(np.abs(x)))))


@pytest.mark.parametrize("seed", range(4))
def test_every_authored_transform_survives_float32_in_blender(tiny_base, tmp_path, seed):
    """A randomly posed camera, the sun light, an anomaly and the inspection light: the Blender
    objects built from a real layer match the authored float64 transforms to float32 precision
    (budget 1e-5 rad; measured at most 4e-8 rad, and positions within half a float32 ulp)."""
    from pxr import Usd, UsdGeom

    from allo_usd.usd.read import open_stage
    from allo_usd.scene.spec import AnomalySpec, BodySpec
    from allo_usd.plan.settings import EffectsSpec

    rng = np.random.default_rng(seed)
    cam_pos = rng.uniform(-100.0, 100.0, 3)
    cam_rot = _random_rotation(rng)
    assert abs(cam_rot[2, 2]) < 0.95  # looking along a slant (vertical poses: the test above)
    sun_dir = rng.standard_normal(3)
    sun_dir /= np.linalg.norm(sun_dir)
    anomaly = AnomalySpec("Crate", "blue", tuple(rng.uniform(-30.0, 30.0, 3)), _random_rotation(rng))
    base = make_spec(anomaly=True)
    spec = replace(base, camera=CameraSpec(tuple(cam_pos), cam_rot), anomaly=anomaly,
                   sun=replace(base.sun, direction=tuple(sun_dir)),
                   bodies={**base.bodies, "Sun": BodySpec(tuple(sun_dir * 1.496e11), 6.9634e8)},
                   effects=EffectsSpec(inspection_light=True))
    layer = write_scene_layer(spec, tmp_path / "s.usda", tiny_base)
    desc = read_scene(layer)
    build_scene(desc)
    got = _blender_matrices()

    # Camera: Blender's float32 matrix against the spec's float64 pose.
    m = got["/World/Camera"]
    assert _angle(m[:3, :3], cam_rot) <= 1e-5
    assert np.abs(m[:3, 3] - cam_pos).max() <= _ulps32(cam_pos)
    # Sun light: its local +Z points at the Sun (light travels along -Z).
    z = got["/World/Sky/SunLight"][:3, 2]
    assert math.atan2(np.linalg.norm(np.cross(z, sun_dir)), z @ sun_dir) <= 1e-5

    # Anomaly and inspection light: composed in float64 by USD from the authored ops.
    stage = open_stage(layer)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())

    def authored(path: str) -> np.ndarray:
        return np.array(cache.GetLocalToWorldTransform(stage.GetPrimAtPath(path)), dtype=np.float64).T

    root = authored("/World/Anomaly")
    assert _angle(root[:3, :3], anomaly.rotation) <= 1e-12
    np.testing.assert_allclose(root[:3, 3], anomaly.position, rtol=0, atol=1e-12)
    parts = [name for name in got if name.startswith("/World/Anomaly/")]
    assert parts
    for name in parts:
        want = authored(name)
        scale = np.linalg.norm(want[:3, :3], axis=0)
        assert _angle(got[name][:3, :3] / scale, want[:3, :3] / scale) <= 1e-5, name
        assert np.abs(got[name][:3, 3] - want[:3, 3]).max() <= _ulps32(want[:3, 3]), name
    spot = authored("/World/Camera/InspectionLight")
    assert _angle(spot[:3, :3], cam_rot) <= 1e-12  # rides on the camera, unrotated
    m = got["/World/Camera/InspectionLight"]
    assert _angle(m[:3, :3], spot[:3, :3]) <= 1e-5
    assert np.abs(m[:3, 3] - spot[:3, 3]).max() <= _ulps32(spot[:3, 3])
