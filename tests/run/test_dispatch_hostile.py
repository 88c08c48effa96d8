"""The dispatcher against hostile inputs: FIFOs, devices and huge files named like layers, a
scene that never finishes (the per-scene time limit), binary .usdc scene layers, the output lock
of a single-layer render, and the workers' temporary folders."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from allo_usd.core.files import RunLock
from allo_usd.run.dispatch import LOCK, dispatch, find_layers, time_limit, TIMEOUT_BASE_S
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support import hooks
from tests.support.helpers import make_spec

ROOT = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()", "render"]


def make_layers(base, root: Path, n: int) -> list[Path]:
    return [write_scene_layer(make_spec(seed=20 + i, scene_id=f"h{i}", samples=2), root / f"h{i}.usda", base)
            for i in range(n)]


def _scan_in_child(root: Path, tmp_path: Path) -> dict:
    """find_layers(root) in a child process with a deadline: a scan that blocks (a FIFO) or reads a
    whole device fails the test instead of hanging it. Returns the layers found and the warnings."""
    code = textwrap.dedent(f"""
        import json, resource, warnings
        from allo_usd.run.dispatch import find_layers
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            layers = find_layers({str(root)!r})
        # VmHWM: this process's own peak (ru_maxrss also counts the peak of the pytest process it was
        # started from, which Linux carries over exec)
        hwm = [line for line in open("/proc/self/status") if line.startswith("VmHWM:")]
        peak = int(hwm[0].split()[1]) if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print(json.dumps({{"layers": [p.name for p in layers], "warnings": [str(x.message) for x in w],
                          "maxrss_kb": peak}}))
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.splitlines()[-1])


@pytest.mark.process
def test_scan_never_opens_fifos_or_devices_and_reads_a_bounded_prefix(tiny_base, tmp_path):
    root = tmp_path / "layers"
    make_layers(tiny_base, root, 1)
    os.mkfifo(root / "p.usda")                               # would block an open() for reading
    (root / "z.usda").symlink_to("/dev/zero")                 # would fill memory with read_bytes()
    with open(root / "sparse.usda", "wb") as f:               # a 2 GB sparse shared layer: 16 KiB are enough
        f.write(b'#usda 1.0\n(\n    doc = "shared"\n)\n')
        f.truncate(2 << 30)
    try:
        found = _scan_in_child(root, tmp_path)
    except subprocess.TimeoutExpired:
        pytest.fail("the layer scan blocked (a FIFO named p.usda, or /dev/zero read whole)")
    # kept unopened, for dispatch to record as failed layers (tests/system/test_adversarial.py renders that)
    assert found["layers"] == ["h0.usda", "p.usda", "sparse.usda", "z.usda"] and not found["warnings"]
    assert found["maxrss_kb"] < 1_000_000  # not a 2 GB read


@pytest.mark.process
def test_a_fifo_or_device_given_as_the_layer_is_an_error(tmp_path):
    from allo_usd.core.errors import AlloError

    os.mkfifo(tmp_path / "p.usda")
    with pytest.raises(AlloError, match="not a regular file"):
        find_layers([tmp_path / "p.usda"])
    r = subprocess.run(CLI + [str(tmp_path / "p.usda"), "--out", str(tmp_path / "out")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "not a regular file" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_default_time_limit_grows_with_pixels_and_samples(tiny_base, tmp_path):
    small = write_scene_layer(make_spec(scene_id="a", resolution=(64, 36), samples=2), tmp_path / "a.usda", tiny_base)
    big = write_scene_layer(make_spec(scene_id="b", resolution=(640, 360), samples=64), tmp_path / "b.usda",
                            tiny_base)
    assert TIMEOUT_BASE_S <= time_limit(small) < time_limit(big)
    assert time_limit(big, timeout=7) == 7.0


def note_tmpdir(markers: Path, scene: str) -> None:
    """A before_render hook: record where this worker's Blender keeps its session folder."""
    import bpy

    (Path(markers) / f"{scene}.tmpdir").write_text(bpy.app.tempdir)


def hang_or_note(markers: Path, hang, scene: str) -> None:
    note_tmpdir(markers, scene)
    hooks.pause_at(markers, hang, (), scene)


@pytest.mark.render
def test_a_scene_past_its_time_limit_is_killed_retried_then_failed(tiny_base, tmp_path):
    make_layers(tiny_base, tmp_path / "layers", 3)
    out, markers = tmp_path / "out", tmp_path / "markers"
    markers.mkdir()
    summary = dispatch(tmp_path / "layers", out, workers=2, retries=1, progress=False, timeout=25,
                       before_render=functools.partial(hang_or_note, markers, {"h1"}))
    assert sorted(summary.rendered) == ["h0", "h2"]
    rows = [json.loads(x) for x in (out / "failed.jsonl").read_text().splitlines()]
    assert [(r["scene"], r["kind"], r["attempts"]) for r in rows] == [("h1", "timeout", 2)]
    assert "time limit of 25 s" in rows[0]["reason"] and len(rows[0]["reasons"]) == 2
    # the hung workers were killed: no process is left holding the scene
    for pid_file in markers.glob("h1.before"):
        with pytest.raises(ProcessLookupError):
            os.kill(int(pid_file.read_text()), 0)
    # each worker's Blender kept its session folder under OUT/.allo-tmp/PID, removed with the run
    tmpdirs = [Path(p.read_text()) for p in markers.glob("*.tmpdir")]
    assert tmpdirs and all(out / ".allo-tmp" in d.parents for d in tmpdirs), tmpdirs
    assert not any(d.exists() for d in tmpdirs)


@pytest.mark.render
def test_binary_usdc_scene_layers_are_found_and_rendered(tiny_base, tmp_path):
    from pxr import Sdf

    root = tmp_path / "layers"
    text = make_layers(tiny_base, root, 2)
    crate = root / "h1.usdc"
    assert Sdf.Layer.FindOrOpen(str(text[1])).Export(str(crate))
    text[1].unlink()
    shared = root / "shared.usdc"  # a binary shared sublayer (no sceneId) is not a scene
    assert Sdf.Layer.CreateAnonymous().Export(str(shared))
    assert [p.name for p in find_layers(root)] == ["h0.usda", "h1.usdc"]
    r = subprocess.run(CLI + [str(crate), "--out", str(tmp_path / "one")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "one" / "h1.png").is_file()


@pytest.mark.render
def test_single_layer_render_takes_the_output_lock(tiny_base, tmp_path):
    layer = make_layers(tiny_base, tmp_path / "layers", 1)[0]
    out = tmp_path / "out"
    out.mkdir()
    with RunLock(out, LOCK, "render"):
        r = subprocess.run(CLI + [str(layer), "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and "another render run is writing" in r.stderr, (r.stdout, r.stderr)
    assert not (out / "h0.png").exists()


FILL_BEFORE_EXR = textwrap.dedent("""
    import os
    from allo_usd.run import job

    real = job.write_rgb_exr

    def fill_then_write(path, *args, **kwargs):
        '''Fill the device just before the EXR is written: OpenEXR itself then meets ENOSPC.'''
        st = os.statvfs(os.path.dirname(path))
        with open(os.path.join(os.path.dirname(path), "ballast"), "wb") as f:
            try:
                f.write(bytes(st.f_bavail * st.f_frsize))
            except OSError:
                pass
        return real(path, *args, **kwargs)

    job.write_rgb_exr = fill_then_write
    from allo_usd.cli import main
    main()
""")


@pytest.mark.render
def test_single_layer_full_disk_at_openexrs_write_is_one_line_exit_2(tiny_base, tmp_path, small_tmpfs):
    layer = make_layers(tiny_base, tmp_path / "layers", 1)[0]
    out = small_tmpfs / "out"
    r = subprocess.run([sys.executable, "-c", FILL_BEFORE_EXR, "render", str(layer), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 2, (r.stdout, r.stderr[-3000:])
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: no space left on the device holding"), r.stderr
    assert "free space" in lines[0]
    assert not [p.name for p in out.iterdir() if p.name.startswith(".") and p.name != LOCK]  # no temporary left


@pytest.mark.render
def test_dask_scene_past_its_time_limit_is_cancelled_retried_then_failed(tiny_base, tmp_path):
    from distributed import Client, LocalCluster

    layers = make_layers(tiny_base, tmp_path / "layers", 3)
    out, markers = tmp_path / "out", tmp_path / "markers"
    markers.mkdir()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        summary = dispatch(layers, out, scheduler=client, threads=1, retries=1, progress=False, timeout=25,
                           before_render=functools.partial(hooks.pause_at, markers, {"h1"}, ()))
        assert len(client.scheduler_info()["workers"]) == 2  # the stuck worker was restarted
    assert sorted(summary.rendered) == ["h0", "h2"]
    assert [(r["scene"], r["kind"], r["attempts"]) for r in summary.failed] == [("h1", "timeout", 2)]


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for t in Path(f"/proc/{pid}/task").iterdir()
                for c in (t / "children").read_text().split()]
    except OSError:
        return []


@pytest.mark.process
@pytest.mark.slow
def test_ctrl_c_while_render_workers_start_is_130_with_no_worker_traceback(tiny_base, tmp_path):
    """A Ctrl-C at the terminal reaches every process of the group. Workers still starting (Python's
    site, their module's imports) printed KeyboardInterrupt tracebacks above the final line in 6 of
    17 tries. Workers now start with SIGINT blocked and drop it: 10 tries at varied moments of the
    workers' start, each exit 130 with the one line and nothing from a worker."""
    import signal
    import time

    make_layers(tiny_base, tmp_path / "layers", 4)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for i in range(10):
        proc = subprocess.Popen([sys.executable, "-m", "allo_usd.cli", "render", str(tmp_path / "layers"), "--out",
                                 str(tmp_path / f"out{i}"), "--workers", "2", "--threads", "1"],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        deadline = time.monotonic() + 60
        while not _children(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)
        time.sleep(0.03 * (i % 5))  # 0 to 0.12 s into the first worker's start (its imports take ~1 s)
        os.killpg(proc.pid, signal.SIGINT)
        _, stderr = proc.communicate(timeout=120)
        lines = [x for x in stderr.splitlines() if x.strip()]
        assert proc.returncode == 130, (i, proc.returncode, stderr[-2000:])
        assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, (i, stderr[-3000:])
        assert len(lines) == 1 and lines[0].startswith("interrupted"), (i, stderr[-2000:])


@pytest.mark.process
@pytest.mark.render
def test_a_sigkilled_single_layer_render_leaves_nothing_in_the_system_temp_dir(tiny_base, tmp_path):
    """Blender makes its session folder (blender_XXXXXX) when bpy loads; a SIGKILL left it, empty, in
    the system temp dir for good. A single-layer render now keeps its temporaries under
    OUT/.allo-tmp, which the next run into OUT removes (and a finished run leaves nothing)."""
    import glob
    import signal
    import time

    layer = make_layers(tiny_base, tmp_path / "layers", 1)[0]
    system_tmp, out = tmp_path / "system_tmp", tmp_path / "out"
    system_tmp.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(system_tmp)}
    cmd = [sys.executable, "-m", "allo_usd.cli", "render", str(layer), "--out", str(out)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while not glob.glob(f"{system_tmp}/**/blender_*", recursive=True) + \
            glob.glob(f"{out}/.allo-tmp/**/blender_*", recursive=True):
        assert proc.poll() is None and time.monotonic() < deadline, "Blender never made its session folder"
        time.sleep(0.01)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert sorted(os.listdir(system_tmp)) == []
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(system_tmp)) == [] and not (out / ".allo-tmp").exists()
    assert (out / f"{layer.stem}.png").is_file()
