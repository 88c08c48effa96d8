"""The resume's quick check: a finished output is trusted on the size, mtime_ns and inode
its manifest row recorded, without being read; `render --verify` / dispatch(verify=True) reads
every byte. Real renders at 64x36, 2 samples, one worker."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from allo_usd.run import render_index as manifest_mod
from allo_usd.run.dispatch import dispatch
from allo_usd.run.render_index import MANIFEST, is_done, is_verified, load_manifest, resume_check
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

pytestmark = pytest.mark.render

CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()", "render"]


@pytest.fixture(scope="module")
def finished(tiny_base, tmp_path_factory):
    """Five tiny scenes rendered once by the dispatcher: (layers dir, render dir), copied by each test."""
    root = tmp_path_factory.mktemp("quick")
    for i in range(5):
        write_scene_layer(make_spec(seed=60 + i, scene_id=f"q{i}", anomaly=i == 1, samples=2),
                          root / "layers" / f"q{i}.usda", tiny_base)
    summary = dispatch(root / "layers", root / "out", workers=1, progress=False)
    assert sorted(summary.rendered) == [f"q{i}" for i in range(5)] and not summary.failed
    return root / "layers", root / "out"


def _copy(finished, tmp_path: Path, reindex: bool = True) -> tuple[Path, Path]:
    """The finished folder for one test: copies that keep their mtimes (new inodes, as `cp -a`),
    re-indexed by a resume that renders nothing (`reindex`), so that every row's stat holds again."""
    layers, out = finished
    mine = tmp_path / "out"
    shutil.copytree(out, mine, copy_function=shutil.copy2)
    if reindex:
        summary = dispatch(layers, mine, workers=1, progress=False)
        assert not summary.rendered and len(summary.skipped) == 5, summary
    return layers, mine


def _same_stat_new_bytes(path: Path) -> None:
    """Flip one byte in the middle of `path`, in place, and put its mtime back by hand."""
    st = path.stat()
    with open(path, "r+b") as f:
        f.seek(st.st_size // 2)
        b = f.read(1)
        f.seek(st.st_size // 2)
        f.write(bytes([b[0] ^ 0xFF]))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    now = path.stat()
    assert (now.st_size, now.st_mtime_ns, now.st_ino) == (st.st_size, st.st_mtime_ns, st.st_ino)


def test_the_quick_check_reads_no_output(finished, tmp_path):
    layers, out = _copy(finished, tmp_path)
    rows = load_manifest(out)
    assert all(set(r["stat"]) == set(r["files"]) for r in rows.values())  # every output's stat is recorded
    manifest_mod._SHA256.clear()
    for layer in sorted(layers.glob("*.usda")):
        assert is_done(layer, out, rows)
    hashed = {Path(k[0]).name for k in manifest_mod._SHA256}
    assert hashed and not {n for r in rows.values() for n in r["files"]} & hashed, hashed  # inputs only


def test_edited_in_place_with_its_mtime_restored_passes_quick_and_fails_verify(finished, tmp_path):
    """The quick check's known blind spot, and what --verify is for; plus the four ways an output
    changes that the quick check does see (re-rendered without --verify)."""
    layers, out = _copy(finished, tmp_path)
    ref = {p.name: p.read_bytes() for p in finished[1].iterdir() if p.suffix in (".png", ".exr")}
    _same_stat_new_bytes(out / "q0.exr")                       # in place, mtime restored: passes the quick check
    with open(out / "q1.png", "r+b") as f:                     # truncated
        f.truncate(100)
    (out / "q2_mask.tmp").write_bytes((out / "q0_mask.png").read_bytes())
    os.replace(out / "q2_mask.tmp", out / "q2_mask.png")      # replaced by another file (new inode, new mtime)
    st = (out / "q3.exr").stat()                               # touched: the same bytes, a new mtime
    os.utime(out / "q3.exr", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    st = (out / "q4.png").stat()                               # same size and mtime, other bytes, new inode
    (out / "q4.tmp").write_bytes(bytes(b ^ 1 for b in (out / "q4.png").read_bytes()))
    os.utime(out / "q4.tmp", ns=(st.st_atime_ns, st.st_mtime_ns))
    os.replace(out / "q4.tmp", out / "q4.png")

    rows = load_manifest(out)
    assert is_verified(rows["q0"], layers / "q0.usda", out)
    assert not is_verified(rows["q0"], layers / "q0.usda", out, verify=True)
    summary = dispatch(layers, out, workers=1, progress=False)
    assert sorted(summary.rendered) == ["q1", "q2", "q3", "q4"] and summary.skipped == ["q0"], summary
    assert (out / "q0.exr").read_bytes() != ref["q0.exr"]  # the quick check kept the edited file
    for name in ("q1.png", "q2_mask.png", "q3.exr", "q4.png"):
        assert (out / name).read_bytes() == ref[name], name   # rendered again: the same bytes

    r = subprocess.run(CLI + [str(layers), "--out", str(out), "--workers", "1", "--verify"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "1 rendered, 4 skipped" in r.stdout, r.stdout
    assert (out / "q0.exr").read_bytes() == ref["q0.exr"]
    rows = load_manifest(out)
    assert all(is_verified(rows[f"q{i}"], layers / f"q{i}.usda", out, verify=True) for i in range(5))


def test_a_copy_is_hashed_once_and_its_rows_take_the_new_stat(finished, tmp_path):
    """A copy that keeps mtimes (cp -a: new inodes) is checked by checksum and re-indexed, not
    re-rendered; a row written before rows had stat is hashed and upgraded the same way; a copy
    that lost its mtimes needs --verify (which keeps what checksums and records its stat)."""
    layers, out = _copy(finished, tmp_path, reindex=False)
    rows = load_manifest(out)
    old = {s: {k: v for k, v in r.items() if k != "stat"} for s, r in rows.items()}
    (out / MANIFEST).write_text("".join(json.dumps(old[s], sort_keys=True) + "\n" for s in ("q0", "q1")) +
                                "".join(json.dumps(rows[s], sort_keys=True) + "\n" for s in ("q2", "q3", "q4")))
    summary = dispatch(layers, out, workers=1, progress=False)
    assert not summary.rendered and len(summary.skipped) == 5
    now = load_manifest(out)
    for s, row in now.items():
        assert row["stat"] == {n: {"size": (out / n).stat().st_size, "mtime_ns": (out / n).stat().st_mtime_ns,
                                   "ino": (out / n).stat().st_ino} for n in row["files"]}, s
        assert {k: v for k, v in row.items() if k != "stat"} == old[s]  # nothing else changed

    for p in out.iterdir():  # a copy that did not keep mtimes: every stat differs
        if p.is_file() and p.name != MANIFEST:
            os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 5_000_000_000))
    rows = load_manifest(out)
    layer = layers / "q2.usda"
    assert not is_done(layer, out, rows) and resume_check(layer, out, rows["q2"]) == (False, None)
    done, upgraded = resume_check(layer, out, rows["q2"], verify=True)
    assert done and upgraded["stat"] != rows["q2"]["stat"] and is_verified(upgraded, layer, out)
    summary = dispatch(layers, out, workers=1, progress=False, verify=True)
    assert not summary.rendered and len(summary.skipped) == 5
    assert all(is_verified(r, layers / f"{s}.usda", out) for s, r in load_manifest(out).items())


def test_the_quick_check_opens_no_render_json_and_an_old_row_learns_its_record(finished, tmp_path, monkeypatch):
    """A row carries what the resume needs of the render JSON (its inputs' paths and passes:
    manifest.record_fields), trusted because the JSON itself is one of the row's checked files: a
    51,409-scene resume opens no JSON. A row without it (older) reads the JSON once and is upgraded;
    a JSON changed since its row was made fails the check (its stat) like any output."""
    layers, out = _copy(finished, tmp_path)
    rows = load_manifest(out)
    for s, r in rows.items():
        meta = json.loads((out / f"{s}.json").read_text())
        assert r["record"] == {"inputs": sorted(meta["inputs"]), "layer_passes": meta["layer_passes"],
                               "passes": meta.get("passes", meta["layer_passes"])}
    opened = []
    real_meta = manifest_mod._meta
    monkeypatch.setattr(manifest_mod, "_meta", lambda p: opened.append(Path(p).name) or real_meta(p))
    for layer in sorted(layers.glob("*.usda")):
        assert resume_check(layer, out, rows[layer.stem]) == (True, None)
    assert opened == []

    bare = {k: v for k, v in rows["q1"].items() if k != "record"}   # a row from before rows carried it
    done, upgraded = resume_check(layers / "q1.usda", out, bare)
    assert done and opened == ["q1.json"] and upgraded["record"] == rows["q1"]["record"]
    assert {k: v for k, v in upgraded.items() if k != "record"} == bare
    for broken in ({**rows["q1"], "record": {"inputs": "x"}}, {**rows["q1"], "record": None}):
        opened.clear()   # a malformed copy is not used: the JSON decides
        assert resume_check(layers / "q1.usda", out, broken)[0] and opened == ["q1.json"]

    meta = json.loads((out / "q2.json").read_text())   # the JSON rewritten (an input dropped): its stat changed
    meta["inputs"] = {k: v for k, v in meta["inputs"].items() if "stages" not in k}
    (out / "q2.json").write_text(json.dumps(meta))
    assert resume_check(layers / "q2.usda", out, rows["q2"]) == (False, None)
    summary = dispatch(layers, out, workers=1, progress=False)
    assert summary.rendered == ["q2"] and len(summary.skipped) == 4
