"""The dataset's cache (annotations/records.json) is a derivation, never a source, and manifest.csv's
index column is checked:

- no place is read from the cache: a cached BOP folder of ../x writes nothing outside --out;
- a cached value is checked as any input is: an edited COCO bbox, an image of /etc/passwd, a
  record without a field, category ids that are not numbers are recomputed (a warning names the
  cache), and the annotation files equal a clean run's;
- records.json goes through the read gate: a FIFO, a link to /dev/zero, a 5 GB sparse file, JSON
  nested 200,000 deep and a directory in its place cost a recompute and a warning, never a hang, a
  traceback or a message naming a temporary;
- the cache still saves the work: a re-run recomputes no record, and a record's entry rebuilt
  from the row equals compute_record's;
- manifest.csv's index column: abc, -5, 1e30, 1000000, a duplicate stop the run in one line.

Renders here are synthetic (tests/support/renders.py fake_render): no Cycles run."""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import pytest

from allo_usd.core.errors import AlloError
from allo_usd.output import annotation_files as af
from allo_usd.output.dataset import read_manifest

from tests.output.test_dataset_hostile import run
from tests.support.renders import fake_render

ANNOTATIONS = ("annotations/instances_train.json", "annotations/instances_test.json", "instances.json")


def _renders(root: Path) -> Path:
    d = root / "renders"
    fake_render(d, "n1", split="train")
    fake_render(d, "n2", split="test")
    fake_render(d, "a1", split="test", variant="anomaly", anomaly=50)
    return d


def _run(renders: Path, out: Path) -> list[str]:
    return run([renders], out)   # the warnings' messages


def _outputs(out: Path) -> dict[str, bytes]:
    """Every annotation file (COCO, instances.json, BOP), by path from OUT."""
    found = {p: (out / p).read_bytes() for p in ANNOTATIONS}
    found |= {p.relative_to(out).as_posix(): p.read_bytes() for p in (out / "bop").rglob("*.json")}
    return found


@pytest.fixture
def made(tmp_path):
    """(renders, a dataset assembled from them, its annotation files)."""
    renders, out = _renders(tmp_path), tmp_path / "ds"
    _run(renders, out)
    return renders, out, _outputs(out)


def _edit(out: Path, change) -> None:
    path = out / "annotations" / "records.json"
    cache = json.loads(path.read_text())
    change(cache, cache["records"]["allo/a1"])
    path.write_text(json.dumps(cache))


def _names_the_cache(notes: list[str]) -> bool:
    return any("records.json" in n and "recomputed" in n for n in notes)


def test_a_cached_bop_folder_is_never_a_place(made, tmp_path):
    renders, out, clean = made

    def folder(cache, entry):
        entry.setdefault("bop", {})["folder"] = "../x"
        entry["bop"]["camera"] = {"cam_K": [1.0] * 9, "depth_scale": 10.0, "cam_R_w2c": [1.0] * 9,
                                  "cam_t_w2c": [0.0] * 3, "INJECTED": "attacker text"}
    _edit(out, folder)
    notes = _run(renders, out)
    assert not (tmp_path / "x").exists(), sorted(p.name for p in (tmp_path / "x").iterdir())
    assert _outputs(out) == clean and _names_the_cache(notes), notes


@pytest.mark.parametrize("change", [
    lambda c, e: e["coco"][0].update(bbox=[0, 0, 1, 1]),
    lambda c, e: e["coco"][0].update(area=1),
    lambda c, e: e["coco"][0]["segmentation"].update(size=[1, 1]),
    lambda c, e: e.update(image="/etc/passwd"),
    lambda c, e: e.update(width=10 ** 9) if "width" in e else None,
    lambda c, e: [e.pop(k, None) for k in ("split", "width")],
    lambda c, e: c.update(categories={"crate": "abc"}),
    lambda c, e: c.update(records=[]),
], ids=["bbox", "area", "rle size", "image", "width", "a field missing", "category ids", "records a list"])
def test_an_edited_cache_is_recomputed_with_a_warning(made, change):
    renders, out, clean = made
    _edit(out, change)
    notes = _run(renders, out)
    assert _outputs(out) == clean
    assert "/etc/passwd" not in (out / "annotations" / "instances_test.json").read_text()
    assert _names_the_cache(notes), notes
    assert not _names_the_cache(_run(renders, out))   # written again: the next run uses it


def _fifo(path: Path) -> None:
    os.mkfifo(path)

    def unblock():   # today's plain read_text() waits for a writer: give it one, late, so the test ends
        time.sleep(6)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:
            return   # no reader: nothing ever opened it
        os.write(fd, b"{}")
        os.close(fd)
    threading.Thread(target=unblock, daemon=True).start()


@pytest.mark.parametrize("make", [
    _fifo,
    lambda p: os.symlink("/dev/zero", p),
    lambda p: (p.write_bytes(b"{}"), os.truncate(p, 5 << 30)),
    lambda p: p.write_text("[" * 200_000 + "]" * 200_000),
    lambda p: p.mkdir(),
    lambda p: p.write_bytes(b"\xff\xfe not json"),
], ids=["fifo", "dev zero", "5 GB sparse", "200,000 deep", "directory", "not utf-8"])
def test_a_hostile_cache_file_is_refused_by_the_read_gate(made, make):
    renders, out, clean = made
    path = out / "annotations" / "records.json"
    path.unlink()
    make(path)
    start = time.monotonic()
    notes = _run(renders, out)
    assert time.monotonic() - start < 5, "records.json was waited on"
    assert _outputs(out) == clean and _names_the_cache(notes), notes
    assert not any(".records.json." in n for n in notes), notes   # no temporary named
    if path.is_dir():
        assert any("is a directory" in n and "remove it" in n for n in notes), notes
    else:
        assert path.is_file() and not path.is_symlink() and path.stat().st_size < 1 << 20


def test_the_cache_still_saves_the_work(made, monkeypatch):
    renders, out, clean = made
    computed = []
    real = af.compute_record
    monkeypatch.setattr(af, "compute_record", lambda *a, **k: computed.append(a[1]["name"]) or real(*a, **k))
    notes = _run(renders, out)
    assert computed == [] and not _names_the_cache(notes) and _outputs(out) == clean
    rows = read_manifest(out / "manifest.csv")
    for row in rows:   # what the cache gives back is what compute_record gives
        rec = real(out, row)
        assert af.record_of(row, af.entry_of(rec, "b")) == rec
        assert af.entry_problem(af.entry_of(rec, "b"), row) is None


def test_a_changed_mask_is_not_answered_from_the_cache(made, monkeypatch):
    renders, out, _ = made
    row = next(r for r in read_manifest(out / "manifest.csv") if r["name"] == "a1")
    mask = out / row["allo_mask"]
    st = mask.stat()
    os.utime(mask, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))   # the binding's stat changed
    computed = []
    real = af.compute_record
    monkeypatch.setattr(af, "compute_record", lambda *a, **k: computed.append(a[1]["name"]) or real(*a, **k))
    _run(renders, out)
    assert computed == ["a1"]


def _set_index(out: Path, name: str, value: str) -> None:
    path = out / "manifest.csv"
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    i = header.index("index")
    for n, line in enumerate(lines[1:], start=1):
        cells = line.split(",")
        if cells[header.index("name")] == name:
            cells[i] = value
            lines[n] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("value", ["abc", "-5", "1e30", "1000000", "2", " 1"])
def test_manifest_index_is_checked(made, value):
    renders, out, _ = made
    _set_index(out, "a1", value)   # 2: n2's (a duplicate); " 1": not the plain digits the dataset writes
    before = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
    with pytest.raises(AlloError) as caught:
        _run(renders, out)
    message = str(caught.value)
    assert "manifest.csv line" in message and "index" in message and "fix:" in message and "\n" not in message
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == before


@pytest.mark.parametrize("target", ["/proc/self/environ", "fifo"])
def test_a_manifest_that_is_no_file_on_disk_is_refused_by_the_gate(made, target):
    """manifest.csv is read through the read gate: a link to a pseudo-file or a FIFO is one line naming
    the manifest and the fix, never its content, and it never blocks."""
    renders, out, _ = made
    (out / "manifest.csv").unlink()
    if target == "fifo":
        os.mkfifo(out / "manifest.csv")
    else:
        (out / "manifest.csv").symlink_to(target)
    with pytest.raises(AlloError) as caught:
        _run(renders, out)
    message = str(caught.value)
    assert "manifest" in message and "fix:" in message and "\n" not in message and "PATH=" not in message


def test_a_recorded_full_silhouette_is_used_only_when_it_can_be_the_objects():
    """The render JSON's amodal_segmentation (the full silhouette in the image) is not trusted: an RLE whose
    count is not amodal_pixels, that misses a visible pixel, or is not an RLE of the image's size, is not
    used (scene_gt_info then has no px_count_valid and no mask/ file for the object)."""
    import numpy as np

    from allo_usd.output.rle import rle

    full = np.zeros((6, 8), dtype=bool)
    full[1:4, 2:7] = True
    visible = full.copy()
    visible[1, :] = False
    obj = {"amodal_segmentation": rle(full), "amodal_pixels": int(full.sum())}
    assert (af._recorded_silhouette(obj, full.shape, visible) == full).all()
    assert af._recorded_silhouette({**obj, "amodal_pixels": 14}, full.shape, visible) is None
    assert af._recorded_silhouette({**obj, "amodal_pixels": True}, full.shape, visible) is None
    outside = visible.copy()
    outside[5, 0] = True
    assert af._recorded_silhouette(obj, full.shape, outside) is None
    assert af._recorded_silhouette(obj, (8, 6), np.zeros((8, 6), dtype=bool)) is None
    assert af._recorded_silhouette({**obj, "amodal_segmentation": {"size": [6, 8], "counts": 7}},
                                   full.shape, visible) is None
