"""A warm Session applies only what differs between scenes, and renders exactly what a fresh build renders."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.core.geometry import look_at
from allo_usd.scene.spec import AnomalySpec, SunSpec
from allo_usd.plan.settings import EffectsSpec

from tests.support.helpers import make_spec

pytestmark = pytest.mark.render


def _sequence() -> list[tuple[str, object]]:
    """normal -> anomaly A -> anomaly B -> other camera and day -> umbra -> lunar eclipse (the Moon's
    lamp off, the Earth's turned) -> glare -> no body shine -> normal."""
    base = make_spec(samples=2)
    red = replace(base, anomaly=AnomalySpec("Crate", "red", (8.0, 4.0, 2.5), np.eye(3)))
    blue = replace(red, anomaly=replace(red.anomaly, variant="blue"))
    pos = np.array([12.0, -9.0, 6.0])
    sun_dir = np.array([-0.4, 0.2, 0.9]) / np.linalg.norm([-0.4, 0.2, 0.9])
    other = replace(blue, camera=replace(blue.camera, position=tuple(pos), rotation=look_at(pos, [0, 0, 0])),
                    sun=replace(blue.sun, direction=tuple(sun_dir), irradiance=1300.0, angular_diameter_deg=0.52),
                    day=7, epoch="2030-01-08T00:00:00Z")
    umbra = replace(other, sun=replace(other.sun, irradiance=0.0, lit_fraction=0.0, eclipse_state="umbra",
                                       eclipse_body="earth"),
                    render=replace(other.render, seed=5, samples=3))
    earth_dir = np.array([-0.3, 0.3, 0.9]) / np.linalg.norm([-0.3, 0.3, 0.9])
    lunar = replace(umbra, bodies={
        **umbra.bodies,
        "Moon": replace(umbra.bodies["Moon"], light=SunSpec(tuple(sun_dir), 0.0, 1300.0, 0.52, 1.5e11, 0.0, "umbra",
                                                            "earth")),
        "Earth": replace(umbra.bodies["Earth"], light=SunSpec(tuple(earth_dir), 1290.0, 1290.0, 0.52, 1.5e11))})
    glare = replace(base, effects=EffectsSpec(glare=True))
    no_shine = replace(base, effects=EffectsSpec(body_shine=False))
    return [("normal", base), ("anomaly_red", red), ("anomaly_blue", blue), ("other_day", other),
            ("umbra", umbra), ("lunar", lunar), ("glare", glare), ("no_shine", no_shine), ("normal_again", base)]


@pytest.fixture(scope="module")
def descs(tiny_base, tmp_path_factory):
    from allo_usd.usd.read import read_scene

    root = tmp_path_factory.mktemp("session")
    return [(name, read_scene(write_scene_layer(spec, root / f"{name}.usda", tiny_base)))
            for name, spec in _sequence()]


def test_incremental_renders_are_byte_identical_to_fresh_builds(descs):
    import bpy

    from allo_usd.blender.render import render_scene
    from allo_usd.blender.session import Session

    fresh = {name: render_scene(d) for name, d in descs}
    session = Session()
    station = None
    for i, (name, d) in enumerate(descs):
        got = session.render(d)
        stats = session.last
        if i == 0:
            assert stats.full_build
            station = {o.name: o.as_pointer() for o in bpy.context.scene.objects if o.name.startswith("/World/Station")}
            assert station
        else:
            assert not stats.full_build, name
        assert {o.name: o.as_pointer() for o in bpy.context.scene.objects
                if o.name.startswith("/World/Station")} == station, name  # never rebuilt
        assert got.rgb.dtype == fresh[name].rgb.dtype
        np.testing.assert_array_equal(got.rgb, fresh[name].rgb, err_msg=name)
        np.testing.assert_array_equal(got.mask, fresh[name].mask, err_msg=name)
        # Every patched matrix went in as a quaternion, never as Euler angles (docs/physics.md section 4).
        assert {o.rotation_mode for o in bpy.context.scene.objects} == {"QUATERNION"}, name
        lamps = {o.name: o for o in bpy.context.scene.objects if o.type == "LIGHT" and o.data.type == "SUN"}
        assert sorted(lamps) == sorted(s.path for s in d.suns), name
        for sun in d.suns:  # the receiver collections a fresh build would make, member for member
            coll = lamps[sun.path].light_linking.receiver_collection
            if sun.link is None:  # a normal day's one lamp lights everything: no collection
                assert coll is None, name
                continue
            assert sorted(o.name for o in coll.objects) == sorted(sun.link.paths), name
            assert {m.light_linking.link_state for m in coll.collection_objects} == \
                {"EXCLUDE" if sun.link.exclude else "INCLUDE"}, name
    assert session.full_builds == 1
    # The sequence exercised every kind of change.
    assert fresh["anomaly_red"].mask.max() == 2 and fresh["normal"].mask.max() == 1
    assert fresh["umbra"].rgb.mean() < fresh["other_day"].rgb.mean()
    assert len(dict(descs)["lunar"].suns) == 1  # only the Earth's lamp is on


def test_session_applies_only_differences(descs):
    from allo_usd.blender.session import Session

    d = dict(descs)
    session = Session()
    session.apply(d["normal"])
    s = session.apply(d["anomaly_red"])
    assert s.meshes_added and all("Anomaly" in p or "Crate" in p for p in s.meshes_added) and not s.meshes_removed
    s = session.apply(d["anomaly_blue"])  # same box, other colour: a material patch, no mesh work
    assert not s.meshes_added and not s.meshes_removed and s.materials_patched
    s = session.apply(d["umbra"])
    assert "sun" in s.changed and "camera" in s.changed
    s = session.apply(d["lunar"])
    assert s.changed == ["sun"] and not (s.meshes_added or s.meshes_removed)
    s = session.apply(d["glare"])
    assert "compositor" in s.changed and s.meshes_removed
    s = session.apply(d["glare"])
    assert not (s.changed or s.meshes_added or s.meshes_removed or s.materials_patched)


def test_anomaly_in_and_out_leaves_no_orphans(descs):
    import bpy

    from allo_usd.blender.session import Session

    d = dict(descs)
    session = Session()
    counts = []
    for _ in range(3):
        for name in ("normal", "anomaly_red", "glare", "anomaly_blue", "umbra", "lunar"):
            session.apply(d[name])
        session.apply(d["normal"])
        counts.append((len(bpy.data.meshes), len(bpy.data.materials), len(bpy.data.objects), len(bpy.data.lights),
                       len(bpy.data.node_groups), len(bpy.data.worlds), len(bpy.data.collections)))
    assert counts[0] == counts[1] == counts[2]
    n = d["normal"]
    lights = len(n.suns) + (n.spot is not None)
    assert counts[0][:4] == (len(n.meshes), len(n.materials), len(n.meshes) + 1 + lights, lights)
    assert counts[0][4] == 0 and counts[0][5] == 1
    assert len(n.suns) == 1 and counts[0][6] == 0  # a normal day: one unlinked lamp, no receiver collection
    assert all(s.link is not None for s in d["umbra"].suns)  # an eclipse day: the bodies' own linked lamps


def test_render_layer_uses_a_session(tiny_base, tmp_path):
    from allo_usd.blender.session import Session
    from allo_usd.run.job import render_layer

    session = Session()
    layers = [write_scene_layer(spec, tmp_path / f"{name}.usda", tiny_base) for name, spec in _sequence()[:3]]
    for layer in layers:
        render_layer(layer, tmp_path / "warm", session=session)
    assert session.full_builds == 1 and session.applies == 3
    for layer in layers:
        render_layer(layer, tmp_path / "cold")
    # A fresh build elsewhere in the process replaced the Blender scene: the session notices and rebuilds.
    render_layer(layers[0], tmp_path / "again", session=session)
    assert session.full_builds == 2
    for p in sorted((tmp_path / "cold").glob("*")):
        if p.suffix != ".json":
            assert (tmp_path / "warm" / p.name).read_bytes() == p.read_bytes(), p.name


def test_other_geometry_builds_from_scratch(descs):
    from allo_usd.blender.session import Session

    d = dict(descs)
    session = Session()
    session.apply(d["normal"])
    one = replace(d["normal"], meshes=(replace(d["normal"].meshes[0], points=d["normal"].meshes[0].points * 1.01),
                                       *d["normal"].meshes[1:]))
    s = session.apply(one)  # one mesh changed: only it is rebuilt
    assert not s.full_build and s.meshes_added == [one.meshes[0].path] == s.meshes_removed
    other = replace(one, meshes=tuple(replace(m, points=m.points * 0.5) for m in one.meshes))
    assert session.apply(other).full_build and session.full_builds == 2  # nothing to keep: another stage


def _with_lights(d):
    """`d` with the other lamps and the dome: each kind, then changed, then fewer."""
    from allo_usd.usd.description import AreaDesc, CylinderDesc, DomeDesc, LampRays, SpotDesc

    m = np.eye(4)
    m[:3, 3] = d.camera.matrix[:3, 3]
    m[:3, :3] = d.camera.matrix[:3, :3]  # at the camera, facing where it looks
    point = SpotDesc(m, 0.05, 2e6, (1.0, 1.0, 1.0), 90.0, 0.0, "/World/Lamp", shaped=False)
    rect = AreaDesc("/World/Panel", m, "RECTANGLE", (0.5, 0.4), 4e4, 4e4 * 0.2 * math.pi, (1.0, 0.5, 0.5),
                    rays=LampRays(specular=False))
    tube = CylinderDesc("/World/Tube", m, 0.05, 1.0, 2e5, (0.5, 1.0, 0.5))
    dome = DomeDesc("/World/Dome", (0.2, 0.4, 1.0), 100.0)
    many = replace(d, lights=(point, rect, tube), dome=dome)
    changed = replace(d, lights=(point, replace(rect, power=rect.power * 2), tube),
                      dome=replace(dome, color=(1.0, 0.5, 0.2)))
    fewer = replace(d, lights=(rect,))
    return [("lights", many), ("lights_changed", changed), ("lights_fewer", fewer), ("lights_none", d)]


def test_added_changed_and_removed_lights_render_as_fresh_builds(descs):
    import bpy

    from allo_usd.blender.render import render_scene
    from allo_usd.blender.session import Session

    d = dict(descs)
    seq = [("normal", d["normal"])] + _with_lights(d["normal"])
    fresh = {name: render_scene(x) for name, x in seq}
    session = Session()
    counts = {}
    for name, x in seq:
        got = session.render(x)
        np.testing.assert_array_equal(got.rgb, fresh[name].rgb, err_msg=name)
        np.testing.assert_array_equal(got.mask, fresh[name].mask, err_msg=name)
        counts[name] = (len(bpy.data.meshes), len(bpy.data.materials), len(bpy.data.objects), len(bpy.data.lights))
    assert session.full_builds == 5  # other lamps or a dome that differ: built from scratch (Session._lamps_differ)
    same = session.apply(seq[1][1])
    assert same.full_build and not session.apply(seq[1][1]).full_build  # the same lamps again: patched
    assert counts["lights_none"] == counts["normal"]  # the cylinder's mesh and material went with it
    assert fresh["lights"].rgb.mean() > fresh["normal"].rgb.mean()
    assert not np.array_equal(fresh["lights"].rgb, fresh["lights_changed"].rgb)
    np.testing.assert_array_equal(fresh["lights"].mask, fresh["normal"].mask)  # lamps are never labelled


def test_material_subsets_render_as_fresh_builds(descs):
    """A mesh whose faces are split between materials (MeshDesc.subsets), then the subset's material
    changed, then no subset: each warm render equals a fresh build of the same description."""
    from allo_usd.blender.render import render_scene
    from allo_usd.blender.session import Session

    d = dict(descs)["normal"]
    i, mesh = max(enumerate(d.meshes), key=lambda x: len(x[1].face_counts))
    others = sorted(k for k in d.materials if k != mesh.material)
    assert len(mesh.face_counts) >= 2 and len(others) >= 2
    half = np.arange(len(mesh.face_counts) // 2, dtype=np.int32)

    def with_subset(key):
        meshes = list(d.meshes)
        meshes[i] = replace(mesh, subsets=((key, half),))
        return replace(d, meshes=tuple(meshes))

    seq = [("normal", d), ("subset", with_subset(others[0])), ("subset_other", with_subset(others[1])),
           ("normal_again", d)]
    fresh = {name: render_scene(x) for name, x in seq}
    session = Session()
    for name, x in seq:
        np.testing.assert_array_equal(session.render(x).rgb, fresh[name].rgb, err_msg=name)
    assert not np.array_equal(fresh["subset"].rgb, fresh["normal"].rgb)   # the subset's faces changed colour
