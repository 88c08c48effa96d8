"""Labels of a user's layer come from the composed stage, through every record: the render JSON,
`inspect`, the dataset's manifest, COCO and BOP (docs/usd/what_renders.md, "Labels").

Over the demo's drill scene: a variant selection (yellow -> red) says red everywhere; a second anomaly
asset (the wrench, referenced beside the drill) is an object of its own with its own instance id, COCO
annotation and BOP entry; relabelling the drill (allo:anomaly:asset = "wrench") is refused in one line;
a user's mesh labelled `anomaly` through semantics:labels:class is an anomaly object named by its prim.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from allo_usd.core.errors import LayerError
from tests.support.user_layers import DEMO_ANOMALY, demo_layers, override, render

pytestmark = pytest.mark.render

RES = (192, 108)   # the wrench, 0.4 m beside the drill, covers a few dozen pixels at this size


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return demo_layers(tmp_path_factory.mktemp("labels")) / f"{DEMO_ANOMALY}.usda"


def wrench_body(scene: Path) -> str:
    """The wrench referenced at /World/Wrench, 0.4 m to the drill's side in the camera frame, twice its size."""
    from allo_usd.usd.read import read_scene

    d = read_scene(scene)
    drill = np.array(d.meta["anomaly_model"]["local_to_world"])[:3, 3]
    side = d.camera.matrix[:3, 0] / np.linalg.norm(d.camera.matrix[:3, 0])
    x, y, z = drill - 0.4 * side
    return f'''over "World"
{{
    def Xform "Wrench" (
        prepend references = @../stages/anomalies/wrench.usda@
    )
    {{
        double3 xformOp:translate = ({x!r}, {y!r}, {z!r})
        float3 xformOp:scale = (2, 2, 2)
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:scale"]
    }}
}}
'''


RED = '''over "World"
{
    over "Anomaly" (
        variants = {
            string variant = "red"
        }
    )
    {
    }
}
'''

RELABEL = '''over "World"
{
    over "Anomaly"
    {
        string allo:anomaly:asset = "wrench"
    }
}
'''


def _layer(scene: Path, name: str, body: str) -> Path:
    return override(scene, scene.parent / "user" / f"{name}.usda", body, resolution=RES,
                    metadata=f'    customLayerData = {{ dictionary allo = {{ string sceneId = "{name}" }} }}\n')


@pytest.fixture(scope="module")
def dataset(scene, tmp_path_factory):
    """The red-drill and drill-and-wrench renders (with the instance pass), and the dataset assembled from them."""
    from allo_usd.output.dataset import assemble

    renders = tmp_path_factory.mktemp("label_renders")
    done = {name: render(_layer(scene, name, body), renders, passes=("rgb", "mask", "instance"))
            for name, body in (("red", RED), ("wrench", wrench_body(scene)))}
    out = renders.parent / "label_dataset"
    manifest = assemble([renders], out)
    return done, out, manifest


def _coco(out: Path) -> dict:
    return json.loads((out / "annotations" / "instances_test.json").read_text())


def test_variant_selection_says_red_everywhere(scene, dataset):
    from allo_usd.output.dataset import read_manifest
    from allo_usd.usd.inspect import describe

    done, out, manifest = dataset
    rec = done["red"].record
    assert rec["scene"]["anomaly"]["assetVariant"] == "red"
    assert rec["annotations"]["anomaly"]["model"]["model_id"] == "power_drill/red"
    assert describe(scene.parent / "user" / "red.usda")["anomaly"]["variant"] == "red"
    row = next(r for r in read_manifest(manifest) if r["name"].startswith("red"))
    assert (row["anomaly_asset"], row["anomaly_variant"]) == ("power_drill", "red")
    coco = _coco(out)
    image = next(i for i in coco["images"] if i["scene"] == row["name"])
    assert [a["variant"] for a in coco["annotations"] if a["image_id"] == image["id"]] == ["red"]
    models = json.loads((out / "bop" / row["category"] / "models.json").read_text())
    assert "power_drill/red" in {m["model_id"] for m in models.values()}
    red = np.asarray(done["red"].rgb, dtype=float)[done["red"].mask == 2].mean(axis=0)
    assert red[0] > 1.5 * red[1], red   # and the drill the image shows is red


def test_second_asset_is_its_own_object(scene, dataset):
    from allo_usd.output.dataset import read_manifest

    done, out, manifest = dataset
    r = done["wrench"]
    objects = {a["path"]: a for a in r.record["annotations"]["anomalies"]}
    assert list(objects) == ["/World/Anomaly", "/World/Wrench"]
    ids = np.asarray(Image.open(r.file("instance")))
    for path, a in objects.items():
        assert r.record["instances"][str(a["instance_id"])] == path
        rows, cols = np.nonzero(ids == a["instance_id"])
        assert a["pixels"] == rows.size > 0, path
        assert a["bbox_xyxy_px"] == [cols.min(), rows.min(), cols.max(), rows.max()], path
    assert objects["/World/Wrench"]["model"]["model_id"] == "wrench/chrome"
    assert r.record["annotations"]["anomaly"] == objects["/World/Anomaly"]   # the planned anomaly, as before
    drill, wrench = (objects[p]["bbox_xyxy_px"] for p in objects)
    assert drill[2] < wrench[0] or wrench[2] < drill[0], (drill, wrench)  # side by side, not merged

    row = next(x for x in read_manifest(manifest) if x["name"].startswith("wrench"))
    coco = _coco(out)
    cats = {c["id"]: c["name"] for c in coco["categories"]}
    image = next(i for i in coco["images"] if i["scene"] == row["name"])
    anns = {cats[a["category_id"]]: a for a in coco["annotations"] if a["image_id"] == image["id"]}
    assert set(anns) == {"power_drill", "wrench"}
    for name, path in (("power_drill", "/World/Anomaly"), ("wrench", "/World/Wrench")):
        x0, y0, x1, y1 = objects[path]["bbox_xyxy_px"]
        assert anns[name]["bbox"] == [x0, y0, x1 - x0 + 1, y1 - y0 + 1]
        assert anns[name]["area"] == objects[path]["pixels"]
    folder = out / "bop" / row["category"] / "test" / f"{int(row['index']) // 1000:06d}"
    gt = json.loads((folder / "scene_gt.json").read_text())[str(row["index"])]
    info = json.loads((folder / "scene_gt_info.json").read_text())[str(row["index"])]
    models = json.loads((out / "bop" / row["category"] / "models.json").read_text())
    assert [models[str(g["obj_id"])]["model_id"] for g in gt] == ["power_drill/yellow", "wrench/chrome"]
    masks = [np.asarray(Image.open(folder / "mask_visib" / f"{int(row['index']):06d}_{k:06d}.png")) > 0
             for k in range(2)]
    for k, path in enumerate(objects):
        assert np.array_equal(masks[k], ids == objects[path]["instance_id"]), path
        assert info[k]["px_count_visib"] == objects[path]["pixels"]
    assert not (masks[0] & masks[1]).any()


def test_relabelling_is_refused_in_one_line(scene, tmp_path):
    with pytest.raises(LayerError) as err:
        render(_layer(scene, "relabel", RELABEL), tmp_path)
    assert "\n" not in str(err.value) and "'wrench'" in str(err.value) and "power_drill.usda" in str(err.value)


PATCH = '''over "World"
{{
    def Mesh "Patch" (
        prepend apiSchemas = ["SemanticsLabelsAPI:class"]
    )
    {{
        int[] faceVertexCounts = [4, 4]
        int[] faceVertexIndices = [0, 1, 2, 3, 3, 2, 1, 0]
        point3f[] points = [{points}]
        token[] semantics:labels:class = ["anomaly"]
    }}
}}
'''


def test_user_mesh_labelled_anomaly_is_its_own_object(scene, tmp_path):
    """A square (both faces) 0.4 m beside the drill, facing the camera, labelled `anomaly` on itself:
    its own annotation, its asset its prim's name (it references no file)."""
    from allo_usd.usd.read import read_scene

    d = read_scene(scene)
    m = d.camera.matrix
    drill = np.array(d.meta["anomaly_model"]["local_to_world"])[:3, 3] + 0.4 * m[:3, 0] / np.linalg.norm(m[:3, 0])
    u, v = 0.1 * m[:3, 0] / np.linalg.norm(m[:3, 0]), 0.1 * m[:3, 1] / np.linalg.norm(m[:3, 1])
    corners = [drill - u - v, drill + u - v, drill + u + v, drill - u + v]
    points = ", ".join("({}, {}, {})".format(*map(float, c)) for c in corners)
    r = render(_layer(scene, "patch", PATCH.format(points=points)), tmp_path)
    objects = {a["path"]: a for a in r.record["annotations"]["anomalies"]}
    assert list(objects) == ["/World/Anomaly", "/World/Patch"]
    patch = objects["/World/Patch"]
    assert patch["model"]["asset"] == "Patch" and patch["model"]["variant"] is None and patch["pixels"] > 10
    x0, y0, x1, y1 = patch["bbox_xyxy_px"]
    assert (r.mask[y0:y1 + 1, x0:x1 + 1] == 2).mean() > 0.5    # the mask says anomaly there


IMPORT_PROBE = r"""
import bpy, json, sys
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=sys.argv[1])
wrench = bpy.data.objects.get("Wrench")
meshes = [o.name for o in wrench.children_recursive if o.type == "MESH"] if wrench else []
print("PROBE " + json.dumps({"wrench": wrench is not None, "meshes": meshes}))
"""


@pytest.mark.process
def test_blenders_importer_shows_the_wrench(scene):
    """Blender's own importer brings the referenced wrench in as its own object tree, as the render does."""
    layer = _layer(scene, "wrench_import", wrench_body(scene))
    r = subprocess.run([sys.executable, "-c", IMPORT_PROBE, str(layer)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.split("PROBE ", 1)[1])
    assert got["wrench"] and got["meshes"], got
