"""The one header every docs/benchmarks/bench_*.md opens with: when, where and how its figures were measured.

A benchmark figure is only worth what its context says: the commit (a later commit may be faster
or slower), the date, the CPU (its model and the SIMD sets Embree, Cycles and OIDN pick their
kernels by), the core count, the load average before and after (other work on a shared machine
slows wall time), and the command that made it (so anyone can re-run it). Every scripts.bench_*
module calls this one, and tests/system/test_bench_smoke.py checks that each docs/benchmarks/bench_*.md names
a commit that exists, the CPU, the load and the command.

    from scripts import benchinfo
    run = benchinfo.start()                # before the first measurement: commit, date, CPU, load before
    ...                                    # measure
    benchinfo.finish(run)                  # after the last one: load after
    text = f"# Title\\n\\n{benchinfo.header(run)}\\n\\n..."

`start()` returns a plain dict (JSON-serialisable, so a benchmark run in phases can keep each
phase's dict beside its cached rows and `header()` them all).
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The SIMD sets that decide which kernels Embree/Cycles/OIDN run (absent ones are simply not listed).
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "f16c", "bmi2", "avx512f", "avx512bw", "avx512vl", "avx512_vnni",
              "avx_vnni", "amx_tile")
HEADER_START = "> **Measured**"   # how the header line starts (tests find it by this)


def git_commit(root: Path = ROOT) -> str:
    """`git rev-parse HEAD`, plus " (dirty)" if tracked files differ from it; "unknown" outside git."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                             timeout=30).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=60).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if not sha:
        return "unknown"
    return f"{sha} (dirty)" if dirty else sha


def cpu_info(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict:
    """CPU model, the SIMD sets of SIMD_FLAGS it has, and the cores this process may use."""
    model, flags = "", set()
    try:
        for line in cpuinfo.read_text().splitlines():
            key, _, value = line.partition(":")
            key = key.strip()
            if key == "model name" and not model:
                model = value.strip()
            elif key in ("flags", "Features") and not flags:
                flags = set(value.split())
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"model": model or platform.processor() or platform.machine(),
            "simd": [f for f in SIMD_FLAGS if f in flags], "cores": cores}


def command_line(argv: list[str] | None = None) -> str:
    """The command as one would type it at the checkout's root: `python -m scripts.NAME ARGS` for a
    module of the checkout (under -m, sys.argv[0] is its file), `python FILE ARGS` for any other file."""
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0]) if argv else Path("?")
    try:
        module = script.resolve().relative_to(ROOT)
    except ValueError:
        return shlex.join(["python", str(script), *argv[1:]])
    if module.suffix != ".py":
        return shlex.join(["python", str(module), *argv[1:]])
    return shlex.join(["python", "-m", ".".join(module.with_suffix("").parts), *argv[1:]])


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def start(argv: list[str] | None = None) -> dict:
    """Everything known before the measurements: commit, date, CPU, cores, load before, command."""
    return {"commit": git_commit(), "date": _utc_now(), "cpu": cpu_info(), "load_before": list(os.getloadavg()),
            "load_after": None, "command": command_line(argv)}


def finish(run: dict) -> dict:
    """Record the load average after the measurements (in place; returns `run`)."""
    run["load_after"] = list(os.getloadavg())
    run["date_end"] = _utc_now()
    return run


def _load(v) -> str:
    return "not recorded" if not v else "/".join(f"{x:.2f}" for x in v)


def header(*runs: dict) -> str:
    """The markdown header line(s), one per run (a benchmark made in phases lists each phase)."""
    lines = []
    for run in runs:
        cpu = run["cpu"]
        simd = " ".join(cpu["simd"]) or "none of " + " ".join(SIMD_FLAGS[:4])
        lines.append(f"{HEADER_START} at commit `{run['commit']}`, {run['date']}; CPU: {cpu['model']} "
                     f"({simd}), {cpu['cores']} cores; load (1/5/15 min): {_load(run['load_before'])} before, "
                     f"{_load(run.get('load_after'))} after; command: `{run['command']}`")
    return "\n>\n".join(lines)
