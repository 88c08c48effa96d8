"""The dispatcher: local pool and Dask, resume after SIGKILL, crashing workers, a full disk."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from PIL import Image

from allo_usd.author.scene import write_scene_layer
from allo_usd.dispatch import MANIFEST, core_sets, dispatch, is_verified, load_manifest
from allo_usd.errors import DiskFullError

from conftest import make_spec

pytestmark = pytest.mark.render


def make_layers(base, root: Path, n: int) -> list[Path]:
    return [write_scene_layer(make_spec(seed=10 + i, scene_id=f"s{i}", anomaly=i % 2 == 1, samples=2),
                              root / f"s{i}.usda", base) for i in range(n)]


def manifest_rows(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / MANIFEST).read_text().splitlines()]


def check_outputs(out: Path, layers: list[Path]) -> None:
    """Every scene has decodable outputs, one unique manifest row, and no temporaries are left."""
    rows = manifest_rows(out)
    assert sorted(r["scene"] for r in rows) == sorted(p.stem for p in layers)  # unique, complete
    for layer in layers:
        s = layer.stem
        assert np.asarray(Image.open(out / f"{s}.png")).shape == (36, 64, 3)
        assert set(np.unique(np.asarray(Image.open(out / f"{s}_mask.png")))) <= {0, 1, 2}
        with OpenEXR.File(str(out / f"{s}.exr"), separate_channels=True) as f:
            assert f.channels()["R"].pixels.shape == (36, 64)
        assert json.loads((out / f"{s}.json").read_text())["files"]["rgb"] == f"{s}.png"
        assert is_verified(load_manifest(out)[s], layer, out)
    assert not [p.name for p in out.iterdir() if p.name.startswith(".") and p.name != ".allo-dispatch.lock"]


def test_core_sets_pin_only_what_fits():
    assert core_sets(2, 1, [0, 1]) == [(0,), (1,)]
    assert core_sets(2, 2, [3, 5, 7, 9]) == [(3, 5), (7, 9)]
    assert core_sets(1, 2, [0, 1]) == [(0, 1)]
    assert core_sets(2, 2, [0, 1]) == [None, None]  # oversubscribed: leave placement to the OS
    assert core_sets(3, 1, [0, 1]) == [None, None, None]


def test_local_pool_renders_resumes_and_repairs(tiny_base, tmp_path):
    layers = make_layers(tiny_base, tmp_path / "layers", 4)
    (tmp_path / "layers" / "shared.usda").write_text('#usda 1.0\n(\n    doc = "a shared sublayer"\n)\n')
    out = tmp_path / "out"
    summary = dispatch(tmp_path / "layers", out, workers=2, progress=False)
    assert sorted(summary.rendered) == ["s0", "s1", "s2", "s3"] and not summary.failed
    check_outputs(out, layers)
    assert {r["worker"] for r in manifest_rows(out)}.__len__() == 2  # both workers took scenes
    if len(os.sched_getaffinity(0)) >= 2:  # 2 workers x 1 thread: each pinned to a core of its own
        cores = {r["worker"]: tuple(r["cores"]) for r in manifest_rows(out)}
        assert sorted(cores.values()) == [(c,) for c in sorted(os.sched_getaffinity(0))[:2]]

    # corrupt one output, delete another, leave a stale temporary: only those two scenes re-render
    (out / "s1.exr").write_bytes(b"garbage")
    (out / "s2_mask.png").unlink()
    (out / ".s3.png.abcd1234.png").write_bytes(b"half")
    before = (out / "s0.png").stat().st_mtime_ns
    summary = dispatch(tmp_path / "layers", out, workers=2, progress=False)
    assert sorted(summary.rendered) == ["s1", "s2"] and sorted(summary.skipped) == ["s0", "s3"]
    assert (out / "s0.png").stat().st_mtime_ns == before
    check_outputs(out, layers)


def test_dask_local_cluster_renders(tiny_base, tmp_path):
    from distributed import Client, LocalCluster

    layers = make_layers(tiny_base, tmp_path / "layers", 3)
    out = tmp_path / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        summary = dispatch(layers, out, scheduler=client, threads=1, progress=False)
    assert sorted(summary.rendered) == ["s0", "s1", "s2"] and not summary.failed
    check_outputs(out, layers)


def test_sigkill_mid_run_then_resume(tiny_base, tmp_path):
    layers = make_layers(tiny_base, tmp_path / "layers", 6)
    out = tmp_path / "out"
    code = ("import sys; from allo_usd.dispatch import dispatch; "
            "dispatch(sys.argv[1], sys.argv[2], workers=2, progress=False)")
    env = {**os.environ, "ALLO_TEST_DELAY": "0.6"}
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "layers"), str(out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not (out / MANIFEST).is_file():
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    time.sleep(1.5)  # workers die with their parent (PR_SET_PDEATHSIG)
    finished = {r["scene"] for r in manifest_rows(out)}
    assert 1 <= len(finished) < 6
    mtimes = {s: (out / f"{s}.png").stat().st_mtime_ns for s in finished}

    summary = dispatch(tmp_path / "layers", out, workers=2, progress=False)
    assert sorted(summary.skipped) == sorted(finished)
    assert sorted(summary.rendered) == sorted({p.stem for p in layers} - finished)
    assert {s: (out / f"{s}.png").stat().st_mtime_ns for s in finished} == mtimes
    check_outputs(out, layers)


def test_crashing_worker_is_retried_then_recorded(tiny_base, tmp_path, monkeypatch):
    layers = make_layers(tiny_base, tmp_path / "layers", 3)
    out = tmp_path / "out"
    monkeypatch.setenv("ALLO_TEST_CRASH_SCENE", "s1")
    summary = dispatch(layers, out, workers=2, progress=False)
    assert sorted(summary.rendered) == ["s0", "s2"]
    [row] = [json.loads(line) for line in (out / "failed.jsonl").read_text().splitlines()]
    assert row["scene"] == "s1" and row["kind"] == "crash" and row["attempts"] == 3
    assert "SIGSEGV" in row["reason"] and len(row["reasons"]) == 3
    assert not (out / "s1.png").exists()

    monkeypatch.delenv("ALLO_TEST_CRASH_SCENE")  # the next run retries the failed scene only
    summary = dispatch(layers, out, workers=2, progress=False)
    assert summary.rendered == ["s1"] and not (out / "failed.jsonl").exists()
    check_outputs(out, layers)


def test_full_disk_stops_cleanly(tiny_base, tmp_path, monkeypatch):
    layers = make_layers(tiny_base, tmp_path / "layers", 4)
    out = tmp_path / "out"
    monkeypatch.setenv("ALLO_TEST_ENOSPC_SCENE", "s1")
    with pytest.raises(DiskFullError, match="no space left"):
        dispatch(layers, out, workers=1, progress=False)
    done = load_manifest(out)
    assert set(done) == {"s0"}  # stopped at s1: s2 and s3 never started
    assert not (out / "s1.exr").exists() and not (out / "s2.png").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".s")]  # no temporaries left
    [row] = [json.loads(line) for line in (out / "failed.jsonl").read_text().splitlines()]
    assert row["kind"] == "disk_full"

    monkeypatch.delenv("ALLO_TEST_ENOSPC_SCENE")
    summary = dispatch(layers, out, workers=2, progress=False)
    assert summary.skipped == ["s0"] and sorted(summary.rendered) == ["s1", "s2", "s3"]
    check_outputs(out, layers)


def test_cli_renders_a_directory_and_rejects_plans_cleanly(tiny_base, tmp_path):
    layers = make_layers(tiny_base, tmp_path / "layers", 2)
    out = tmp_path / "out"
    cli = [sys.executable, "-c", "from allo_usd.cli import main; main()", "render"]
    r = subprocess.run(cli + [str(tmp_path / "layers"), "--out", str(out), "--workers", "2"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "2 rendered" in r.stdout
    check_outputs(out, layers)
    r = subprocess.run(cli + [str(tmp_path / "nothing.txt"), "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and "error:" in r.stderr
