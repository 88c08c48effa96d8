"""The README's worked example (a plan with its own hazard, camera, pose file and tracking
arrays), run as the README writes it: the plan and pose file it shows are the example's files, its
`allo-usd` commands author, inspect and render the example from a copy of its folder."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "bring_your_own"
SECTION = "### Worked example: your camera, your poses, your hazard, tracking arrays\n"


def section() -> str:
    return (ROOT / "docs" / "guide" / "bring_your_own.md").read_text().split(SECTION, 1)[1].split("\n## ", 1)[0].split("\n### ", 1)[0]


def commands() -> list[list[str]]:
    """The `allo-usd ...` commands of the section's sh block, in order (comments dropped)."""
    block = re.findall(r"```sh\n(.*?)```", section(), re.S)
    assert len(block) == 1
    return [shlex.split(line.split("#")[0]) for line in block[0].splitlines() if line.startswith("allo-usd ")]


def cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    assert args[0] == "allo-usd"
    return subprocess.run([sys.executable, "-c", "from allo_usd.cli import main; main()", *args[1:]], cwd=cwd,
                          capture_output=True, text=True, timeout=900)


def test_the_readme_shows_the_examples_files():
    text = section()
    assert re.findall(r"```toml\n(.*?)```", text, re.S) == [(EXAMPLE / "plan.toml").read_text()]
    assert re.findall(r"```csv\n(.*?)```", text, re.S) == [(EXAMPLE / "poses.csv").read_text()]
    assert "cd examples/bring_your_own" in text


@pytest.fixture(scope="module")
def authored(tmp_path_factory):
    here = tmp_path_factory.mktemp("byo") / "bring_your_own"
    shutil.copytree(EXAMPLE, here)
    author = [c for c in commands() if c[1] == "author"]
    assert len(author) == 1
    r = cli(author[0], here)
    assert r.returncode == 0, r.stderr
    return here, here / author[0][author[0].index("--out") + 1]


def test_the_example_authors_every_kind_of_scene(authored):
    _, tree = authored
    layers = sorted((tree / "scenes").rglob("*.usda"))
    kinds = {p.parent.relative_to(tree / "scenes").as_posix(): 0 for p in layers}
    for p in layers:
        kinds[p.parent.relative_to(tree / "scenes").as_posix()] += 1
    assert kinds == {"train/normal": 4, "test/normal": 2, "test/anomaly": 10}
    assert (tree / "inputs" / "poses.csv").read_bytes() == (EXAMPLE / "poses.csv").read_bytes()
    assert json.loads((tree / "hazards" / "bracket" / "source.json").read_text())["source"] == "bracket.obj"
    assert all("_p5" in p.name for p in layers)   # only the file's poses (51, 52, 53)


def test_every_layer_passes_usd_validation(authored):
    from tests.support.validation import validation_errors

    _, tree = authored
    for layer in sorted((tree / "scenes").rglob("*.usda")):
        assert validation_errors(layer) == [], layer.name


def test_inspect_names_where_each_part_came_from(authored):
    here, _ = authored
    inspect = [c for c in commands() if c[1] == "inspect"]
    assert len(inspect) == 1
    r = cli(inspect[0], here)
    assert r.returncode == 0, r.stderr
    for words in ("pose file: node_nadir from poses.csv:6", "(plan camera)", "focal length 12 mm",
                  "from bracket.obj (your hazard", "unit mm, up axis y", "joints   AlphaS", "sigma 0.5 m, 0.1 rad"):
        assert words in r.stdout, words


@pytest.mark.render
def test_the_example_renders_with_its_camera(authored):
    """The render command as written, given one anomalous and one normal layer instead of the whole tree."""
    from PIL import Image

    here, tree = authored
    render = [c for c in commands() if c[1] == "render"]
    assert len(render) == 1 and render[0][2] == "out/tree"
    layers = [str(next((tree / "scenes" / "test" / "anomaly").glob("*red_z2.usda")).relative_to(here)),
              str(next((tree / "scenes" / "test" / "normal").glob("*.usda")).relative_to(here))]
    for layer in layers:
        r = cli([*render[0][:2], layer, *render[0][3:]], here)
        assert r.returncode == 0, r.stderr
    out = here / render[0][render[0].index("--out") + 1]
    metas = [json.loads(p.read_text()) for p in sorted(out.glob("*.json"))]
    assert len(metas) == 2
    for meta in metas:
        cam = meta["annotations"]["camera"]
        assert (cam["width"], cam["height"]) == (640, 400)
        k = np.array(cam["K_px"])
        assert k[0, 0] == pytest.approx(12.0 / 11.26 * 640) and k[0, 2] == pytest.approx(319.5 + 6.5)
        assert k[1, 2] == pytest.approx(199.5 - 4.0)
        mask = np.asarray(Image.open(out / meta["files"]["mask"]))
        rgb = np.asarray(Image.open(out / meta["files"]["rgb"]))
        assert mask.shape == (400, 640) and 0.05 < (mask == 1).mean() < 0.99 and rgb.mean() > 5
        anomaly = meta["annotations"]["anomaly"]
        assert (anomaly is None) == ("bracket" not in meta["files"]["rgb"])
        if anomaly is not None:
            assert anomaly["pixels"] == int((mask == 2).sum()) > 100
