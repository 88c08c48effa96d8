"""Each render's JSON records the CPU kernel Cycles used (`cycles_cpu`), as Cycles reports it; and
scripts/bench_rerender.py (same kernel twice vs a forced lower kernel) writes its table and plot."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.render


def _cycles_capabilities() -> list[str]:
    """Cycles' own report: `_cycles.system_info()` has a line "CPU device capabilities: AVX2"."""
    import bpy  # noqa: F401 - registers _cycles
    import _cycles

    for line in _cycles.system_info().splitlines():
        if line.startswith("CPU device capabilities:"):
            return line.partition(":")[2].split()
    raise AssertionError(f"no CPU line in Cycles' system_info: {_cycles.system_info()!r}")


def test_render_json_records_the_kernel_cycles_used(rendered):
    from allo_usd.blender.device import CYCLES_AVX2_FLAGS, NO_AVX2_ENV, cpu_model, cycles_kernel

    _, meta, _ = rendered["normal"]
    rec = meta["cycles_cpu"]
    assert set(rec) >= {"cpu", "kernel", "build_march", "cpu_flags"}
    assert rec["cpu"] == cpu_model() and rec["cpu"]
    assert rec["kernel"] == cycles_kernel() in ("AVX2", "default")
    assert rec["build_march"] and rec["build_march"].startswith("x86-64")   # bpy 5.0.1 on x86-64: x86-64-v2
    # What Cycles itself reports in this process: its CPU capabilities decide the kernel.
    caps = _cycles_capabilities()
    if NO_AVX2_ENV not in os.environ:
        assert rec["kernel"] == ("AVX2" if "AVX2" in caps else "default")
        assert "env" not in rec
    # Cycles' AVX2 test and the CPU flags the record lists agree (the flags are the record of another machine).
    assert ("AVX2" in caps) == all(f in rec["cpu_flags"] for f in CYCLES_AVX2_FLAGS)
    assert meta["device"]["cpu_model"] == rec["cpu"]


def test_bench_rerender_writes_its_table_and_plot(rendered, tmp_path):
    """The smallest run of the bench: one layer, 32x18, 1 sample, three fresh processes."""
    from PIL import Image

    from allo_usd.blender.device import CYCLES_AVX2_FLAGS, cpu_flags

    layer, _, _ = rendered["normal"]
    docs = tmp_path / "docs"
    env = {k: v for k, v in os.environ.items() if k != "CYCLES_CPU_NO_AVX2"}
    r = subprocess.run([sys.executable, "-m", "scripts.bench_rerender", str(layer), "--size", "32x18",
                        "--samples", "1", "--out", str(tmp_path / "work"), "--docs", str(docs)],
                       capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    md = (docs / "bench_rerender.md").read_text()
    for field in ("- machine:", "- commit:", "- date:", "- command:"):
        assert field in md
    header = next(line for line in md.splitlines() if line.startswith("| scene |"))
    cols = [c.strip() for c in header.strip("|").split("|")]
    assert cols == ["scene", "pair", "kernels", "PNG identical", "EXR identical", "mask identical",
                    "EXR max abs diff", "EXR mean abs diff", "EXR pixels differing", "PNG PSNR (dB)",
                    "PNG max diff (levels)", "PNG pixels differing", "mask pixels differing"]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in md.splitlines()
            if line.startswith(f"| {layer.stem} |")]
    assert [row[1] for row in rows] == ["same kernel, again", "other kernel"]
    same, other = rows
    assert same[3:6] == ["yes", "yes", "yes"] and same[6] == "0" and same[9] == "inf"   # same kernel: same bytes
    if all(f in cpu_flags() for f in CYCLES_AVX2_FLAGS):   # the lower kernel can be forced here
        assert other[2] == "AVX2 / default"
    with Image.open(docs / "bench_rerender.png") as im:
        assert im.size[0] > 100 and im.size[1] > 100
