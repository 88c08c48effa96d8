"""Your own hazards, attacked: a USD hazard works from the command line; every file
its composition reads is checked before USD opens it (allo_usd.usd.dependencies.walk_hazard: inside
the hazard's own folder, regular files, no variable expressions) and is part of source.json's record,
so an edit to a sublayer is caught on resume; and every triangle a conversion drops is counted in the
records (the layer's provenance, source.json, `asset import`'s line)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.support.helpers import ROOT, one_line_error, sandboxed_cli

CANARY = "CANARY_4f1d_outside"   # text of a file outside the hazard's folder: must never be printed or copied

BOX_CM = """#usda 1.0
(
    metersPerUnit = 0.01
    upAxis = "Y"
)

def Xform "Part"
{
    def Mesh "Body"
    {
        int[] faceVertexCounts = [4, 4, 4, 4, 4, 4]
        int[] faceVertexIndices = [0, 3, 2, 1, 4, 5, 6, 7, 0, 1, 5, 4, 1, 2, 6, 5, 2, 3, 7, 6, 3, 0, 4, 7]
        point3f[] points = [(0, 0, 0), (50, 0, 0), (50, 20, 0), (0, 20, 0),
                            (0, 0, 10), (50, 0, 10), (50, 20, 10), (0, 20, 10)]
        color3f[] primvars:displayColor = [(0.9, 0.4, 0.05)]
    }
}
"""


def usd_hazard(folder, body: str = BOX_CM, sub: str = "geo/body.usda"):
    """A two-file USD hazard: FOLDER/part.usda (the units and axis) sublayers FOLDER/SUB (the mesh).
    Returns the main file."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / sub).parent.mkdir(parents=True, exist_ok=True)
    (folder / sub).write_text(body)
    main = folder / "part.usda"
    main.write_text(f'#usda 1.0\n(\n    metersPerUnit = 0.01\n    upAxis = "Y"\n    subLayers = [@./{sub}@]\n)\n')
    return main


def outside_layer(folder, parses: bool = True):
    """A layer outside the hazard's folder holding the canary: as a prim name (copied into the tree if
    read) or, `parses=False`, as text USD's parser would quote in its error."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "secret.usda"
    if parses:
        path.write_text(BOX_CM.replace('"Part"', f'"{CANARY}"'))
    else:
        path.write_text(f"#usda 1.0\ndef Xform {CANARY} {CANARY} ((( \n")
    return path


def write_plan(folder, hazard_file: str, extra: str = ""):
    """A one-scene plan (the project's base stage) whose only anomaly is the hazard `hazard_file`."""
    from allo_usd.core.paths import BASE_STAGE

    plan = folder / "plan.toml"
    plan.write_text(f'name = "usd-hazard"\nbase_stage = "{BASE_STAGE}"\n\n[dates]\ndays = 1\n\n[poses]\ntrain = []\n'
                    f'test = [41]\n\n[[anomalies.assets]]\nid = "part"\nfile = "{hazard_file}"\n{extra}\n[counts]\n'
                    'normal_test = 0\nanomalous_test = 1\n\n[quality]\npreset = "draft"\nresolution = [64, 36]\n'
                    "samples = 4\n")
    return plan


def cli_within(seconds: float, *args, cwd=None) -> subprocess.CompletedProcess:
    """sandboxed_cli with a time limit: a hang (a FIFO read) fails the test instead of stalling it."""
    from allo_usd.usd.safety import ENV_ROOTS

    env = {**{k: v for k, v in os.environ.items() if k != ENV_ROOTS}, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", "from allo_usd.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=seconds)


def tree_text(tree) -> str:
    """Every byte under `tree`, as text (for looking for the canary)."""
    return "".join(p.read_bytes().decode("latin-1") for p in tree.rglob("*") if p.is_file()) if tree.exists() else ""


# ------------------------------------------------------------------------- USD hazards from the CLI


@pytest.mark.process
def test_author_converts_a_usd_hazard_from_the_command_line(tmp_path):
    """`allo-usd author` with a plan naming a two-file .usda hazard: converted, authored, and every file
    it composes recorded in source.json (no 'the allo-usd schema did not register')."""
    from allo_usd.core.files import sha256_file

    usd_hazard(tmp_path)
    write_plan(tmp_path, "part.usda")
    r = sandboxed_cli("author", "plan.toml", "--out", "tree", "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert len(list((tmp_path / "tree" / "scenes").rglob("*.usda"))) == 1
    record = json.loads((tmp_path / "tree" / "hazards" / "part" / "source.json").read_text())
    assert record["source"] == "part.usda" and record["sha256"] == sha256_file(tmp_path / "part.usda")
    assert record["composes"] == {os.path.join("geo", "body.usda"): sha256_file(tmp_path / "geo" / "body.usda")}
    assert record["converted"] == {"triangles": 12, "droppedTriangles": 0}
    from pxr import Sdf

    from allo_usd.usd.hazard import hazard_provenance

    prov = hazard_provenance(Sdf.Layer.FindOrOpen(str(tmp_path / "tree" / "hazards" / "part" / "part.usda")))
    assert dict(prov["composes"]) == record["composes"] and prov["droppedTriangles"] == 0


@pytest.mark.process
def test_asset_import_converts_a_usd_file_from_the_command_line(tmp_path):
    from allo_usd.usd.stage_geometry import read_triangles

    src = usd_hazard(tmp_path / "in")
    r = sandboxed_cli("asset", "import", src, "--out", tmp_path / "out", "--label", "anomaly")
    assert r.returncode == 0, r.stderr
    assert "unit cm, up axis y, 12 triangles" in r.stdout
    pts, tris = read_triangles(tmp_path / "out" / "part.usda", "/part")
    assert len(tris) == 12 and sorted(round(float(e), 6) for e in pts.max(axis=0) - pts.min(axis=0)) == [0.1, 0.2, 0.5]


# ------------------------------------------------------------------------- nothing outside is read


HEAD = '#usda 1.0\n(\n    metersPerUnit = 1\n    upAxis = "Z"\n'
OUTSIDE = {   # how the hazard names the outside layer SECRET (the hazard's folder is a sibling of SECRET's)
    "sublayer": lambda secret: f"{HEAD}    subLayers = [@../out/{secret.name}@]\n)\n",
    "reference": lambda secret: f'{HEAD})\ndef Xform "P" (\n    prepend references = @{secret}@</{CANARY}>\n)\n{{\n}}\n',
    "payload": lambda secret: f'{HEAD})\ndef Xform "P" (\n    prepend payload = @../out/{secret.name}@</{CANARY}>\n)\n'
                              "{\n}\n",
    "variable expression": lambda secret: f'{HEAD}    expressionVariables = {{\n        string D = "out"\n    }}\n'
                                          f'    subLayers = [@`"../${{D}}/{secret.name}"`@]\n)\n',
}


def refused_in_process(main, monkeypatch, capfd) -> str:
    """`asset import`'s reader on `main` (its own folder as the only root, as from the command line):
    the PlanError's text, after checking that nothing printed the canary."""
    from allo_usd.core.errors import PlanError
    from allo_usd.usd.hazard import import_model
    from allo_usd.usd.safety import ENV_ROOTS

    monkeypatch.delenv(ENV_ROOTS, raising=False)
    with pytest.raises(PlanError) as e:
        import_model(main, None, "auto", "auto", what="model")
    printed = capfd.readouterr()
    assert CANARY not in str(e.value) + printed.out + printed.err
    assert "; " in str(e.value)   # the fix
    return str(e.value)


@pytest.mark.parametrize("how", sorted(OUTSIDE))
def test_a_usd_file_naming_a_layer_outside_its_folder_is_refused(tmp_path, how, monkeypatch, capfd):
    secret = outside_layer(tmp_path / "out")
    (tmp_path / "h").mkdir()
    (tmp_path / "h" / "part.usda").write_text(OUTSIDE[how](secret))
    message = refused_in_process(tmp_path / "h" / "part.usda", monkeypatch, capfd)
    if how == "variable expression":
        assert "is a variable expression, which allo-usd does not follow" in message
    else:
        assert f"{secret} resolves outside the hazard's folder ({tmp_path / 'h'})" in message


@pytest.mark.parametrize("parses", [True, False], ids=["valid", "garbage"])
@pytest.mark.process
def test_author_refuses_a_hazard_sublayer_outside_and_never_reads_it(tmp_path, parses):
    """The outside file is never parsed (no USD warning quotes it) nor copied into OUT/hazards."""
    secret = outside_layer(tmp_path / "elsewhere", parses)
    work = tmp_path / "work"
    usd_hazard(work)
    main = work / "part.usda"
    main.write_text(main.read_text().replace("./geo/body.usda", "../elsewhere/secret.usda"))
    write_plan(work, "part.usda")
    r = sandboxed_cli("author", "plan.toml", "--out", "tree", "--no-progress", cwd=work)
    line = one_line_error(r, "anomaly 'part'", str(secret), "outside the hazard's folder", hidden=CANARY)
    assert "; " in line and "ALLO_ASSET_ROOTS" in line      # the fix
    assert CANARY not in tree_text(work / "tree") and not (work / "tree" / "hazards" / "part").exists()


def test_a_link_in_the_hazards_folder_to_an_outside_layer_is_refused(tmp_path, monkeypatch, capfd):
    secret = outside_layer(tmp_path / "out")
    main = usd_hazard(tmp_path / "h")
    (tmp_path / "h" / "geo" / "body.usda").unlink()
    (tmp_path / "h" / "geo" / "body.usda").symlink_to(secret)
    assert "geo/body.usda resolves outside the hazard's folder" in refused_in_process(main, monkeypatch, capfd)


def test_a_missing_sublayer_is_refused_and_a_linked_hazard_reaches_its_targets_folder(tmp_path, monkeypatch, capfd):
    """A sublayer that does not exist: the stage does not compose, refused (not a hazard missing its
    geometry). A hazard file that is a link to another folder is read (the target's folder is a root
    too; USD anchors the paths it names beside the link)."""
    from allo_usd.usd.hazard import import_model
    from allo_usd.usd.safety import ENV_ROOTS

    main = usd_hazard(tmp_path / "models")
    (tmp_path / "models" / "geo" / "body.usda").rename(tmp_path / "models" / "geo" / "moved.usda")
    assert "does not compose" in refused_in_process(main, monkeypatch, capfd)
    (tmp_path / "models" / "one.usda").write_text(BOX_CM)
    (tmp_path / "plan").mkdir()
    (tmp_path / "plan" / "part.usda").symlink_to(tmp_path / "models" / "one.usda")
    monkeypatch.delenv(ENV_ROOTS, raising=False)
    _, info = import_model(tmp_path / "plan" / "part.usda", "part", None, None)
    assert info["triangles"] == 12 and "composes" not in info


@pytest.mark.process
def test_asset_import_refuses_an_outside_sublayer_in_one_line(tmp_path):
    """The command line's view of the walk's refusal: exit 2, one line naming the path and the rule."""
    secret = outside_layer(tmp_path / "out", parses=False)
    (tmp_path / "h").mkdir()
    (tmp_path / "h" / "part.usda").write_text(OUTSIDE["sublayer"](secret))
    r = sandboxed_cli("asset", "import", tmp_path / "h" / "part.usda", "--out", tmp_path / "asset",
                      "--label", "anomaly")
    one_line_error(r, "model 'part'", str(secret), "outside the hazard's folder", hidden=CANARY)
    assert not (tmp_path / "asset").exists() or not any((tmp_path / "asset").iterdir())


# ------------------------------------------------------------------------- a FIFO sublayer


@pytest.mark.process
def test_a_fifo_sublayer_is_refused_by_stat_not_read(tmp_path):
    """`asset import` and `author` both refuse it by name at once (neither hangs on the read)."""
    main = usd_hazard(tmp_path, sub="geo/pipe.usda")
    (tmp_path / "geo" / "pipe.usda").unlink()
    os.mkfifo(tmp_path / "geo" / "pipe.usda")
    write_plan(tmp_path, "part.usda")
    for args in (("asset", "import", main, "--out", tmp_path / "asset", "--label", "anomaly"),
                 ("author", "plan.toml", "--out", "tree", "--no-progress")):
        try:
            r = cli_within(120, *args, cwd=tmp_path)
        except subprocess.TimeoutExpired:
            pytest.fail(f"`allo-usd {args[0]}` hung on a FIFO sublayer of a USD hazard")
        one_line_error(r, "pipe.usda", "is not a regular file", hidden=CANARY)


# ------------------------------------------------------------------------- the record covers every file


@pytest.mark.slow
def test_an_edited_sublayer_is_caught_on_resume(tmp_path, monkeypatch):
    """The hazard file is unchanged, its sublayer is not: resuming is refused (as for an edited hazard
    file), and --replace converts the new geometry."""
    from allo_usd.core.errors import PlanError
    from allo_usd.plan.io import load_plan
    from allo_usd.run.author import author_plan
    from allo_usd.usd.stage_geometry import read_triangles
    from allo_usd.usd.safety import ENV_ROOTS

    monkeypatch.delenv(ENV_ROOTS, raising=False)   # the hazard's own folder only, as from the command line
    monkeypatch.chdir(tmp_path)
    usd_hazard(tmp_path)
    plan = load_plan(write_plan(tmp_path, "part.usda"))
    tree = tmp_path / "tree"
    author_plan(plan, tree, progress=False)
    author_plan(plan, tree, progress=False)   # unchanged: resumes
    asset = tree / "hazards" / "part" / "part.usda"
    pts, _ = read_triangles(asset, "/part")
    assert round(float(pts[:, 0].max() - pts[:, 0].min()), 6) == 0.5
    body = tmp_path / "geo" / "body.usda"
    body.write_text(BOX_CM.replace("(50, ", "(70, "))   # the mesh is 20 cm longer; part.usda is the same
    with pytest.raises(PlanError, match="changed since its scenes were authored.*fix"):
        author_plan(plan, tree, progress=False)
    author_plan(plan, tree, progress=False, replace=True)
    pts, _ = read_triangles(asset, "/part")
    assert round(float(pts[:, 0].max() - pts[:, 0].min()), 6) == 0.7


# ------------------------------------------------------------------------- dropped triangles are recorded


SQUARE = "v 0 0 0\nv 0.5 0 0\nv 0 0.5 0\nv {x} {y} {z}\nf 1 2 3\nf 2 4 3\n"


@pytest.mark.parametrize("name, fourth", [("nan", ("0.5", "0.5", "nan")), ("inf", ("0.5", "inf", "0")),
                                          ("zero area", ("1", "-0.5", "0"))])   # 2, 4, 3 on one line
def test_every_dropped_triangle_is_counted(tmp_path, name, fourth):
    from allo_usd.usd.hazard import import_model

    (tmp_path / "two.obj").write_text(SQUARE.format(x=fourth[0], y=fourth[1], z=fourth[2]))
    asset, info = import_model(tmp_path / "two.obj", "two", "m", "z")
    assert (info["triangles"], info["droppedTriangles"]) == (1, 1)
    assert sum(p.face_counts.size for p in asset.parts) == 1


def test_a_gltf_index_outside_its_points_is_a_counted_drop(tmp_path):
    import base64

    import numpy as np

    from allo_usd.usd.hazard import import_model

    pts = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0.5, 0.5, 0.2]], dtype="<f4")
    idx = np.array([0, 1, 2, 1, 3, 7], dtype="<u2")   # the second triangle names point 7 of 4
    blob = pts.tobytes() + idx.tobytes()
    gltf = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
            "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                         + base64.b64encode(blob).decode()}],
            "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                            {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                           "min": [0, 0, 0], "max": [0.5, 0.5, 0.2]},
                          {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}]}
    (tmp_path / "two.gltf").write_text(json.dumps(gltf))
    _, info = import_model(tmp_path / "two.gltf", "two", "m", "z")
    assert (info["triangles"], info["droppedTriangles"]) == (1, 1)


def test_a_zero_area_usd_triangle_is_a_counted_drop(tmp_path):
    from allo_usd.usd.hazard import import_model

    body = BOX_CM.replace("[4, 4, 4, 4, 4, 4]", "[4, 4, 4, 4, 4, 4, 3]").replace(
        "3, 0, 4, 7]", "3, 0, 4, 7, 0, 1, 1]")   # a seventh face with a repeated vertex
    _, info = import_model(usd_hazard(tmp_path, body), "part", None, None)
    assert (info["triangles"], info["droppedTriangles"]) == (12, 1)


@pytest.mark.process
def test_the_records_show_a_dropped_triangle(tmp_path, monkeypatch):
    """A hazard OBJ with a NaN vertex, one of its two faces dropped: source.json, the layer's provenance
    and `asset import`'s line all say 1 dropped (droppedTriangles = 1, not 0)."""
    from pxr import Sdf

    from allo_usd.plan.io import load_plan
    from allo_usd.run.author import author_plan
    from allo_usd.usd.hazard import hazard_provenance

    (tmp_path / "two.obj").write_text(SQUARE.format(x="0.5", y="0.5", z="nan"))
    monkeypatch.chdir(tmp_path)
    plan = load_plan(write_plan(tmp_path, "two.obj", 'units = "m"\nup_axis = "z"\n'))
    author_plan(plan, tmp_path / "tree", progress=False)
    hazard = tmp_path / "tree" / "hazards" / "part"
    assert json.loads((hazard / "source.json").read_text())["converted"] == {"triangles": 1, "droppedTriangles": 1}
    prov = hazard_provenance(Sdf.Layer.FindOrOpen(str(hazard / "part.usda")))
    assert (prov["triangles"], prov["droppedTriangles"]) == (1, 1)
    r = sandboxed_cli("asset", "import", tmp_path / "two.obj", "--out", tmp_path / "asset", "--label", "anomaly",
                      "--units", "m", "--up-axis", "z")
    assert r.returncode == 0, r.stderr
    assert "1 triangles, 1 dropped" in r.stdout
