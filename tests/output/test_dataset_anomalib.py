"""The dataset tree loads in anomalib's MVTecAD and Folder loaders: one folder per defect, or merged.

anomalib is not installed here (it pulls torch), and none of its path functions can be imported
without it: src/anomalib/data/utils/path.py imports torchvision at module level. So the functions
below restate, line for line in plain Python, what anomalib does with a directory tree, as of
open-edge-platform/anomalib commit b7233686172e3485bfbe01272a8cd7a7e4576986:

- src/anomalib/data/datasets/image/mvtecad.py, make_mvtec_ad_dataset: validate_path(root); glob
  root/"**/*" for suffix .png/.PNG; split, label, file = the last three path parts; the image path
  is the string root/split/label/file; label "good" is normal (0), anything else abnormal (1);
  ground_truth rows are the masks; masks and the other rows are each sorted by that string; the
  abnormal test rows get the masks by position; every abnormal image's stem must be contained in
  its mask's stem (else MisMatchError).
- src/anomalib/data/datasets/image/folder.py, make_folder_dataset: each of normal_dir,
  abnormal_dir, normal_test_dir, mask_dir is a path or a list of paths, resolved against root
  (path.py resolve_path) and validated (path.py validate_path: at most 512 characters, printable
  ASCII, existing); path.py _prepare_files_labels globs each dir/"**/*" (suffix, lower-cased, in
  torchvision's IMG_EXTENSIONS, not a directory; a dir with no image is a RuntimeError); every
  file gets its dir's type; all rows are sorted together by image path (pathlib.Path objects, so
  Path ordering); abnormal rows get the mask rows' paths by position, with the same stem check;
  normal is train, abnormal and normal_test are test.
- src/anomalib/data/utils/image.py, read_mask: Image.open(path).convert("L"), then > 0.

The tree is assembled from real Cycles renders (tests/support/renders.py's fixture) plus render
records copied from them under other anomaly assets, named so that folder order and index order
disagree and one defect name is a prefix of another (where string and Path ordering differ).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from allo_usd.output.dataset import assemble, read_manifest

from tests.support.renders import fabricate, renders  # noqa: F401  (the fixture: four real renders)

pytestmark = pytest.mark.render

ANOMALIB_COMMIT = "b7233686172e3485bfbe01272a8cd7a7e4576986"
MVTEC_EXTENSIONS = (".png", ".PNG")
TORCHVISION_IMG_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".bmp", ".pgm", ".tif", ".tiff", ".webp")
NORMAL, ABNORMAL = 0, 1


def validate_path(path) -> Path:
    """anomalib.data.utils.path.validate_path (should_exist=True, no extensions)."""
    if len(str(path)) > 512:
        raise ValueError(f"Path is too long: {path}")
    if not re.match(r"^[\x20-\x7E]+$", str(path)):
        raise ValueError(f"Path contains non-printable characters: {path}")
    path = Path(path).resolve()
    if not path.exists():
        raise FileNotFoundError(f"Path does not exist: {path}")
    return path


def make_mvtec_ad_dataset(root: Path, split: str | None = None) -> list[dict]:
    root = validate_path(root)
    samples = [(str(root), *f.parts[-3:]) for f in root.glob("**/*") if f.suffix in MVTEC_EXTENSIONS]
    if not samples:
        raise RuntimeError(f"Found 0 images in {root}")
    rows = [{"split": s, "label": label, "image_path": f"{path}/{s}/{label}/{name}",
             "label_index": NORMAL if label == "good" else ABNORMAL} for path, s, label, name in samples]
    masks = sorted((r for r in rows if r["split"] == "ground_truth"), key=lambda r: r["image_path"])
    rows = sorted((r for r in rows if r["split"] != "ground_truth"), key=lambda r: r["image_path"])
    abnormal_test = [r for r in rows if r["split"] == "test" and r["label_index"] == ABNORMAL]
    assert len(abnormal_test) == len(masks), "pandas: Length of values does not match length of index"
    for r in rows:
        r["mask_path"] = None
    for r, m in zip(abnormal_test, masks):
        r["mask_path"] = m["image_path"]
    for r in rows:
        if r["label_index"] == ABNORMAL and Path(r["image_path"]).stem not in Path(r["mask_path"]).stem:
            raise AssertionError(f"MisMatchError: {r['image_path']} vs {r['mask_path']}")
    return [r for r in rows if split is None or r["split"] == split]


def _prepare_files_labels(path: Path, path_type: str) -> list[tuple[Path, str]]:
    files = [f for f in path.glob("**/*") if f.suffix.lower() in TORCHVISION_IMG_EXTENSIONS and not f.is_dir()]
    if not files:
        raise RuntimeError(f"Found 0 {path_type} images in {path}")
    return [(f, path_type) for f in files]


def make_folder_dataset(normal_dir, root, abnormal_dir=None, normal_test_dir=None, mask_dir=None) -> list[dict]:
    def paths(p):
        if p is None:
            return []
        return [validate_path(d if Path(d).is_absolute() else (Path(root) / d).resolve())
                for d in (p if isinstance(p, (list, tuple)) else [p])]

    dirs = {"normal": paths(normal_dir), "abnormal": paths(abnormal_dir), "normal_test": paths(normal_test_dir),
            "mask_dir": paths(mask_dir)}
    samples = sorted((f for t, ds in dirs.items() for d in ds for f in _prepare_files_labels(d, t)),
                     key=lambda s: s[0])   # DataFrame.sort_values on a column of Path objects
    rows = [{"image_path": f, "label": t, "mask_path": "",
             "label_index": {"normal": NORMAL, "normal_test": NORMAL, "abnormal": ABNORMAL}.get(t)}
            for f, t in samples]
    if dirs["mask_dir"] and dirs["abnormal"]:
        abnormal = [r for r in rows if r["label"] == "abnormal"]
        masks = [r["image_path"] for r in rows if r["label"] == "mask_dir"]
        assert len(abnormal) == len(masks), "pandas: Length of values does not match length of index"
        for r, m in zip(abnormal, masks):
            r["mask_path"] = str(m)
            if Path(r["image_path"]).stem not in Path(r["mask_path"]).stem:
                raise AssertionError(f"MisMatchError: {r['image_path']} vs {r['mask_path']}")
    rows = [r for r in rows if r["label"] != "mask_dir"]
    for r in rows:
        r["image_path"] = str(r["image_path"])
        r["split"] = "train" if r["label"] == "normal" else "test"
    return rows


def read_mask(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("L")) > 0


EXTRA = {  # name: anomaly asset; "Crate-lid" sorts before "Crate/" as a string, after "Crate" as a Path part
    "a_wrench_z1": "wrench",
    "b_crate_lid_z2": "Crate-lid",
    "c_crate_z1": "Crate",
}


@pytest.fixture(scope="module")
def more(renders, tmp_path_factory):  # noqa: F811
    """Anomalous test records copied from the real anomalous render, under other assets."""
    d = tmp_path_factory.mktemp("more")
    for name, asset in EXTRA.items():
        fabricate(renders, "d003_p41_crate_z0", d, name, split="test",
                  anomaly={"asset": asset, "assetVariant": "blue", "depthIndex": 1, "depthOffset": 0.5})
    return d


def expected(out: Path) -> dict[str, dict]:
    """What the manifest says each image is: absolute image path -> (split, label index, mask path)."""
    return {str((out / r["image"]).resolve()): {"split": r["split"], "label_index": NORMAL if r["kind"] == "good"
                                                else ABNORMAL, "mask": str((out / r["mask"]).resolve())
                                                if r["mask"] else None, "allo_mask": out / r["allo_mask"]}
            for r in read_manifest(out / "manifest.csv")}


def check_samples(samples: list[dict], want: dict[str, dict]) -> None:
    """Every image of the tree is loaded once, with the manifest's split and label, and each
    anomalous one with its own mask, whose pixels are the anomaly class of its 3-class mask."""
    assert sorted(s["image_path"] for s in samples) == sorted(want)
    for s in samples:
        w = want[s["image_path"]]
        assert (s["split"], s["label_index"]) == (w["split"], w["label_index"]), s
        assert (s["mask_path"] or None) == w["mask"], s
        if w["mask"]:
            np.testing.assert_array_equal(read_mask(s["mask_path"]), np.asarray(Image.open(w["allo_mask"])) == 2)
    assert all(s["label_index"] == NORMAL for s in samples if s["split"] == "train"), "train holds only good"


def test_one_folder_per_defect_loads_in_mvtec_and_folder(renders, more, tmp_path):  # noqa: F811
    out = tmp_path / "ds"
    assemble([renders, more], out)
    cat = out / "allo"
    assert sorted(p.name for p in (cat / "test").iterdir()) == ["Crate", "Crate-lid", "good", "wrench"]
    assert sorted(p.name for p in (cat / "ground_truth").iterdir()) == ["Crate", "Crate-lid", "wrench"]
    assert [p.name for p in (cat / "train").iterdir()] == ["good"]
    want = expected(out)
    assert sum(w["label_index"] for w in want.values()) == 4 and len(want) == 7
    samples = make_mvtec_ad_dataset(cat)
    check_samples(samples, want)
    assert {s["image_path"].split("/")[-2] for s in samples if s["label_index"] == ABNORMAL} == {
        "Crate", "Crate-lid", "wrench"}
    assert [s["image_path"] for s in make_mvtec_ad_dataset(cat, "train")] == sorted(
        k for k, w in want.items() if w["split"] == "train")
    defects = sorted(p.name for p in (cat / "test").iterdir() if p.name != "good")
    check_samples(make_folder_dataset("train/good", cat, [f"test/{d}" for d in defects], "test/good",
                                      [f"ground_truth/{d}" for d in defects]), want)
    # one defect folder on its own, as a Folder dataset of that defect
    one = make_folder_dataset("train/good", cat, "test/Crate-lid", "test/good", "ground_truth/Crate-lid")
    assert [Path(s["image_path"]).name for s in one if s["label_index"] == ABNORMAL] == ["000001_b_crate_lid_z2.png"]
    for r in read_manifest(out / "manifest.csv"):
        mask = np.asarray(Image.open(out / r["mask"])) if r["mask"] else None
        assert mask is None or (mask.dtype == np.uint8 and mask.ndim == 2 and set(np.unique(mask)) == {0, 255})
        assert not r["mask"] or Path(r["mask"]).name == Path(r["image"]).stem + "_mask.png"  # MVTec AD's naming


def test_merged_defects_load_and_a_rerun_moves_files_between_layouts(renders, more, tmp_path):  # noqa: F811
    out = tmp_path / "ds"
    assemble([renders, more], out, defects="merged")
    cat = out / "allo"
    assert sorted(p.name for p in (cat / "test").iterdir()) == ["anomaly", "good"]
    check_samples(make_mvtec_ad_dataset(cat), expected(out))
    check_samples(make_folder_dataset("train/good", cat, "test/anomaly", "test/good", "ground_truth/anomaly"),
                  expected(out))
    before = {r["name"]: r["index"] for r in read_manifest(out / "manifest.csv")}
    assemble([renders, more], out)   # per-asset now: the same indices, moved, the merged folders gone
    assert {r["name"]: r["index"] for r in read_manifest(out / "manifest.csv")} == before
    assert sorted(p.name for p in (cat / "test").iterdir()) == ["Crate", "Crate-lid", "good", "wrench"]
    assert not (out / "allo_masks/allo/test/anomaly").exists()
    check_samples(make_mvtec_ad_dataset(cat), expected(out))
