"""Real Cycles renders of tiny images: masks line up with classes, outputs are deterministic."""

from __future__ import annotations

import json

import numpy as np
import OpenEXR
import pytest
from PIL import Image

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.run.job import render_layer

from tests.support.helpers import make_spec

pytestmark = pytest.mark.render


def test_normal_mask_has_background_and_station(rendered):
    layer, meta, d = rendered["normal"]
    mask = np.asarray(Image.open(d / meta["files"]["mask"]))
    assert mask.dtype == np.uint8 and mask.shape == (36, 64)
    assert set(np.unique(mask)) == {0, 1}
    rgb = np.asarray(Image.open(d / meta["files"]["rgb"]))
    assert rgb.shape == (36, 64, 3)
    # Lit station pixels are bright but not clipped; background is black space.
    assert 60 < rgb[mask == 1].mean() < 250
    assert rgb[mask == 0].mean() < 8  # edge pixels are anti-aliased; the mask is not


def test_anomaly_mask_has_class_2_where_the_anomaly_is(rendered):
    _, meta, d = rendered["anomaly"]
    mask = np.asarray(Image.open(d / meta["files"]["mask"]))
    assert set(np.unique(mask)) == {0, 1, 2}
    assert meta["class_pixels"]["anomaly"] == int((mask == 2).sum()) > 0
    rgb = np.asarray(Image.open(d / meta["files"]["rgb"])).astype(int)
    blue = rgb[mask == 2]
    assert blue[:, 2].mean() > blue[:, 0].mean()  # the blue variant was rendered


def test_exr_is_linear_half_and_matches_png(rendered):
    _, meta, d = rendered["normal"]
    with OpenEXR.File(str(d / meta["files"]["exr"]), separate_channels=True) as f:
        r = f.channels()["R"].pixels
    assert r.dtype == np.float16 and r.shape == (36, 64)
    mask = np.asarray(Image.open(d / meta["files"]["mask"]))
    assert float(r[mask == 1].max()) < 1.2  # exposure puts sunlit white near 0.9


def test_same_layer_same_bytes(rendered, tmp_path):
    layer, meta, d = rendered["anomaly"]
    again = render_layer(layer, tmp_path)
    for key in ("rgb", "mask", "exr"):
        assert (tmp_path / again["files"][key]).read_bytes() == (d / meta["files"][key]).read_bytes(), key


def test_rerun_skips_finished_scene(rendered):
    layer, meta, d = rendered["normal"]
    before = (d / meta["files"]["meta"]).stat().st_mtime_ns
    render_layer(layer, d)
    assert (d / meta["files"]["meta"]).stat().st_mtime_ns == before
    assert json.loads((d / meta["files"]["meta"]).read_text())["scene"]["seed"] == 7


def test_sensor_noise_only_when_declared(tiny_base, tmp_path):
    from dataclasses import replace

    from allo_usd.plan.settings import EffectsSpec

    metas = {}
    for noisy in (False, True):
        spec = replace(make_spec(), effects=EffectsSpec(sensor_noise=noisy))
        layer = write_scene_layer(spec, tmp_path / f"n{int(noisy)}.usda", tiny_base)
        metas[noisy] = render_layer(layer, tmp_path / "out")
    assert metas[False]["effects"] == {}
    assert metas[True]["effects"]["sensor_noise"]["model"] == "EMVA 1288"
    clean = np.asarray(Image.open(tmp_path / "out" / metas[False]["files"]["rgb"])).astype(int)
    noisy = np.asarray(Image.open(tmp_path / "out" / metas[True]["files"]["rgb"])).astype(int)
    mask = np.asarray(Image.open(tmp_path / "out" / metas[True]["files"]["mask"]))
    assert (clean != noisy).mean() > 0.3
    assert abs(clean[mask == 1].mean() - noisy[mask == 1].mean()) < 6  # same level, plus noise


def test_glare_builds_a_compositor_only_when_declared(tiny_base, tmp_path):
    from dataclasses import replace

    import bpy

    from allo_usd.blender.render import render_scene
    from allo_usd.usd.read import read_scene
    from allo_usd.plan.settings import EffectsSpec

    from allo_usd.core.geometry import look_at

    base = make_spec(resolution=(320, 180), samples=2)
    pos = np.array([0.0, 0.0, 30.0])
    sun_at = pos + np.array(base.sun.direction)
    results = {}
    for glare in (False, True):  # the Sun in frame: its disc is far above the glare threshold
        spec = replace(base, effects=EffectsSpec(glare=glare),
                       camera=replace(base.camera, position=tuple(pos), rotation=look_at(pos, sun_at)))
        desc = read_scene(write_scene_layer(spec, tmp_path / f"g{int(glare)}.usda", tiny_base))
        results[glare] = render_scene(desc)
        tree = bpy.context.scene.compositing_node_group
        if glare:
            assert tree is not None and any(n.bl_idname == "CompositorNodeGlare" for n in tree.nodes)
        else:
            assert tree is None and not bpy.context.scene.render.use_compositing
    # Glare spreads the Sun's light into the black sky around the disc.
    bg = results[False].mask == 0
    assert results[True].rgb[bg].mean() > 10 * max(results[False].rgb[bg].mean(), 1e-6)
    np.testing.assert_array_equal(results[True].mask, results[False].mask)


def test_denoiser_follows_the_layer(tiny_base, tmp_path):
    from dataclasses import replace

    import bpy

    from allo_usd.blender.render import render_scene
    from allo_usd.usd.read import read_scene

    base = make_spec(samples=2)
    for prefilter, quality in (("ACCURATE", "HIGH"), ("FAST", "BALANCED")):
        spec = replace(base, render=replace(base.render, denoise=True, denoise_prefilter=prefilter,
                                            denoise_quality=quality))
        result = render_scene(read_scene(write_scene_layer(spec, tmp_path / f"{prefilter}.usda", tiny_base)))
        cycles = bpy.context.scene.cycles
        assert cycles.use_denoising and (cycles.denoising_prefilter, cycles.denoising_quality) == (prefilter, quality)
        assert result.rgb.max() > 0


def test_depth_and_mask_only_outputs(tiny_base, tmp_path, rendered):
    from dataclasses import replace

    from allo_usd.usd.sniff import layer_outputs

    base = make_spec(anomaly=True)
    with_depth = replace(base, render=replace(base.render, passes=("rgb", "exr", "mask", "depth")))
    layer = write_scene_layer(with_depth, tmp_path / "depth.usda", tiny_base)
    assert layer_outputs(layer) == ("rgb", "exr", "mask", "depth")
    meta = render_layer(layer, tmp_path / "out")
    with OpenEXR.File(str(tmp_path / "out" / meta["files"]["depth"]), separate_channels=True) as f:
        z = f.channels()["Z"].pixels
    mask = np.asarray(Image.open(tmp_path / "out" / meta["files"]["mask"]))
    assert z.dtype == np.float32 and z.shape == mask.shape
    station_z = z[mask == 1]
    assert 5.0 < np.median(station_z) < 40.0  # metres from the camera 19 m from the station centre
    assert z[mask == 2].max() < np.median(station_z)  # the anomaly floats in front of the station

    mask_only = replace(base, render=replace(base.render, passes=("mask",)))
    layer = write_scene_layer(mask_only, tmp_path / "maskonly.usda", tiny_base)
    assert layer_outputs(layer) == ("mask",)
    meta = render_layer(layer, tmp_path / "out")
    assert set(meta["files"]) == {"mask", "meta"}
    assert not (tmp_path / "out" / "maskonly.png").exists()
    full_layer, full_meta, d = rendered["anomaly"]
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "out" / meta["files"]["mask"])),
                                  np.asarray(Image.open(d / full_meta["files"]["mask"])))


@pytest.mark.parametrize("ior", [1.0, 1.5])  # Lambertian, and Principled's default specular layer
def test_sunlit_white_plate_renders_near_but_below_white(tmp_path, ior):
    """A white plate (base colour 1, roughness 1, metallic 0) facing a 1361 W/m^2 sun at normal
    incidence, at the default exposure 0.9*pi/1361: linear 0.9 (radiance E/pi times exposure),
    sRGB 8-bit 243, not 255. Spot off; the bodies sit behind the plate, unseen and lighting nothing."""
    from dataclasses import replace

    from allo_usd.assets.primitives import grid, uv_sphere
    from allo_usd.scene.spec import CameraPose
    from allo_usd.usd.base_stage import write_base_stage
    from allo_usd.core.geometry import look_at, rotation_towards
    from allo_usd.assets.mesh import Asset, Material
    from allo_usd.scene.spec import BodySpec, CameraSpec
    from allo_usd.plan.settings import EffectsSpec
    from allo_usd.output.writers import linear_to_srgb8

    from tests.support.helpers import EXPOSURE, tiny_anomalies

    spec = make_spec(resolution=(64, 36), samples=16)
    n = np.array(spec.sun.direction)  # the plate's normal points at the Sun
    plate = np.eye(4)
    plate[:3, :3] = rotation_towards(n)
    station = Asset("Station", (grid("Plate", 200.0, 200.0, "white", matrix=plate),),
                    (Material("white", (1.0, 1.0, 1.0), 0.0, 1.0, ior=ior),))
    bodies = {name: Asset(name, (uv_sphere("Surface", 1.0, "Grey"),), (Material("Grey", (0.2, 0.2, 0.2)),))
              for name in ("Moon", "Earth", "Sun")}
    cam = 20.0 * (n + 0.4 * rotation_towards(n)[:, 0])  # 22 deg off the normal, 22 m from the plate
    poses = [CameraPose(1, "train", cam, look_at(cam, [0, 0, 0]))]
    base = write_base_stage(tmp_path / "stages", station, bodies, tiny_anomalies(), poses)
    behind = {name: BodySpec(tuple(-n * d), r) for name, d, r in
              (("Moon", 7e6, 1.7374e6), ("Earth", 3.8e8, 6.371e6), ("Sun", 1.496e11, 6.9634e8))}
    spec = replace(spec, camera=CameraSpec(tuple(cam), look_at(cam, [0, 0, 0])), bodies=behind,
                   effects=EffectsSpec(inspection_light=False))
    assert spec.render.exposure == EXPOSURE and spec.sun.irradiance == 1361.0
    layer = write_scene_layer(spec, tmp_path / "plate.usda", base)
    meta = render_layer(layer, tmp_path / "out")
    mask = np.asarray(Image.open(tmp_path / "out" / meta["files"]["mask"]))
    assert (mask == 1).all()  # the plate fills the frame
    with OpenEXR.File(str(tmp_path / "out" / meta["files"]["exr"]), separate_channels=True) as f:
        linear = np.stack([f.channels()[c].pixels for c in "RGB"], -1).astype(np.float64)
    assert 0.85 <= linear.min() and linear.max() <= 0.95
    if ior == 1.0:  # Lambertian: exactly E/pi * albedo * exposure
        assert linear.mean() == pytest.approx(0.9, abs=0.005)
    png = np.asarray(Image.open(tmp_path / "out" / meta["files"]["rgb"]))
    assert 240 <= png.min() and png.max() <= 250  # near white, never clipped to 255
    assert int(linear_to_srgb8(np.full((1, 1, 3), 0.9, np.float32)).max()) == 243
