"""Hard cases: an eclipsed station lit only by the inspection light (and body shine),
an anomaly tiny and far, and one that fills the frame."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.blender.render import render_scene
from allo_usd.core.geometry import look_at
from allo_usd.usd.read import read_scene
from allo_usd.plan.settings import EffectsSpec
from allo_usd.scene.spec import SunSpec

from tests.support.helpers import CAM_POS, make_spec

pytestmark = pytest.mark.render


def _render(spec, base, path):
    return render_scene(read_scene(write_scene_layer(spec, path, base)))


def test_eclipsed_station_is_lit_by_the_inspection_light_and_body_shine_only(tiny_base, tmp_path):
    # In the Moon's umbra the Sun is behind the Moon (straight down): the Moon shows the station its
    # night side, and the Earth, on the horizon, half of its day side.
    umbra = SunSpec((0.0, 0.0, -1.0), 0.0, 1361.0, 0.533, 1.5e11, 0.0, "umbra", "moon")
    base = replace(make_spec(resolution=(64, 36), samples=16), sun=umbra)
    on = _render(base, tiny_base, tmp_path / "on.usda")
    off = _render(replace(base, effects=EffectsSpec(inspection_light=False)), tiny_base, tmp_path / "off.usda")
    dark = _render(replace(base, effects=EffectsSpec(inspection_light=False, body_shine=False)), tiny_base,
                   tmp_path / "dark.usda")
    lit = _render(replace(make_spec(resolution=(64, 36), samples=16)), tiny_base, tmp_path / "lit.usda")
    station = on.mask == 1
    assert np.isfinite(on.rgb).all()
    assert on.rgb[station].mean() > 5 * max(off.rgb[station].mean(), 1e-9)  # the spot is what lights it
    assert on.rgb[station].mean() < 0.1 * lit.rgb[station].mean()           # far dimmer than sunlight
    # Without the spot only the sunlit Earth (its own lamp) can light the station: earthshine, ~1e-4 of
    # sunlight, which 16 samples rarely find (tests/blender/test_render_sky.py measures it on the real umbra day).
    assert off.rgb[station].mean() < 1e-3 * lit.rgb[station].mean()
    assert dark.rgb.max() == 0.0  # and without body shine, nothing


def test_station_sun_never_lights_the_bodies_on_an_eclipse_day(tiny_base, tmp_path):
    """Toggle the station's eclipse (lit, umbra, half lit): the Moon looks the same, since on an eclipse
    day only its own lamp lights it (light linking), and on a normal day the one lamp is the same Sun;
    the station changes."""
    pos = np.array([0.0, 0.0, -5.0])  # under the station, looking straight down at the Moon
    cam = replace(make_spec().camera, position=tuple(pos), rotation=look_at(pos, pos + [0.0, 0.0, -1.0]))
    spec = replace(make_spec(resolution=(64, 36), samples=4), camera=cam, effects=EffectsSpec(inspection_light=False))
    suns = {"lit": spec.sun, "umbra": replace(spec.sun, irradiance=0.0, lit_fraction=0.0, eclipse_state="umbra"),
            "half": replace(spec.sun, irradiance=0.5 * 1361.0, lit_fraction=0.5, eclipse_state="penumbra")}
    moon = {name: _render(replace(spec, sun=s), tiny_base, tmp_path / f"moon_{name}.usda").rgb
            for name, s in suns.items()}
    assert moon["lit"].mean() > 0.01  # the Moon's near side is sunlit and fills the frame
    np.testing.assert_allclose(moon["umbra"], moon["lit"], rtol=1e-5, atol=0)
    np.testing.assert_allclose(moon["half"], moon["lit"], rtol=1e-5, atol=0)
    station = {name: _render(replace(make_spec(resolution=(64, 36), samples=4), sun=s), tiny_base,
                             tmp_path / f"station_{name}.usda") for name, s in suns.items()}
    lit_station = station["lit"].rgb[station["lit"].mask == 1].mean()
    assert station["half"].rgb[station["lit"].mask == 1].mean() == pytest.approx(0.5 * lit_station, rel=0.02)
    assert station["umbra"].rgb[station["lit"].mask == 1].mean() < 0.05 * lit_station


def test_tiny_far_anomaly_and_frame_filling_anomaly(tiny_base, tmp_path):
    spec = make_spec(anomaly=True, resolution=(128, 72), samples=2)
    fwd = (np.zeros(3) - CAM_POS) / np.linalg.norm(CAM_POS)
    far = replace(spec, anomaly=replace(spec.anomaly, position=tuple(CAM_POS + 14.0 * fwd)))
    near = replace(spec, anomaly=replace(spec.anomaly, position=tuple(CAM_POS + 0.45 * fwd)))
    r_far = _render(far, tiny_base, tmp_path / "far.usda")
    r_near = _render(near, tiny_base, tmp_path / "near.usda")
    n = r_far.mask.size
    assert 0 < (r_far.mask == 2).sum() < 0.005 * n       # a few pixels, still labelled
    assert (r_near.mask == 2).mean() > 0.5               # fills most of the frame
    assert np.isfinite(r_near.rgb).all() and np.isfinite(r_far.rgb).all()


def test_body_shine_only_when_declared(tiny_base, tmp_path):
    # The Moon 7,000 km below, its near side sunlit: moonshine brightens the station's underside.
    spec = make_spec(resolution=(64, 36), samples=16)
    on = read_scene(write_scene_layer(spec, tmp_path / "on.usda", tiny_base))
    off_spec = replace(spec, effects=EffectsSpec(body_shine=False))
    off = read_scene(write_scene_layer(off_spec, tmp_path / "off.usda", tiny_base))
    vis = {m.path: m.ray_visibility for m in off.meshes}
    assert vis["/World/Sky/Moon/Geom/Surface"] == "cameraOnly"
    assert {m.path: m.ray_visibility for m in on.meshes}["/World/Sky/Moon/Geom/Surface"] == "noShadow"
    r_on, r_off = render_scene(on), render_scene(off)
    station = r_on.mask == 1
    assert r_on.rgb[station].mean() > r_off.rgb[station].mean()
