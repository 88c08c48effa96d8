"""Every scripts/bench_*.py runs (issue 28, "benchmarks that stay true").

Each script runs in a subprocess with the smallest arguments it accepts (a few scenes, 32x18 or
64x36 pixels, 1-2 samples), writes into tmp_path (never into docs/ or out/), and its table (.md
and/or .csv) and plot (.png) must be there with the expected columns. SMOKE lists the arguments
per script and must name every scripts/bench_*.py (a new script without a smoke run fails
test_every_bench_script_has_a_smoke_run), except the scripts whose smoke run lives in another test
(COVERED_ELSEWHERE). bench_gpu.py runs its CPU rows (its fallback on a machine without a GPU).
"""

from __future__ import annotations

import csv
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
TESTS = Path(__file__).resolve().parent

pytestmark = pytest.mark.slow

# script -> the test that runs it (its smallest run and its table), and the test's name there.
COVERED_ELSEWHERE = {
    "bench_rerender.py": ("test_rerender_record.py", "test_bench_rerender_writes_its_table_and_plot"),
    "check_determinism.py": ("test_determinism.py", "test_check_determinism_quick"),
}

# script -> its runs, in order (each a list of arguments; {out}, {tmp} and {layer} are filled in:
# {layer} is a 32x18, 1-sample scene layer over the tests' tiny base stage).
SMOKE: dict[str, list[list[str]]] = {
    "bench_accuracy.py": [  # the report after the reference alone, then after the presets alone
        ["--phase", "reference", "--layer", "{layer}", "--ref-samples", "2", "--cache", "{tmp}/cache",
         "--out", "{out}"],
        ["--phase", "presets", "--layer", "{layer}", "--ref-samples", "2", "--cache", "{tmp}/cache",
         "--out", "{out}"],
    ],
    "bench_author.py": [["--normal", "5", "--placements", "2", "--workers", "1", "--out", "{out}/bench_author.md"]],
    "bench_gpu.py": [["--layer", "{layer}", "--size", "32x18", "--cpu-size", "32x18", "--presets", "draft,preview",
                      "--out", "{out}"]],
    "bench_light_linking.py": [["--size", "32x18", "--samples", "1", "--poses", "3", "--work", "{tmp}/work",
                                "--out", "{out}"]],
    "bench_placement.py": [["--n", "3", "--check-scenes", "2", "--render-scenes", "1", "--reps", "1",
                            "--resolution", "64x36", "--out", "{out}"]],
    "bench_session.py": [["--quick", "--scenes", "10", "--repeats", "1", "--identity", "2", "--out", "{tmp}/work",
                          "--docs", "{out}"]],
    "bench_sky.py": [["--runs", "1", "--phases", "1", "--out", "{out}"]],
    "bench_workers.py": [["--scenes", "2", "--width", "32", "--height", "18", "--samples", "1", "--out", "{out}"]],
}
NO_RENDER = {"bench_author.py", "bench_sky.py"}

ACCURACY_CSV = ["group", "preset", "samples", "denoiser", "adaptive", "bounces", "scale", "seconds", "wall",
                "psnr_srgb8", "psnr_linear", "ssim_srgb8", "loadavg"]
# script -> {file written: the CSV's columns, or a table header line the .md holds}; every run writes a plot too.
EXPECT: dict[str, dict[str, list[str] | str]] = {
    "bench_accuracy.py": {"bench_accuracy.csv": ACCURACY_CSV,
                          "bench_accuracy.md": "| setting | seconds | PSNR sRGB | PSNR linear | SSIM |"},
    "bench_author.py": {"bench_author.md": "| part | per unit | full plan, 1 core |"},
    "bench_gpu.py": {"bench_gpu.csv": ["device", "preset", "size", "samples", "seconds", "seconds_first",
                                       "rerender_identical", "psnr_vs_cpu", "speedup_vs_cpu"],
                     "bench_gpu.md": "| device | preset | size | spp | seconds | identical re-render | "
                                     "PSNR vs CPU (dB) | speed-up vs CPU |"},
    "bench_light_linking.py": {"bench_light_linking.md": "| case | pose | station px | allo-usd radiance | "
                                                         "ratio as imported | ratio undone | as rendered (undone) | "
                                                         "view error | imported lamps (W/m², W) |"},
    "bench_placement.py": {"bench_placement.csv": ["scene_id", "asset", "variant", "pose", "day", "predicted_px",
                                                   "rendered_px", "abs_diff_px", "rel_diff", "pass", "xor_px",
                                                   "attempts", "depths_skipped", "resolve_ms", "render_1spp_s",
                                                   "build_render_1spp_s"],
                           "bench_placement.md": "| metric | value | target | |"},
    "bench_session.py": {"bench_session.md": "| step | median seconds | share of the preview render |"},
    "bench_sky.py": {"bench_sky.md": "| what | ms |"},
    "bench_workers.py": {"bench_workers.md": "| workload | workers | Cycles threads each | seconds | images/hour | "
                                             "load average before -> after |"},
}
PLOTS = {name: name.replace(".py", ".png") for name in SMOKE} | {"bench_author.py": None}   # bench_author: a table only


def test_every_bench_script_has_a_smoke_run():
    scripts = {p.name for p in SCRIPTS.glob("bench_*.py")}
    assert scripts - set(COVERED_ELSEWHERE) == set(SMOKE), "give every scripts/bench_*.py a smoke run in SMOKE"
    assert set(SMOKE) == set(EXPECT) == set(PLOTS)
    for script, (test_file, test_name) in COVERED_ELSEWHERE.items():
        assert (SCRIPTS / script).is_file(), script
        text = (TESTS / test_file).read_text()
        assert f"def {test_name}(" in text and script in text, (script, test_file)


@pytest.fixture(scope="module")
def small_layer(tiny_base, tmp_path_factory):
    """A 32x18, 1-sample normal scene over the tiny base stage."""
    from allo_usd.usd.scene_layer import write_scene_layer

    from helpers import make_spec

    return write_scene_layer(make_spec(resolution=(32, 18), samples=1), tmp_path_factory.mktemp("bench") /
                             "layers" / "small.usda", tiny_base)


def _docs_state() -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in (ROOT / "docs").glob("bench_*")}


def _check(script: str, out: Path) -> dict[str, str]:
    texts = {}
    for name, want in EXPECT[script].items():
        path = out / name
        assert path.is_file(), f"{script} wrote no {name}: {sorted(p.name for p in out.iterdir())}"
        text = texts[name] = path.read_text()
        if name.endswith(".csv"):
            assert next(csv.reader(text.splitlines())) == want, name
        else:
            assert text.startswith("# "), name
            assert want in text.splitlines(), f"{name} has no table header {want!r}"
    if PLOTS[script]:
        from PIL import Image

        with Image.open(out / PLOTS[script]) as im:
            assert im.format == "PNG" and im.size[0] > 100 and im.size[1] > 100
    return texts


@pytest.mark.parametrize("script", [pytest.param(s, marks=() if s in NO_RENDER else pytest.mark.render)
                                    for s in sorted(SMOKE)])
def test_bench_smoke(script, tmp_path, request):
    out = tmp_path / "docs"
    docs_before = _docs_state()
    needs_layer = any("{layer}" in a for run in SMOKE[script] for a in run)
    layer = request.getfixturevalue("small_layer") if needs_layer else None
    for k, run in enumerate(SMOKE[script]):
        args = [a.format(out=out, tmp=tmp_path, layer=layer) for a in run]
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, str(SCRIPTS / script), *args], capture_output=True, text=True, cwd=ROOT,
                           timeout=240)
        assert r.returncode == 0, f"{script} {' '.join(args)}:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
        print(f"{script} run {k + 1}: {time.perf_counter() - t0:.1f} s")
        texts = _check(script, out)
        if script == "bench_accuracy.py":
            rows = list(csv.DictReader(texts["bench_accuracy.csv"].splitlines()))
            if k == 0:   # the reference alone: no rows, an empty front, still a report and a plot
                assert rows == [] and "## Presets" not in texts["bench_accuracy.md"]
            else:        # the presets alone
                from allo_usd.plan.settings import PRESETS

                assert {r["preset"] for r in rows} == set(PRESETS) and {r["group"] for r in rows} == {"preset"}
                assert "## Presets" in texts["bench_accuracy.md"]
    if script == "bench_gpu.py":   # the CPU rows are always there; GPU rows only where Cycles finds a GPU
        rows = list(csv.DictReader(texts["bench_gpu.csv"].splitlines()))
        assert [r["preset"] for r in rows if not r["device"].startswith("GPU")][:2] == ["draft", "preview"]
    assert _docs_state() == docs_before, "a smoke run wrote into docs/"
