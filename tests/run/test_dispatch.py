"""The dispatcher: local pool and Dask, resume after SIGKILL, crashing workers, a full disk."""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import OpenEXR
import psutil
import pytest
from PIL import Image

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.run.dispatch import core_sets, dispatch, find_layers
from allo_usd.run.render_index import MANIFEST, WORKDIR, append_jsonl, clean_stale, is_done, is_verified, load_manifest
from allo_usd.core.errors import AlloError, DiskFullError, RenderFailedError
from allo_usd.core.files import temp_name_re

from tests.support import hooks
from tests.support.helpers import make_spec

pytestmark = pytest.mark.render

CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()", "render"]
BLENDER_NOISE = ("Saved:", "CUEW", "Fra:", "Time:", "cycles", "| ")


def make_layers(base, root: Path, n: int) -> list[Path]:
    return [write_scene_layer(make_spec(seed=10 + i, scene_id=f"s{i}", anomaly=i % 2 == 1, samples=2),
                              root / f"s{i}.usda", base) for i in range(n)]


def manifest_rows(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / MANIFEST).read_text().splitlines()]


def check_outputs(out: Path, layers: list[Path], size=(64, 36)) -> None:
    """Every scene has decodable outputs, one unique manifest row, and no temporaries are left."""
    w, h = size
    rows = manifest_rows(out)
    assert sorted(r["scene"] for r in rows) == sorted(p.stem for p in layers)  # unique, complete
    for layer in layers:
        s = layer.stem
        assert np.asarray(Image.open(out / f"{s}.png")).shape == (h, w, 3)
        assert set(np.unique(np.asarray(Image.open(out / f"{s}_mask.png")))) <= {0, 1, 2}
        with OpenEXR.File(str(out / f"{s}.exr"), separate_channels=True) as f:
            assert f.channels()["R"].pixels.shape == (h, w)
        assert json.loads((out / f"{s}.json").read_text())["files"]["rgb"] == f"{s}.png"
        assert is_verified(load_manifest(out)[s], layer, out) and is_done(layer, out, load_manifest(out))
        assert is_done(layer, out)  # what `allo-usd render LAYER` checks agrees
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
    rows = manifest_rows(out)
    assert len({r["worker"] for r in rows}) == 2  # both workers took scenes ...
    assert sum(r["full_build"] for r in rows) == 2  # ... and each built its Blender scene once, then patched it
    if len(os.sched_getaffinity(0)) >= 2:  # 2 workers x 1 thread: each pinned to a core of its own
        cores = {r["worker"]: tuple(r["cores"]) for r in rows}
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


def test_same_layers_same_bytes_across_processes_and_thread_counts(tiny_base, tmp_path):
    """Determinism does not hang on one process: 1 worker x 2 threads and 2 workers x 1 thread (each
    a fresh process) write byte-identical images, masks and EXRs for the same layers (denoised, so
    OIDN's threads are covered too)."""
    from dataclasses import replace

    specs = [make_spec(seed=40 + i, scene_id=f"d{i}", anomaly=i == 1, samples=8) for i in range(2)]
    layers = [write_scene_layer(replace(s, render=replace(s.render, denoise=True)), tmp_path / "layers" / f"{s.scene_id}.usda",
                                tiny_base) for s in specs]
    outs = {}
    for workers, threads in ((1, 2), (2, 1)):
        out = tmp_path / f"out_{workers}x{threads}"
        summary = dispatch(layers, out, workers=workers, threads=threads, progress=False)
        assert sorted(summary.rendered) == ["d0", "d1"] and not summary.failed
        outs[workers, threads] = {p.name: p.read_bytes() for p in out.iterdir()
                                  if p.suffix in (".png", ".exr")}
    assert len(outs[1, 2]) == 6 and outs[1, 2] == outs[2, 1]


# ---------------------------------------------------------------- which layers

@pytest.fixture(scope="module")
def authored_plan(tmp_path_factory):
    """A tiny authored plan over the committed base stage: 2 days x 2 poses (one train, one test) at
    64x36, laid out as `allo-usd author` writes it (scenes/SPLIT/KIND/, sky/, poses/, plan.toml)."""
    from allo_usd.run.author import author_plan
    from allo_usd.core.paths import BASE_STAGE
    from allo_usd.plan.model import Anomalies, Dates, Plan, Poses, Quality

    plan = Plan(name="dispatch", dates=Dates(days=2), poses=Poses(train=[1], test=[41]),
                anomalies=Anomalies(assets=[]), quality=Quality(resolution=(64, 36), samples=2),
                base_stage=str(BASE_STAGE))
    root = tmp_path_factory.mktemp("plan")
    layers = author_plan(plan, root, progress=False)
    assert len(layers) == 4
    return root, layers


def test_find_layers_recurses_into_an_authored_plan(authored_plan, tmp_path):
    root, layers = authored_plan
    assert find_layers(root) == sorted(layers)  # scenes/SPLIT/KIND only: not sky/, poses/
    assert {p.parent.parent.name for p in find_layers(root)} == {"train", "test"}
    assert find_layers(root / "scenes" / "test") == sorted(p for p in layers if "/test/" in str(p))
    nested = tmp_path / "a" / "b"  # any directory is searched recursively, hidden ones skipped
    nested.mkdir(parents=True)
    (nested / "x.usda").write_text(layers[0].read_text())
    (tmp_path / ".hidden").mkdir()
    (tmp_path / ".hidden" / "y.usda").write_text(layers[1].read_text())
    assert find_layers(tmp_path) == [nested / "x.usda"]
    for empty in (root / "sky", root / "poses"):
        with pytest.raises(AlloError, match=r"no scene layers under .*sky/, poses/ and stages/ .* not scenes"):
            find_layers(empty)
    with pytest.raises(AlloError, match="no layers to render"):
        find_layers([])


def test_cli_renders_an_authored_plan_quietly(authored_plan, tmp_path):
    """`allo-usd render PLAN_DIR` renders every scene of the plan; Blender's prints go to the
    workers' logs, so the terminal shows only our summary. An empty directory is an error."""
    root, layers = authored_plan
    out = tmp_path / "out"
    r = subprocess.run(CLI + [str(root), "--out", str(out), "--workers", "2"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "4 rendered" in r.stdout and "0 failed" in r.stdout
    terminal = r.stdout + r.stderr
    assert not [n for n in BLENDER_NOISE if n in terminal], terminal
    check_outputs(out, layers)
    logs = sorted((out / "logs").glob("worker-*.log"))
    assert [p.name for p in logs] == ["worker-0.log", "worker-1.log"]
    assert sum(p.read_text().count("Saved:") for p in logs) == 4  # Blender's own line per render, in the logs

    (tmp_path / "empty" / "sky").mkdir(parents=True)
    r = subprocess.run(CLI + [str(tmp_path / "empty"), "--out", str(tmp_path / "out2")], capture_output=True,
                       text=True)
    assert r.returncode == 2 and "no scene layers under" in r.stderr, r.stderr


def test_cli_single_layer_keeps_blender_output_in_its_log(tiny_base, tmp_path):
    [layer] = make_layers(tiny_base, tmp_path / "layers", 1)
    out = tmp_path / "out"
    r = subprocess.run(CLI + [str(layer), "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"{layer} -> {out}: ") and not [n for n in BLENDER_NOISE if n in r.stdout + r.stderr]
    assert "Saved:" in (out / "logs" / "render.log").read_text()
    assert np.asarray(Image.open(out / "s0.png")).shape == (36, 64, 3)


# ---------------------------------------------------------------- Dask

def test_dask_local_cluster_renders(tiny_base, tmp_path):
    from distributed import Client, LocalCluster

    layers = make_layers(tiny_base, tmp_path / "layers", 3)
    out = tmp_path / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        summary = dispatch(layers, out, scheduler=client, threads=1, progress=False)
    assert sorted(summary.rendered) == ["s0", "s1", "s2"] and not summary.failed
    check_outputs(out, layers)


def test_dask_worker_with_two_threads_renders_one_scene_at_a_time(tiny_base, tmp_path):
    """bpy is not thread-safe: a Dask worker with 2 threads takes the per-process lock in turn
    (without it, two renders in one process crash it) and keeps one warm Blender scene."""
    from distributed import Client, LocalCluster

    layers = make_layers(tiny_base, tmp_path / "layers", 4)
    out = tmp_path / "out"
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        summary = dispatch(layers, out, scheduler=client, threads=1, retries=0, progress=False)
    assert sorted(summary.rendered) == ["s0", "s1", "s2", "s3"] and not summary.failed
    check_outputs(out, layers)
    rows = manifest_rows(out)
    assert len({r["worker"] for r in rows}) == 1 and all(r["attempts"] == 1 for r in rows)
    assert sum(r["full_build"] for r in rows) == 1  # one Session per worker process, warm after its first scene


def test_dask_by_address_renders_an_authored_plan_from_relative_paths(authored_plan, tmp_path, monkeypatch):
    """Connect by the scheduler's address; pass the plan directory and the output as paths
    relative to a working directory the workers do not share (they started elsewhere)."""
    from distributed import Client, LocalCluster

    root, layers = authored_plan
    started_in = tmp_path / "workers_cwd"
    started_in.mkdir()
    monkeypatch.chdir(started_in)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        monkeypatch.chdir(root.parent)
        summary = dispatch(root.name, Path(tmp_path.name) / "renders", scheduler=cluster.scheduler_address,
                           threads=1, progress=False)
        with Client(cluster) as client:  # the run put the scheduler's allowed-failures back
            assert client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.allowed_failures) == 3
    assert sorted(summary.rendered) == sorted(p.stem for p in layers) and not summary.failed
    out = tmp_path / "renders"
    check_outputs(out, layers)
    assert not (started_in / root.name).exists() and not list(started_in.iterdir())
    assert {r["layer"] for r in manifest_rows(out)} == {str(p.resolve()) for p in layers}


def test_dask_crash_costs_one_worker_death_per_attempt(tiny_base, tmp_path):
    """Dask would retry a task whose worker died `allowed-failures` (3) times on its own; the run
    makes each of its attempts cost exactly one worker death, so `retries` bounds the deaths.

    s1 crashes only once s0 and s2 are in the manifest: a worker's death also fails the tasks
    queued on it, so the outcome would otherwise hang on which worker Dask gave which scene."""
    from distributed import Client, LocalCluster

    layers = make_layers(tiny_base, tmp_path / "layers", 3)
    out = tmp_path / "out"
    crash = functools.partial(hooks.crash_after, {"s1"}, out, {"s0", "s2"})
    with LocalCluster(n_workers=3, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        summary = dispatch(layers, out, scheduler=client, threads=1, retries=1, progress=False, before_render=crash)
        events = [msg for _, msg in client.get_events("all")  # one event per worker removal
                  if isinstance(msg, dict) and msg.get("action") == "remove-worker" and not msg.get("expected")]
        assert client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.allowed_failures) == 3
    assert sorted(summary.rendered) == ["s0", "s2"]
    [row] = summary.failed
    assert row["scene"] == "s1" and row["kind"] == "crash" and row["attempts"] == 2
    assert "KilledWorker" in row["reason"] and len(row["reasons"]) == 2
    assert len(events) == 2, events  # 2 attempts, 2 worker deaths (Dask's own retries would make it 4 each)
    assert all(any("allo-render-s1-" in str(k) for k in e.get("processing-tasks", ())) for e in events), events
    check_outputs(out, [p for p in layers if p.stem != "s1"])


# ---------------------------------------------------------------- crash safety

def _writer_processes(pid: int) -> list:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _check_nothing_corrupt(out: Path, ref: Path, layers: list[Path]) -> set[str]:
    """After a kill: every manifest row is verified, every file under a final name is complete
    (byte-identical to the uninterrupted run's, or a parsable JSON), and anything else is a
    recognisable temporary. Returns the finished scenes."""
    stems = {p.stem: p for p in layers}
    finished = set()
    for row in manifest_rows(out) if (out / MANIFEST).is_file() else []:
        assert is_verified(row, stems[row["scene"]], out), row["scene"]
        finished.add(row["scene"])
    for p in out.iterdir():
        if p.name in (MANIFEST, "failed.jsonl", ".allo-dispatch.lock", "logs", WORKDIR):
            continue
        if p.name.startswith("."):
            assert temp_name_re().match(p.name), p.name  # a writer's temporary, removed by the next run
        elif p.suffix == ".json":
            assert json.loads(p.read_text())["files"]
        else:
            assert p.read_bytes() == (ref / p.name).read_bytes(), p.name  # same layer -> same bytes
    return finished


KILLABLE = """
import functools, sys
sys.path.insert(0, sys.argv[3])
from tests.support import hooks
from allo_usd.run.dispatch import dispatch
pause = functools.partial(hooks.pause_at, sys.argv[4], sys.argv[5].split(","), sys.argv[6].split(","))
summary = dispatch(sys.argv[1], sys.argv[2], workers=2, progress=False, before_render=pause)
print("interrupted" if summary.interrupted else "finished", flush=True)
"""


# (signal, scenes that stop before rendering, scenes that stop half-way through their EXR, finished after)
ROUNDS = [
    (signal.SIGKILL, ["s0", "s1"], [], set()),  # start-up: both workers about to render their first scene
    (signal.SIGINT, ["s2"], ["s1"], {"s0"}),  # Ctrl-C: s0 done, s1 mid-write, s2 about to render
    (signal.SIGKILL, ["s5"], ["s4"], {"s0", "s1", "s2", "s3"}),  # s4 mid-write (its PNG whole), s5 about to render
]


def test_kills_at_well_defined_points_then_resume(tiny_base, tmp_path):
    """Stop a run (parent and workers) three times over the same output directory, each time once
    both workers have reached a known point (the before_render hook stops them there and leaves a
    marker file), with SIGKILL or SIGINT; then resume: no missing, duplicated or corrupt file;
    finished scenes are never rendered again; the rest render once, byte-identical to an
    uninterrupted run. Which worker took which scene does not matter: with one worker stopped for
    good, the other goes on until it reaches its own stop."""
    layers = make_layers(tiny_base, tmp_path / "layers", 6)
    names = sorted(p.stem for p in layers)
    ref = tmp_path / "ref"
    assert sorted(dispatch(layers, ref, workers=2, progress=False).rendered) == names
    check_outputs(ref, layers)

    out = tmp_path / "out"
    finished: set[str] = set()
    for i, (sig, before, mid_write, expected) in enumerate(ROUNDS):
        markers = tmp_path / f"markers{i}"
        markers.mkdir()
        kept = {s: ((out / f"{s}.png").stat().st_mtime_ns, load_manifest(out)[s]) for s in finished}
        proc = subprocess.Popen([sys.executable, "-c", KILLABLE, str(tmp_path / "layers"), str(out),
                                 str(Path(hooks.__file__).resolve().parents[2]), str(markers), ",".join(before), ",".join(mid_write)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        stops = [markers / f"{s}.before" for s in before] + [markers / f"{s}.mid_write" for s in mid_write]
        deadline = time.monotonic() + 300
        while not all(p.is_file() for p in stops):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        children = _writer_processes(proc.pid)
        assert len(children) >= 2
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=120)
        gone, alive = psutil.wait_procs(children, timeout=30)  # workers die with their parent
        assert not alive
        if sig == signal.SIGINT:  # a clean stop: summary, exit 0, no temporaries left
            assert proc.returncode == 0 and stdout.strip() == "interrupted", (stdout, stderr)
            assert not [p.name for p in out.iterdir() if p.name.startswith(".") and p.name != ".allo-dispatch.lock"]
        now = _check_nothing_corrupt(out, ref, layers) if out.is_dir() else set()
        assert now == expected and now >= finished  # finished scenes stay finished ...
        assert {s: ((out / f"{s}.png").stat().st_mtime_ns, load_manifest(out)[s]) for s in finished} == kept
        for s in mid_write:  # the PNG written before the stop is whole; the EXR never got its name
            assert s not in now and (out / f"{s}.png").is_file() and not (out / f"{s}.exr").exists()
        finished = now  # ... and were not rendered again

    summary = dispatch(tmp_path / "layers", out, workers=2, progress=False)
    assert sorted(summary.skipped) == sorted(finished)
    assert sorted(summary.rendered) == sorted(set(names) - finished)
    check_outputs(out, layers)
    for s in names:
        for suffix in (".png", ".exr", "_mask.png"):
            assert (out / f"{s}{suffix}").read_bytes() == (ref / f"{s}{suffix}").read_bytes()


def test_crashing_worker_is_retried_then_recorded(tiny_base, tmp_path):
    """A worker that dies rendering s1 is replaced and s1 alone retried (a local worker holds one
    task at a time, so whichever worker took it, no other scene pays)."""
    layers = make_layers(tiny_base, tmp_path / "layers", 3)
    out = tmp_path / "out"
    summary = dispatch(layers, out, workers=2, progress=False, before_render=functools.partial(hooks.crash_on, {"s1"}))
    assert sorted(summary.rendered) == ["s0", "s2"]
    [row] = [json.loads(line) for line in (out / "failed.jsonl").read_text().splitlines()]
    assert row["scene"] == "s1" and row["kind"] == "crash" and row["attempts"] == 3
    assert "SIGSEGV" in row["reason"] and len(row["reasons"]) == 3
    assert "logs/worker-" in row["reason"]  # where the dead worker's own output went
    assert not (out / "s1.png").exists()

    summary = dispatch(layers, out, workers=2, progress=False)  # the next run retries the failed scene only
    assert summary.rendered == ["s1"] and not (out / "failed.jsonl").exists()
    check_outputs(out, layers)


WRITER = """
import sys
from pathlib import Path
from allo_usd.run.worker import render_workdir
from allo_usd.core.files import atomic_path
out = Path(sys.argv[1])
(render_workdir(out) / "render.exr").write_bytes(b"Blender's file")
with atomic_path(out / sys.argv[2]) as tmp:
    tmp.write_bytes(b"complete")
    print("writing", flush=True)
    sys.stdin.readline()
"""


def test_cleanup_after_a_crash_spares_live_writers(tmp_path):
    """When a worker dies, only its own temporaries go: a live worker's half-written output (and its
    Blender render directory) stay, and its rename then succeeds."""
    out = tmp_path / "out"
    out.mkdir()
    writers = [subprocess.Popen([sys.executable, "-c", WRITER, str(out), f"s{i}.png"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True) for i in range(2)]
    dead, live = writers
    for w in writers:
        assert w.stdout.readline().strip() == "writing"
    dead.kill()
    dead.wait()
    temps = sorted(p.name for p in out.iterdir() if p.name.startswith("."))
    assert [temp_name_re(w.pid).match(n) is not None for w in writers for n in temps].count(True) == 2

    assert clean_stale(out, pid=dead.pid) == 1
    assert not (out / WORKDIR / str(dead.pid)).exists() and (out / WORKDIR / str(live.pid) / "render.exr").is_file()
    assert [n for n in os.listdir(out) if temp_name_re(live.pid).match(n)]
    live.communicate("go\n")
    assert live.returncode == 0 and (out / "s1.png").read_bytes() == b"complete"
    assert not (out / "s0.png").exists()
    assert clean_stale(out) == 0 and not (out / WORKDIR).exists()


def test_manifest_appends_never_leave_a_torn_line(tmp_path):
    path = tmp_path / MANIFEST
    path.write_text('{"scene": "a"}\n{"scene": "b", "fil')  # a line torn by a power cut
    append_jsonl(path, {"scene": "c"})
    assert [r["scene"] for r in load_manifest(tmp_path).values()] == ["a", "c"]
    assert path.read_text().endswith('"fil\n{"scene": "c"}\n')


# ---------------------------------------------------------------- full disk

def test_full_disk_stops_cleanly(tiny_base, tmp_path):
    layers = make_layers(tiny_base, tmp_path / "layers", 4)
    out = tmp_path / "out"
    with pytest.raises(DiskFullError, match="no space left"):
        dispatch(layers, out, workers=1, progress=False, before_render=functools.partial(hooks.full_disk_on, {"s1"}))
    done = load_manifest(out)
    assert set(done) == {"s0"}  # stopped at s1: s2 and s3 never started
    assert not (out / "s1.exr").exists() and not (out / "s2.png").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".s")]  # no temporaries left
    [row] = [json.loads(line) for line in (out / "failed.jsonl").read_text().splitlines()]
    assert row["kind"] == "disk_full"

    summary = dispatch(layers, out, workers=2, progress=False)
    assert summary.skipped == ["s0"] and sorted(summary.rendered) == ["s1", "s2", "s3"]
    check_outputs(out, layers)


def _fill(path: Path, leave: int) -> Path:
    """A ballast file that leaves `leave` bytes free on the file system holding `path`."""
    ballast = path / "ballast"
    with open(ballast, "wb") as f:
        f.write(b"\0" * (os.statvfs(path).f_bfree * os.statvfs(path).f_frsize - leave))
    return ballast


def test_real_full_disk_stops_the_run_at_blenders_write(tiny_base, tmp_path, small_tmpfs):
    """On a real full device Blender's own EXR write is cut short (Blender still says "Saved" and
    FINISHED); the run must stop with exit 2 and a clear error instead of recording bad layers,
    leave nothing corrupt, and finish everything once there is space again."""
    layers = make_layers(tiny_base, tmp_path / "layers", 3)
    out = small_tmpfs / "out"
    out.mkdir()
    ballast = _fill(small_tmpfs, leave=8192)  # Blender's 64x36 render file is ~8.4 kB
    r = subprocess.run(CLI + [str(tmp_path / "layers"), "--out", str(out), "--workers", "1"], capture_output=True,
                       text=True)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "error: no space left on the device" in r.stderr and "Blender" in r.stderr, r.stderr
    assert "failed" not in r.stdout  # stopped: no summary of bad layers
    failed = out / "failed.jsonl"
    assert not failed.is_file() or all(json.loads(x)["kind"] == "disk_full" for x in failed.read_text().splitlines())
    assert not [p.name for p in out.iterdir() if p.suffix in (".png", ".exr", ".json")]  # nothing half-made
    assert not [p.name for p in out.iterdir() if p.name.startswith(".") and p.name != ".allo-dispatch.lock"]

    ballast.unlink()
    r = subprocess.run(CLI + [str(tmp_path / "layers"), "--out", str(out), "--workers", "1"], capture_output=True,
                       text=True)
    assert r.returncode == 0 and "3 rendered" in r.stdout, r.stderr
    check_outputs(out, layers)


def test_a_cut_short_render_file_is_retried_unless_the_disk_is_full(tmp_path, small_tmpfs):
    """What Blender leaves on a failed write: with room on the device it is a retriable render
    failure (not the layer's fault), on a full device it is DiskFullError."""
    from allo_usd.blender.render import read_multilayer_exr, unreadable_render_file, check_render_file
    from allo_usd.output.writers import write_exr

    good = write_exr(tmp_path / "good.exr", {"R": np.ones((36, 64), np.float32)}, half=False)
    for d in (tmp_path / "roomy", small_tmpfs / "full"):
        d.mkdir()
        cut = d / "render.exr"
        cut.write_bytes(good.read_bytes()[:300])
        if d.parent == small_tmpfs:
            _fill(small_tmpfs, leave=0)
        with pytest.raises(Exception) as err:
            read_multilayer_exr(cut)
        problem = unreadable_render_file(cut, "s.usda", f"cannot be read ({err.value})")
        expected = DiskFullError if d.parent == small_tmpfs else RenderFailedError
        assert type(problem) is expected
        if expected is DiskFullError:
            with pytest.raises(DiskFullError, match="Blender does not report a failed write"):
                check_render_file(cut, True, "s.usda")
        else:
            check_render_file(cut, True, "s.usda")  # plenty of room: the file may be read
            with pytest.raises(RenderFailedError, match="retries it"):
                check_render_file(d / "missing.exr", True, "s.usda")


def test_cli_renders_a_directory_and_rejects_plans_cleanly(tiny_base, tmp_path):
    layers = make_layers(tiny_base, tmp_path / "layers", 2)
    out = tmp_path / "out"
    r = subprocess.run(CLI + [str(tmp_path / "layers"), "--out", str(out), "--workers", "2"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "2 rendered" in r.stdout
    check_outputs(out, layers)
    r = subprocess.run(CLI + [str(tmp_path / "nothing.txt"), "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and "error:" in r.stderr
