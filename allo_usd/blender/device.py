"""The Cycles render device: `auto`, `cpu` or `gpu` (a run-time choice, never written into a layer).

- `cpu` renders on the CPU and never asks Cycles for devices;
- `auto` uses the GPUs of the first backend Cycles lists devices for (OptiX, CUDA, HIP, oneAPI,
  Metal, in that order: OptiX before CUDA because it uses the RTX ray-tracing cores of the same
  NVIDIA cards), otherwise the CPU, with a one-line notice printed to stderr once per process (a
  pool worker's stderr is its log; the dispatcher and the CLI show it once per run);
- `gpu` is the same probe, but finding no GPU is a DeviceError that names the fix.

The probe goes through the Cycles add-on's preferences, as Blender's own Preferences > System >
Cycles Render Devices does: `refresh_devices()` fills `preferences.devices` (name, type, id of
every device of every compiled backend, plus the CPU), and a render uses the GPUs through
`compute_device_type` = the backend, `devices[].use` and `scene.cycles.device = 'GPU'`. The
probe runs once per process and is cached (`probe`): the first call initialises the drivers
(CUDA/HIP libraries), later renders only re-apply the choice. `choose` is the pure decision on
the list the probe returns.

`bpy.ops.wm.read_factory_settings` (every fresh build, allo_usd.blender.build.reset) resets the
preferences too, so `activate` sets the device after every reset (build.configure_render) and
whenever a warm session's device changes (allo_usd.blender.session).

The device changes a render's noise pattern and last bits, not what the scene means, so it is
recorded in each render's JSON (`record`), not in the layer, and not in the render identity
(allo_usd.output.identity): a scene rendered on the CPU counts as done on a GPU machine too
(re-render with --force). Determinism per device: docs/guide/dispatch.md, "GPU rendering".

The JSON also records the CPU kernel Cycles renders with (`cycles_cpu`: "AVX2" or "default", by
Cycles' own rule from the CPU flags, which it records too): two machines with the same
kernel and Blender build give the same bytes, others differ in the last bits (docs/reliability/rerendering.md,
docs/benchmarks/bench_rerender.md). It is not in the render identity either.
"""

from __future__ import annotations

import platform
import sys
from dataclasses import dataclass

from allo_usd.core.errors import AlloError
from allo_usd.plan.settings import DEVICES

# The GPU backends, in the order `auto` and `gpu` prefer them (Cycles' compute_device_type names).
BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")
BACKEND_NAMES = {"OPTIX": "OptiX", "CUDA": "CUDA", "HIP": "HIP", "ONEAPI": "oneAPI", "METAL": "Metal"}
GPU_FIX = ("install the GPU's driver (NVIDIA: CUDA/OptiX, driver 535 or newer; AMD: HIP, ROCm 6 or newer; Intel: "
           "oneAPI level-zero; Apple: Metal on Apple Silicon) so that Blender's Preferences > System > Cycles Render "
           "Devices lists it, or render with --device auto (the CPU when there is no GPU) or --device cpu")


class DeviceError(AlloError):
    """The device asked for cannot be used (`gpu` on a machine where Cycles finds none, an unknown name)."""


@dataclass(frozen=True)
class Device:
    """What renders: kind 'CPU', or 'GPU' with a backend and its devices ((name, id) pairs)."""
    requested: str
    kind: str = "CPU"
    backend: str | None = None
    devices: tuple[tuple[str, str], ...] = ()
    notice: str | None = None   # the one-line note of an `auto` that fell back to the CPU

    @property
    def label(self) -> str:
        if self.kind == "CPU":
            return f"CPU ({cpu_model()})"
        return f"GPU {BACKEND_NAMES.get(self.backend, self.backend)} ({', '.join(n for n, _ in self.devices)})"


CPU = Device("cpu")


def check_device(name: str, where: str = "--device") -> str:
    """`name` lower-cased if it is one of DEVICES, else a DeviceError naming the choices."""
    value = name.strip().lower() if isinstance(name, str) else name
    if value not in DEVICES:
        raise DeviceError(f"{where} {name!r} is not a render device; fix: use one of {', '.join(DEVICES)}")
    return value


def choose(requested: str, reported: list[tuple[str, str, str]]) -> Device:
    """The device for `requested` ('auto', 'cpu', 'gpu') given what Cycles reports: (name, type, id)
    per device, as `preferences.devices` lists them after refresh_devices() (the CPU is one of
    them, type 'CPU'). All devices of the first backend in BACKENDS that has any are used."""
    requested = check_device(requested)
    if requested == "cpu":
        return CPU
    for backend in BACKENDS:
        found = tuple((name, ident) for name, kind, ident in reported if kind == backend)
        if found:
            return Device(requested, "GPU", backend, found)
    looked = ", ".join(BACKEND_NAMES[b] for b in BACKENDS)
    if requested == "gpu":
        raise DeviceError(f"--device gpu: Cycles finds no GPU on "
                          f"{platform.node() or 'this machine'} (looked for {looked}; it lists only "
                          f"{', '.join(sorted({f'{n} ({k})' for n, k, _ in reported})) or 'nothing'}); fix: {GPU_FIX}")
    return Device("auto", notice=f"--device auto: Cycles finds no GPU ({looked}), so scenes render on the CPU "
                                 f"({cpu_model()}); pass --device cpu to skip the GPU probe")


# ---------------------------------------------------------------- the probe (bpy)

_PROBED: list[tuple[str, str, str]] | None = None
_NOTED: set[str] = set()
probes = 0   # how many times this process asked Cycles for its devices (at most once)


def _prefs():
    import bpy

    return bpy.context.preferences.addons["cycles"].preferences


def probe() -> list[tuple[str, str, str]]:
    """Every device Cycles finds, (name, type, id), the CPU included; asked once per process."""
    global _PROBED, probes
    if _PROBED is None:
        prefs = _prefs()
        prefs.refresh_devices()
        probes += 1
        _PROBED = [(d.name, d.type, d.id) for d in prefs.devices]
    return list(_PROBED)


def select(requested: str) -> Device:
    """The device this process renders `requested` with: `cpu` without a probe, else `choose` on the
    cached probe. An `auto` that falls back to the CPU prints its notice to stderr once per process."""
    requested = check_device(requested)
    device = CPU if requested == "cpu" else choose(requested, probe())
    if device.notice and device.notice not in _NOTED:
        _NOTED.add(device.notice)
        print(f"note: {device.notice}", file=sys.stderr, flush=True)
    return device


def noticed() -> list[str]:
    """The notices `select` printed in this process (for a caller whose stderr went to a log meanwhile)."""
    return sorted(_NOTED)


def activate(device: Device | None) -> None:
    """Make the current scene render on `device` (None: the CPU). A GPU device sets the add-on's
    compute_device_type and uses exactly the chosen devices (not the CPU beside them: one device
    type per render keeps the image reproducible on that device)."""
    import bpy

    scene = bpy.context.scene
    if device is None or device.kind == "CPU":
        scene.cycles.device = "CPU"
        return
    prefs = _prefs()
    prefs.compute_device_type = device.backend
    prefs.get_devices_for_type(device.backend)   # entries again after a factory reset (Cycles caches the list)
    wanted = {ident for _, ident in device.devices}
    for d in prefs.devices:
        d.use = d.type == device.backend and d.id in wanted
    scene.cycles.device = "GPU"


# ---------------------------------------------------------------- the record

_CPU_MODEL: str | None = None


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux, else what `platform` says)."""
    global _CPU_MODEL
    if _CPU_MODEL is None:
        name = ""
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
                for line in fh:
                    if line.lower().startswith(("model name", "hardware", "cpu model")):
                        name = line.partition(":")[2].strip()
                        break
        except OSError:
            pass
        _CPU_MODEL = name or platform.processor() or platform.machine() or "unknown CPU"
    return _CPU_MODEL


def blender_version() -> dict:
    """The Blender (and so Cycles, which ships inside it) that renders: version and build."""
    import bpy

    def text(v) -> str:
        return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)

    return {"version": bpy.app.version_string, "build_hash": text(bpy.app.build_hash),
            "build_date": text(bpy.app.build_date), "build_branch": text(bpy.app.build_branch)}


def record(device: Device) -> dict:
    """The device part of a render's JSON: what rendered, on which hardware, with which Blender."""
    rec = {"requested": device.requested, "used": device.kind, "backend": device.backend,
           "gpus": [name for name, _ in device.devices], "cpu_model": cpu_model(), "label": device.label,
           "blender": blender_version()}
    if device.notice:
        rec["notice"] = device.notice
    return rec


# ---------------------------------------------------------------- the CPU kernel Cycles renders with

# Cycles 5.0 (x86-64) has two CPU kernels and picks one per process, when its first CPU render
# builds the kernel table (ccl::Device::get_cpu_kernels(), a function-local static):
# "AVX2" when the CPU passes Cycles' AVX2 test (SSE4.2, AVX with OS support, F16C, AVX2, FMA, BMI1,
# BMI2: ccl::system_cpu_support_avx2) and CYCLES_CPU_NO_AVX2 is unset, otherwise "default" (compiled
# for Blender's baseline, -march=x86-64-v2 in bpy 5.0.1: SSE4.2). The two kernels round differently
# (FMA), so images differ in the last bits (docs/benchmarks/bench_rerender.md). Embree and OpenImageDenoise,
# which ship with Blender, pick their own instruction sets from the same CPU flags (this bpy's Embree
# has SSE2, AVX and AVX2 code; its OIDN names SSE4.1, AVX2 and AVX-512); CYCLES_CPU_NO_AVX2 changes
# neither.
CYCLES_AVX2_FLAGS = ("sse4_2", "avx", "f16c", "avx2", "fma", "bmi1", "bmi2")   # /proc/cpuinfo names
RECORDED_FLAGS = ("sse4_1", "sse4_2", "avx", "avx2", "fma", "f16c", "bmi1", "bmi2",
                  "avx512f", "avx512dq", "avx512bw", "avx512vl")
NO_AVX2_ENV = "CYCLES_CPU_NO_AVX2"
_CPU_FLAGS: tuple[str, ...] | None = None


def cpu_flags() -> tuple[str, ...]:
    """The instruction-set flags of RECORDED_FLAGS this CPU has, as /proc/cpuinfo lists them (what
    Cycles' AVX2 test, Embree and OIDN look at); () where there is no /proc/cpuinfo."""
    global _CPU_FLAGS
    if _CPU_FLAGS is None:
        found: set[str] = set()
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
                for line in fh:
                    if line.lower().startswith("flags"):
                        found = set(line.partition(":")[2].split())
                        break
        except OSError:
            pass
        _CPU_FLAGS = tuple(f for f in RECORDED_FLAGS if f in found)
    return _CPU_FLAGS


def build_march() -> str | None:
    """The instruction set Blender is compiled for (-march of bpy.app.build_cxxflags): what Cycles'
    "default" CPU kernel runs (x86-64-v2 in bpy 5.0.1); None if the flags do not say."""
    import re

    import bpy

    flags = bpy.app.build_cxxflags
    flags = flags.decode("utf-8", "replace") if isinstance(flags, bytes) else str(flags)
    found = re.findall(r"-march=(\S+)", flags)
    return found[-1] if found else None


def cycles_kernel(flags: tuple[str, ...] | None = None) -> str:
    """The CPU kernel Cycles picks on this machine: "AVX2" when the CPU has every flag of
    CYCLES_AVX2_FLAGS (Cycles' own test, ccl::system_cpu_support_avx2) and CYCLES_CPU_NO_AVX2 is unset,
    else "default". tests/blender/test_device_record.py checks it against Cycles' report in-process
    (`_cycles.system_info()`), which is not called here: it also initialises the GPU libraries."""
    import os

    flags = cpu_flags() if flags is None else flags
    capable = platform.machine().lower() in ("x86_64", "amd64") and all(f in flags for f in CYCLES_AVX2_FLAGS)
    return "AVX2" if capable and NO_AVX2_ENV not in os.environ else "default"


def cycles_cpu() -> dict:
    """What a render's JSON records as "cycles_cpu": the CPU kernel Cycles used and what decides it.

    - `kernel`: "AVX2" or "default", as Cycles names its CPU kernels (`cycles_kernel`);
    - `build_march`: what the "default" kernel (and the rest of Blender) is compiled for;
    - `cpu_flags`: the CPU's SSE4/AVX/AVX2/FMA/F16C/BMI/AVX-512 flags (Embree and OIDN pick their own
      code paths from these);
    - `env`: CYCLES_CPU_NO_AVX2, only when it is set.
    Two renders of a layer give the same bytes when `kernel`, the AVX2/AVX-512 flags and the Blender
    build match (docs/reliability/rerendering.md)."""
    import os

    flags = cpu_flags()
    rec = {"cpu": cpu_model(), "kernel": cycles_kernel(flags), "build_march": build_march(), "cpu_flags": list(flags)}
    if NO_AVX2_ENV in os.environ:
        rec["env"] = {NO_AVX2_ENV: os.environ[NO_AVX2_ENV]}
    return rec
