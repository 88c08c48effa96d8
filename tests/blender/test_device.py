"""The render device (`--device auto|cpu|gpu`, a plan's render.device): the decision on the devices
Cycles reports, the real probe on this machine, the notice and the error, the record in each
render's JSON, and that `auto` on a machine without a GPU renders the CPU's bytes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from allo_usd.blender.device import BACKENDS, DeviceError, check_device, choose
from allo_usd.core.errors import PlanError
from allo_usd.plan.io import load_plan, make_plan, save_plan
from allo_usd.plan.model import Plan, Render
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

ROOT = Path(__file__).resolve().parents[2]
NOTICE = "--device auto: Cycles finds no GPU"

# Device lists in the form the Cycles add-on's preferences.devices holds them after refresh_devices()
# (name, type, id; the ids as Cycles makes them), one machine each.
EPYC = ("AMD EPYC", "CPU", "CPU")
RTX = [("NVIDIA GeForce RTX 4090", "CUDA", "CUDA_NVIDIA GeForce RTX 4090_0000:01:00"),
       ("NVIDIA GeForce RTX 4090", "OPTIX", "CUDA_NVIDIA GeForce RTX 4090_0000:01:00_OptiX"), EPYC]
TWO_GTX = [("NVIDIA GeForce GTX 1080", "CUDA", "CUDA_NVIDIA GeForce GTX 1080_0000:01:00"),
           ("NVIDIA GeForce GTX 1080", "CUDA", "CUDA_NVIDIA GeForce GTX 1080_0000:02:00"), EPYC]
RADEON = [EPYC, ("AMD Radeon RX 7900 XTX", "HIP", "HIP_AMD Radeon RX 7900 XTX_0000:03:00")]
ARC = [("Intel(R) Arc(TM) A770 Graphics", "ONEAPI", "ONEAPI_Intel(R) Arc(TM) A770 Graphics_0000:04:00"), EPYC]
M2 = [("Apple M2 Max (GPU - 38 cores)", "METAL", "METAL_Apple M2 Max (GPU - 38 cores)"),
      ("Apple M2 Max", "CPU", "CPU")]


# ---------------------------------------------------------------- the decision (pure)

@pytest.mark.parametrize("devices, backend, names", [
    (RTX, "OPTIX", ["NVIDIA GeForce RTX 4090"]),        # OptiX before CUDA on the same card
    (TWO_GTX, "CUDA", ["NVIDIA GeForce GTX 1080"] * 2),  # no OptiX listed: CUDA, both cards
    (RADEON, "HIP", ["AMD Radeon RX 7900 XTX"]),
    (ARC, "ONEAPI", ["Intel(R) Arc(TM) A770 Graphics"]),
    (M2, "METAL", ["Apple M2 Max (GPU - 38 cores)"]),
])
@pytest.mark.parametrize("requested", ["auto", "gpu"])
def test_auto_and_gpu_use_every_device_of_the_first_backend_found(devices, backend, names, requested):
    d = choose(requested, devices)
    assert (d.kind, d.backend, [n for n, _ in d.devices], d.notice) == ("GPU", backend, names, None)
    assert all(ident.startswith(backend if backend != "OPTIX" else "CUDA") for _, ident in d.devices)


@pytest.mark.parametrize("devices", [[EPYC], [], RTX, M2])
def test_cpu_is_the_cpu_whatever_is_found(devices):
    d = choose("cpu", devices)
    assert (d.kind, d.backend, d.devices, d.notice) == ("CPU", None, (), None)


def test_without_a_gpu_auto_is_the_cpu_with_a_one_line_notice_and_gpu_an_error():
    for devices in ([EPYC], []):
        d = choose("auto", devices)
        assert (d.kind, d.backend) == ("CPU", None)
        assert d.notice.startswith(NOTICE) and "\n" not in d.notice and "--device cpu" in d.notice
        with pytest.raises(DeviceError, match=r"--device gpu: Cycles finds no GPU.*fix: install the GPU's driver.*"
                                              r"--device auto.*--device cpu") as exc:
            choose("gpu", devices)
        assert "\n" not in str(exc.value)
    assert BACKENDS[0] == "OPTIX" and set(BACKENDS) == {"OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"}


@pytest.mark.parametrize("bad", ["tpu", "", "GPU0", "cuda"])
def test_an_unknown_device_names_the_choices(bad):
    with pytest.raises(DeviceError, match=r"not a render device; fix: use one of auto, cpu, gpu"):
        check_device(bad)
    assert check_device(" GPU ") == "gpu"


# ---------------------------------------------------------------- the plan field

def test_plan_render_device_validates_and_round_trips(tmp_path):
    assert Plan(name="x").render.device == "auto"
    for bad in ("tpu", 3, None, "optix", "CPU", " gpu"):
        with pytest.raises(PlanError, match=r"render\.device: device .* is not a render device; fix: use one of "
                                            r"auto, cpu, gpu"):
            make_plan({"name": "x", "render": {"device": bad}})
    with pytest.raises(PlanError, match=r"render\.threads: .*fix: remove it"):
        make_plan({"name": "x", "render": {"threads": 2}})
    for suffix in (".toml", ".yaml"):
        p = tmp_path / f"plan{suffix}"
        save_plan(make_plan({"name": "x", "render": {"device": "cpu"}}), p)
        assert load_plan(p).render == Render(device="cpu")
        save_plan(Plan(name="x"), p)
        assert "device" not in p.read_text()   # a default left out stays out


def test_the_device_is_not_part_of_what_a_tree_compares():
    from allo_usd.run.author_tree import plan_differences

    a = make_plan({"name": "x", "render": {"device": "cpu"}})
    b = make_plan({"name": "x", "render": {"device": "gpu"}})
    assert plan_differences(a, b) == []
    assert plan_differences(a, make_plan({"name": "y", "render": {"device": "cpu"}}))


# ---------------------------------------------------------------- the real probe (a fresh process)

PROBE = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    from allo_usd.blender import device
    from allo_usd.run.job import render_layer

    layer, out = Path(sys.argv[1]), Path(sys.argv[2])
    cpu = render_layer(layer, out / "cpu", device="cpu")
    import bpy
    prefs = bpy.context.preferences.addons["cycles"].preferences
    after_cpu = {"probes": device.probes, "listed": len(prefs.devices)}
    render_layer(layer, out / "auto", device="auto")
    render_layer(layer, out / "auto2", device="auto")   # a second scene: no second probe, no second notice
    found = device.probe()
    try:
        device.select("gpu")
        gpu = None
    except device.DeviceError as exc:
        gpu = str(exc)
    print(json.dumps({"after_cpu": after_cpu, "probes": device.probes, "found": found, "gpu_error": gpu,
                      "cpu_record": cpu["device"]}))
""")


@pytest.fixture(scope="module")
def layer(tiny_base, tmp_path_factory):
    root = tmp_path_factory.mktemp("device")
    return write_scene_layer(make_spec(anomaly=True), root / "layers" / "dev.usda", tiny_base)


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


@pytest.mark.render
def test_the_real_probe_on_this_machine(layer, tmp_path):
    """cpu renders without asking Cycles for devices; auto probes once per process, and on this
    machine (no GPU) renders on the CPU, saying so once on stderr; gpu is the error."""
    r = subprocess.run([sys.executable, "-c", PROBE, str(layer), str(tmp_path)], capture_output=True, text=True,
                       env=_env(), timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["after_cpu"] == {"probes": 0, "listed": 0}   # preferences.devices is filled only by a probe
    assert got["probes"] == 1
    assert any(kind == "CPU" for _, kind, _ in got["found"])
    if any(kind in BACKENDS for _, kind, _ in got["found"]):
        pytest.skip(f"this machine has a GPU Cycles can use: {got['found']}")
    assert r.stderr.count(NOTICE) == 1, r.stderr
    assert "fix: install the GPU's driver" in got["gpu_error"]
    rec = got["cpu_record"]
    assert (rec["requested"], rec["used"], rec["backend"], rec["gpus"]) == ("cpu", "CPU", None, [])
    assert "notice" not in rec
    for name in ("cpu", "auto", "auto2"):
        meta = json.loads((tmp_path / name / "dev.json").read_text())
        assert meta["device"]["used"] == "CPU"
        assert ("notice" in meta["device"]) == (name != "cpu")
    for ext in ("png", "exr"):
        assert (tmp_path / "auto" / f"dev.{ext}").read_bytes() == (tmp_path / "cpu" / f"dev.{ext}").read_bytes()
    assert (tmp_path / "auto" / "dev_mask.png").read_bytes() == (tmp_path / "cpu" / "dev_mask.png").read_bytes()


# ---------------------------------------------------------------- the command line

def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "from allo_usd.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, env=_env(), timeout=600)


@pytest.mark.render
def test_render_json_records_device_blender_and_cpu(layer, tmp_path):
    import platform

    r = cli("render", layer, "--out", tmp_path / "a", "--device", "auto")
    assert r.returncode == 0, r.stderr
    notes = [x for x in r.stderr.splitlines() if NOTICE in x]
    if not notes:
        pytest.skip("this machine has a GPU Cycles can use")
    assert notes == [f"note: {json.loads((tmp_path / 'a' / 'dev.json').read_text())['device']['notice']}"]
    meta = json.loads((tmp_path / "a" / "dev.json").read_text())
    dev = meta["device"]
    assert (dev["requested"], dev["used"], dev["backend"], dev["gpus"]) == ("auto", "CPU", None, [])
    model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), None) if Path("/proc/cpuinfo").is_file() else None
    assert dev["cpu_model"] == (model or platform.processor() or platform.machine())
    assert dev["label"] == f"CPU ({dev['cpu_model']})"
    from importlib.metadata import version

    assert dev["blender"]["version"] == version("bpy")                     # 5.0.1
    assert len(dev["blender"]["build_hash"]) >= 7 and dev["blender"]["build_hash"] != "unknown"
    # the device is not the render's identity: a re-run on the CPU skips the scene
    r2 = cli("render", layer, "--out", tmp_path / "a", "--device", "cpu")
    assert r2.returncode == 0 and NOTICE not in r2.stderr, r2.stderr
    assert json.loads((tmp_path / "a" / "dev.json").read_text()) == meta


@pytest.mark.render
def test_a_pool_run_shows_the_notice_once_and_records_the_device_in_the_manifest(tiny_base, tmp_path):
    layers = tmp_path / "layers"
    for i in range(3):
        write_scene_layer(make_spec(scene_id=f"s{i}", seed=i + 1), layers / f"s{i}.usda", tiny_base)
    r = cli("render", layers, "--out", tmp_path / "out", "--workers", "2", "--threads", "1", "--device", "auto")
    assert r.returncode == 0, r.stderr
    if NOTICE not in r.stderr:
        pytest.skip("this machine has a GPU Cycles can use")
    assert r.stderr.count(NOTICE) == 1, r.stderr                 # two workers, three scenes, one note
    rows = [json.loads(x) for x in (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()]
    assert len(rows) == 3 and all(row["device"]["used"] == "CPU" and row["device"]["gpus"] == [] for row in rows)
    assert all("device_notice" not in row for row in rows)
    logs = "".join(p.read_text() for p in (tmp_path / "out" / "logs").glob("worker-*.log"))
    assert 1 <= logs.count(NOTICE) <= 2                          # once per worker process, in its log


@pytest.mark.render
@pytest.mark.parametrize("how", ["layer", "pool"])
def test_gpu_without_a_gpu_is_one_clear_error(layer, tmp_path, how):
    args = ["render", layer, "--out", tmp_path / "out", "--device", "gpu"]
    r = cli(*args, *(["--workers", "1"] if how == "pool" else []))
    if r.returncode == 0:
        pytest.skip("this machine has a GPU Cycles can use")
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = [x for x in r.stderr.splitlines() if x.startswith("error")]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "--device gpu: Cycles finds no GPU" in lines[0] and "fix: install the GPU's driver" in lines[0]
    assert not (tmp_path / "out" / "dev.png").exists()


@pytest.mark.process
def test_a_bad_device_on_the_command_line_is_one_line(layer, tmp_path):
    for args in (["render", layer, "--out", tmp_path / "o"], ["demo", "--out", tmp_path / "d"]):
        r = cli(*args, "--device", "tpu")
        assert r.returncode == 2 and r.stderr.strip().splitlines() == [
            "error: --device 'tpu' is not a render device; fix: use one of auto, cpu, gpu"], r.stderr


@pytest.mark.render
def test_a_plans_device_is_used_and_the_command_line_wins(tmp_path):
    """`render PLAN` renders on the plan's render.device; --device overrides it, on the same tree."""
    from allo_usd.core.paths import BASE_STAGE

    plan = make_plan({"name": "dev", "dates": {"days": 1}, "poses": {"train": [1], "test": [41]},
                      "counts": {"normal_train": 1, "normal_test": 0, "anomalous_test": 0},
                      "quality": {"resolution": [64, 36], "samples": 2}, "base_stage": str(BASE_STAGE),
                      "render": {"device": "gpu"}})
    save_plan(plan, tmp_path / "plan.toml")
    r = cli("render", tmp_path / "plan.toml", "--out", tmp_path / "out")
    if r.returncode == 0:
        pytest.skip("this machine has a GPU Cycles can use")
    assert r.returncode == 2 and "--device gpu: Cycles finds no GPU" in r.stderr, r.stderr
    r = cli("render", tmp_path / "plan.toml", "--out", tmp_path / "out", "--device", "cpu")
    assert r.returncode == 0 and "1 rendered" in r.stdout and NOTICE not in r.stderr, (r.stdout, r.stderr)
    meta = [json.loads(p.read_text()) for p in (tmp_path / "out" / "renders").glob("*.json")]
    assert [m["device"]["requested"] for m in meta] == ["cpu"]
