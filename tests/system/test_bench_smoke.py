"""Every scripts/bench_*.py runs, so the benchmarks stay true.

Each script runs in a subprocess with the smallest arguments it accepts (a few scenes, 32x18 or
64x36 pixels, 1-2 samples), writes into tmp_path (never into docs/ or out/), and its table (.md
and/or .csv) and plot (.png) must be there with the expected columns. SMOKE lists the arguments
per script and must name every scripts/bench_*.py (a new script without a smoke run fails
test_every_bench_script_has_a_smoke_run), except the scripts whose smoke run lives in another test
(COVERED_ELSEWHERE). bench_gpu.py runs its CPU rows (its fallback on a machine without a GPU).
"""

from __future__ import annotations

import csv
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from scripts import benchinfo

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = ROOT / "scripts"
TESTS = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs" / "benchmarks"

SHA = re.compile(r"commit `?([0-9a-f]{7,40})`?( \(dirty\))?")

pytestmark = pytest.mark.slow

# script -> the test that runs it (its smallest run and its table), and the test's name there.
COVERED_ELSEWHERE = {
    "bench_rerender.py": ("blender/test_device_record.py", "test_bench_rerender_writes_its_table_and_plot"),
    "check_determinism.py": ("system/test_determinism.py", "test_check_determinism_quick"),
}

# script -> its runs, in order (each a list of arguments; {out}, {tmp} and {layer} are filled in:
# {layer} and {layer2} are 32x18, 1-sample scene layers over the tests' tiny base stage, two views).
SMOKE: dict[str, list[list[str]]] = {
    "bench_accuracy.py": [  # two views; the report after the reference alone (2 chunks: its noise is measured),
        # then after the presets alone, then with the target mode and the fixed sweep of the layer's denoiser
        ["--phase", "reference", "--layer", "{layer}", "--layer", "{layer2}", "--ref-samples", "2", "--ref-chunk", "1",
         "--cache", "{tmp}/cache", "--out", "{out}"],
        ["--phase", "presets", "--layer", "{layer}", "--layer", "{layer2}", "--ref-samples", "2", "--ref-chunk", "1",
         "--rounds", "1", "--cache", "{tmp}/cache", "--out", "{out}"],
        ["--phase", "target", "--layer", "{layer}", "--layer", "{layer2}@48x27", "--ref-samples", "2",
         "--ref-chunk", "1", "--targets", "20", "--target-cap", "64", "--cache", "{tmp}/cache", "--out", "{out}"],
        ["--phase", "sweep", "--layer", "{layer}", "--layer", "{layer2}@48x27", "--ref-samples", "2",
         "--ref-chunk", "1", "--oidn-samples", "1,2", "--cache", "{tmp}/cache", "--out", "{out}"],
    ],
    "bench_amodal.py": [["--layer", "{layer2}", "--sizes", "32x18,64x36", "--samples", "1", "--repeats", "1",
                         "--work", "{tmp}/work", "--out", "{out}"]],
    "bench_author.py": [["--normal", "5", "--placements", "2", "--workers", "1", "--out", "{out}/bench_author.md"]],
    "bench_gpu.py": [["--layer", "{layer}", "--size", "32x18", "--cpu-size", "32x18", "--presets", "draft,preview",
                      "--out", "{out}"]],
    "bench_light_linking.py": [["--size", "32x18", "--samples", "1", "--poses", "3", "--work", "{tmp}/work",
                                "--out", "{out}"]],
    "bench_placement.py": [["--n", "3", "--check-scenes", "2", "--render-scenes", "1", "--reps", "1",
                            "--resolution", "64x36", "--out", "{out}"]],
    "bench_scale.py": [["--plan", "demo", "--skip-author", "--cache", "{tmp}/tree", "--work", "{tmp}/work",
                        "--verify-sample", "2", "--add", "4", "--evict", "fadvise", "--out", "{out}"]],
    "bench_session.py": [["--quick", "--scenes", "10", "--repeats", "1", "--identity", "2", "--out", "{tmp}/work",
                          "--docs", "{out}"]],
    "bench_sky.py": [["--runs", "1", "--phases", "1", "--out", "{out}"]],
    "bench_workers.py": [["--scenes", "2", "--width", "32", "--height", "18", "--samples", "1", "--out", "{out}"]],
}
NO_RENDER = {"bench_author.py", "bench_scale.py", "bench_sky.py"}

ACCURACY_CSV = ["view", "group", "preset", "samples", "denoiser", "adaptive", "bounces", "scale", "seconds", "wall",
                "x_paper", "psnr_srgb8", "psnr_vs_paper", "psnr_linear", "ssim_srgb8", "psnr_converged", "ref_samples",
                "measured_mse", "measured_stderr", "target_psnr", "est_psnr", "est_low", "est_minus_measured", "z",
                "rounds", "stopped_by", "size", "loadavg"]
# script -> {file written: the CSV's columns, or a table header line the .md holds}; every run writes a plot too.
EXPECT: dict[str, dict[str, list[str] | str]] = {
    "bench_accuracy.py": {"bench_accuracy.csv": ACCURACY_CSV,
                          "bench_accuracy.md": "| view | reference spp | reference CPU s | PSNR of its two independent "
                                               "halves (dB) | its own noise: est. PSNR vs converged (dB) |"},
    "bench_amodal.py": {"bench_amodal.md": "| size | samples | RGB render s | amodal render s | amodal / RGB | "
                                           "ray cast s | amodal px | visible px | pass vs ray cast: differing px |"},
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
    "bench_scale.py": {"bench_scale.md": "| figure | seconds | per scene | CPU s | peak RSS (MB) | load before -> after "
                                         "| goal |"},
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

    from tests.support.helpers import make_spec

    return write_scene_layer(make_spec(resolution=(32, 18), samples=1), tmp_path_factory.mktemp("bench") /
                             "layers" / "small.usda", tiny_base)


@pytest.fixture(scope="module")
def small_layer2(tiny_base, tmp_path_factory):
    """A second view for the scripts that take several: the anomalous scene, 32x18, 1 sample."""
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    return write_scene_layer(make_spec(anomaly=True, resolution=(32, 18), samples=1),
                             tmp_path_factory.mktemp("bench") / "layers" / "small_anomaly.usda", tiny_base)


def _docs_state() -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in DOCS.glob("bench_*")}


def _git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=60)


def header_lines(text: str) -> list[str]:
    """The benchinfo header lines of a docs/benchmarks/bench_*.md: right under its title, before the first table."""
    top = text.split("\n|", 1)[0].splitlines()[:12]
    return [line for line in top if line.startswith(benchinfo.HEADER_START)]


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
            heads = header_lines(text)   # the run's own header: this checkout's commit, this CPU, the command
            assert heads, f"{name} has no {benchinfo.HEADER_START!r} header line"
            assert SHA.search(heads[-1]).group(1) == _git("rev-parse", "HEAD").stdout.strip(), heads[-1]
            assert f"command: `python -m scripts.{script.removesuffix('.py')} " in heads[-1] \
                and benchinfo.cpu_info()["model"] in heads[-1]
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
    layer2 = request.getfixturevalue("small_layer2") if any("{layer2}" in a for run in SMOKE[script] for a in run) \
        else None
    for k, run in enumerate(SMOKE[script]):
        args = [a.format(out=out, tmp=tmp_path, layer=layer, layer2=layer2) for a in run]
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", f"scripts.{script.removesuffix('.py')}", *args],
                           capture_output=True, text=True, cwd=ROOT, timeout=240)
        assert r.returncode == 0, f"{script} {' '.join(args)}:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
        print(f"{script} run {k + 1}: {time.perf_counter() - t0:.1f} s")
        texts = _check(script, out)
        if script == "bench_accuracy.py":
            rows = list(csv.DictReader(texts["bench_accuracy.csv"].splitlines()))
            md = texts["bench_accuracy.md"]
            if k == 0:   # the reference alone: no rows, still a report (each view's reference) and a plot
                assert rows == [] and "## P1 per view" not in md
                assert "| small | 2 |" in md and "| small_anomaly | 2 |" in md, md
            elif k == 1:  # the presets alone, on both views, scored against the references, relative to paper
                from allo_usd.plan.settings import PRESETS

                assert {(r["view"], r["preset"]) for r in rows} == {(v, p) for v in ("small", "small_anomaly")
                                                                    for p in PRESETS}
                assert {r["group"] for r in rows} == {"preset"}
                for r in rows:
                    assert 0.0 < float(r["psnr_srgb8"]) < 100.0 and r["ref_samples"] == "2", r
                    if r["preset"] == "paper":
                        assert float(r["x_paper"]) == 1.0 and float(r["psnr_vs_paper"]) == 0.0
                for heading in ("## P1 per view", "### small ", "### small_anomaly ", "## P1 overall",
                                "## Does the reference cap the PSNR?"):
                    assert heading in md, heading
                for r in rows:   # every fixed row carries the renderer's estimate (a second, independent render)
                    assert 0.0 < float(r["est_psnr"]) < 100.0 and r["stopped_by"] == "samples", r
            elif k == 2:  # the target mode without denoise (and with it where blender.oidn is there), each view
                targets = [r for r in rows if r["group"] == "target"]
                assert {r["view"] for r in targets if r["denoiser"] == "off"} == {"small", "small_anomaly"}, targets
                for r in targets:
                    assert r["target_psnr"] == "20.0000" and r["stopped_by"] in ("target", "samples"), r
                    assert 0 < int(r["samples"]) <= 64 and float(r["est_psnr"]) > 0.0, r
                assert {r["size"] for r in targets} == {"32x18", "48x27"}   # a view's own size: PATH@WxH
                assert "## Time to 35, 40 and 45 dB per view" in md
                assert "## The estimate against the measured PSNR, every row" in md
                assert "| small | target 20 | " in md and "| small_anomaly | target 20 | " in md, md
            else:         # the fixed sweep of the layer's own denoiser, 1 and 2 spp, each with its estimate
                sweep = [r for r in rows if r["group"] == "sweep"]
                assert {(r["view"], r["samples"]) for r in sweep} == {(v, n) for v in ("small", "small_anomaly")
                                                                      for n in ("1", "2")}, sweep
                assert all(float(r["est_psnr"]) > 0.0 for r in sweep)
    if script == "bench_gpu.py":   # the CPU rows are always there; GPU rows only where Cycles finds a GPU
        rows = list(csv.DictReader(texts["bench_gpu.csv"].splitlines()))
        assert [r["preset"] for r in rows if not r["device"].startswith("GPU")][:2] == ["draft", "preview"]
    assert _docs_state() == docs_before, "a smoke run wrote into docs/"


def test_benchinfo_header(tmp_path):
    """The header names this checkout's commit (dirty or not, as git status says), the CPU's SIMD sets
    as /proc/cpuinfo lists them, the load before and after, and the command as typed."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nmodel name\t: Test CPU 9000\nflags\t\t: fpu sse2 sse4_2 avx avx2 fma\n\n"
                       "processor\t: 1\nmodel name\t: Test CPU 9000\nflags\t\t: fpu sse2 sse4_2 avx avx2 fma\n")
    cpu = benchinfo.cpu_info(cpuinfo)
    assert cpu["model"] == "Test CPU 9000" and cpu["simd"] == ["sse4_2", "avx", "avx2", "fma"] and cpu["cores"] >= 1
    run = benchinfo.start([str(SCRIPTS / "bench_sky.py"), "--runs", "1", "--out", "a b"])
    assert run["load_after"] is None
    benchinfo.finish(run)
    head = benchinfo.header(run)
    sha = _git("rev-parse", "HEAD").stdout.strip()
    dirty = bool(_git("status", "--porcelain", "--untracked-files=no").stdout.strip())
    assert SHA.search(head).groups() == (sha, " (dirty)" if dirty else None), head
    assert head.startswith(benchinfo.HEADER_START)
    assert "command: `python -m scripts.bench_sky --runs 1 --out 'a b'`" in head
    assert "before" in head and "after" in head and "not recorded" not in head
    assert all(f in head for f in benchinfo.cpu_info()["simd"])


def test_every_bench_doc_names_its_commit_cpu_load_and_command():
    """Each docs/benchmarks/bench_*.md opens with a header naming a commit that exists in this repository's
    history, the CPU, the load and the command (benchinfo.header, or the same written by hand for a
    doc measured before the header existed)."""
    docs = sorted(DOCS.glob("bench_*.md"))
    assert docs
    for doc in docs:
        heads = header_lines(doc.read_text())
        assert heads, f"{doc.name}: no {benchinfo.HEADER_START!r} line under its title; re-run its script"
        for head in heads:
            m = SHA.search(head)
            assert m, f"{doc.name}: its header names no commit: {head}"
            assert _git("cat-file", "-e", f"{m.group(1)}^{{commit}}").returncode == 0, \
                f"{doc.name}: commit {m.group(1)} is not in this repository's history"
            for word in ("CPU", "load", "command"):
                assert word in head, f"{doc.name}: its header does not name the {word}: {head}"
