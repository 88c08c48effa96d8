"""The README's five-minute tour, run as written: its ```sh block (the one after the
`<!-- tour` marker under "## Five-minute tour") runs in bash with `set -euo pipefail`, in an
empty temporary folder, with this interpreter's bin folder first on PATH (where `allo-usd` is)
and without ALLO_ASSET_ROOTS, as a user would run it. Then each step must have made what the
README says it makes: the plan, the authored tree, inspect's and diff's output, the renders, the
dataset and the package. Renders the demo plan's 16 scenes at 160x90, 4 samples, with Cycles
(about 20 s of CPU).
"""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
SECTION = "\n## Five-minute tour\n"
MARKER = "<!-- tour"
ANOMALY = "s2030_d000_p41_power_drill-yellow_z0"


def tour_block() -> str:
    """The sh block right after the tour marker in the README's "Five-minute tour" section."""
    text = README.read_text()
    assert SECTION in text, "README.md has no '## Five-minute tour' section"
    section = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    assert MARKER in section, f"the tour section has no {MARKER!r} marker before its sh block"
    block = re.match(r"[^\n]*\n```sh\n(.*?)```", section.split(MARKER, 1)[1], re.S)
    assert block, "the tour marker is not followed by a ```sh block"
    return block.group(1)


def test_the_tour_names_every_step():
    """The tour shows each command the README promises: plan, author, render, dataset, inspect, diff, pack."""
    commands = {line.split()[1] for line in tour_block().splitlines() if line.startswith("allo-usd ")}
    assert {"plan", "author", "render", "dataset", "inspect", "diff", "pack"} <= commands, commands


@pytest.fixture(scope="module")
def tour(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    work = tmp_path_factory.mktemp("tour")
    env = {k: v for k, v in os.environ.items() if k != "ALLO_ASSET_ROOTS"}   # as a user runs it
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    r = subprocess.run(["bash", "-c", "set -euo pipefail\n" + tour_block()], cwd=work, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"the tour failed (exit {r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return work, r


@pytest.mark.render
def test_the_readme_tour_runs_and_each_step_makes_what_it_says(tour):
    work, r = tour
    # plan: a demo plan, edited to 160x90 at the draft preset
    plan = (work / "demo.toml").read_text()
    assert 'name = "demo"' in plan and "160" in plan and "90" in plan and "480" not in plan and 'preset = "draft"' in plan

    # author: 16 scene layers (4 normal train, 2 normal test, 10 anomalous) over shared layers
    tree = work / "tree"
    scenes = sorted(p.relative_to(tree / "scenes").as_posix() for p in (tree / "scenes").rglob("*.usda"))
    assert len(scenes) == 16, scenes
    assert sum(s.startswith("test/anomaly/") for s in scenes) == 10
    assert (tree / "stages" / "base.usda").is_file() and (tree / "sky" / "d000.usda").is_file()

    # inspect printed the scene
    out = r.stdout
    assert re.search(rf"^scene\s+{ANOMALY}\s+\(test, anomaly\)", out, re.M), out[:2000]
    assert re.search(r"^anomaly\s+power_drill/yellow", out, re.M)
    assert re.search(r"^render\s+160x90", out, re.M)
    assert re.search(r"^stack\s+\./" + ANOMALY + r"\.usda -> ", out, re.M)

    # diff listed what differs: the anomaly prim and the scene id
    assert "/World/Anomaly (prim): <absent> -> Xform" in out
    assert f"/World allo:sceneId: s2030_d000_p41 -> {ANOMALY}" in out

    # render: every scene's PNG, EXR, mask and JSON record, at 160x90
    renders = work / "renders"
    records = sorted(renders.glob("*.json"))
    assert len(records) == 16, records
    for rec in records:
        stem = rec.with_suffix("")
        for suffix in (".png", ".exr", "_mask.png"):
            assert Path(f"{stem}{suffix}").is_file(), f"{stem}{suffix}"
    from PIL import Image

    with Image.open(renders / f"{ANOMALY}.png") as im:
        assert im.size == (160, 90)
    meta = json.loads((renders / f"{ANOMALY}.json").read_text())
    assert meta["class_pixels"]["anomaly"] > 0 and meta["layer_relative"].endswith(f"{ANOMALY}.usda")

    # dataset: the MVTec AD tree, its manifest, COCO and BOP files
    allo = work / "dataset" / "allo"
    assert len(list((allo / "train" / "good").glob("*.png"))) == 4
    assert len(list((allo / "test" / "good").glob("*.png"))) == 2
    assert len(list((allo / "test" / "power_drill").glob("*.png"))) == 10
    assert len(list((allo / "ground_truth" / "power_drill").glob("*_mask.png"))) == 10
    with open(work / "dataset" / "manifest.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 16 and {row["split"] for row in rows} == {"train", "test"}
    coco = json.loads((work / "dataset" / "annotations" / "instances_test.json").read_text())
    assert len(coco["images"]) == 12 and len(coco["annotations"]) == 10
    assert (work / "dataset" / "bop" / "allo" / "models.json").is_file()

    # pack: one .usdz holding the scene layer and what it composes
    usdz = work / "drill.usdz"
    assert zipfile.is_zipfile(usdz)
    with zipfile.ZipFile(usdz) as z:
        names = z.namelist()
    assert names[0].endswith(f"{ANOMALY}.usda"), names[:3]
    assert any(n.endswith("base.usda") for n in names) and any(n.endswith("d000.usda") for n in names)
