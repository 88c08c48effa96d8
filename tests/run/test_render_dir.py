"""What a new user trips over when rendering a directory: `render DIR` on the demo's own tree
renders exactly its scene layers, one rule for "done" whatever rendered the scene, progress lines
where stderr is not a terminal, and a render record that moves with its tree."""

from __future__ import annotations

import io
import json
import re
import shutil
import subprocess
import sys
from contextlib import redirect_stderr
from pathlib import Path

import pytest

from allo_usd.core.errors import AlloError
from allo_usd.run.dispatch import find_layers
from allo_usd.run.render_index import MANIFEST, is_done, is_verified, load_manifest

pytestmark = pytest.mark.render

CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()", "render"]


def author_demo_tree(out: Path, resolution=(64, 36), samples: int = 1) -> list[Path]:
    """OUT/layers as `allo-usd demo` authors it (scene layers over sky/, poses/, stages/, schema/,
    versions.json), at a tiny size, without rendering."""
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.core.provenance import record_tree_versions
    from allo_usd.core.timefmt import format_utc
    from allo_usd.run.demo import DEMO_SCENES, DEMO_TRACK_SUN, demo_spec, write_demo_layer
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.usd.compose import copy_base_stage, copy_schema
    from allo_usd.usd.stage_geometry import scene_inputs

    tree = out / "layers"
    tree.mkdir(parents=True)
    stage = copy_base_stage(BASE_STAGE, tree)
    copy_schema(tree)
    record_tree_versions(tree)
    orbit = Orbit()
    inputs = scene_inputs(stage, compute_sky(default_epochs(), orbit), format_utc(orbit.perilune_epoch),
                          track_sun=DEMO_TRACK_SUN)
    return [write_demo_layer(demo_spec(inputs, i, resolution, samples), tree, stage) for i in range(len(DEMO_SCENES))]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo's tree; its first scene rendered by render_layer (a script), then the whole tree by
    allo_usd.render into the same folder: (root, scene layers, render folder, summary)."""
    import allo_usd
    from allo_usd.run.job import render_layer

    root = tmp_path_factory.mktemp("first_contact")
    layers = sorted(author_demo_tree(root))
    out = root / "renders"
    render_layer(layers[0], out)
    summary = allo_usd.render(root / "layers", out, workers=2, progress=False)
    return root, layers, out, summary


# ---------------------------------------------------------------- 1: which layers a directory renders

def test_the_demo_tree_renders_exactly_its_scene_layers(demo, tmp_path):
    """`render out/demo/layers` exited 1: the scan took layers/schema/generatedSchema.usda (whose
    AlloSceneAPI declares `string allo:sceneId`) for a scene. A scene layer is one whose own layer
    metadata holds customLayerData.allo.sceneId; the tree's support folders are not even searched."""
    from allo_usd.run.dispatch import _is_scene_layer

    root, layers, out, summary = demo
    tree = root / "layers"
    assert find_layers(tree) == layers and len(layers) == 4
    assert not summary.failed and sorted(summary.rendered + summary.skipped) == sorted(p.stem for p in layers)
    # the content rule alone: every support file of the tree says "not a scene" by itself
    support = [tree / "schema" / "generatedSchema.usda", tree / "stages" / "base.usda",
               *sorted((tree / "sky").glob("*.usda")), *sorted((tree / "poses").rglob("*.usda"))]
    assert len(support) == 10
    assert [p for p in support if _is_scene_layer(p) is not False] == []
    loose = tmp_path / "loose"           # the same files outside any tree: found by content, not place
    loose.mkdir()
    for p in support:
        shutil.copy(p, loose / p.name)
    with pytest.raises(AlloError, match="no scene layers under"):
        find_layers(loose)
    shutil.copy(layers[1], loose / layers[1].name)
    assert find_layers(loose) == [loose / layers[1].name]


def test_only_the_layer_metadata_names_a_scene(tmp_path):
    """`sceneId` in a comment, a string or a prim's property is not a scene; customLayerData after a
    doc string holding parentheses and quotes is."""
    from allo_usd.run.dispatch import _is_scene_layer

    cases = {
        "prop.usda": ('#usda 1.0\n(\n    doc = "x"\n)\n\nover "World"\n{\n    string allo:sceneId = "a"\n}\n', False),
        "comment.usda": ('#usda 1.0\n# sceneId = "a"\n(\n    doc = "sceneId = (\\")"\n)\n', False),
        "none.usda": ('#usda 1.0\n\ndef Xform "World"\n{\n    string sceneId = "a"\n}\n', False),
        "scene.usda": ('#usda 1.0\n(\n    doc = """a (tricky) \\"doc\\" ) """\n    customLayerData = {\n'
                       '        dictionary allo = {\n            string sceneId = "s"\n        }\n    }\n'
                       '    subLayers = [@./a(b).usda@]\n)\n', True),
        "other_dict.usda": ('#usda 1.0\n(\n    customLayerData = {\n        dictionary mine = {\n'
                            '            string sceneId = "s"\n        }\n    }\n)\n', False),
        "not_usd.usda": ("hello", True),   # kept: the reader reports it instead of the scan hiding it
        "broken.usda": ('#usda 1.0\n(\n    customLayerData = { dictionary allo = { string sceneId = } }\n)\n', True),
    }
    for name, (text, expected) in cases.items():
        (tmp_path / name).write_text(text)
        assert _is_scene_layer(tmp_path / name) is expected, name


def test_the_cli_renders_the_demo_tree_and_ends_with_a_progress_line_on_a_pipe(demo):
    """`allo-usd render` of the demo's tree (everything already done here): exit 0, and on a pipe
    the run's last progress line reaches stderr."""
    root, layers, out, _ = demo
    r = subprocess.run(CLI + [str(root / "layers"), "--out", str(out), "--workers", "1"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 rendered, 4 skipped (already done), 0 failed" in r.stdout
    assert "render: 4/4 scenes done (0 rendered, 4 already done, 0 failed)" in r.stderr, r.stderr


# ---------------------------------------------------------------- 3: one rule for "done"

def test_a_scene_render_layer_finished_is_done_for_render_and_back(demo):
    """render() rendered again what render_layer() had just finished into the same folder; now it
    skips it and indexes it from its JSON, and render_layer skips what render() rendered."""
    from allo_usd.run.job import render_layer

    root, layers, out, summary = demo
    assert summary.skipped == [layers[0].stem], summary
    assert sorted(summary.rendered) == sorted(p.stem for p in layers[1:])
    manifest = load_manifest(out)
    assert sorted(manifest) == sorted(p.stem for p in layers)
    assert manifest[layers[0].stem]["indexed_from"] == "json"  # the index caught up with the record
    for layer in layers:
        assert is_verified(manifest[layer.stem], layer, out)
        assert is_done(layer, out) and is_done(layer, out, manifest)
    png = out / f"{layers[1].stem}.png"
    before = png.stat().st_mtime_ns
    meta = render_layer(layers[1], out)  # rendered by render(): done for render_layer too
    assert png.stat().st_mtime_ns == before and meta["identity"] == manifest[layers[1].stem]["identity"]


def test_done_still_means_outputs_and_inputs_unchanged(demo, tmp_path):
    """The JSON vouches for its outputs by checksum: a changed output or input is not done for any
    entry point; a JSON without output checksums (an older record) is not enough for the dispatcher."""
    from allo_usd.output.identity import done_record

    root, layers, _, _ = demo
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    tree, out = copy / "layers", copy / "renders"
    scene = tree / layers[0].name
    (out / MANIFEST).unlink()                    # the JSON alone
    assert is_done(scene, out) and is_done(scene, out, {})
    png = out / f"{scene.stem}.png"
    good = png.read_bytes()
    png.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))   # same size, one bit off
    assert not is_done(scene, out) and not is_done(scene, out, {})
    png.write_bytes(good)
    meta_path = out / f"{scene.stem}.json"
    meta = json.loads(meta_path.read_text())
    old = {k: v for k, v in meta.items() if k != "outputs_sha256"}
    meta_path.write_text(json.dumps(old))
    assert done_record(scene, out) is not None           # render_layer: as before, on presence
    assert done_record(scene, out, strict=True) is None and not is_done(scene, out, {})
    meta_path.write_text(json.dumps(meta))
    sky = sorted((tree / "sky").glob("*.usda"))
    for s in sky:                                         # an input changed: not done
        s.write_text(s.read_text() + "\n")
    assert not is_done(scene, out) and not is_done(scene, out, {})


def test_render_layer_keeps_a_dispatch_folders_index_true(demo, tmp_path):
    """A forced render_layer into a dispatcher's folder appends the scene's row, so the manifest
    never names outputs a later render replaced."""
    from allo_usd.run.job import render_layer

    root, layers, _, _ = demo
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    scene, out = copy / "layers" / layers[2].name, copy / "renders"
    n = len((out / MANIFEST).read_text().splitlines())
    render_layer(scene, out, force=True)
    rows = (out / MANIFEST).read_text().splitlines()
    assert len(rows) == n + 1 and json.loads(rows[-1])["scene"] == scene.stem
    assert is_verified(load_manifest(out)[scene.stem], scene, out)


# ---------------------------------------------------------------- 8: progress without a terminal

def _run_lines(out: Path, progress, interval: float, tty: bool = False, n: int = 3, last_line: bool = True) -> str:
    """What _Run writes to a stderr that is (not) a terminal while `n` scenes fail one by one."""
    from allo_usd.run.dispatch import Summary, _Run, _Task

    class Err(io.StringIO):
        def isatty(self):
            return tty

    err = Err()
    with redirect_stderr(err):
        run = _Run(out, n, 0, progress, Summary(), interval)
        for i in range(n):
            run.fail(_Task(Path(f"s{i}.usda"), attempts=1), "layer", "broken")
        run.close(last_line=last_line)
    return err.getvalue()


def _lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if re.match(r"render: \d+/\d+ scenes done", ln)]


def test_progress_lines_where_stderr_is_not_a_terminal(tmp_path):
    """On a pipe, nohup or a CI log: a line (done, failed, rate, ETA) at most every `interval`
    seconds, and a final one; a terminal keeps its tqdm bar; progress=False prints nothing."""
    every = _lines(_run_lines(tmp_path, None, 0.0))
    assert len(every) == 4 and every[0].startswith("render: 1/3 scenes done (0 rendered, 0 already done, 1 failed)")
    assert "scenes/h, ETA " in every[0] and every[-1].startswith("render: 3/3 scenes done") and "ETA" not in every[-1]
    limited = _lines(_run_lines(tmp_path, None, 3600.0))
    assert len(limited) == 1 and limited[0].startswith("render: 3/3 scenes done")   # the final line only
    assert not _lines(_run_lines(tmp_path, False, 0.0))                            # asked for none
    assert not _lines(_run_lines(tmp_path, None, 3600.0, last_line=False))  # a run that stops on an error: its one line
    on_tty = _run_lines(tmp_path, None, 0.0, tty=True)       # a terminal keeps its tqdm bar, no plain lines
    assert not _lines(on_tty) and "3/3" in on_tty


def test_dispatch_takes_the_progress_interval(demo):
    """The interval is a parameter of dispatch (default 30 s); with nothing left to render the run
    still ends with its line."""
    import inspect

    from allo_usd.run.dispatch import PROGRESS_INTERVAL_S, dispatch

    assert inspect.signature(dispatch).parameters["progress_interval"].default == PROGRESS_INTERVAL_S == 30.0
    root, layers, out, _ = demo
    err = io.StringIO()
    with redirect_stderr(err):
        summary = dispatch(root / "layers", out, workers=1, progress=None, progress_interval=0.0)
    assert len(summary.skipped) == 4
    assert err.getvalue().splitlines()[-1].startswith("render: 4/4 scenes done (0 rendered, 4 already done, 0 failed)")


# ---------------------------------------------------------------- 10: the record moves with its tree

def test_the_render_json_names_its_layer_relative_to_the_render_folder(demo, tmp_path):
    root, layers, out, _ = demo
    for layer in layers:
        meta = json.loads((out / f"{layer.stem}.json").read_text())
        assert meta["layer_relative"] == f"../layers/{layer.name}"
        assert Path(meta["layer"]) == layer.resolve()     # where it was rendered from, as before
        assert load_manifest(out)[layer.stem]["layer_relative"] == meta["layer_relative"]
    moved = tmp_path / "elsewhere" / "demo"     # layers and renders moved together: still right, still done
    shutil.copytree(root, moved)
    for layer in layers:
        meta = json.loads((moved / "renders" / f"{layer.stem}.json").read_text())
        here = moved / "layers" / layer.name
        assert (moved / "renders" / meta["layer_relative"]).resolve() == here.resolve()
        assert is_done(here, moved / "renders", load_manifest(moved / "renders")) and is_done(here, moved / "renders")
