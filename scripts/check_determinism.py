"""Do authored bytes depend on the CPU's SIMD path or BLAS kernel? (the same bytes on every machine)

Authors, each in a fresh subprocess, (a) the demo plan, (b) a slice of the paper plan spread over the
year, anomalous scenes included, and (c) the base stage (scripts/make_base_stage.py), under each
environment variant below, and compares every file of each tree byte for byte with the baseline's:

    baseline          the environment as given
    blas-<core>       OPENBLAS_CORETYPE = Prescott, Nehalem, Sandybridge, Haswell, Zen, SkylakeX (a core
                      this CPU cannot run is skipped: SkylakeX needs AVX-512)
    npy-<level>       NPY_DISABLE_CPU_FEATURES: numpy's dispatched loops pushed down to AVX2 (no AVX-512),
                      AVX (no AVX2/FMA3), SSE4.2 (no AVX) and SSE3 (numpy's x86-64 baseline, which it
                      refuses to disable); a variant that disables nothing this CPU has is skipped
    glibc-no-avx      GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA,-FMA4,-AVX: libm's ifuncs (sin, cos,
                      tan, atan, exp, log, pow, ...) take their SSE2 variants (the spelling this glibc
                      accepts is found with `ld.so --list-diagnostics`: glibc < 2.33 wants AVX2_Usable)
    lowest            all of the lowest at once: Prescott, SSE3, glibc-no-avx
    blas-threads      OPENBLAS_NUM_THREADS = OMP_NUM_THREADS = the core count (every other run uses 1)

Each subprocess records what was really in force after its work: the kernel each loaded OpenBLAS
reports (openblas_get_corename), the features numpy reports enabled
(numpy.core._multiarray_umath.__cpu_features__), and where libm's ifunc symbols resolved (their
offsets in libm, compared with the baseline's). Not covered: Embree (ray casting) picks its SSE2 or
AVX2 kernels from the CPU with no environment switch.

Writes DOCS/determinism.md (a header, one row per workload and variant, the differing files and
attributes, a diff excerpt), DOCS/determinism.png (differing files per variant) and OUT/results.json.
Exit status 1 if any file differs from the baseline, 2 if a run failed.

    python -m scripts.check_determinism                       # full size (8 to 16 min on 2 cores)
    python -m scripts.check_determinism --rev HEAD            # the committed code (git archive), not the working tree
    python -m scripts.check_determinism --report-only --out DIR   # rewrite the report from DIR's kept trees
    python -m scripts.check_determinism --quick --variants baseline,npy-sse3 --out /tmp/d --docs /tmp/d
"""

from __future__ import annotations

import argparse
import difflib
import functools
import hashlib
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import tarfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from datetime import date, datetime, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BASE_STAGE_SCRIPT = Path("scripts/make_base_stage.py")
WORKLOADS = ("demo", "paper-slice", "base-stage")
BLAS_CORES = ("Prescott", "Nehalem", "Sandybridge", "Haswell", "Zen", "SkylakeX")
BLAS_NEEDS = {"SkylakeX": ("avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl")}   # /proc/cpuinfo flags
# numpy's dispatch targets (numpy.core._multiarray_umath.__cpu_dispatch__ on x86-64), lowest first; a
# variant disables every target above its level. numpy refuses to disable its baseline (SSE SSE2 SSE3).
NPY_LEVELS = {"npy-no-avx512": "AVX2", "npy-no-avx2": "F16C", "npy-sse42": "SSE42", "npy-sse3": "SSE3"}
GLIBC_OFF = ("AVX2", "FMA", "FMA4", "AVX")          # the libm ifunc selectors (sysdeps/x86_64/fpu/multiarch)
LIBM_SYMBOLS = ("sin", "cos", "tan", "sincos", "atan", "atan2", "asin", "acos", "exp", "exp2", "log", "log2",
                "pow", "sinf", "cosf", "expf", "logf", "powf")
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
SIMD_FLAGS = re.compile(r"^(sse\w*|pni|ssse3|avx\w*|fma\w*|f16c|aes|vaes|pclmulqdq|vpclmulqdq|sha_ni|"
                        r"bmi1|bmi2|popcnt|abm|movbe|amx\w*)$")
# Days worth having in the paper slice when its spacing allows (docs/guide/scenes.md, Conventions): the lunar eclipse
# (three sun lamps, the Moon's lit fraction 0.948) and the station's umbra.
SLICE_DAYS = (date(2030, 12, 10), date(2030, 9, 27))
OWN_OUTPUTS = ("docs/reliability/determinism.md", "docs/reliability/determinism.png")   # not counted as making the tree dirty


# ---------------------------------------------------------------------------------------------
# The child: one workload in a fresh process, then a record of what was in force


def openblas_in_force() -> list[dict]:
    """Each OpenBLAS loaded in this process: its file, the kernel it runs (corename), config, threads."""
    import ctypes

    paths = []
    with open("/proc/self/maps") as f:
        for line in f:
            p = line.split()[-1]
            if "openblas" in p.rsplit("/", 1)[-1].lower() and p not in paths:
                paths.append(p)
    found = []
    for p in paths:
        lib, rec = ctypes.CDLL(p), {"library": p.rsplit("/", 1)[-1]}
        for prefix in ("", "scipy_"):
            for suffix in ("", "64_"):
                for key, name in (("core", "openblas_get_corename"), ("config", "openblas_get_config"),
                                  ("threads", "openblas_get_num_threads")):
                    fn = getattr(lib, f"{prefix}{name}{suffix}", None)
                    if fn is None or key in rec:
                        continue
                    if key == "threads":
                        rec[key] = int(fn())
                    else:
                        fn.restype = ctypes.c_char_p
                        rec[key] = fn().decode(errors="replace").strip()
        found.append(rec)
    return found


def libm_in_force() -> dict[str, str]:
    """Where libm's (ifunc) symbols resolved, as offsets from libm's load address: dlsym returns the
    variant the ifunc resolver picked, so GLIBC_TUNABLES shows here."""
    import ctypes

    libm = ctypes.CDLL("libm.so.6")
    base = None
    with open("/proc/self/maps") as f:
        for line in f:
            if "/libm.so" in line or "/libm-" in line:
                base = int(line.split("-", 1)[0], 16)
                break
    out = {}
    for name in LIBM_SYMBOLS:
        fn = getattr(libm, name, None)
        if fn is not None and base is not None:
            out[name] = hex(ctypes.cast(fn, ctypes.c_void_p).value - base)
    return out


def in_force() -> dict:
    from numpy.core._multiarray_umath import __cpu_baseline__, __cpu_dispatch__, __cpu_features__

    import allo_usd
    import numpy

    return {"openblas": openblas_in_force(),
            "numpy": numpy.__version__,
            "numpy_baseline": list(__cpu_baseline__),
            "numpy_enabled": [k for k in (*__cpu_baseline__, *__cpu_dispatch__) if __cpu_features__.get(k)],
            "libm": libm_in_force(),
            "allo_usd": str(Path(allo_usd.__file__).parent),
            "env": {k: os.environ[k] for k in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES", "GLIBC_TUNABLES",
                                              *THREAD_VARS) if k in os.environ}}


_PREP = r"""
import json, sys, tomllib
from datetime import date, timedelta
from pathlib import Path

import tomli_w

import allo_usd

out, n, paper_toml, slice_days = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]), sys.argv[4:]
data = tomllib.loads(paper_toml.read_text())
plan = allo_usd.load_plan(paper_toml)
start, days, step = plan.dates.start, plan.dates.days, plan.dates.step_days
counts = {k: getattr(plan.counts, k) for k in ("normal_train", "normal_test", "anomalous_test")}
total = sum(counts.values())
k = max(2, min(days, round(n * days / total)))            # the slice's days, evenly spaced over the plan's
stride = days // k
offset = 0
for d in (date.fromisoformat(s) for s in slice_days):    # a day worth having, if the spacing reaches it
    i, r = divmod((d - start).days, step)
    if r == 0 and 0 <= i < days and i // stride < k and i % stride + (k - 1) * stride < days:
        offset = i % stride
        break
seeds, poses = len(plan.seeds), {s: len(plan.poses.numbers(s)) for s in ("train", "test")}
grid = {"normal_train": k * seeds * poses["train"], "normal_test": k * seeds * poses["test"],
        "anomalous_test": k * seeds * poses["test"] * len(plan.anomalies.depths)}
data["name"] = f"{plan.name}-slice{n}"
data["dates"] = {**data.get("dates", {}), "start": start + timedelta(days=offset * step), "days": k,
                 "step_days": stride * step}
data["counts"] = {key: min(grid[key], round(c * n / total)) for key, c in counts.items()}
path = out / "paper_slice.toml"
path.write_text(tomli_w.dumps(data))
sliced = allo_usd.load_plan(path)                         # validates it
epochs = [e.date().isoformat() for e in sliced.dates.epochs()]
print(json.dumps({"plan": str(path), "scenes": len(allo_usd.enumerate_scenes(sliced)), "days": epochs,
                  "counts": data["counts"], "paper_scenes": total}))
"""


def child(spec: dict) -> int:
    """Run one workload in this (fresh) process, then record what was in force into spec['probe']."""
    rc = 0
    try:
        if spec["kind"] == "author":
            from allo_usd.cli import main

            sys.argv = ["allo-usd", *spec["argv"]]
            main()
        elif spec["kind"] == "stage":
            import runpy

            sys.argv = [spec["script"], *spec["argv"]]
            runpy.run_path(spec["script"], run_name="__main__")
        elif spec["kind"] == "prep":
            sys.argv = ["prep", *spec["argv"]]
            exec(compile(_PREP, "<prep>", "exec"), {"__name__": "__prep__"})
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    if spec.get("probe"):
        Path(spec["probe"]).write_text(json.dumps(in_force(), indent=1))
    return rc


# ---------------------------------------------------------------------------------------------
# Variants


@dataclass
class Variant:
    name: str
    env: dict[str, str]
    skip: str = ""          # why this CPU cannot run it (or it would change nothing here)


def cpu_info() -> dict:
    info = {"model": platform.processor() or platform.machine(), "flags": [], "family": "", "model_id": ""}
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return info
    for line in text.splitlines():
        key, _, value = (s.strip() for s in line.partition(":"))
        if key == "model name" and info["model"] in (platform.processor(), platform.machine()):
            info["model"] = value
        elif key == "cpu family" and not info["family"]:
            info["family"] = value
        elif key == "model" and not info["model_id"]:
            info["model_id"] = value
        elif key == "flags" and not info["flags"]:
            info["flags"] = value.split()
    return info


@functools.lru_cache(maxsize=1)
def glibc_tunable() -> tuple[str, str]:
    """(GLIBC_TUNABLES value that turns libm's AVX/FMA ifuncs off, how it was checked). glibc 2.33 and
    later spell the features AVX2, FMA, ...; older ones AVX2_Usable, FMA_Usable, ... and an unknown
    name is silently ignored, so each spelling is tried on `ld.so --list-diagnostics` (glibc >= 2.33),
    which prints the active CPU feature words: the spelling that changes them is the one that works."""
    spellings = [",".join(f"-{f}" for f in GLIBC_OFF), ",".join(f"-{f}_Usable" for f in GLIBC_OFF)]
    ldso = next((p for p in ("/lib64/ld-linux-x86-64.so.2", "/lib/x86_64-linux-gnu/ld-linux-x86-64.so.2")
                 if Path(p).exists()), None)

    def active(tunable: str | None) -> str | None:
        env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
        if tunable:
            env["GLIBC_TUNABLES"] = f"glibc.cpu.hwcaps={tunable}"
        try:
            r = subprocess.run([ldso, "--list-diagnostics"], env=env, capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.SubprocessError):
            return None
        lines = [line for line in r.stdout.splitlines() if ".active[" in line or "subdirs_active" in line]
        return "\n".join(lines) if r.returncode == 0 and lines else None

    if ldso is not None:
        plain = active(None)
        if plain is not None:
            for s in spellings:
                if active(s) not in (None, plain):
                    return f"glibc.cpu.hwcaps={s}", "ld.so --list-diagnostics: active CPU features change"
            return "", "no spelling changes ld.so's active CPU features"
    version = tuple(int(x) for x in re.findall(r"\d+", platform.libc_ver()[1])[:2] or (0, 0))
    s = spellings[0] if version >= (2, 33) else spellings[1]
    return f"glibc.cpu.hwcaps={s}", f"unverified before the runs (glibc {platform.libc_ver()[1]}); see libm in force"


def npy_disable(level: str) -> tuple[str, list[str]]:
    """(NPY_DISABLE_CPU_FEATURES for `level`: every dispatched target above it, the ones of them this CPU has)."""
    from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    order = list(__cpu_dispatch__)
    above = order[order.index(level) + 1:] if level in order else order
    return " ".join(above), [f for f in above if __cpu_features__.get(f)]


def all_variants(cpu: dict) -> list[Variant]:
    flags = set(cpu["flags"])
    out = [Variant("baseline", {})]
    for core in BLAS_CORES:
        missing = [f for f in BLAS_NEEDS.get(core, ()) if f not in flags]
        out.append(Variant(f"blas-{core.lower()}", {"OPENBLAS_CORETYPE": core},
                           f"this CPU lacks {' '.join(missing)}" if missing else ""))
    for name, level in NPY_LEVELS.items():
        value, present = npy_disable(level)
        out.append(Variant(name, {"NPY_DISABLE_CPU_FEATURES": value},
                           "" if present else "no-op here: this CPU has none of these features"))
    tunable, how = glibc_tunable()
    out.append(Variant("glibc-no-avx", {"GLIBC_TUNABLES": tunable} if tunable else {},
                       "" if tunable else f"GLIBC_TUNABLES: {how}"))
    lowest = {"OPENBLAS_CORETYPE": "Prescott", "NPY_DISABLE_CPU_FEATURES": npy_disable("SSE3")[0]}
    if tunable:
        lowest["GLIBC_TUNABLES"] = tunable
    out.append(Variant("lowest", lowest))
    n = str(os.cpu_count() or 2)
    out.append(Variant("blas-threads", {k: n for k in THREAD_VARS}))
    return out


# ---------------------------------------------------------------------------------------------
# Running and comparing


@dataclass
class Job:
    workload: str
    variant: str
    env: dict
    out: str
    seconds: float = 0.0
    rc: int | None = None
    in_force: dict = field(default_factory=dict)
    stderr_tail: str = ""
    compared: int = 0
    differing: list = field(default_factory=list)


def run_child(spec: dict, env_extra: dict, cwd: Path, code_root: Path, log: Path,
              timeout: float) -> tuple[int, float, str]:
    """`python -m scripts.check_determinism --child SPEC` in `cwd`, with PYTHONPATH led by `code_root`
    (the allo_usd under test: this checkout, or --rev's export) and then this checkout, whose scripts
    package serves an export that has none."""
    env = dict(os.environ)
    for k in THREAD_VARS:
        env.setdefault(k, "1")          # two runs share the cores; blas-threads sets them itself
    env.update(env_extra)
    roots = dict.fromkeys([str(code_root), str(REPO)])
    env["PYTHONPATH"] = os.pathsep.join([*roots, *filter(None, [env.get("PYTHONPATH")])])
    cwd.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        try:
            r = subprocess.run([sys.executable, "-m", "scripts.check_determinism", "--child", json.dumps(spec)],
                               env=env, cwd=cwd, stdout=f, stderr=subprocess.STDOUT, timeout=timeout)
            rc = r.returncode
        except subprocess.TimeoutExpired:
            rc = -999
    seconds = time.perf_counter() - t0
    tail = "\n".join(log.read_text(errors="replace").splitlines()[-15:])
    return rc, seconds, tail


def tree_files(root: Path) -> dict[str, Path]:
    return {p.relative_to(root).as_posix(): p for p in sorted(root.rglob("*")) if p.is_file()} if root.is_dir() else {}


def compare_trees(a: Path, b: Path) -> tuple[int, list[str]]:
    fa, fb = tree_files(a), tree_files(b)
    names = sorted(set(fa) | set(fb))
    differing = [n for n in names if n not in fa or n not in fb or fa[n].read_bytes() != fb[n].read_bytes()]
    return len(names), differing


def layer_text(path: Path) -> list[str]:
    """A file as text lines: .usdc through Sdf (usdcat's text), other binaries as a hash."""
    if path.suffix in (".usdc", ".usd"):
        try:
            from pxr import Sdf

            layer = Sdf.Layer.OpenAsAnonymous(str(path))
            if layer is not None:
                return layer.ExportToString().splitlines()
        except Exception:   # noqa: BLE001 (an excerpt only)
            pass
    data = path.read_bytes()
    try:
        return data.decode().splitlines()
    except UnicodeDecodeError:
        return [f"<binary, {len(data)} bytes, sha256 {hashlib.sha256(data).hexdigest()[:16]}>"]


_ATTR = re.compile(r"^\s*(?:(?:uniform|custom|prepend|append|add|delete|rel)\s+)*[\w:\[\]]+\s+([\w:.]+)\s*=")
_KEY = re.compile(r'^\s*(?:"([^"]+)"|(\w[\w:]*))\s*=')
_NUM = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _attr_of(line: str) -> str:
    m = _ATTR.match(line) or _KEY.match(line)
    if m:
        return next(g for g in m.groups() if g)
    return (line.strip()[:50] + "...") if len(line.strip()) > 50 else line.strip()


def _numbers(line: str) -> list[str]:
    """The numbers of a line's value (after its first '='; a type such as double3 is not one)."""
    return _NUM.findall(line.split("=", 1)[1] if "=" in line else line)


def attribute_changes(a: Path, b: Path) -> dict[str, float]:
    """Attribute (or line) name -> the largest |difference| of its numbers, for one pair of files
    (nan: the line changed shape, or was added or removed)."""
    la, lb = layer_text(a), layer_text(b)
    out: dict[str, float] = {}
    sm = difflib.SequenceMatcher(None, la, lb, autojunk=False)
    for tag, i1, i2, j1, j2 in sm.get_opcodes():
        if tag == "equal":
            continue
        paired = i2 - i1 == j2 - j1
        for k in range(max(i2 - i1, j2 - j1)):
            x = la[i1 + k] if i1 + k < i2 else None
            y = lb[j1 + k] if j1 + k < j2 else None
            name = f"{a.name} row" if a.suffix == ".csv" else _attr_of(x if x is not None else y)
            delta = float("nan")
            if paired and x is not None and y is not None:
                nx, ny = _numbers(x), _numbers(y)
                if len(nx) == len(ny) and _NUM.sub("#", x) == _NUM.sub("#", y):
                    delta = max((abs(float(p) - float(q)) for p, q in zip(nx, ny)), default=0.0)
            old = out.get(name, 0.0)
            out[name] = float("nan") if delta != delta or old != old else max(old, delta)
    return out


def _pair_lines(x: str, y: str, width: int) -> list[str]:
    """A changed line as '-'/'+' lines; a long one (a mesh's points or normals) as a count of the
    numbers that differ and the first of them."""
    if len(x) <= width and len(y) <= width:
        return ["-" + x, "+" + y]
    nx, ny = _numbers(x), _numbers(y)
    head = x.split("=", 1)[0].rstrip() + " = [...]"
    if len(nx) != len(ny):
        return ["-" + head + f" ({len(nx)} numbers)", "+" + head + f" ({len(ny)} numbers)"]
    diffs = [(k, p, q) for k, (p, q) in enumerate(zip(nx, ny)) if p != q]
    if not diffs:
        return ["-" + x[:width] + " ...", "+" + y[:width] + " ..."]
    k, p, q = diffs[0]
    worst = max(abs(float(p) - float(q)) for _, p, q in diffs)
    return ["-" + head + f" ({len(nx)} numbers)",
            "+" + head + f" ({len(diffs)} of {len(nx)} numbers differ; the first, number {k}: {p} -> {q}; "
                         f"max |difference| {worst:.3g})"]


def diff_excerpt(a: Path, b: Path, label_a: str, label_b: str, lines: int = 40, width: int = 220) -> str:
    la, lb = layer_text(a), layer_text(b)
    out = [f"--- {label_a}", f"+++ {label_b}"]
    hunks = [op for op in difflib.SequenceMatcher(None, la, lb, autojunk=False).get_opcodes() if op[0] != "equal"]
    for n, (tag, i1, i2, j1, j2) in enumerate(hunks):
        if len(out) >= lines:
            out.append(f"... ({len(hunks) - n} more changed blocks)")
            break
        out.append(f"@@ -{i1 + 1},{i2 - i1} +{j1 + 1},{j2 - j1} @@")
        if i1 > 0:
            ctx = la[i1 - 1]
            out.append(" " + (ctx if len(ctx) <= width else ctx[:width] + " ..."))
        if i2 - i1 == j2 - j1:
            for x, y in zip(la[i1:i2], lb[j1:j2]):
                out += _pair_lines(x, y, width)
        else:
            out += ["-" + (x if len(x) <= width else x[:width] + " ...") for x in la[i1:i2]]
            out += ["+" + (y if len(y) <= width else y[:width] + " ...") for y in lb[j1:j2]]
    return "\n".join(out)


def _pick_example(names: list[str]) -> str:
    for pattern in (r"^scenes/.*\.usda$", r"^sky/", r"^poses/", r"\.usda$", r"\.usdc$"):
        for n in names:
            if re.search(pattern, n):
                return n
    return names[0]


# ---------------------------------------------------------------------------------------------
# The repository's state, the report


def git(*args: str) -> str:
    r = subprocess.run(["git", "--no-optional-locks", "-C", str(REPO), *args], capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else ""


def working_tree_state() -> tuple[bool, str]:
    """(dirty, a fingerprint of the uncommitted edits), this script's own outputs left out; read-only
    (--no-optional-locks: not even the index is refreshed)."""
    excludes = [f":(exclude){p}" for p in OWN_OUTPUTS]
    status = git("status", "--porcelain", "--untracked-files=all", "--", ".", *excludes)
    h = hashlib.sha256(git("diff", "HEAD", "--binary", "--", ".", *excludes).encode())
    for line in status.splitlines():
        if line.startswith("??"):
            p = REPO / line[3:].strip().strip('"')
            h.update(p.as_posix().encode())
            if p.is_file():
                h.update(p.read_bytes())
    return bool(status), h.hexdigest()[:12]


def export_rev(rev: str, dest: Path) -> str:
    """`git archive REV` unpacked into dest (read-only for git); returns the short commit."""
    short = git("rev-parse", "--short", rev)
    if not short:
        raise SystemExit(f"error: {rev!r} is not a commit of {REPO}")
    if not (dest / ".exported").is_file() or (dest / ".exported").read_text() != short:
        import shutil

        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir(parents=True)
        proc = subprocess.Popen(["git", "-C", str(REPO), "archive", "--format=tar", rev], stdout=subprocess.PIPE)
        with tarfile.open(fileobj=proc.stdout, mode="r|") as tar:
            tar.extractall(dest, filter="data")
        if proc.wait() != 0:
            raise SystemExit(f"error: git archive {rev} failed")
        (dest / ".exported").write_text(short)
    return short


def compact_in_force(rec: dict, base: dict | None) -> str:
    if not rec:
        return "-"
    blas = ", ".join(f"{'numpy' if 'scipy' not in o['library'] else 'scipy'} {o.get('core', '?')}"
                     f"{'' if o.get('threads', 1) == 1 else ' x' + str(o.get('threads'))}"
                     for o in rec.get("openblas", []))
    dispatched = [f for f in rec.get("numpy_enabled", []) if f not in rec.get("numpy_baseline", [])]
    npy = "numpy " + (f"up to {dispatched[-1]}" if dispatched else "baseline " + "/".join(rec.get("numpy_baseline", [])))
    libm = rec.get("libm", {})
    if base and base.get("libm"):
        changed = [k for k in libm if base["libm"].get(k) != libm[k]]
        libm_s = f"libm {len(changed)}/{len(libm)} ifuncs moved" if changed else "libm as baseline"
    else:
        libm_s = "libm (reference)"
    return f"BLAS {blas or 'not loaded'}; {npy}; {libm_s}"


def _env_cell(env: dict) -> str:
    """A variant's environment for the table; a long feature list shortened (the full one is listed below it)."""
    cells = []
    for k, value in env.items():
        words = value.split()
        if len(words) > 4:
            value = f"{words[0]} .. {words[-1]} ({len(words)} features)"
        cells.append(f"{k}={value}")
    return (" ".join(cells) or "(as given)").replace("|", "\\|")


def write_report(args, jobs: list[Job], variants: list[Variant], info: dict, docs: Path) -> Path:
    docs.mkdir(parents=True, exist_ok=True)
    by_key = {(j.workload, j.variant): j for j in jobs}
    cpu = info["cpu"]
    simd = " ".join(f for f in cpu["flags"] if SIMD_FLAGS.match(f))
    base_probe = next((j.in_force for j in jobs if j.variant == "baseline" and j.in_force), {})
    blas_versions = "; ".join(f"{o['library']}: {o.get('config', '?')}" for o in base_probe.get("openblas", []))
    L = ["# Determinism across SIMD paths and BLAS kernels", "",
         "Written by `python -m scripts.check_determinism`: each workload is authored in a fresh subprocess under each "
         "environment variant, and every file of its tree is compared byte for byte with the baseline's tree. "
         "\"In force\" is what the subprocess itself reported after its work: the kernel of each OpenBLAS it "
         "loaded (`openblas_get_corename`), the highest numpy dispatch target enabled "
         "(`__cpu_features__`), and whether libm's ifunc symbols resolved elsewhere than in the baseline run.",
         "",
         f"- commit: `{info['commit']}`" + (f" ({info['source']})" if info.get("source") else ""),
         f"- date: {info['date']}",
         f"- CPU: {cpu['model']} (family {cpu['family']}, model {cpu['model_id']}), {os.cpu_count()} cores; "
         f"SIMD flags: {simd}",
         f"- numpy {base_probe.get('numpy', '?')}; OpenBLAS: {blas_versions or '?'}; glibc {platform.libc_ver()[1]}; "
         f"Python {platform.python_version()}",
         f"- GLIBC_TUNABLES spelling: `{info['glibc'][0] or '(none works)'}` ({info['glibc'][1]})",
         f"- load average (1, 5, 15 min): before {' '.join(map(str, info['load_before']))}, after "
         f"{' '.join(map(str, info['load_after']))} (the seconds below count other work on this machine too)",
         f"- every run: {', '.join(f'{k}=1' for k in THREAD_VARS)} unless set (blas-threads sets "
         f"{os.cpu_count()}); {args.jobs} runs at a time; authoring with `--workers 1`",
         f"- workloads: {info['workloads_doc']}",
         f"- command: `{info['command']}`",
         f"- total: {info['total_seconds']:.0f} s", ""]
    if info.get("tree_changed"):
        L += ["**The working tree changed while the runs went on; runs may have used different code.**", ""]
    L += ["| workload | variant | environment | files compared | files differing | in force | seconds |",
          "|---|---|---|---|---|---|---|"]
    for w in info["workloads"]:
        for v in variants:
            env = _env_cell(v.env)
            if v.skip:
                L.append(f"| {w} | {v.name} | {env} | - | skipped: {v.skip} | - | - |")
                continue
            j = by_key.get((w, v.name))
            if j is None:
                continue
            base = by_key.get((w, "baseline"))
            if j.rc != 0:
                diff = f"FAILED (exit {j.rc})"
            elif j.variant == "baseline":
                diff = "(reference)"
            else:
                groups = Counter(n.split("/", 1)[0] if "/" in n else n for n in j.differing)
                diff = str(len(j.differing)) + (f" ({', '.join(f'{g} {c}' for g, c in groups.most_common())})"
                                                if j.differing else "")
            forced = compact_in_force(j.in_force, None if j.variant == "baseline" or base is None else base.in_force)
            L.append(f"| {w} | {v.name} | {env} | {j.compared or '-'} | {diff} | {forced} | {j.seconds:.1f} |")
    L += ["", "Variants' full environments:", ""]
    L += [f"- {v.name}: " + (", ".join(f"`{k}={val}`" for k, val in v.env.items()) or "as given")
          + (f" (skipped: {v.skip})" if v.skip else "") for v in variants]
    L.append("")
    differing = [j for j in jobs if j.differing and j.variant != "baseline"]
    if not differing and all(j.rc == 0 for j in jobs):
        L += ["**No file differs under any variant.**", ""]
    else:
        L += ["Summary:", ""]
        for w in info["workloads"]:
            ran = [j for j in jobs if j.workload == w and j.variant != "baseline"]
            bad = [f"{j.variant} ({len(j.differing)})" for j in ran if j.differing]
            same = [j.variant for j in ran if j.rc == 0 and not j.differing]
            L.append(f"- {w}: differ: {', '.join(bad) or 'none'}; byte-identical: {', '.join(same) or 'none'}")
        L.append("")
    for w in info["workloads"]:
        js = [j for j in differing if j.workload == w]
        if not js:
            continue
        base_out = Path(by_key[(w, "baseline")].out)
        L += [f"## {w}: what differs", "",
              "Per variant: the differing files by folder, then each attribute (or line) that differs, in how many "
              "files, and the largest |difference| of its numbers (nan: a line changed shape, or was added or "
              "removed)" + (f"; attributes over the first {args.attr_files} differing files" if any(
                  len(j.differing) > args.attr_files for j in js) else "") + ".", ""]
        for j in js:
            attrs: dict[str, list[float]] = {}
            for n in j.differing[:args.attr_files]:
                a, b = base_out / n, Path(j.out) / n
                if not (a.is_file() and b.is_file()):
                    attrs.setdefault("(file only in one tree)", []).append(float("nan"))
                    continue
                for name, delta in attribute_changes(a, b).items():
                    attrs.setdefault(name, []).append(delta)
            groups = Counter(n.split("/", 1)[0] if "/" in n else n for n in j.differing)
            parts = []
            for name, deltas in sorted(attrs.items(), key=lambda kv: (-len(kv[1]), kv[0]))[:12]:
                finite = [d for d in deltas if d == d]
                worst = "nan" if not finite else f"{max(finite):.2g}" + ("" if len(finite) == len(deltas) else ", nan")
                parts.append(f"`{name}` {len(deltas)} ({worst})")
            shown = ", ".join(f"`{n}`" for n in j.differing[:4])
            more = f" and {len(j.differing) - 4} more" if len(j.differing) > 4 else ""
            L.append(f"- **{j.variant}**: {len(j.differing)} files ({', '.join(f'{g} {c}' for g, c in groups.most_common())})"
                     f"; {'; '.join(parts) or 'no attribute found'}. E.g. {shown}{more}")
        L.append("")
        # one excerpt per kind of variant (blas, npy, glibc, ...), "lowest" only when nothing else shows
        families: dict[str, Job] = {}
        for j in js:
            families.setdefault(j.variant.split("-")[0], j)
        picked = [j for f, j in families.items() if f not in ("lowest",)] or list(families.values())
        examples = [(j, _pick_example(j.differing)) for j in picked]
        binary = next((n for n in js[0].differing if n.endswith((".usdc", ".usd"))), None)
        if binary and binary not in {e for _, e in examples}:
            examples.append((js[0], binary))   # a crate file's difference, read through Sdf as text
        for j, example in examples:
            a, b = base_out / example, Path(j.out) / example
            if a.is_file() and b.is_file():
                L += [f"Diff excerpt, `{example}`, baseline against {j.variant}:", "", "```diff",
                      diff_excerpt(a, b, f"baseline/{example}", f"{j.variant}/{example}", lines=24), "```", ""]
    failed = [j for j in jobs if j.rc != 0]
    if failed:
        L += ["## Failed runs", ""]
        for j in failed:
            L += [f"- {j.workload} / {j.variant}: exit {j.rc}", "", "```", j.stderr_tail, "```", ""]
    L += ["Not covered: Embree's ray casting (placement) picks its SSE2 or AVX2 kernels from the CPU, and no "
          "environment variable caps it (only `rtcNewDevice(\"isa=...\")` in code).", ""]
    md = docs / "determinism.md"
    md.write_text("\n".join(L))
    return md


def write_plot(jobs: list[Job], variants: list[Variant], workloads: list[str], png: Path) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    names = [v.name for v in variants if not v.skip and v.name != "baseline"]
    by_key = {(j.workload, j.variant): j for j in jobs}
    fig, ax = plt.subplots(figsize=(10, 4))
    width = 0.8 / max(1, len(workloads))
    for i, w in enumerate(workloads):
        js = [by_key.get((w, n)) for n in names]
        counts = [len(j.differing) if j else 0 for j in js]
        ys = [100.0 * c / j.compared if j and j.compared else 0.0 for c, j in zip(counts, js)]
        xs = [k + (i - (len(workloads) - 1) / 2) * width for k in range(len(names))]
        ax.bar(xs, ys, width, label=w)
        for x, y, c in zip(xs, ys, counts):
            if c:
                ax.annotate(str(c), (x, y), ha="center", va="bottom", fontsize=7, rotation=90,
                            xytext=(0, 2), textcoords="offset points")
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_ylabel("% of files differing from baseline\n(number above each bar)")
    ax.margins(y=0.15)
    ax.set_title("Authored bytes vs SIMD path / BLAS kernel")
    ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return png


# ---------------------------------------------------------------------------------------------


def _own_pin(jobs: list[Job]) -> str:
    """' (it set X=Y itself)' when the base-stage script set BLAS variables the baseline run was not given."""
    base = next((j for j in jobs if j.workload == "base-stage" and j.variant == "baseline"), None)
    env = base.in_force.get("env", {}) if base else {}
    own = [f"{k}={v}" for k, v in env.items() if k.startswith("OPENBLAS_CORETYPE") and k not in os.environ]
    return f" (in the baseline run it set {', '.join(own)} itself)" if own else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "out" / "determinism", help="scratch directory (trees, logs)")
    ap.add_argument("--docs", type=Path, default=REPO / "docs" / "reliability", help="where determinism.md/.png go")
    ap.add_argument("--slice", type=int, default=None, help="paper-slice size in scenes (default 2000; --quick 30)")
    ap.add_argument("--variants", default=None, help="comma-separated subset (baseline is always run); "
                                                     "default: all")
    ap.add_argument("--workloads", default=None, help=f"comma-separated subset of {','.join(WORKLOADS)}")
    ap.add_argument("--quick", action="store_true", help="demo plan's first 7 scenes, a 30-scene paper slice, "
                                                         "no base stage")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="runs at a time (default 2)")
    ap.add_argument("--rev", default=None, help="author with this commit's code (git archive into OUT/src), not "
                                                "the working tree")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per run")
    ap.add_argument("--attr-files", type=int, default=5000, help="differing files per variant read for the "
                                                                 "attribute summary")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from OUT/results.json and the "
                                                               "trees kept in OUT, without authoring again")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(json.loads(args.child))

    t_start = time.perf_counter()
    load_before = tuple(round(x, 2) for x in os.getloadavg())
    cpu = cpu_info()
    every = all_variants(cpu)
    known = {v.name for v in every}
    chosen = known if args.variants is None else {s.strip() for s in args.variants.split(",") if s.strip()}
    unknown = chosen - known
    if unknown:
        ap.error(f"unknown variants {', '.join(sorted(unknown))}; choose from {', '.join(v.name for v in every)}")
    variants = [v for v in every if v.name in chosen or v.name == "baseline"]
    workloads = list(WORKLOADS[:2] if args.quick else WORKLOADS)
    if args.workloads:
        wanted = [w.strip() for w in args.workloads.split(",") if w.strip()]
        bad = [w for w in wanted if w not in WORKLOADS]
        if bad:
            ap.error(f"unknown workloads {', '.join(bad)}; choose from {', '.join(WORKLOADS)}")
        workloads = [w for w in WORKLOADS if w in wanted]
    n_slice = args.slice if args.slice is not None else (30 if args.quick else 2000)

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    if args.report_only:
        res = json.loads((out / "results.json").read_text())
        variants, jobs = [Variant(**v) for v in res["variants"]], [Job(**j) for j in res["jobs"]]
        md = write_report(args, jobs, variants, res["info"], args.docs)
        png = write_plot(jobs, variants, res["info"]["workloads"], args.docs / "determinism.png")
        print(f"wrote {md}" + (f" and {png}" if png else ""))
        return res["status"]
    if args.rev:
        src = out / "src"
        commit = export_rev(args.rev, src)
        source, dirty_before, code_root = f"`git archive {args.rev}`; working-tree edits not included", None, src
    else:
        dirty, dirty_before = working_tree_state()
        commit = (git("rev-parse", "--short", "HEAD") or "unknown") + ("+dirty" if dirty else "")
        source, code_root = (f"working tree; uncommitted edits fingerprint {dirty_before}" if dirty
                             else "working tree"), REPO

    # The plans: the demo's and the paper's, written by the CLI, and the paper slice, in one prep process.
    plans = out / "plans"
    plans.mkdir(exist_ok=True)
    prep_log = out / "prep.log"
    for flag, name in (("--demo", "demo.toml"), ("--paper", "paper.toml")):
        rc, _, tail = run_child({"kind": "author", "argv": ["plan", flag, "--out", str(plans / name)]}, {}, plans,
                                code_root, prep_log, 300)
        if rc != 0:
            raise SystemExit(f"error: allo-usd plan {flag} failed:\n{tail}")
    slice_info = {}
    if "paper-slice" in workloads:
        spec = {"kind": "prep", "argv": [str(plans), str(n_slice), str(plans / "paper.toml"),
                                         *(d.isoformat() for d in SLICE_DAYS)]}
        rc, _, tail = run_child(spec, {}, plans, code_root, prep_log, 600)
        if rc != 0:
            raise SystemExit(f"error: could not make the paper slice:\n{tail}")
        slice_info = json.loads(next(line for line in reversed(prep_log.read_text().splitlines())
                                     if line.startswith("{")))

    demo_argv = ["--limit", "7"] if args.quick else []
    specs = {
        "demo": lambda d: {"kind": "author", "argv": ["author", str(plans / "demo.toml"), "--out", str(d),
                                                      "--workers", "1", "--no-progress", *demo_argv]},
        "paper-slice": lambda d: {"kind": "author", "argv": ["author", slice_info.get("plan", ""), "--out", str(d),
                                                             "--workers", "1", "--no-progress"]},
        "base-stage": lambda d: {"kind": "stage", "script": str(code_root / BASE_STAGE_SCRIPT),
                                 "argv": ["--out", str(d)]},
    }
    jobs: list[Job] = []
    for w in workloads:
        for v in variants:
            if v.skip:
                continue
            d = out / "trees" / w / v.name
            jobs.append(Job(w, v.name, v.env, str(d)))
    # the base stage (the longest) first, so that two runs at a time finish together
    order = sorted(jobs, key=lambda j: (WORKLOADS.index(j.workload) != 2, j.variant != "baseline"))

    def run(job: Job) -> Job:
        import shutil

        shutil.rmtree(job.out, ignore_errors=True)
        logs = out / "logs"
        logs.mkdir(exist_ok=True)
        probe = logs / f"{job.workload}.{job.variant}.json"
        probe.unlink(missing_ok=True)
        spec = {**specs[job.workload](Path(job.out)), "probe": str(probe)}
        job.rc, job.seconds, job.stderr_tail = run_child(spec, job.env, out / "cwd" / f"{job.workload}.{job.variant}",
                                                         code_root, logs / f"{job.workload}.{job.variant}.log",
                                                         args.timeout)
        if probe.is_file():
            job.in_force = json.loads(probe.read_text())
        print(f"{job.workload:12s} {job.variant:14s} exit {job.rc} {job.seconds:7.1f} s", flush=True)
        return job

    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        list(pool.map(run, order))

    status = 0
    for j in jobs:
        base = next(b for b in jobs if b.workload == j.workload and b.variant == "baseline")
        if j.rc != 0:
            status = 2
            continue
        if base.rc == 0:
            j.compared, j.differing = compare_trees(Path(base.out), Path(j.out))
            if j.differing and status == 0:
                status = 1
        where = j.in_force.get("allo_usd", "")
        if where and not Path(where).resolve().is_relative_to(Path(code_root).resolve()):
            print(f"warning: {j.workload}/{j.variant} imported allo_usd from {where}, not {code_root}", file=sys.stderr)

    tree_changed = False
    if not args.rev:
        tree_changed = working_tree_state()[1] != dirty_before
    load_after = tuple(round(x, 2) for x in os.getloadavg())
    if slice_info:
        days = slice_info["days"]
        slice_doc = (f"paper-slice = the paper plan on {len(days)} days ({days[0]} .. {days[-1]}, every "
                     f"{(date.fromisoformat(days[1]) - date.fromisoformat(days[0])).days if len(days) > 1 else 0} "
                     f"days) with counts {slice_info['counts']} scaled from its {slice_info['paper_scenes']:,}: "
                     f"{slice_info['scenes']} planned scenes, plus their top-up")
    else:
        slice_doc = ""
    workloads_doc = "; ".join(filter(None, [
        "demo = the demo plan" + (" (its first 7 scenes)" if args.quick else " (16 scenes)") if "demo" in workloads else "",
        slice_doc,
        "base-stage = python -m scripts.make_base_stage --out DIR" + _own_pin(jobs)
        if "base-stage" in workloads else ""]))
    info = {"commit": commit, "source": source, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "cpu": cpu, "glibc": glibc_tunable(), "load_before": load_before, "load_after": load_after,
            "command": shlex.join(["python", "-m", "scripts.check_determinism",
                                   *(sys.argv[1:] if argv is None else argv)]),
            "workloads": workloads, "workloads_doc": workloads_doc, "tree_changed": tree_changed,
            "total_seconds": time.perf_counter() - t_start, "slice": slice_info}
    md = write_report(args, jobs, variants, info, args.docs)
    png = write_plot(jobs, variants, workloads, args.docs / "determinism.png")
    (out / "results.json").write_text(json.dumps({"info": info, "variants": [asdict(v) for v in variants],
                                                  "jobs": [asdict(j) for j in jobs], "status": status}, indent=1))
    print(f"wrote {md}" + (f" and {png}" if png else "") + f"; results in {out / 'results.json'}")
    if tree_changed:
        print("warning: the working tree changed during the runs", file=sys.stderr)
    print({0: "no file differs", 1: "files differ (see the table)", 2: "a run failed"}[status])
    return status


if __name__ == "__main__":
    sys.exit(main())
