"""The per-record shortcuts of `allo-usd dataset` give the answers of the work they skip.

- a re-run does not parse a render record whose JSON kept the stat at which it passed check_render
  (its Brief in records.json's state stands for it), and still notices a record whose JSON, image
  or mask changed, one added and one removed;
- an anomalous mask is decoded once: the kept anomaly pixels (AnomalyPixels) give back the mask's
  anomaly class exactly, and the annotation record made from them equals the one made from the mask;
- the one-lstat real paths (real_path, inside, from_root) agree with os.path.realpath, links included;
- a re-run that changes nothing leaves manifest.csv untouched.

Renders here are synthetic (tests/support/renders.py fake_render): no Cycles run."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from allo_usd.core.errors import AlloError
from allo_usd.output import dataset as ds
from allo_usd.output.annotation_files import compute_record
from allo_usd.output.dataset import assemble, read_manifest
from allo_usd.output.dataset_files import FOLDERS, AnomalyPixels, inside, real_path

from tests.support.renders import edit, fake_render


def _assemble(renders: Path, out: Path) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assemble([renders], out)
    return [str(w.message) for w in caught]


def _rows(out: Path) -> dict[str, dict]:
    return {r["name"]: r for r in read_manifest(out / "manifest.csv")}


@pytest.fixture
def parsed(monkeypatch):
    """The render records the dataset parses, by file name."""
    seen: list[str] = []
    real = ds.read_user_json

    def counting(path, *args, **kwargs):
        seen.append(Path(path).name)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(ds, "read_user_json", counting)
    return seen


@pytest.mark.slow
def test_a_rerun_parses_only_the_records_that_changed(tmp_path, parsed):
    renders, out = tmp_path / "renders", tmp_path / "ds"
    for i in range(3):
        fake_render(renders, f"n{i}")
    fake_render(renders, "a0", split="test", variant="anomaly", anomaly=40)
    _assemble(renders, out)
    assert sorted(parsed) == ["a0.json", "n0.json", "n1.json", "n2.json"]
    checks = json.loads((out / "annotations" / "records.json").read_text())["state"]["checks"]
    assert checks["../renders/a0.json"]["brief"]["scene"]["anomaly"]["asset"] == "crate"
    manifest = (out / "manifest.csv").read_bytes()

    parsed.clear()
    _assemble(renders, out)
    assert parsed == []                                              # nothing changed: no JSON parsed
    assert (out / "manifest.csv").read_bytes() == manifest

    fake_render(renders, "n3")                                       # added
    edit(renders / "n1.json", lambda m: m.update(layer_sha256="f" * 64))   # changed JSON: another layer
    (renders / "n2.json").unlink()                                   # removed record (its files stay)
    (renders / "n0.png").unlink()
    fake_render(renders, "n0x")                                      # n0's image re-rendered under n0.png
    os.replace(renders / "n0x.png", renders / "n0.png")
    (renders / "n0x.json").unlink()
    parsed.clear()
    _assemble(renders, out)
    assert sorted(parsed) == ["n0.json", "n1.json", "n3.json"]
    rows = _rows(out)
    assert rows["n1"]["layer_sha256"] == "f" * 64 and "n3" in rows and "n2" in rows   # n2's files are still in its folder
    assert rows["n0"]["sha256"] == ds.sha256_file(renders / "n0.png")


def test_a_record_whose_mask_changed_under_its_brief_is_checked_again(tmp_path, parsed):
    renders, out = tmp_path / "renders", tmp_path / "ds"
    fake_render(renders, "a1", split="test", variant="anomaly", anomaly=40)
    fake_render(renders, "n1")
    _assemble(renders, out)
    fake_render(tmp_path / "other", "a1", split="test", variant="anomaly", anomaly=41)
    os.replace(tmp_path / "other" / "a1_mask.png", renders / "a1_mask.png")   # contradicts the JSON's 40
    parsed.clear()
    messages = _assemble(renders, out)
    assert parsed == ["a1.json"]
    assert any("refused" in m and "a1.json" in m and "anomaly pixels" in m for m in messages), messages


@pytest.mark.parametrize("shape, box", [((36, 64), (3, 5, 9, 20)), ((7, 9), (0, 0, 6, 8)), ((5, 5), None)])
def test_anomaly_pixels_give_back_the_masks_anomaly_class(shape, box):
    rng = np.random.default_rng(7)
    mask = rng.integers(0, 2, shape).astype(np.uint8)
    if box is not None:
        r0, c0, r1, c1 = box
        mask[r0:r1 + 1, c0:c1 + 1] = np.where(rng.random((r1 - r0 + 1, c1 - c0 + 1)) < 0.5, 2, 1)
        mask[r0, c0] = mask[r1, c1] = 2
    kept = AnomalyPixels.of(mask)
    assert kept.box == box and kept.shape == shape and kept.count == int((mask == 2).sum())
    assert np.array_equal(kept.full(), mask == 2)


def test_the_record_from_kept_pixels_equals_the_record_from_the_mask(tmp_path):
    renders, out = tmp_path / "renders", tmp_path / "ds"
    fake_render(renders, "a1", split="test", variant="anomaly", anomaly=140)
    fake_render(renders, "n1")
    _assemble(renders, out)
    row = _rows(out)["a1"]
    from allo_usd.output.contact import read_pixels

    mask = read_pixels(out / row["allo_mask"])
    meta = json.loads((renders / "a1.json").read_text())
    assert compute_record(out, row, meta=meta, visible=AnomalyPixels.of(mask)) == compute_record(out, row)


def test_one_lstat_real_paths_agree_with_realpath(tmp_path):
    out = tmp_path / "ds"
    (out / "a" / "b").mkdir(parents=True)
    (out / "a" / "b" / "f.png").write_bytes(b"x")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "g.png").write_bytes(b"y")
    (out / "a" / "link").symlink_to(outside)
    (out / "a" / "b" / "l.png").symlink_to(outside / "g.png")
    token = FOLDERS.set({})
    try:
        for rel in ("a/b/f.png", "a/b/l.png", "a/link/g.png", "a/b/missing.png", "a/b", "a/b/../b/f.png"):
            assert real_path(out / rel) == os.path.realpath(out / rel), rel
        assert inside(out, "a/b/f.png") == out / "a/b/f.png"
        for rel in ("a/b/l.png", "a/link/g.png", "/etc/passwd"):
            with pytest.raises(AlloError):
                inside(out, rel)
        assert ds.from_root(out / "a" / "b" / "f.png", out) == "a/b/f.png"
        assert ds.from_root(outside / "g.png", out) == "../elsewhere/g.png"
    finally:
        FOLDERS.reset(token)
