"""The reader's geometry over a layer of one's own: each construct read into the right MeshDescs
(implicit shapes, instance proxies, point instancers, display colours, purposes), each refusal one
line. Layers over the demo's anomalous scene (tests/support/user_layers.py)."""

from __future__ import annotations

import numpy as np
import pytest

from allo_usd.core.errors import LayerError
from allo_usd.usd.read import open_stage, read_scene
from allo_usd.usd.read_geometry import DEFAULT_MATERIAL, RENDERED, included_purposes, read_geometry
from tests.support.user_geometry import USER, in_view, prim
from tests.support.user_layers import DEMO_ANOMALY, demo_layers, override

AT = "double3 xformOp:translate = (0, 0, -5)"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return demo_layers(tmp_path_factory.mktemp("demo")) / f"{DEMO_ANOMALY}.usda"


@pytest.fixture(scope="module")
def camera(scene):
    return read_scene(scene).camera.matrix


@pytest.fixture
def read(scene, camera, tmp_path):
    """read(*prims, extra=..., settings=...) -> {path: MeshDesc} of the user's geometry, and the materials."""
    made = []

    def go(*prims, extra="", settings=""):
        made.append(tmp_path / f"user{len(made)}.usda")   # a new file each time: USD keeps a layer it has read
        layer = override(scene, made[-1], in_view(camera, *prims, extra=extra))
        if settings:   # more render settings, in the override's own `over "Settings"`
            text = layer.read_text()
            layer.write_text(text.replace('over "Settings"\n    {\n', 'over "Settings"\n    {\n' + settings + "\n", 1))
        desc = read_scene(layer)
        return {m.path: m for m in desc.meshes if m.path.startswith(USER)}, desc.materials
    return go


def material(name: str, colour: str) -> str:
    """A UsdPreviewSurface material under /World/UserGeom."""
    return (f'def Material "{name}" {{\n token outputs:surface.connect = </World/UserGeom/{name}/S.outputs:surface>\n'
            f'def Shader "S" {{\n uniform token info:id = "UsdPreviewSurface"\n color3f inputs:diffuseColor = {colour}\n'
            'token outputs:surface\n}\n}\n')


def refused(read, *prims, **kw) -> str:
    with pytest.raises(LayerError) as e:
        read(*prims, **kw)
    text = str(e.value)
    assert "\n" not in text
    return text


SHAPES = [
    ("Cube", ["double size = 0.5"], 8),
    ("Sphere", ["double radius = 0.4"], 100 * 49 + 2),
    ("Cylinder", ["double radius = 0.3", "double height = 1", 'uniform token axis = "X"'], 4 * 72),
    ("Cylinder_1", ["double radiusBottom = 0.3", "double radiusTop = 0.1", "double height = 1"], 4 * 72),
    ("Cone", ["double radius = 0.3", "double height = 1", 'uniform token axis = "Y"'], 2 * 72 + 1),
    ("Capsule", ["double radius = 0.2", "double height = 0.5"], 100 * 50 + 2),
    ("Capsule_1", ["double radiusBottom = 0.2", "double radiusTop = 0.2", "double height = 0.5"], 100 * 50 + 2),
    ("Plane", ["double width = 1", "double length = 2", 'uniform token axis = "X"'], 4),
]


@pytest.fixture(scope="module")
def shapes(scene, camera, tmp_path_factory):
    """Every implicit shape at (0.5, 0, -5) in the camera's frame, read once."""
    layer = override(scene, tmp_path_factory.mktemp("shapes") / "shapes.usda",
                     in_view(camera, *(prim(kind, kind, (0.5, 0, -5), *props) for kind, props, _ in SHAPES)))
    desc = read_scene(layer)
    return {m.path: m for m in desc.meshes}, desc.materials


@pytest.mark.parametrize("kind,props,n_points", SHAPES)
def test_implicit_shape(shapes, camera, kind, props, n_points):
    meshes, materials = shapes
    m = meshes[f"{USER}/{kind}"]
    assert len(m.points) == n_points and m.smooth == (kind not in ("Cube", "Plane"))
    np.testing.assert_allclose(m.matrix[:3, 3], (camera @ [0.5, 0, -5, 1])[:3], atol=1e-9)
    assert m.material == DEFAULT_MATERIAL.path and materials[m.material] == DEFAULT_MATERIAL


def test_implicit_shape_extent_is_not_read(read):
    small = read(prim("Sphere", "s", None, "double radius = 2"))[0][f"{USER}/s"]
    lying = read(prim("Sphere", "s", None, "double radius = 2", "float3[] extent = [(-9, -9, -9), (9, 9, 9)]"))[0]
    np.testing.assert_array_equal(small.points, lying[f"{USER}/s"].points)
    assert np.abs(small.points).max() == pytest.approx(2.0)


def test_implicit_shape_bad_values(read):
    assert "s.radius = 0: a Sphere needs it > 0; fix the layer" in refused(read, prim("Sphere", "s", None, "double radius = 0"))
    assert "Capsule_1 with radiusBottom 0.2 != radiusTop 0.1" in refused(read, prim(
        "Capsule_1", "c", None, "double radiusBottom = 0.2", "double radiusTop = 0.1"))


def test_instanceable_reference(read, camera):
    proto = prim("Xform", "Proto", None, children=prim("Cube", "box", (0, 0, 0), "double size = 0.3"))
    insts = [prim("Xform", f"I{k}", (k - 1.0, 0, -5), meta="instanceable = true\nreferences = </World/Proto>")
             for k in range(3)]
    meshes, _ = read(*insts, extra=proto.replace('def Xform "Proto"', 'class Xform "Proto"'))
    assert sorted(meshes) == [f"{USER}/I{k}/box" for k in range(3)]          # the proxies' paths
    for k in range(3):
        np.testing.assert_allclose(meshes[f"{USER}/I{k}/box"].matrix[:3, 3], (camera @ [k - 1.0, 0, -5, 1])[:3],
                                   atol=1e-9)


def instancer(protos: str, indices="[0, 1, 0]", extra_props=()) -> str:
    props = [f"int[] protoIndices = {indices}", "point3f[] positions = [(-1, 0, 0), (0, 0, 0), (1, 0, 0)]",
             "rel prototypes = [</World/UserGeom/PI/Protos/Ball>, </World/UserGeom/PI/Protos/Box>]", *extra_props]
    return prim("PointInstancer", "PI", (0, 0, -5), *props, children=protos)


PROTOS = prim("Scope", "Protos", None, children=prim("Sphere", "Ball", (0, 0, 0), "double radius = 0.2")
              + prim("Xform", "Box", (0, 0.5, 0), children=prim("Cube", "geom", (0, 0, 0), "double size = 0.2")))


def test_point_instancer(read, camera):
    meshes, _ = read(instancer(PROTOS))
    assert sorted(meshes) == [f"{USER}/PI/Ball_0", f"{USER}/PI/Ball_2", f"{USER}/PI/Box_1/geom"]   # not the prototypes
    # the instance transform holds the prototype root's own (Box at y = 0.5)
    np.testing.assert_allclose(meshes[f"{USER}/PI/Box_1/geom"].matrix[:3, 3], (camera @ [0, 0.5, -5, 1])[:3], atol=1e-9)
    np.testing.assert_allclose(meshes[f"{USER}/PI/Ball_2"].matrix[:3, 3], (camera @ [1, 0, -5, 1])[:3], atol=1e-9)
    masked, _ = read(instancer(PROTOS, extra_props=["int64[] invisibleIds = [2]"]))
    assert sorted(masked) == [f"{USER}/PI/Ball_0", f"{USER}/PI/Box_1/geom"]


def test_point_instancer_refusals(read, scene, camera, tmp_path):
    assert "protoIndices holds 5" in refused(read, instancer(PROTOS, indices="[0, 5, 0]"))
    assert "3 positions for 2 protoIndices" in refused(read, instancer(PROTOS, indices="[0, 1]"))
    # the cap on the points a scene holds: the expansion is counted before it is made
    layer = override(scene, tmp_path / "pi.usda", in_view(camera, instancer(PROTOS)))
    stage = open_stage(layer)
    from pxr import Usd, UsdGeom

    with pytest.raises(LayerError, match=r"expands to 3 meshes of 9,812 points in all \(3 instances\)"):
        read_geometry(stage.GetPrimAtPath(f"{USER}/PI"), UsdGeom.XformCache(Usd.TimeCode.Default()), {}, set(),
                      frozenset({"default", "render"}), room=9_000)


def test_display_color_constant(read):
    meshes, materials = read(prim("Cube", "c", None, "color3f[] primvars:displayColor = [(0.1, 0.8, 0.1)]",
                                  "float[] primvars:displayOpacity = [0.5]"))
    mat = materials[meshes[f"{USER}/c"].material]
    assert mat.base_color == pytest.approx((0.1, 0.8, 0.1)) and mat.opacity == 0.5
    assert (mat.metallic, mat.roughness, mat.color_attribute) == (0.0, 0.5, None)
    assert meshes[f"{USER}/c"].colors is None


def test_display_color_inherited_and_bound_material_wins(read):
    inherited = prim("Xform", "X", None, "color3f[] primvars:displayColor = [(0.9, 0.1, 0.1)]",
                     children=prim("Sphere", "s", None))
    meshes, materials = read(inherited)
    assert materials[meshes[f"{USER}/X/s"].material].base_color == pytest.approx((0.9, 0.1, 0.1))
    bound = prim("Sphere", "b", None, "color3f[] primvars:displayColor = [(0.9, 0.1, 0.1)]",
                 "rel material:binding = </World/UserGeom/M>", meta='prepend apiSchemas = ["MaterialBindingAPI"]')
    meshes, materials = read(bound, material("M", "(0, 0, 1)"))
    assert meshes[f"{USER}/b"].material == f"{USER}/M" and materials[f"{USER}/M"].base_color == (0, 0, 1)


QUAD = ["int[] faceVertexCounts = [4, 3]", "int[] faceVertexIndices = [0, 1, 2, 3, 0, 2, 4]",
        "point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 2, 0)]"]


@pytest.mark.parametrize("interp,values,want", [
    ("vertex", "[(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1)]", [0, 1, 2, 3, 0, 2, 4]),
    ("uniform", "[(1, 0, 0), (0, 1, 0)]", [0, 0, 0, 0, 1, 1, 1]),
    ("faceVarying", "[(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1), (1, 0, 1), (1, 1, 1)]", list(range(7))),
])
def test_display_color_per_corner(read, interp, values, want):
    meshes, materials = read(prim("Mesh", "m", None, *QUAD,
                                  f'color3f[] primvars:displayColor = {values} (interpolation = "{interp}")'))
    m = meshes[f"{USER}/m"]
    table = np.array(eval(values), dtype=np.float32)
    np.testing.assert_array_equal(m.colors[:, :3], table[want])
    np.testing.assert_array_equal(m.colors[:, 3], 1.0)
    assert materials[m.material].color_attribute == "displayColor"


def test_display_color_refusals(read):
    assert "needs 5" in refused(read, prim("Mesh", "m", None, *QUAD, 'color3f[] primvars:displayColor = '
                                           '[(1, 0, 0), (0, 1, 0)] (interpolation = "vertex")'))
    assert "implicit shape takes one display colour" in refused(read, prim(
        "Sphere", "s", None, 'color3f[] primvars:displayColor = [(1, 0, 0), (0, 1, 0)] (interpolation = "uniform")'))
    assert "outside 0..1" in refused(read, prim("Cube", "c", None, "float[] primvars:displayOpacity = [2]"))


def test_purpose(read, scene):
    meshes, _ = read(prim("Cube", "guide", None, 'uniform token purpose = "guide"'),
                     prim("Cube", "render", None, 'uniform token purpose = "render"'),
                     prim("Xform", "proxy", None, 'uniform token purpose = "proxy"', children=prim("Cube", "c", None)))
    assert sorted(meshes) == [f"{USER}/render"]
    settings = 'uniform token[] includedPurposes = ["default", "guide"]'
    meshes, _ = read(prim("Cube", "guide", None, 'uniform token purpose = "guide"'),
                     prim("Cube", "render", None, 'uniform token purpose = "render"'), settings=settings)
    assert sorted(meshes) == [f"{USER}/guide"]
    assert included_purposes(open_stage(scene).GetPrimAtPath("/Render/Settings")) == {"default", "render"}


def test_subdivision_surface_is_its_cage(read):
    meshes, _ = read(prim("Mesh", "m", None, *QUAD))       # subdivisionScheme's fallback: catmullClark
    assert len(meshes[f"{USER}/m"].points) == 5


@pytest.mark.parametrize("kind,props", [
    ("BasisCurves", ["int[] curveVertexCounts = [2]", "point3f[] points = [(0, 0, 0), (1, 0, 0)]"]),
    ("NurbsCurves", []), ("HermiteCurves", []), ("Points", ["point3f[] points = [(0, 0, 0)]"]),
    ("NurbsPatch", []), ("TetMesh", []), ("Volume", []),
])
def test_other_gprims_refused(read, kind, props):
    text = refused(read, prim(kind, "g", None, *props))
    assert text.startswith(f"{USER}/g is a {kind}: {RENDERED}; fix the layer")


def test_volume_field_refused(read):
    text = refused(read, prim("OpenVDBAsset", "f", None, 'asset filePath = @none.vdb@'))
    assert text.startswith(f"{USER}/f is a OpenVDBAsset: {RENDERED}")


def test_light_emitting_mesh_refused(read):
    text = refused(read, prim("Mesh", "m", None, *QUAD, meta='prepend apiSchemas = ["MeshLightAPI"]'))
    assert text.startswith(f"{USER}/m (Mesh) applies MeshLightAPI, LightAPI: geometry that emits light is not rendered")


def _subset(name: str, faces: str, material_name: str, element: str = "face") -> str:
    return (f'def GeomSubset "{name}" (prepend apiSchemas = ["MaterialBindingAPI"]) {{\nuniform token elementType = '
            f'"{element}"\nuniform token familyName = "materialBind"\nint[] indices = [{faces}]\n'
            f'rel material:binding = </World/UserGeom/{material_name}>\n}}\n')


def _bound_mesh(*subsets: str) -> str:
    return prim("Mesh", "m", None, *QUAD, "rel material:binding = </World/UserGeom/A>",
                meta='prepend apiSchemas = ["MaterialBindingAPI"]', children="".join(subsets))


MATERIALS = "".join(material(n, c) for n, c in (("A", "(1, 0, 0)"), ("B", "(0, 0, 1)")))


def test_a_subset_bound_to_its_own_material_is_its_faces_material(read):
    """UsdShade: a GeomSubset of the materialBind family binds its faces to its material; the rest of
    the mesh keeps the mesh's."""
    meshes, materials = read(_bound_mesh(_subset("half", "1", "B")), MATERIALS)
    m = meshes[f"{USER}/m"]
    assert m.material == f"{USER}/A" and [(k, f.tolist()) for k, f in m.subsets] == [(f"{USER}/B", [1])]
    assert materials[f"{USER}/B"].base_color == (0.0, 0.0, 1.0)


@pytest.mark.parametrize("subsets, words", [
    ((_subset("h", "2", "B"),), "GeomSubset /World/UserGeom/m/h.indices names face 2, but /World/UserGeom/m has 2 faces"),
    ((_subset("h", "0, 1", "B"), _subset("k", "1", "A2")), "shares faces with another materialBind subset"),
    ((_subset("h", "0", "B", element="point"),), "binds material /World/UserGeom/B to points"),
])
def test_subset_refusals(read, subsets, words):
    text = refused(read, _bound_mesh(*subsets), MATERIALS + material("A2", "(0, 1, 0)"))
    assert words in text


def _face_normal(points: np.ndarray, face: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)[face]
    n = np.cross(p[1] - p[0], p[2] - p[0])
    return n / np.linalg.norm(n)


def test_left_handed_mesh_faces_the_same_way(read):
    """A leftHanded face wound the other way is the same surface facing the same way (UsdGeom.Mesh
    orientation): the reader reverses its corners, with their st, so Blender's front is USD's."""
    quad = ["int[] faceVertexCounts = [4]", "point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]"]
    st = 'texCoord2f[] primvars:st = [(0, 0), (1, 0), (1, 1), (0, 1)] (\n interpolation = "faceVarying"\n)'
    st_left = 'texCoord2f[] primvars:st = [(0, 0), (0, 1), (1, 1), (1, 0)] (\n interpolation = "faceVarying"\n)'
    meshes, _ = read(prim("Mesh", "right", None, *quad, "int[] faceVertexIndices = [0, 1, 2, 3]", st),
                     prim("Mesh", "left", None, *quad, "int[] faceVertexIndices = [0, 3, 2, 1]", st_left,
                          'uniform token orientation = "leftHanded"'))
    right, left = meshes[f"{USER}/right"], meshes[f"{USER}/left"]
    assert np.allclose(_face_normal(left.points, left.face_indices), [0, 0, 1])
    assert np.allclose(_face_normal(right.points, right.face_indices), [0, 0, 1])
    by_vertex = lambda m: {int(i): tuple(map(float, uv)) for i, uv in zip(m.face_indices, m.uv)}  # noqa: E731
    assert by_vertex(left) == by_vertex(right)   # each corner keeps its own st


def test_mesh_normals_make_it_smooth_and_are_not_read(read):
    """Authored vertex normals make a mesh smooth-shaded; their values are not read (Blender computes
    the normals from the faces): two meshes whose normals differ read the same but for their path."""
    quad = ["int[] faceVertexCounts = [4]", "int[] faceVertexIndices = [0, 1, 2, 3]",
            "point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]"]
    normals = 'normal3f[] normals = [{n}, {n}, {n}, {n}] (\n interpolation = "vertex"\n)'
    meshes, _ = read(prim("Mesh", "flat", None, *quad),
                     prim("Mesh", "up", None, *quad, normals.format(n="(0, 0, 1)")),
                     prim("Mesh", "tilted", None, *quad, normals.format(n="(0, 0.6, 0.8)")))
    flat, up, tilted = (meshes[f"{USER}/{n}"] for n in ("flat", "up", "tilted"))
    assert not flat.smooth and up.smooth and tilted.smooth
    assert np.array_equal(up.face_indices, tilted.face_indices) and np.array_equal(up.points, tilted.points)


def test_an_anomaly_labelled_prototype_is_refused(read):
    """An anomaly is a prim with its own pose and record: a point instancer cannot multiply one."""
    proto = prim("Cube", "c", None, "double size = 0.2",
                 meta='prepend apiSchemas = ["SemanticsLabelsAPI:class"]', children="")
    proto = proto.replace("double size = 0.2", 'double size = 0.2\ntoken[] semantics:labels:class = ["anomaly"]')
    text = refused(read, prim("PointInstancer", "pi", None, f"rel prototypes = <{USER}/pi/protos/c>",
                              "int[] protoIndices = [0, 0]", "point3f[] positions = [(0, 0, -5), (1, 0, -5)]",
                              children=prim("Xform", "protos", None, children=proto)))
    assert text.startswith(f"point instancer {USER}/pi: prototype {USER}/pi/protos/c is labelled anomaly")
