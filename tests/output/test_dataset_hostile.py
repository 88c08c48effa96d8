"""`dataset` does not trust render JSON: it writes only inside --out, reads only files of the render
folder, takes split and kind from fixed sets, refuses to mix resolutions and says when a folder
holds no renders (the record is the truth).

Renders here are synthetic (numpy images in job.py's JSON format, tests/support/renders.py), so no
Cycles run is needed."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from allo_usd.core.errors import AlloError
from allo_usd.output.dataset import assemble, read_manifest

from tests.support.renders import edit, fake_render

CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()", "dataset"]


def run(render_dirs, out: Path, **kw) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assemble(render_dirs, out, **kw)
    return [str(w.message) for w in caught]


def everything(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in root.rglob("*")}


def placed(out: Path) -> dict[str, str]:
    return {r["name"]: f"{r['split']}/{r['kind']}" for r in read_manifest(out / "manifest.csv")}


def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=300)


def one_error_line(r: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith("reading ")]  # progress bars
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    return lines[0]


def test_split_and_kind_come_from_fixed_sets(tmp_path):
    renders, out = tmp_path / "renders" / "r", tmp_path / "renders" / "ds"
    fake_render(renders, "ok")
    fake_render(renders, "escaped", split="../../escaped")
    fake_render(renders, "weird", variant="../../variant")
    fake_render(renders, "bad_asset", split="test", variant="anomaly", anomaly=40)
    edit(renders / "bad_asset.json", lambda m: m["scene"].update(anomaly={"asset": "../../x", "assetVariant": "b"}))
    fake_render(renders, "disguised", split="test", variant="normal", anomaly=40)        # its mask shows an anomaly
    fake_render(renders, "labelled", split="test", variant="normal")
    edit(renders / "labelled.json", lambda m: m["scene"].update(anomaly={"asset": "crate", "assetVariant": "b"}))
    before = everything(tmp_path) - everything(out)
    notes = run([renders], out)
    assert placed(out) == {"ok": "train/good"}
    assert {p for p in everything(tmp_path) if not p.startswith("renders/ds")} == before  # nothing outside --out
    refused = next(n for n in notes if "refused" in n)
    for name, why in (("escaped", "split '../../escaped'"), ("weird", "variant '../../variant'"),
                      ("bad_asset", "anomaly {'asset': '../../x'"), ("disguised", "a normal scene whose mask has 40 anomaly pixels"),
                      ("labelled", "a normal scene that records an anomaly")):
        assert f"{name}.json: {why}" in refused, refused


def test_source_files_must_be_regular_files_of_the_render_folder(tmp_path):
    renders, out, elsewhere = tmp_path / "r", tmp_path / "ds", tmp_path / "elsewhere"
    fake_render(renders, "ok")
    secret = fake_render(elsewhere, "secret").with_suffix(".png")
    fake_render(renders, "hostname")
    edit(renders / "hostname.json", lambda m: m["files"].update(rgb="/etc/hostname", mask="/etc/hostname"))
    fake_render(renders, "climber")
    edit(renders / "climber.json", lambda m: m["files"].update(rgb="../elsewhere/secret.png"))
    fake_render(renders, "linked")
    (renders / "linked.png").unlink()
    os.symlink(secret, renders / "linked.png")        # a symlink out of the render folder
    fake_render(renders, "folder")
    edit(renders / "folder.json", lambda m: m["files"].update(rgb="."))
    notes = run([renders], out)
    assert placed(out) == {"ok": "train/good"}
    outside = {os.stat(p).st_ino for p in ("/etc/hostname", secret) if os.path.exists(p)}
    assert not [p for p in out.rglob("*") if p.is_file() and p.stat().st_ino in outside]
    refused = next(n for n in notes if "refused" in n)
    assert "hostname.json: file name '/etc/hostname' is not a plain file name" in refused
    assert "climber.json: file name '../elsewhere/secret.png'" in refused
    assert "linked.json: file 'linked.png' resolves to" in refused and "folder.json" in refused


def test_nothing_is_written_outside_out(tmp_path):
    renders, out, victim = tmp_path / "r", tmp_path / "ds", tmp_path / "victim"
    fake_render(renders, "ok")
    with pytest.raises(AlloError, match="category '..' must be a plain directory name"):
        assemble([renders], out, category="..")
    victim.mkdir()
    os.symlink(victim, out / "allo")                   # a symlinked folder inside --out
    with pytest.raises(AlloError, match="outside the dataset"):
        assemble([renders], out)
    assert list(victim.iterdir()) == []
    (out / "allo").unlink()
    assemble([renders], out)
    # a manifest row naming a file outside --out: never removed, the run stops in one line
    (victim / "precious.png").write_bytes(b"mine")
    manifest = (out / "manifest.csv").read_text()
    (out / "manifest.csv").write_text(manifest.replace("allo/train/good/000000_ok.png", "../victim/precious.png"))
    edit(renders / "ok.json", lambda m: m.update(layer_sha256="changed"))  # re-rendered: its old files would go
    with pytest.raises(AlloError, match="outside the dataset"), pytest.warns(UserWarning, match="no manifest row"):
        assemble([renders], out)   # (the image that row no longer names is removed as unlisted)
    assert (victim / "precious.png").read_bytes() == b"mine"


@pytest.mark.process
def test_a_folder_without_renders_says_so(tmp_path):
    (tmp_path / "empty").mkdir()
    fake_render(tmp_path / "top" / "renders", "a")
    with pytest.raises(AlloError, match="no renders in"):
        assemble([tmp_path / "empty"], tmp_path / "ds")
    line = one_error_line(cli(tmp_path / "top", "--out", tmp_path / "ds"))
    assert "no renders in" in line and "OUT/renders" in line


@pytest.mark.process
def test_renders_of_different_resolutions_are_not_mixed(tmp_path):
    small, big, out = tmp_path / "small", tmp_path / "big", tmp_path / "ds"
    fake_render(small, "a")
    fake_render(small, "b")
    fake_render(big, "c", size=(160, 90))
    line = one_error_line(cli(small, big, "--out", out))
    assert "different resolutions" in line and "64x36: 2" in line and "160x90: 1 (e.g. c)" in line, line
    assert not (out / "manifest.csv").exists()
    assemble([small], out)                             # a dataset of 64x36 images ...
    with pytest.raises(AlloError, match="already in the dataset"):
        assemble([big], out)                           # ... takes no 160x90 ones later
    assert set(placed(out)) == {"a", "b"}
    fake_render(big, "d", size=(160, 90))
    edit(big / "d.json", lambda m: m.update(resolution=[64, 36]))   # a JSON that lies about its image
    with pytest.raises(AlloError, match="different resolutions"):
        assemble([small, big], tmp_path / "ds2")
    (big / "c.json").unlink()
    notes = run([small, big], tmp_path / "ds3")
    assert "d.json: its JSON says [64, 36], its image is 160x90" in next(n for n in notes if "refused" in n)


def test_anomalous_scenes_are_filed_by_their_mask(tmp_path):
    renders, out = tmp_path / "r", tmp_path / "ds"
    fake_render(renders, "normal", split="test")
    fake_render(renders, "seen", split="test", variant="anomaly", anomaly=50)
    fake_render(renders, "unseen", split="test", variant="anomaly", anomaly=0)   # left out, not filed as good
    fake_render(renders, "liar", split="test", variant="anomaly", anomaly=0)
    edit(renders / "liar.json", lambda m: m["class_pixels"].update(anomaly=50, background=m["class_pixels"]
                                                                    ["background"] - 50))  # its mask has none
    notes = run([renders], out)
    assert placed(out) == {"normal": "test/good", "seen": "test/anomaly"}
    assert "liar.json: its JSON counts 50 anomaly pixels, its mask 0" in next(n for n in notes if "refused" in n)
    assert "unseen" in next(n for n in notes if "anomaly not visible" in n)


def test_suspicious_renders_are_flagged(tmp_path):
    renders, out = tmp_path / "r", tmp_path / "ds"
    fake_render(renders, "fine")
    fake_render(renders, "nothing_seen", station=0)
    fake_render(renders, "black", black=True)
    notes = run([renders], out)
    assert set(placed(out)) == {"fine", "nothing_seen", "black"}   # kept: an umbra scene may be black
    dark = next(n for n in notes if n.startswith("SUSPICIOUS"))
    assert "station_and_bodies = 0" in dark and "nothing_seen" in dark and "fine" not in dark
    black = next(n for n in notes if "all-black" in n)
    assert "black" in black and "fine" not in black and "nothing_seen" not in black


@pytest.mark.process
def test_an_anomaly_asset_named_good_is_not_filed_as_normal(tmp_path):
    """MVTec loaders read any folder named `good` as normal images: a defect folder may not be one."""
    renders, out = tmp_path / "r", tmp_path / "ds"
    fake_render(renders, "normal")
    fake_render(renders, "odd", split="test", variant="anomaly", anomaly=50)
    edit(renders / "odd.json", lambda m: m["scene"]["anomaly"].update(asset="good"))
    line = one_error_line(cli(renders, "--out", out))
    assert "named 'good'" in line and "--defects merged" in line, line
    assert not (out / "allo").exists()   # refused before anything is placed
    merged = tmp_path / "merged"
    assert run([renders], merged, defects="merged") == []
    assert placed(merged) == {"normal": "train/good", "odd": "test/anomaly"}
    assert (merged / "allo/test/anomaly/000001_odd.png").is_file()
    line = one_error_line(cli(renders, "--out", tmp_path / "x", "--defects", "one-each"))
    assert "unknown defects layout 'one-each'" in line and "per-asset, merged" in line
