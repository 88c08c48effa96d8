"""Authored bytes do not depend on the CPU's SIMD path (the same bytes on every machine).

The demo plan's first 7 scenes (the set tests/system/test_golden.py compares) are authored in fresh
subprocesses with numpy's dispatched loops pushed down (NPY_DISABLE_CPU_FEATURES: no AVX2/FMA3, and
down to numpy's SSE3 baseline) and with libm's AVX/FMA ifunc variants turned off (GLIBC_TUNABLES,
when this glibc takes it), and every file of each tree must equal the tree authored in this process.
Each subprocess also reports that the variant took effect. OPENBLAS_CORETYPE and OPENBLAS_L2_SIZE
are left as the machine sets them (scripts/check_determinism.py varies the BLAS kernel).

Also: scripts/check_determinism.py --quick runs and writes its table.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from scripts import check_determinism as cd
from tests.support.goldens import LIMIT, author_demo

pytestmark = pytest.mark.slow   # about 30 s: five authoring subprocesses and the script's quick run

ROOT = Path(__file__).resolve().parents[2]

CHILD = """
import json, sys
from pathlib import Path
from tests.support.goldens import author_demo
author_demo(Path(sys.argv[1]))
from scripts.check_determinism import in_force
print(json.dumps(in_force()))
"""


def _variants() -> dict[str, dict[str, str]]:
    no_avx2, _ = cd.npy_disable("F16C")     # FMA3, AVX2 and every AVX-512 target off
    sse3, _ = cd.npy_disable("SSE3")        # every dispatched target off: numpy's baseline only
    out = {"npy-no-avx2": {"NPY_DISABLE_CPU_FEATURES": no_avx2},
           "npy-sse3": {"NPY_DISABLE_CPU_FEATURES": sse3}}
    tunable, _ = cd.glibc_tunable()
    if tunable:
        out["glibc-no-avx"] = {"GLIBC_TUNABLES": tunable}
        out["npy-sse3+glibc"] = {"NPY_DISABLE_CPU_FEATURES": sse3, "GLIBC_TUNABLES": tunable}
    return out


VARIANTS = _variants()


def _author_in_subprocess(env_extra: dict[str, str], out: Path) -> dict:
    env = {**os.environ, **env_extra}   # OPENBLAS_CORETYPE / OPENBLAS_L2_SIZE untouched
    r = subprocess.run([sys.executable, "-c", CHILD, str(out)], env=env, cwd=ROOT,   # -c puts the cwd first on sys.path
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"authoring under {env_extra} failed:\n{r.stderr[-3000:]}"
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def trees(tmp_path_factory):
    """{"in-process": (tree, in force), variant: (tree, in force)}; the subprocesses two at a time."""
    root = tmp_path_factory.mktemp("determinism")
    author_demo(root / "in-process")
    with ThreadPoolExecutor(2) as pool:
        futures = {name: pool.submit(_author_in_subprocess, env, root / name) for name, env in VARIANTS.items()}
        out = {name: (root / name, f.result()) for name, f in futures.items()}
    out["in-process"] = (root / "in-process", cd.in_force())
    return out


def test_glibc_tunable_is_found_where_glibc_reads_it():
    """glibc >= 2.33 lists its active CPU features (ld.so --list-diagnostics); there the tunable must
    be found, or the glibc variant would silently test nothing."""
    version = tuple(int(x) for x in re.findall(r"\d+", os.confstr("CS_GNU_LIBC_VERSION") or "")[:2] or (0, 0))
    if version < (2, 33):
        pytest.skip(f"glibc {version}: no --list-diagnostics to check the tunable's spelling with")
    assert "glibc-no-avx" in VARIANTS, cd.glibc_tunable()[1]


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_tree_is_byte_identical(trees, variant):
    ref, _ = trees["in-process"]
    got, _ = trees[variant]
    compared, differing = cd.compare_trees(ref, got)
    assert compared >= 2 * LIMIT, f"only {compared} files in the trees"
    assert not differing, (f"{len(differing)} of {compared} files differ under {VARIANTS[variant]}: "
                           f"{differing[:10]}; run scripts/check_determinism.py for the attributes")


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_variant_took_effect(trees, variant):
    """The subprocess really ran with the features disabled (not a silently ignored variable)."""
    _, here = trees["in-process"]
    _, there = trees[variant]
    env = VARIANTS[variant]
    if "NPY_DISABLE_CPU_FEATURES" in env:
        off = set(env["NPY_DISABLE_CPU_FEATURES"].split())
        assert not off & set(there["numpy_enabled"]), there["numpy_enabled"]
        assert set(there["numpy_enabled"]) >= set(there["numpy_baseline"])
    if "GLIBC_TUNABLES" in env:
        moved = [k for k, v in there["libm"].items() if here["libm"].get(k) != v]
        has_avx_fma = {"AVX2", "FMA3"} <= set(here["numpy_enabled"])   # numpy's own CPUID check
        if has_avx_fma:
            assert moved, f"libm's ifuncs resolved as without {env['GLIBC_TUNABLES']}: {there['libm']}"


def test_check_determinism_quick(tmp_path):
    out, docs = tmp_path / "out", tmp_path / "docs"
    r = subprocess.run([sys.executable, "-m", "scripts.check_determinism", "--quick", "--variants", "npy-sse3",
                        "--out", str(out), "--docs", str(docs)], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode in (0, 1), f"exit {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    md = (docs / "determinism.md").read_text()
    header = "| workload | variant | environment | files compared | files differing | in force | seconds |"
    assert header in md
    for key in ("- commit: `", "- date: ", "- CPU: ", "SIMD flags: ", "- numpy ", "OpenBLAS: ",
                "- load average (1, 5, 15 min): before ", "- command: `python -m scripts.check_determinism --quick"):
        assert key in md, f"{key!r} missing from the header"
    rows = {tuple(c.strip() for c in line.strip("|").split("|")[:2]): line
            for line in md.splitlines() if line.startswith("| ") and not line.startswith(("| workload", "|---"))}
    assert set(rows) == {(w, v) for w in ("demo", "paper-slice") for v in ("baseline", "npy-sse3")}, rows
    row = [c.strip() for c in rows[("demo", "npy-sse3")].strip("|").split("|")]
    assert int(row[3]) > 2 * LIMIT and re.fullmatch(r"\d+( \(.*\))?", row[4]), row
    assert "numpy baseline" in row[5] and float(row[6]) > 0, row
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == r.returncode
    assert (docs / "determinism.png").stat().st_size > 0
