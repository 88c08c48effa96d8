"""The labels come from the composed stage (allo_usd.usd.read_labels): an anomaly object's asset is the
file it references, its variant the selection as composed; a label that contradicts the composition
from at least as strong a layer is refused in one line; every anomaly-labelled object is found."""

from __future__ import annotations

import pytest

from allo_usd.core.errors import LayerError
from allo_usd.core.labels import ANOMALY, STATION
from allo_usd.usd.read import read_scene
from tests.support.user_layers import DEMO_ANOMALY, demo_layers, override

WRENCH = '''over "World" {
    def Xform "Wrench" (prepend references = @../stages/anomalies/wrench.usda@)
    {
        double3 xformOp:translate = (2.86, -19.42, -2.36)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
}'''


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return demo_layers(tmp_path_factory.mktemp("labels")) / f"{DEMO_ANOMALY}.usda"


def anomaly_over(metadata: str = "", body: str = "") -> str:
    """An `over` of /World/Anomaly with prim metadata and a body (usda)."""
    return f'over "World"\n{{\n    over "Anomaly" ({metadata})\n    {{\n        {body}\n    }}\n}}\n'


def _read(scene, name, body):
    return read_scene(override(scene, scene.parent / "user" / f"{name}.usda", body))


def test_authored_layer_labels_unchanged(scene):
    d = read_scene(scene)
    assert (d.meta["anomaly"]["asset"], d.meta["anomaly"]["assetVariant"]) == ("power_drill", "yellow")
    assert [(o["path"], o["asset"], o["variant"]) for o in d.meta["anomalies"]] == \
        [("/World/Anomaly", "power_drill", "yellow")]
    anomaly = [m for m in d.meshes if m.class_id == ANOMALY]
    assert anomaly and {m.object_path for m in anomaly} == {"/World/Anomaly"}
    assert all(m.object == "" for m in d.meshes if m.class_id != ANOMALY)   # every other mesh is its own object


def test_variant_selection_supersedes_a_weaker_label(scene):
    d = _read(scene, "red", anomaly_over('variants = { string variant = "red" }'))
    assert d.meta["anomaly"]["assetVariant"] == "red"
    assert d.meta["anomalies"][0]["variant"] == "red"


def test_relabelling_is_refused_in_one_line(scene):
    with pytest.raises(LayerError) as err:
        _read(scene, "relabel", anomaly_over(body='string allo:anomaly:asset = "wrench"'))
    text = str(err.value)
    assert "\n" not in text
    assert "'wrench'" in text and "power_drill.usda" in text and "allo:anomaly:asset" in text


def test_variant_relabelling_is_refused(scene):
    with pytest.raises(LayerError, match=r"assetVariant 'red' but /World/Anomaly selects variant 'yellow'"):
        _read(scene, "relabel_variant", anomaly_over(body='string allo:anomaly:assetVariant = "red"'))


def test_second_asset_is_its_own_object(scene):
    d = _read(scene, "wrench", WRENCH)
    objects = {o["path"]: (o["asset"], o["variant"], o["reference"]) for o in d.meta["anomalies"]}
    assert objects == {"/World/Anomaly": ("power_drill", "yellow", "../stages/anomalies/power_drill.usda"),
                       "/World/Wrench": ("wrench", "chrome", "../stages/anomalies/wrench.usda")}
    wrench = [m for m in d.meshes if m.path.startswith("/World/Wrench/")]
    assert wrench and {(m.class_id, m.object_path) for m in wrench} == {(ANOMALY, "/World/Wrench")}


def test_two_assets_on_one_prim_are_refused(scene):
    body = anomaly_over("prepend references = @../stages/anomalies/wrench.usda@")
    with pytest.raises(LayerError, match=r"/World/Anomaly is one anomaly object but references .*wrench.usda"):
        _read(scene, "two", body)


CUBE = '''def Mesh "{name}" {apis}
    {{
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(2.9, -19.5, -2.4), (3.0, -19.5, -2.4), (3.0, -19.4, -2.4), (2.9, -19.4, -2.4)]
        {labels}
    }}'''


def test_user_mesh_labels(scene):
    labelled = CUBE.format(name="Patch", apis='(prepend apiSchemas = ["SemanticsLabelsAPI:class"])',
                           labels='token[] semantics:labels:class = ["anomaly"]')
    plain = CUBE.format(name="Plate", apis="", labels="")
    d = _read(scene, "meshes", f'over "World" {{\n    {labelled}\n    {plain}\n}}')
    by_path = {m.path: m for m in d.meshes}
    patch, plate = by_path["/World/Patch"], by_path["/World/Plate"]
    assert (patch.class_id, patch.object_path) == (ANOMALY, "/World/Patch")
    assert (plate.class_id, plate.object_path) == (STATION, "/World/Plate")   # unlabelled: station and bodies
    patch_entry = next(o for o in d.meta["anomalies"] if o["path"] == "/World/Patch")
    assert (patch_entry["asset"], patch_entry["variant"], patch_entry["reference"]) == ("Patch", None, None)
