"""Geometry of one's own over the demo's anomalous scene, rendered: each row of docs/usd/what_renders.md's
geometry table placed in front of the camera shows where its projection says, in the class it is
labelled (`station` here, through semantics:labels:class on its parent); a display colour is the
colour; a guide is absent and a render purpose present; a refused row is one line and exit 2; and
Blender's own importer shows each rendered row too."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from allo_usd.core.labels import STATION
from allo_usd.output.annotations import project
from tests.support.helpers import one_line_error, sandboxed_cli
from tests.support.user_geometry import USER, in_view, prim
from tests.support.user_layers import DEMO_ANOMALY, demo_layers, override, render

DEPTH = 4.0   # metres in front of the camera


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """The scene, its camera, the baseline (the override with an empty /World/UserGeom) and two spots:
    background pixels of the baseline far from the station, as (pixel, point in the camera's frame)."""
    from allo_usd.usd.read import read_scene

    root = tmp_path_factory.mktemp("user_geometry")
    scene = demo_layers(root) / f"{DEMO_ANOMALY}.usda"
    camera = read_scene(scene).camera.matrix
    before = render(override(scene, root / "baseline.usda", in_view(camera, label="station")), root / "baseline")
    cam = before.record["annotations"]["camera"]
    k = np.array(cam["K_px"])
    h, w = before.mask.shape
    ys, xs = np.nonzero(before.mask != 0)
    grid = [(u, v) for v in range(6, h - 6) for u in range(6, w - 6) if before.mask[v, u] == 0]
    margin = [min(np.hypot(xs - u, ys - v).min(), u, v, w - 1 - u, h - 1 - v) for u, v in grid]
    order = np.argsort(margin)[::-1]
    first = grid[order[0]]
    second = next(grid[i] for i in order if np.hypot(grid[i][0] - first[0], grid[i][1] - first[1]) > 14)

    def point(uv):   # the pixel's ray at DEPTH, in the camera's USD frame (x right, y up, -z forward)
        x, y = (uv[0] - k[0, 2]) / k[0, 0] * DEPTH, (uv[1] - k[1, 2]) / k[1, 1] * DEPTH
        return (x, -y, -DEPTH)

    return dict(root=root, scene=scene, camera=camera, before=before, k=k,
                w2c=np.array(cam["world_to_cam_opencv"]), spots=[(first, point(first)), (second, point(second))])


def show(base, name: str, *prims: str, label: str | None = "station"):
    layer = override(base["scene"], base["root"] / f"{name}.usda", in_view(base["camera"], *prims, label=label))
    return render(layer, base["root"] / name)


def appears_at(base, after, *world_points, reach_m: float = 0.4, lit: bool = False) -> np.ndarray:
    """The new pixels (background before; labelled after, or with `lit` brighter by 30 levels) lie within the projections of balls of
    `reach_m` around `world_points`, and those around each point have their box centred on its
    projection; returns them."""
    changed = (after.rgb.astype(int) - base["before"].rgb).max(axis=-1) > 30 if lit else after.mask != 0
    new = (base["before"].mask == 0) & changed
    rows, cols = np.indices(new.shape)
    covered = np.zeros_like(new)
    for point in world_points:
        uv, z = project(base["k"], base["w2c"], [point])
        assert z[0] > 0
        near = np.hypot(cols - uv[0, 0], rows - uv[0, 1]) <= reach_m / z[0] * base["k"][0, 0] + 1.5
        ys, xs = np.nonzero(new & near)
        assert len(xs) >= 4, uv
        assert abs((xs.min() + xs.max()) / 2 - uv[0, 0]) <= 1.5 and abs((ys.min() + ys.max()) / 2 - uv[0, 1]) <= 1.5, \
            (uv, xs.min(), xs.max(), ys.min(), ys.max())
        covered |= near
    assert not (new & ~covered).any(), np.argwhere(new & ~covered)
    return new


def world(base, local) -> np.ndarray:
    return (base["camera"] @ [*local, 1.0])[:3]


SHAPES = {
    "Cube": ["double size = 0.5"],
    "Sphere": ["double radius = 0.3"],
    "Cylinder": ["double radius = 0.25", "double height = 0.5", 'uniform token axis = "Y"'],
    "Cone": ["double radius = 0.3", "double height = 0.5", 'uniform token axis = "X"'],
    "Capsule": ["double radius = 0.2", "double height = 0.3"],
    "Plane": ["double width = 0.5", "double length = 0.5"],
}


@pytest.mark.render
@pytest.mark.parametrize("kind", SHAPES)
def test_implicit_shape_appears_where_its_projection_says(base, kind):
    (_, at), _ = base["spots"]
    after = show(base, kind.lower(), prim(kind, "shape", at, *SHAPES[kind]))
    here = appears_at(base, after, world(base, at))
    assert (after.mask[here] == STATION).all()
    assert after.rgb[here].max() > 20        # lit, not a black hole



@pytest.mark.render
def test_instanceable_reference_and_point_instancer_appear(base):
    (_, a), (_, b) = base["spots"]
    proto = 'class Xform "Proto"\n{\n' + prim("Cube", "box", (0, 0, 0), "double size = 0.4") + "}\n"
    ref = prim("Xform", "Inst", a, meta="instanceable = true\nreferences = </World/Proto>")
    layer = override(base["scene"], base["root"] / "instanced.usda",
                     in_view(base["camera"], ref, extra=proto, label="station"))
    after = render(layer, base["root"] / "instanced")
    assert (after.mask[appears_at(base, after, world(base, a))] == STATION).all()
    instancer = prim("PointInstancer", "PI", None, "int[] protoIndices = [0, 0]",
                     f"point3f[] positions = [{a}, {b}]", "rel prototypes = </World/UserGeom/PI/Ball>",
                     children=prim("Sphere", "Ball", (0, 0, 0), "double radius = 0.25"))
    after = show(base, "point_instancer", instancer)
    assert (after.mask[appears_at(base, after, world(base, a), world(base, b))] == STATION).all()


@pytest.mark.render
def test_display_color_is_the_colour(base):
    (_, at), _ = base["spots"]
    after = show(base, "display_color", prim("Sphere", "s", at, "double radius = 0.3",
                                             "color3f[] primvars:displayColor = [(0.05, 0.8, 0.05)]"), label=None)
    here = appears_at(base, after, world(base, at), lit=True)
    r, g, b = after.rgb[here].astype(float).mean(axis=0)
    assert g > 2 * max(r, b) and g > 20, (r, g, b)
    assert (after.mask[here] != 2).all()     # unlabelled: not the anomaly


@pytest.mark.render
def test_guide_is_absent_and_render_purpose_present(base):
    (ua, a), (ub, b) = base["spots"]
    after = show(base, "purpose", prim("Cube", "guide", a, "double size = 0.5", 'uniform token purpose = "guide"'),
                 prim("Cube", "render", b, "double size = 0.5", 'uniform token purpose = "render"'))
    appears_at(base, after, world(base, b))
    assert after.mask[ua[1], ua[0]] == 0 and (after.mask == base["before"].mask)[:, :ua[0] + 4].any()
    uv, _ = project(base["k"], base["w2c"], [world(base, a)])
    u, v = np.round(uv[0]).astype(int)
    assert (after.mask[v - 2:v + 3, u - 2:u + 3] == 0).all()


@pytest.mark.process
def test_a_refused_gprim_is_one_line_and_exit_2(base):
    layer = override(base["scene"], base["root"] / "curves.usda", in_view(base["camera"], prim(
        "BasisCurves", "hair", None, "int[] curveVertexCounts = [2]", "point3f[] points = [(0, 0, -4), (1, 0, -4)]")))
    r = sandboxed_cli("render", layer, "--out", base["root"] / "curves_out", cwd=base["root"])
    one_line_error(r, f"{USER}/hair is a BasisCurves", "allo-usd renders Mesh and the implicit shapes", hidden="\n\n")


# Blender's own importer (bpy.ops.wm.usd_import) on a layer holding every rendered row: what it makes of each.
IMPORT_PROBE = r"""
import bpy, json, sys
bpy.ops.wm.read_factory_settings(use_empty=True)
assert "FINISHED" in bpy.ops.wm.usd_import(filepath=sys.argv[1])
out = {}
for o in bpy.context.scene.objects:
    if o.type == "MESH" or o.instance_type != "NONE" or o.modifiers:
        out[o.name] = {"type": o.type, "modifiers": [m.type for m in o.modifiers],
                       "colors": [a.name for a in o.data.color_attributes] if o.type == "MESH" else []}
print("PROBE " + json.dumps(out))
"""

IMPORTER_ROWS = {**{kind: kind.lower() for kind in SHAPES}, "instanceable reference": "box",
                 "PointInstancer": "PI", "displayColor": "tinted", "purpose render": "rendered"}


@pytest.fixture(scope="module")
def imported(base):
    (_, a), (_, b) = base["spots"]
    prims = [prim(kind, kind.lower(), a, *props) for kind, props in SHAPES.items()]
    prims += [prim("Xform", "Inst", a, meta="instanceable = true\nreferences = </World/Proto>"),
              prim("PointInstancer", "PI", None, "int[] protoIndices = [0, 0]", f"point3f[] positions = [{a}, {b}]",
                   "rel prototypes = </World/UserGeom/PI/Ball>", children=prim("Sphere", "Ball", (0, 0, 0))),
              prim("Cube", "tinted", b, "color3f[] primvars:displayColor = [(0.05, 0.8, 0.05)]"),
              prim("Cube", "guided", b, 'uniform token purpose = "guide"'),
              prim("Cube", "rendered", b, 'uniform token purpose = "render"')]
    proto = 'class Xform "Proto"\n{\n' + prim("Cube", "box", (0, 0, 0)) + "}\n"
    layer = override(base["scene"], base["root"] / "importer.usda", in_view(base["camera"], *prims, extra=proto))
    r = subprocess.run([sys.executable, "-c", IMPORT_PROBE, str(layer)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.split("PROBE ", 1)[1])


@pytest.mark.bpy
@pytest.mark.process
@pytest.mark.parametrize("row", IMPORTER_ROWS)
def test_blenders_importer_shows_the_rendered_rows(imported, row):
    name = IMPORTER_ROWS[row]
    got = {k: v for k, v in imported.items() if k == name or k.startswith(name + ".")}
    assert got, sorted(imported)
    if row == "PointInstancer":   # the importer instances the prototype on a point cloud (geometry nodes)
        assert any("NODES" in v["modifiers"] for v in got.values()), got
    else:
        assert any(v["type"] == "MESH" for v in got.values()), got
    if row == "displayColor":
        assert any("displayColor" in v["colors"] for v in got.values()), got
    if row == "purpose render":
        assert "guided" not in imported    # the importer leaves guides out, as the render does


@pytest.mark.render
def test_invisible_is_absent(base):
    """visibility = invisible (UsdGeom.Imageable): the prim and everything under it is not drawn."""
    (ua, a), (ub, b) = base["spots"]
    after = show(base, "invisible", prim("Cube", "hidden", a, "double size = 0.5", 'token visibility = "invisible"'),
                 prim("Xform", "hidden_parent", b, 'token visibility = "invisible"',
                      children=prim("Sphere", "child", (0.0, 0.0, 0.0), "double radius = 0.3")))
    assert np.array_equal(after.mask, base["before"].mask)
    assert np.array_equal(after.rgb, base["before"].rgb)


def _preview(name: str, colour: str) -> str:
    return (f'def Material "{name}" {{\ntoken outputs:surface.connect = <{USER}/{name}/S.outputs:surface>\n'
            f'def Shader "S" {{\nuniform token info:id = "UsdPreviewSurface"\ncolor3f inputs:diffuseColor = {colour}\n'
            'token outputs:surface\n}\n}\n')


@pytest.mark.render
def test_a_subset_material_colours_its_faces(base):
    """Two faces side by side, the mesh bound red and a materialBind GeomSubset of the right face blue:
    the left face renders red and the right one blue."""
    (_, at), _ = base["spots"]
    x, y, z = at
    quad = ["int[] faceVertexCounts = [4, 4]", "int[] faceVertexIndices = [0, 1, 4, 3, 1, 2, 5, 4]",
            f"point3f[] points = [({x - 0.5}, {y - 0.25}, {z}), ({x}, {y - 0.25}, {z}), ({x + 0.5}, {y - 0.25}, {z}), "
            f"({x - 0.5}, {y + 0.25}, {z}), ({x}, {y + 0.25}, {z}), ({x + 0.5}, {y + 0.25}, {z})]",
            f"rel material:binding = <{USER}/Red>"]
    subset = ('def GeomSubset "right" (prepend apiSchemas = ["MaterialBindingAPI"]) {\nuniform token elementType = '
              f'"face"\nuniform token familyName = "materialBind"\nint[] indices = [1]\nrel material:binding = <{USER}/Blue>\n}}\n')
    after = show(base, "subset", _preview("Red", "(0.8, 0.02, 0.02)"), _preview("Blue", "(0.02, 0.02, 0.8)"),
                 prim("Mesh", "m", None, *quad, meta='prepend apiSchemas = ["MaterialBindingAPI"]', children=subset))
    for dx, channel in ((-0.25, 0), (0.25, 2)):
        uv, _ = project(base["k"], base["w2c"], [world(base, (x + dx, y, z))])
        u, v = np.round(uv[0]).astype(int)
        patch = after.rgb[v - 1:v + 2, u - 1:u + 2].reshape(-1, 3).astype(float).mean(axis=0)
        assert patch[channel] > 2 * max(np.delete(patch, channel)) and patch[channel] > 15, (dx, patch)
