"""Dataset assembly: an MVTec-AD tree anomalib's MVTec/Folder loaders accept, a manifest, idempotent re-runs.

anomalib is not installed (and must not be); `mvtec_pairs` re-states what its make_mvtec_dataset
does with a category directory: glob every image below it, split/label from the last three path
parts, pair sorted anomalous test images with sorted ground-truth masks by position, and require
each image stem to be contained in its mask's stem.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.cli import app
from allo_usd.output.contact import OUTLINE, label_lines
from allo_usd.output.dataset import LOCK, AssemblyInterrupted, assemble, read_manifest
from allo_usd.core.errors import AlloError
from allo_usd.run.job import render_layer

from tests.support.helpers import make_spec
from tests.support.renders import SCENES, fabricate, renders  # noqa: F401  (the fixture: four real renders)

pytestmark = pytest.mark.render

def mvtec_pairs(category_dir: Path) -> dict:
    samples = [f.parts[-3:] for f in category_dir.glob("**/*") if f.suffix == ".png"]
    assert {s[0] for s in samples} <= {"train", "test", "ground_truth"}, "stray images confuse the loader"
    path = lambda s: str(category_dir / s[0] / s[1] / s[2])  # noqa: E731
    masks = sorted(path(s) for s in samples if s[0] == "ground_truth")
    abnormal = sorted(path(s) for s in samples if s[0] == "test" and s[1] != "good")
    assert len(masks) == len(abnormal)
    for image, mask in zip(abnormal, masks):
        assert Path(image).stem in Path(mask).stem, (image, mask)
    return {"train": sorted(path(s) for s in samples if s[0] == "train"),
            "test_good": sorted(path(s) for s in samples if s[:2] == ("test", "good")),
            "pairs": list(zip(abnormal, masks))}


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_layout_is_what_mvtec_loaders_expect(renders, tmp_path):
    out = tmp_path / "ds"
    manifest = assemble([renders], out)
    cat = out / "allo"
    assert sorted(p.name for p in cat.iterdir()) == ["ground_truth", "test", "train"]
    found = mvtec_pairs(cat)
    assert [Path(p).name for p in found["train"]] == ["000000_d000_p01.png", "000001_d001_p02.png"]
    assert [Path(p).name for p in found["test_good"]] == ["000002_d002_p41.png"]
    (image, mask), = found["pairs"]
    assert Path(image).relative_to(cat).as_posix() == "test/Crate/000003_d003_p41_crate_z0.png"  # its asset's folder
    assert Path(mask).relative_to(cat).as_posix() == "ground_truth/Crate/000003_d003_p41_crate_z0_mask.png"
    binary = np.asarray(Image.open(mask))
    three = np.asarray(Image.open(out / "allo_masks/allo/test/Crate/000003_d003_p41_crate_z0_mask.png"))
    assert binary.dtype == np.uint8 and binary.shape == (36, 64) == Image.open(image).size[::-1]
    assert set(np.unique(binary)) == {0, 255}
    np.testing.assert_array_equal(binary == 255, three == 2)
    assert set(np.unique(three)) == {0, 1, 2}
    assert os.path.samefile(image, renders / "d003_p41_crate_z0.png")  # hard link, no copy
    for split, kind, n in (("train", "good", 2), ("test", "good", 1), ("test", "Crate", 1)):
        assert len(list((out / "allo_masks/allo" / split / kind).glob("*_mask.png"))) == n
    for split in ("train", "test"):
        assert Image.open(out / "contact_sheets" / f"allo_{split}.png").size[0] >= 64
    assert manifest == out / "manifest.csv"


def test_manifest_has_one_row_per_image_with_provenance(renders, tmp_path):
    out = tmp_path / "ds"
    rows = {r["name"]: r for r in read_manifest(assemble([renders], out))}
    assert sorted(rows) == sorted(SCENES)
    a = rows["d003_p41_crate_z0"]
    assert (a["split"], a["kind"], a["pose"], a["day"], a["anomaly_asset"], a["anomaly_variant"], a["seed"]) == \
        ("test", "anomaly", "41", "3", "Crate", "blue", "14")
    assert a["depth_index"] == "0" and float(a["depth_offset"]) == 0.0
    meta = json.loads((renders / "d003_p41_crate_z0.json").read_text())
    assert meta["anomaly_fraction"] > 0 and float(a["anomaly_fraction"]) == pytest.approx(meta["anomaly_fraction"])
    assert a["mask"].endswith("_mask.png") and a["allo_mask"].startswith("allo_masks/allo/test/Crate/")
    assert a["epoch"] == "2030-01-01T00:00:00Z"
    # layer and source are relative to the dataset root: no absolute path of this machine
    assert not Path(a["layer"]).is_absolute() and not Path(a["source"]).is_absolute()
    assert (out / a["layer"]).resolve() == Path(meta["layer"]).resolve()
    assert (out / a["source"]).resolve() == (renders / "d003_p41_crate_z0.json").resolve()
    assert a["seed_path"] == "1/0/1/14" and a["plan_seed"] == "1"  # which pipeline run (plan seed) made it
    for r in rows.values():
        assert r["sha256"] == sha(out / r["image"])
        assert r["sha256"] == sha(renders / f"{r['name']}.png")
    n = rows["d000_p01"]
    assert (n["split"], n["kind"], n["mask"], n["anomaly_asset"]) == ("train", "good", "", "")
    # camera and annotation columns, flattened from the render JSON's `annotations` (output/annotations.py)
    rec = meta["annotations"]
    assert (a["width"], a["height"]) == ("64", "36") and float(a["cx"]) == 31.5 and float(a["cy"]) == 17.5
    assert float(a["fx"]) == rec["camera"]["K_px"][0][0] == float(a["fy"])
    assert json.loads(a["world_to_cam_opencv"]) == rec["camera"]["world_to_cam_opencv"]
    assert json.loads(a["cam_to_world_usd"]) == rec["camera"]["cam_to_world_usd"]
    assert [int(a[f"bbox_{k}"]) for k in ("x_min", "y_min", "x_max", "y_max")] == rec["anomaly"]["bbox_xyxy_px"]
    assert int(a["anomaly_pixels"]) == meta["class_pixels"]["anomaly"] and float(a["anomaly_distance_m"]) > 0
    assert a["sun_in_view"] in ("True", "False") and n["fx"] == a["fx"]
    assert n["bbox_x_min"] == n["anomaly_pixels"] == n["anomaly_distance_m"] == ""
    assert 0 < float(a["station_fraction"]) == meta["station_fraction"] < 1  # the passes' keys, as recorded
    assert [int(a[f"{b}_pixels"]) for b in ("sun", "earth", "moon")] == [
        meta["bodies"][b]["pixels"] for b in ("sun", "earth", "moon")]


def test_rows_from_before_the_camera_columns_are_filled_in(renders, tmp_path):
    out = tmp_path / "ds"
    manifest = assemble([renders], out)
    with open(manifest, newline="") as f:
        old = list(csv.DictReader(f))
    keep = [c for c in old[0] if c not in ("fx", "fy", "cx", "cy", "bbox_x_min", "K_px")]
    with open(manifest, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keep, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        w.writerows(old)
    rows = read_manifest(assemble([renders], out))
    assert all(r["fx"] and r["K_px"] for r in rows)


def test_rerun_is_idempotent_and_adds_new_scenes(renders, tmp_path):
    out = tmp_path / "ds"
    manifest = assemble([renders], out)
    before = manifest.read_bytes()
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert assemble([renders], out).read_bytes() == before
    assert sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file()) == files
    more = fabricate(renders, "d002_p41", tmp_path / "more", "d009_p44", day=9, pose=44)
    rows = read_manifest(assemble([renders, more], out))
    assert len(rows) == 5 and len({r["name"] for r in rows}) == 5
    new = next(r for r in rows if r["name"] == "d009_p44")
    assert new["index"] == "4" and new["image"] == "allo/test/good/000004_d009_p44.png"
    assert len(read_manifest(assemble([more, renders], out))) == 5
    mvtec_pairs(out / "allo")


def test_left_out_scenes_and_name_clashes(renders, tmp_path):
    odd = tmp_path / "odd"
    fabricate(renders, "d003_p41_crate_z0", odd, "train_anomaly", split="train")  # the paper's train is normal only
    fabricate(renders, "d000_p01", odd, "hidden_anomaly", split="test", variant="anomaly")  # 0 anomaly pixels
    with pytest.warns(UserWarning, match="2 scene"):
        rows = read_manifest(assemble([renders, odd], tmp_path / "ds"))
    assert sorted(r["name"] for r in rows) == sorted(SCENES)
    clash = fabricate(renders, "d000_p01", tmp_path / "clash", "d000_p01")  # same name, other layer
    with pytest.raises(AlloError, match="two different scenes"):
        assemble([renders, clash], tmp_path / "ds2")


def test_cli_dataset_copies_when_asked(renders, tmp_path):
    out = tmp_path / "ds"
    result = CliRunner().invoke(app, ["dataset", str(renders), "--out", str(out), "--category", "gateway", "--copy"])
    assert result.exit_code == 0, result.output
    assert "train/good 2, test/good 1, test/Crate 1;" in result.output
    assert "assembling gateway" not in result.output  # progress bars only on a terminal (not a pipe or a log)
    image = out / "gateway/train/good/000000_d000_p01.png"
    assert image.is_file() and not os.path.samefile(image, renders / "d000_p01.png")
    with open(out / "manifest.csv", newline="") as f:
        assert {r["category"] for r in csv.DictReader(f)} == {"gateway"}
    assert not (out / "manifest.parquet").exists() or __import__("importlib").util.find_spec("pyarrow")


def tree_files(out: Path, category: str = "allo") -> set[str]:
    """Every indexed image and mask in the tree (what loaders and the manifest care about)."""
    return {p.relative_to(out).as_posix() for top in (out / category, out / "allo_masks" / category)
            for p in top.rglob("*.png")}


def listed_files(out: Path) -> set[str]:
    return {r[k] for r in read_manifest(out / "manifest.csv") for k in ("image", "mask", "allo_mask") if r[k]}


def many_scenes(renders: Path, dst: Path, n: int) -> Path:
    """n render records (real files, fabricated names): normal test scenes for bulk runs."""
    for i in range(n):
        fabricate(renders, "d002_p41", dst, f"bulk_{i:04d}_d{i % 365:03d}_p41", day=i % 365)
    return dst


def test_mask_only_renders_are_left_out_with_a_note(renders, tiny_base, tmp_path):
    spec = make_spec(scene_id="masks", day=5, seed=15)
    spec = replace(spec, split="test", pose=41, render=replace(spec.render, passes=("mask",)))
    masks = tmp_path / "mask_renders"
    meta = render_layer(write_scene_layer(spec, tmp_path / "layers" / "masks.usda", tiny_base), masks)
    assert "rgb" not in meta["files"] and (masks / meta["files"]["mask"]).is_file()  # a real mask-only render
    with pytest.warns(UserWarning, match="1 mask-only render.*no color image.*masks"):
        rows = read_manifest(assemble([renders, masks], tmp_path / "ds"))
    assert sorted(r["name"] for r in rows) == sorted(SCENES)


def test_stale_temporaries_and_unlisted_images_are_removed(renders, tmp_path):
    out = tmp_path / "ds"
    assemble([renders], out)
    gt = out / "allo/ground_truth/Crate"
    stale = [gt / ".000003_d003_p41_crate_z0_mask.png.k2j_9x0a.png",  # write.atomic_path's, after SIGKILL
             out / "allo/train/good" / f".000000_d000_p01.png.{'ab' * 16}.tmp",  # place()'s
             out / ".manifest.csv.abcd1234.csv"]
    for p in stale:
        p.write_bytes(b"partial")
    orphan = out / "allo/test/good/000099_gone.png"
    shutil.copyfile(renders / "d002_p41.png", orphan)
    keep = out / "allo" / "README.txt"  # not ours to remove: neither a temporary nor an indexed image
    keep.write_text("x")
    with pytest.warns(UserWarning, match="removed 3 stale temporary file.*1 image"):
        assemble([renders], out)
    assert not any(p.exists() for p in stale + [orphan]) and keep.is_file()
    keep.unlink()
    mvtec_pairs(out / "allo")
    assert tree_files(out) == listed_files(out)


def test_contact_sheet_labels_keep_the_whole_name(renders, tmp_path):
    from PIL import ImageDraw

    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    name = "s2031_d364_p50_mli_torn_sheet-silver_z4"
    lines = label_lines(name, 160, draw)
    assert "".join(lines) == name and len(lines) >= 2 and lines[-1].endswith("_z4")
    assert all(draw.textlength(line) <= 160 for line in lines)
    assert label_lines("x" * 80, 60, draw) and "".join(label_lines("x" * 80, 60, draw)) == "x" * 80
    out = tmp_path / "ds"
    long = fabricate(renders, "d003_p41_crate_z0", tmp_path / "long", "_".join([name] * 4), split="test")
    assemble([renders, long], out)
    sheet = Image.open(out / "contact_sheets/allo_test.png")
    short = tmp_path / "short"
    assemble([renders], short)
    assert sheet.height > Image.open(short / "contact_sheets/allo_test.png").height  # room for more lines


def magenta(image: Image.Image) -> np.ndarray:
    return np.all(np.asarray(image.convert("RGB")) == OUTLINE, axis=-1)


def test_contact_sheets_are_large_and_outline_each_anomaly(renders, tmp_path):
    """One sheet per split; tiles at least 480 px wide (the 64x36 renders enlarged pixel for pixel),
    each anomaly ringed in OUTLINE around its mask, nothing outlined on the train sheet; many
    images make several sheets, and fewer on a re-run remove the pages no longer drawn."""
    out = tmp_path / "ds"
    assemble([renders], out)
    train, test = (Image.open(out / f"contact_sheets/allo_{s}.png") for s in ("train", "test"))
    assert train.width >= 2 * 480 and test.width >= 2 * 480  # two images a side, each at least 480 wide
    assert not magenta(train).any()
    ring = magenta(test)
    assert ring.any()
    # the anomaly's pixels lie inside the ring: the tile's enlarged mask matches the 3-class mask
    three = np.asarray(Image.open(out / "allo_masks/allo/test/Crate/000003_d003_p41_crate_z0_mask.png")) == 2
    ys, xs = np.nonzero(ring)
    scale = 480 / 64
    assert xs.max() - xs.min() >= (np.ptp(np.nonzero(three)[1]) + 1) * scale  # around the anomaly, scaled up
    many = many_scenes(renders, tmp_path / "many", 14)
    assemble([renders, many], out)
    pages = sorted(p.name for p in (out / "contact_sheets").iterdir())
    assert pages == ["allo_test.png", "allo_test_2.png", "allo_train.png"], pages  # 16 test images, 12 a sheet
    assemble([renders, many], out, sheet_limit=10)
    assert sorted(p.name for p in (out / "contact_sheets").iterdir()) == ["allo_test.png", "allo_train.png"]


def test_manifest_is_relative_with_lf_lines_and_no_lock_is_left(renders, tmp_path):
    out = tmp_path / "ds"
    manifest = assemble([renders], out)
    raw = manifest.read_bytes()
    assert b"\r" not in raw and raw.endswith(b"\n") and raw.count(b"\n") == 1 + len(SCENES)
    for r in read_manifest(manifest):
        for key in ("image", "mask", "allo_mask"):
            assert not r[key] or (not Path(r[key]).is_absolute() and (out / r[key]).is_file()), r[key]
    assert not (out / LOCK).exists() and not [p for p in out.rglob(".*")]
    moved = tmp_path / "elsewhere"
    shutil.move(out, moved)   # relative paths: the tree moves as a whole
    assert all((moved / r["image"]).is_file() for r in read_manifest(moved / "manifest.csv"))


def test_ctrl_c_stops_after_the_scene_in_hand_and_a_rerun_completes(renders, tmp_path):
    many = many_scenes(renders, tmp_path / "many", 12)
    reference = tmp_path / "reference"
    assemble([renders, many], reference)
    out = tmp_path / "ds"
    seen = []

    def press_ctrl_c(name):
        seen.append(name)
        if len(seen) == 3:
            os.kill(os.getpid(), signal.SIGINT)  # a real SIGINT, as a terminal sends it

    with pytest.raises(AssemblyInterrupted, match="interrupted after 3 of 16 scenes"):
        assemble([renders, many], out, on_scene=press_ctrl_c)
    assert len(read_manifest(out / "manifest.csv")) == 3
    assert tree_files(out) == listed_files(out) and len(tree_files(out)) == 6
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handler restored
    assemble([renders, many], out)
    assert (out / "manifest.csv").read_bytes() == (reference / "manifest.csv").read_bytes()
    assert tree_files(out) == tree_files(reference)


def _run_cli_until_files_appear(args, out: Path, sig: int) -> subprocess.CompletedProcess:
    """Start `allo-usd dataset` and send `sig` once its first image exists."""
    cli = [sys.executable, "-c", "from allo_usd.cli import main; main()", "dataset"]
    proc = subprocess.Popen(cli + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not ((out / "allo").is_dir() and any((out / "allo").rglob("*.png"))):
        assert proc.poll() is None and time.monotonic() < deadline, "the run ended before it placed a file"
        time.sleep(0.002)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["ctrl-c", "kill-9"])
def test_an_interrupted_cli_run_never_leaves_unlisted_files(renders, tmp_path, sig):
    many = many_scenes(renders, tmp_path / "many", 600)
    out = tmp_path / "ds"
    r = _run_cli_until_files_appear([str(renders), str(many), "--out", str(out)], out, sig)
    present, listed = tree_files(out), listed_files(out)
    assert present <= listed, present - listed  # every file in the tree is in the manifest
    if sig == signal.SIGINT:
        assert r.returncode == 130 and "interrupted after" in r.stderr and "re-run" in r.stderr, r.stderr
        n = len(read_manifest(out / "manifest.csv"))
        assert present == listed and 0 < n < 604, n
        print(f"SIGINT stopped after {n} of 604 scenes")
    else:
        assert r.returncode == -signal.SIGKILL
    assemble([renders, many], out)  # the re-run completes the rows whose files did not arrive
    rows = read_manifest(out / "manifest.csv")
    assert len(rows) == 604 and sorted(int(r["index"]) for r in rows) == list(range(604))
    assert tree_files(out) == listed_files(out)
    assert not [p for p in out.rglob(".*") if p.is_file()]  # no temporaries, and the re-run removed the lock file
    mvtec_pairs(out / "allo")


def test_one_assembly_at_a_time_per_output(tmp_path):
    from allo_usd.output.dataset import LOCK, assemble
    from allo_usd.core.errors import AlloError
    from allo_usd.core.files import RunLock

    (tmp_path / "ds").mkdir()
    with RunLock(tmp_path / "ds", LOCK, "dataset"):  # another assembly holds the directory
        with pytest.raises(AlloError, match="another dataset run is writing to"):
            assemble([tmp_path / "renders"], tmp_path / "ds")
    assert not (tmp_path / "ds" / "manifest.csv").exists()  # refused before touching anything
