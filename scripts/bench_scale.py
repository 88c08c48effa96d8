"""Benchmark the paper's scale and write docs/benchmarks/bench_scale.md and docs/benchmarks/bench_scale.png.

What it times, each in a subprocess through the real command line (peak memory from the child's
rusage, the machine's load average before and after every figure):

- `allo-usd author` of the plan from scratch, then again as a resume with nothing to do;
- the resume decision of `allo-usd render TREE --out RENDERS` over a finished render folder of the
  whole plan (the quick check of every scene: nothing renders), with the page cache dropped first;
- the same decision with `--verify` (every output read and checksummed) on a sample of scenes whose
  outputs are distinct files, extrapolated to the plan;
- `allo-usd dataset` over all but `--add` records, then a re-run after the last `--add` arrive.

The finished render folder has real-size outputs: one synthesised image (PNG), linear EXR and a
normal and an anomalous mask at the plan's resolution, hard-linked into every scene (the sample's
are copies, so that `--verify` reads distinct data), and for each scene a render JSON that is the
real record of its own layer (read_scene, the dependency walk's inputs and identity, annotations of
its mask) and a manifest row made with allo_usd.run.render_index.manifest_row. The authored tree is
kept in `--cache` and reused; the render folder in `--work` is rebuilt only when the tree changes.

The page cache is dropped with /proc/sys/vm/drop_caches where the process may write it, else every
file of the tree and the render folder is evicted with posix_fadvise(POSIX_FADV_DONTNEED) (the
table says which was used).

    python -m scripts.bench_scale --quick              # the paper plan over 14 days: 1,972 scenes
    python -m scripts.bench_scale                      # the paper plan: 51,409 scenes
    python -m scripts.bench_scale --plan demo --skip-author --out /tmp/docs
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # before numpy loads, as authoring's workers run
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shlex  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from scripts import benchinfo  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent

CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()"]
QUICK_DAYS = 14  # the paper plan over its first 14 days: 1,972 scenes
GOALS = {"author": 120.0, "author_noop": 30.0, "resume": 60.0}  # seconds, the "done means"
REAL_SIZES = "EXR 5.6 MB, PNG 1.2 MB, mask 21 KB, JSON 7 KB"  # a real 1080p render's outputs
STAMP = "bench-scale.json"  # in --work: what the render folder was built from
SETTLE_S = 300  # after removing a previous benchmark's scratch trees: ext4 stops skipping freed inodes
LINKS_PER_SOURCE = 20000  # scenes per synthesised source file: the render folder's link and the dataset's make two
                          # each, under ext4's 65,000 links per inode (past it `dataset` copies instead of linking)


# ---------------------------------------------------------------- the machine

def load() -> float:
    return round(os.getloadavg()[0], 1)


def run(args: list[str], what: str, ok=(0,)) -> dict:
    """`args` in a child process: wall seconds, CPU seconds and peak RSS (the largest of the child and
    the descendants it waited for, from wait4), the load average before and after."""
    import tempfile

    before = load()
    timed = Path("/usr/bin/time").is_file()  # a small parent: a child forked from this (large) process would
    if timed:                                # report this process's RSS as its own peak (Linux keeps it over exec)
        args = ["/usr/bin/time", "-f", "peak_rss_kb=%M", *args]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(args, cwd=ROOT, stdout=out, stderr=err, env={**os.environ, "PYTHONPATH": str(ROOT)})
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - t0
        proc.returncode = code = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if code not in ok:
        raise SystemExit(f"{what} failed (exit {code}): {shlex.join(args)}\n{stdout[-2000:]}\n{stderr[-2000:]}")
    peak_kb = usage.ru_maxrss
    if timed and stderr.rstrip().rpartition("\n")[2].startswith("peak_rss_kb="):
        stderr, _, last = stderr.rstrip().rpartition("\n")
        peak_kb = int(last.split("=", 1)[1])
    return {"what": what, "seconds": seconds, "cpu": usage.ru_utime + usage.ru_stime,
            "peak_mb": peak_kb / 1024, "load": (before, load()), "stdout": stdout, "stderr": stderr,
            "code": code}


# ---------------------------------------------------------------- the page cache

EVICT = "drop"  # --evict: drop (the whole page cache where allowed, else fadvise), fadvise (our files only)


def drop_caches(roots: list[Path]) -> str:
    """Drop the page cache (root and a writable /proc/sys/vm), else evict every file under `roots`."""
    os.sync()
    why = "--evict fadvise"
    if EVICT == "drop":
        try:
            Path("/proc/sys/vm/drop_caches").write_text("3\n")
            return "dropped (echo 3 > /proc/sys/vm/drop_caches)"
        except OSError as exc:
            why = f"not droppable here: {exc.strerror or type(exc).__name__}"
    n = 0
    for root in roots:
        for dirpath, _, files in os.walk(root):
            for f in files:
                try:
                    fd = os.open(os.path.join(dirpath, f), os.O_RDONLY)
                except OSError:
                    continue
                try:
                    os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
                    n += 1
                finally:
                    os.close(fd)
    return f"{n:,} files of the tree and render folder evicted with posix_fadvise(POSIX_FADV_DONTNEED) ({why})"


# ---------------------------------------------------------------- the plan and its tree

def plan_file(name: str, work: Path) -> Path:
    from allo_usd import demo_plan, paper_plan, save_plan

    if name not in ("paper", "quick", "demo"):
        return Path(name)
    if name == "demo":
        plan = demo_plan()
    else:
        plan = paper_plan()
        if name == "quick":
            from scripts.bench_author import scaled_plan

            plan = scaled_plan(plan, QUICK_DAYS)
    path = work / f"plan-{name}.toml"
    work.mkdir(parents=True, exist_ok=True)
    save_plan(plan, path)
    return path


def calibrate() -> float:
    """CPU seconds of a fixed single-threaded workload (Python integer arithmetic and small numpy
    passes), reported beside each author run. On a shared virtual machine the speed moves by a
    third from hour to hour, unseen by the load average; this workload lives in the CPU's caches,
    so it sees a slower core but not contention for the shared cache and memory (docs/benchmarks/bench_scale.md
    records a morning when it stayed flat while unchanged code ran 12-30% slower)."""
    t = time.process_time()
    s = 0
    for i in range(1_500_000):
        s += i * i % 7
    a = np.random.default_rng(0).normal(size=4000)
    for _ in range(10_000):
        a = np.sqrt(a * a + 1.0) - 1.0
    return time.process_time() - t


def create_probe(where: Path, files: int = 1000) -> float:
    """Microseconds per small file created beside the author trees (`where`), as authoring writes its
    ~92,000 layers: an exclusive create, a write and a rename. Reported beside each author run: on
    ext4 without a journal (this machine's root) a create walks past every inode freed in the last
    minutes (fs/ext4/ialloc.c, recently_deleted), so right after a large tree is deleted a create can
    cost 1 ms instead of 80 us, a minute of a paper-plan run. The probe's files are kept until
    `cleanup` (deleting them would slow the next create)."""
    folder = where / f"probe-{time.time_ns()}"
    folder.mkdir(parents=True)
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL
    t = time.perf_counter()
    for i in range(files):
        fd = os.open(folder / f".{i}.tmp", flags, 0o600)
        os.write(fd, b"x" * 3000)
        os.close(fd)
        os.replace(folder / f".{i}.tmp", folder / f"{i}.usda")
    return 1e6 * (time.perf_counter() - t) / files


def author_runs(plan: Path, cache: Path, work: Path, skip: bool, repeat: int = 3) -> list[dict]:
    """`allo-usd author` from scratch (`repeat` times, each into a new tree; the figure is the fastest,
    as timeit reports, every run listed beside it with the machine's calibration and file-create
    probe) and as a resume with nothing to do: into the cache when it is empty, else into the first
    scratch tree. No timed run follows a deletion: scratch trees (and the probes' files) are removed
    only after the last timing, since on this machine's file system a create right after a large
    deletion costs up to ten times as much (`create_probe`). With `skip`, only what fills an empty
    cache (not reported)."""
    from allo_usd.usd.tree import COUNTS_CSV

    have = (cache / COUNTS_CSV).is_file()  # written when an author run ends
    if skip:
        if not have:
            run([*CLI, "author", str(plan), "--out", str(cache)], "author, to fill the cache")
        return []
    scratch = work / "author-scratch"
    if scratch.exists():   # a previous benchmark's, removed, then a pause for the file system to settle
        shutil.rmtree(scratch, ignore_errors=True)
        time.sleep(SETTLE_S)
    trees = [cache if not have and k == 0 else scratch / f"run{k}" for k in range(max(1, repeat))]
    try:
        runs = []
        for tree in trees:
            before, probe = calibrate(), create_probe(scratch)
            r = run([*CLI, "author", str(plan), "--out", str(tree)], "author, from scratch")
            r["calibration"] = (before, calibrate())
            r["create_us"] = probe
            runs.append(r)
        best = dict(min(runs, key=lambda r: r["seconds"]))
        best["runs"] = runs
        if len(runs) > 1:
            best["what"] = f"author, from scratch (fastest of {len(runs)})"
        return [best, run([*CLI, "author", str(plan), "--out", str(trees[0])], "author, resume with nothing to do")]
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


# ---------------------------------------------------------------- the finished render folder

def synthesize(src: Path, size: tuple[int, int]) -> dict[str, Path]:
    """One image, EXR and two masks (normal, anomalous) at `size`, made once: a dark sky, a lit
    station disc with sensor-like noise (so the PNG and EXR compress about as a render does), an
    anomaly patch in the anomalous mask."""
    from allo_usd.output.writers import write_mask_png, write_rgb_exr, write_rgb_png

    src.mkdir(parents=True, exist_ok=True)
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    disc = (xx - w / 2) ** 2 + (yy - h / 2) ** 2 < (0.3 * h) ** 2
    rng = np.random.default_rng(26)
    rgb = np.where(disc[..., None], 0.25, 0.0) + rng.normal(0, 0.01, (h, w, 3)) * disc[..., None]
    rgb = np.clip(rgb, 0, None).astype(np.float32)
    files = {"png": write_rgb_png(src / "image.png", rgb), "exr": write_rgb_exr(src / "image.exr", rgb)}
    mask = disc.astype(np.uint8)
    files["mask_normal"] = write_mask_png(src / "mask_normal.png", mask)
    anomaly = mask.copy()
    anomaly[h // 2 - h // 20:h // 2 + h // 20, w // 2 - w // 40:w // 2 + w // 40] = 2
    files["mask_anomaly"] = write_mask_png(src / "mask_anomaly.png", anomaly)
    return files


_SHARED: dict[frozenset, list[str]] = {}  # per process: the walked files of a set of shared dependencies


def _inputs(layer: Path, check: bool) -> tuple[list[str], object]:
    """The files a render of `layer` reads, as allo_usd.usd.dependencies.walk lists them, and the
    layer (Sdf). A walk costs ~0.1 s (the paper plan: over an hour), so only the first layer of each
    set of shared dependencies (stages/: the base stage, an anomaly asset) is walked; the others
    take its shared files plus their own leaf sublayers (pose, sky). `check` walks anyway and
    stops the benchmark if the two lists differ."""
    from pxr import Sdf

    from allo_usd.usd.dependencies import walk

    sdf = Sdf.Layer.FindOrOpen(str(layer))
    here = layer.parent
    deps = [os.path.normpath(here / d) for d in sdf.GetCompositionAssetDependencies()]
    shared = frozenset(d for d in deps if f"{os.sep}stages{os.sep}" in d)
    own = [str(layer.resolve()), *(os.path.realpath(d) for d in deps if d not in shared)]
    if shared not in _SHARED or check:
        files = walk(layer).files
        if shared not in _SHARED:
            _SHARED[shared] = [f for f in files if f not in own]
        if sorted(files) != sorted([*own, *_SHARED[shared]]):
            raise SystemExit(f"{layer}: its walk reads {sorted(files)}, the shortcut {sorted([*own, *_SHARED[shared]])}")
    return [*own, *_SHARED[shared]], sdf


def _scene_meta(sdf, here: Path) -> dict:
    """What read_meta gives for a plan's scene (the `scene` of its JSON), from its layers alone: the
    World's allo: attributes of the scene layer over its sublayers (pose, sky), the provenance and
    the anomaly's attributes."""
    from pxr import Sdf

    meta = {}
    for sub in reversed(sdf.subLayerPaths):  # weakest first, the scene layer last
        lower = Sdf.Layer.FindOrOpen(os.path.normpath(here / sub))
        prim = lower.GetPrimAtPath("/World") if lower else None
        meta.update({a.name[5:]: a.default for a in (prim.attributes if prim else []) if a.name.startswith("allo:")})
    meta.update({a.name[5:]: a.default for a in sdf.GetPrimAtPath("/World").attributes if a.name.startswith("allo:")})
    meta = {k: tuple(v) if hasattr(v, "__len__") and not isinstance(v, str) else v for k, v in meta.items()}
    meta["provenance"] = dict(sdf.customLayerData.get("allo", {}))
    anomaly = sdf.GetPrimAtPath("/World/Anomaly")
    if anomaly:
        meta["anomaly"] = {a.name.split(":")[-1]: a.default for a in anomaly.attributes
                           if a.name.startswith("allo:anomaly:")}
    return meta


def _record_one(args) -> dict:
    """The render JSON (what job.render_layer writes, with this folder's synthesised pixels and one
    real layer's annotations for its kind) and the manifest row of one layer; the checksums of
    hard-linked outputs are their source's."""
    from allo_usd.core.version import __version__
    from allo_usd.core.files import relpath
    from allo_usd.core.provenance import library_versions
    from allo_usd.output.writers import write_json
    from allo_usd.output.checksums import file_sha256, remember_digest
    from allo_usd.output.identity import input_hashes, outputs_sha256, render_identity, render_versions
    from allo_usd.output.record import RenderRecord
    from allo_usd.output.render_outputs import output_paths
    from allo_usd.run.render_index import manifest_row

    layer, out, src, digests, copy, cpu, templates, group = args
    layer, out = Path(layer), Path(out)
    src = {k: f"{v}.{group}" if group else v for k, v in src.items()}   # this scene's copy of the sources
    files, sdf = _inputs(layer, check=copy)
    inputs = input_hashes(layer, files)
    scene = _scene_meta(sdf, layer.parent)
    kind = "anomaly" if scene.get("variant") == "anomaly" else "normal"
    template = templates[kind]
    paths = output_paths(layer, out, tuple(template["passes"]))
    pick = {"rgb": "png", "exr": "exr", "mask": f"mask_{kind}"}
    for key, path in paths.items():
        if key == "meta":
            continue
        if key not in pick:
            raise SystemExit(f"{layer} orders the {key} pass; this benchmark synthesises rgb, exr and mask only")
        path.unlink(missing_ok=True)
        if copy:
            shutil.copyfile(src[pick[key]], path)
        else:
            os.link(src[pick[key]], path)
            remember_digest(path, os.stat(path), digests[pick[key]])  # the same inode: the source's bytes, checksummed once
    meta = {
        **template,
        "layer": str(layer.resolve()), "layer_relative": relpath(layer, out), "layer_sha256": file_sha256(layer),
        "identity": render_identity(inputs), "inputs": inputs, "versions": render_versions(),
        "libraries": library_versions(), "package_version": __version__,
        "device": {"asked": "cpu", "used": "cpu", "backend": None, "gpus": [], "cpu_model": cpu},
        "scene": scene, "files": {k: p.name for k, p in paths.items()}, "outputs_sha256": outputs_sha256(paths),
        "synthetic": "bench_scale.py: pixels synthesised, annotations one real layer's of its kind, the rest this "
                     "layer's own record",
    }
    write_json(paths["meta"], meta)
    return {**manifest_row(layer, out, RenderRecord.of(meta)), "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def _templates(layers: list[Path], src: dict[str, Path]) -> dict[str, dict]:
    """The per-kind part of a record (render settings, class pixels of its mask, annotations), from
    the first normal and the first anomalous layer read in full (read_scene: ~1.5 s each)."""
    from allo_usd.output.annotations import image_annotations
    from allo_usd.output.contact import read_pixels
    from allo_usd import read_scene
    from pxr import Sdf

    out = {}
    for layer in layers:
        sdf = Sdf.Layer.FindOrOpen(str(layer))
        kind = "anomaly" if sdf.GetPrimAtPath("/World/Anomaly") else "normal"
        if kind in out:
            continue
        desc = read_scene(layer)
        mask = read_pixels(src[f"mask_{kind}"])
        counts = np.bincount(mask.ravel(), minlength=3)
        out[kind] = {"render_seconds": 0.0, "resolution": list(desc.render.resolution),
                     "class_pixels": {"background": int(counts[0]), "station_and_bodies": int(counts[1]),
                                      "anomaly": int(counts[2])},
                     "anomaly_fraction": float(counts[2] / mask.size), "station_fraction": float(counts[1] / mask.size),
                     "passes": list(desc.render.outputs), "layer_passes": list(desc.render.outputs), "effects": {},
                     "annotations": json.loads(json.dumps(image_annotations(desc, mask), default=_plain))}
        if len(out) == 2:
            break
    out.setdefault("anomaly", out.get("normal"))
    out.setdefault("normal", out.get("anomaly"))
    return out


def _plain(v):
    return v.tolist() if hasattr(v, "tolist") else str(v)


def build_renders(tree: Path, renders: Path, sample: int, jobs: int, cpu: str) -> tuple[list[Path], list[Path], dict]:
    """The finished render folder of every scene layer of `tree` (kept when its stamp matches)."""
    from multiprocessing import get_context

    from allo_usd.core.files import sha256_file
    from allo_usd.run.dispatch import find_layers
    from allo_usd.run.render_index import MANIFEST, append_rows
    from allo_usd import read_scene
    from allo_usd.usd.tree import TREE_PLAN

    layers = find_layers(tree)
    step = max(1, len(layers) // max(sample, 1))
    sampled = layers[::step][:sample]
    stamp = {"tree": str(tree.resolve()), "layers": len(layers), "plan": (tree / TREE_PLAN).read_text(),
             "sample": [p.stem for p in sampled], "links_per_source": LINKS_PER_SOURCE}
    stamp_path = renders.parent / STAMP
    if stamp_path.is_file() and json.loads(stamp_path.read_text()) == stamp and (renders / MANIFEST).is_file():
        return layers, sampled, json.loads((renders.parent / "sizes.json").read_text())
    shutil.rmtree(renders, ignore_errors=True)
    renders.mkdir(parents=True)
    src = synthesize(renders.parent / "source", tuple(read_scene(layers[0]).render.resolution))
    digests = {k: sha256_file(p) for k, p in src.items()}
    templates = _templates(layers, src)
    in_sample = {p.stem for p in sampled}
    for g in range(1, (len(layers) - 1) // LINKS_PER_SOURCE + 1):   # same bytes and mtime, another inode
        for p in src.values():
            shutil.copy2(p, f"{p}.{g}")
    tasks = [(str(p), str(renders), {k: str(v) for k, v in src.items()}, digests, p.stem in in_sample, cpu, templates,
              i // LINKS_PER_SOURCE) for i, p in enumerate(layers)]
    t0 = time.perf_counter()
    with get_context("spawn").Pool(jobs) as pool:
        rows = []
        for i, row in enumerate(pool.imap(_record_one, tasks, chunksize=16), 1):
            rows.append(row)
            if i % 1000 == 0:
                print(f"  {i:,}/{len(tasks):,} records, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    append_rows(renders / MANIFEST, rows)
    sizes = {k: p.stat().st_size for k, p in src.items()}
    jsons = [p.stat().st_size for p in renders.glob("*.json")]
    sizes["json_median"] = int(np.median(jsons)) if jsons else 0
    (renders.parent / "sizes.json").write_text(json.dumps(sizes))
    stamp_path.write_text(json.dumps(stamp))
    return layers, sampled, sizes


# ---------------------------------------------------------------- the figures

VERIFY_SAMPLE = """
import sys, time
from pathlib import Path
import allo_usd
layers = [Path(p) for p in sys.argv[2:]]
t0 = time.perf_counter()
s = allo_usd.render(layers, Path(sys.argv[1]), workers=1, retries=0, timeout=1, progress=False, verify=True)
print(len(s.rendered), len(s.skipped), len(s.failed), time.perf_counter() - t0)
"""


def resume_runs(tree: Path, renders: Path, layers: list[Path], sampled: list[Path]) -> tuple[list[dict], str]:
    cache = drop_caches([tree, renders])
    quick = run([*CLI, "render", str(tree), "--out", str(renders), "--workers", "1", "--timeout", "1",
                 "--retries", "0"], f"resume check, quick (all {len(layers):,} scenes)")
    if f"0 rendered, {len(layers)} skipped" not in quick["stdout"]:
        raise SystemExit(f"the resume did not find every scene done: {quick['stdout'][-500:]}{quick['stderr'][-1000:]}")
    drop_caches([tree, renders])
    verify = run([sys.executable, "-c", VERIFY_SAMPLE, str(renders), *map(str, sampled)],
                 f"resume check, --verify ({len(sampled)} scenes)")
    rendered, skipped, failed, inner = verify["stdout"].split()
    if (int(rendered), int(skipped), int(failed)) != (0, len(sampled), 0):
        raise SystemExit(f"--verify did not find the sample done: {verify['stdout']}{verify['stderr'][-1000:]}")
    verify["per_scene"] = verify["seconds"] / len(sampled)
    verify["extrapolated"] = verify["per_scene"] * len(layers)
    return [quick, verify], cache


def dataset_runs(renders: Path, work: Path, layers: list[Path], add: int) -> list[dict]:
    """`allo-usd dataset` over all records but the last `add` (held back beside the folder), then
    again with them: the re-run's cost is what adding scenes to a dataset costs."""
    held = work / "held"
    shutil.rmtree(held, ignore_errors=True)
    held.mkdir()
    late = layers[-add:] if add else []
    for p in late:
        os.replace(renders / f"{p.stem}.json", held / f"{p.stem}.json")
    ds = work / "dataset"
    shutil.rmtree(ds, ignore_errors=True)
    try:
        drop_caches([renders])
        first = run([*CLI, "dataset", str(renders), "--out", str(ds)], f"dataset, first run ({len(layers) - add:,} "
                    "records)", ok=(0, 1))
    finally:
        for p in late:
            os.replace(held / f"{p.stem}.json", renders / f"{p.stem}.json")
    again = run([*CLI, "dataset", str(renders), "--out", str(ds)], f"dataset, re-run adding {add:,}", ok=(0, 1))
    return [first, again]


# ---------------------------------------------------------------- the report

METHOD = "## Method"   # the report's last section: findings measured by hand below the generated paragraph are kept


def report(out: Path, info: dict, rows: list[dict], cache_note: str, n: int, sizes: dict, plan: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def goal(r: dict) -> str:
        w = r["what"]
        if w.startswith("author, from"):
            return f"<= {GOALS['author']:.0f} s"
        if w.startswith("author, resume"):
            return f"<= {GOALS['author_noop']:.0f} s"
        if w.startswith("resume check, quick"):
            return f"<= {GOALS['resume']:.0f} s"
        if w.startswith("dataset, re-run"):
            first = next((x for x in rows if x["what"].startswith("dataset, first")), None)
            return f"< {first['seconds'] / 10:.1f} s (1/10 of the first)" if first else ""
        return ""

    lines = [f"# Scale: resume, author and dataset at {n:,} scenes", "", benchinfo.header(info), "",
             f"Plan: {plan}. Page cache before the resume checks and the first dataset run: {cache_note}.", "",
             f"Render folder: every scene's PNG ({sizes.get('png', 0):,} B), EXR ({sizes.get('exr', 0):,} B) and mask "
             f"({sizes.get('mask_normal', 0):,} / {sizes.get('mask_anomaly', 0):,} B) are hard links to one "
             f"synthesised set (a copy of it per {LINKS_PER_SOURCE:,} scenes, so that no file passes ext4's 65,000 "
             f"links when `dataset` links it again) at the plan's resolution (a real 1080p render: {REAL_SIZES}); the `--verify` sample's "
             f"are copies; each JSON (median {sizes.get('json_median', 0):,} B) is its own layer's record (layer checksum, "
             "inputs and identity, scene labels; the annotations are one real layer's of its kind) and each manifest "
             "row comes from `manifest_row`.", "",
             "| figure | seconds | per scene | CPU s | peak RSS (MB) | load before -> after | goal |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        scenes = r.get("scenes", n)
        what = r["what"] + (f" (exit {r['code']}: {r['stderr'].strip().splitlines()[-1][:120]})" if r["code"] else "")
        lines.append(f"| {what} | {r['seconds']:.1f} | {1000 * r['seconds'] / max(scenes, 1):.2f} ms | "
                     f"{r['cpu']:.1f} | {r['peak_mb']:.0f} | {r['load'][0]} -> {r['load'][1]} | {goal(r)} |")
        if "extrapolated" in r:
            lines.append(f"| resume check, --verify, extrapolated to {n:,} scenes | {r['extrapolated']:.0f} | "
                         f"{1000 * r['per_scene']:.1f} ms | | | | |")
    for r in rows:
        if r.get("runs"):
            lines += ["", f"Every `author` run from scratch (wall s, CPU s, load before -> after; the calibration is "
                      f"calibrate(): CPU seconds of a fixed workload just before and after the run, lower is a faster "
                      f"machine; the file create is create_probe(): microseconds per small file created beside the tree "
                      f"just before the run, as authoring writes its layers): " + "; ".join(
                          f"{x['seconds']:.1f} s, {x['cpu']:.1f} CPU s, load {x['load'][0]} -> {x['load'][1]}, "
                          f"calibration {x['calibration'][0]:.2f} / {x['calibration'][1]:.2f}, "
                          f"file create {x['create_us']:.0f} us" for x in r["runs"]) + "."]
    lines += ["", METHOD, "", "Peak RSS is the largest process of the command (its own or a child's: /usr/bin/time's %M, else "
              "wait4's, which counts this script's own RSS too). The resume "
              "check is `allo-usd render TREE --out RENDERS` over the finished folder: the scan for scene layers, "
              "the manifest load and compaction and, per scene, the layer's refusal check, its checksum, the quick "
              "check of its outputs (size, mtime_ns, inode from the manifest row; the JSON is one of them, and the row "
              "carries the JSON's input paths and passes, so no JSON is opened) and its inputs' identity (each file "
              "checksummed once per run: the scene layer by the scan that reads it). `--verify` reads and checksums every output instead (distinct files: "
              "the sample's outputs are copies), timed on the sample and scaled to the plan."]
    lines += [*_hand_findings(out / "bench_scale.md"), ""]
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_scale.md").write_text("\n".join(lines))

    fig, ax = plt.subplots(figsize=(9, 0.5 + 0.5 * len(rows)))
    labels = [r["what"] for r in rows]
    ax.barh(labels, [r["seconds"] for r in rows], color="#4477aa")
    for i, r in enumerate(rows):
        ax.text(r["seconds"], i, f" {r['seconds']:.1f} s (load {r['load'][0]})", va="center", fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("seconds (wall)")
    ax.set_title(f"{n:,} scenes, {info['cpu']['cores']} cores, {info['date']}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "bench_scale.png", dpi=100)


def _hand_findings(report: Path) -> list[str]:
    """The paragraphs of an existing report's Method section after its first (generated) one: what
    was measured by hand (profiles, file-system findings, run-to-run spread), kept across runs."""
    if not report.is_file():
        return []
    method = report.read_text().split(f"\n{METHOD}\n", 1)
    if len(method) < 2:
        return []
    paragraphs = method[1].split("\n## ", 1)[0].strip().split("\n\n")[1:]
    return [x for p in paragraphs for x in ("", p)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", default="paper", help="paper (51,409 scenes), quick (14 days), demo, or a plan file")
    ap.add_argument("--quick", action="store_true", help="the paper plan over 14 days (1,972 scenes)")
    ap.add_argument("--cache", type=Path, default=None, help="the authored tree, reused (default out/bench/PLAN)")
    ap.add_argument("--work", type=Path, default=None, help="render folder and dataset (default out/bench/scale-PLAN)")
    ap.add_argument("--skip-author", action="store_true", help="no author timings (the cache is filled if empty)")
    ap.add_argument("--author-runs", type=int, default=3, help="author runs from scratch (the fastest is the figure)")
    ap.add_argument("--verify-sample", type=int, default=50, help="scenes timed with --verify (distinct outputs)")
    ap.add_argument("--add", type=int, default=1000, help="records the dataset re-run adds")
    ap.add_argument("--jobs", type=int, default=2, help="processes that build the render folder")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks", help="where bench_scale.md and .png go")
    ap.add_argument("--build-only", action="store_true",
                    help="fill the cache and build the render folder, time nothing (a later run reuses both)")
    ap.add_argument("--evict", choices=("drop", "fadvise"), default="drop",
                    help="drop: the whole page cache where allowed (else fadvise); fadvise: only this run's files")
    a = ap.parse_args()
    global EVICT
    EVICT = a.evict
    name = "quick" if a.quick else a.plan
    tag = Path(name).stem if name not in ("paper", "quick", "demo") else name
    cache = (a.cache or ROOT / "out" / "bench" / f"paper{'' if tag == 'paper' else '-' + tag}").resolve()
    work = (a.work or ROOT / "out" / "bench" / f"scale-{tag}").resolve()
    info = benchinfo.start()
    plan = plan_file(name, work)
    rows = author_runs(plan, cache, work, a.skip_author or a.build_only, a.author_runs)
    for r in rows:
        print(f"{r['what']}: {r['seconds']:.1f} s", file=sys.stderr)
    layers, sampled, sizes = build_renders(cache, work / "renders", a.verify_sample, a.jobs, info["cpu"]["model"])
    if a.build_only:
        print(f"{len(layers):,} scenes: the tree {cache} and the render folder {work / 'renders'} are ready",
              file=sys.stderr)
        return
    add = min(a.add, len(layers) // 2)
    resume, cache_note = resume_runs(cache, work / "renders", layers, sampled)
    resume[1]["scenes"] = len(sampled)
    rows += resume
    data = dataset_runs(work / "renders", work, layers, add)
    data[0]["scenes"], data[1]["scenes"] = len(layers) - add, add
    rows += data
    for r in rows:
        print(f"{r['what']}: {r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB, load {r['load']}", file=sys.stderr)
    report(a.out, benchinfo.finish(info), rows, cache_note, len(layers), sizes, f"{name} ({plan})")


if __name__ == "__main__":
    main()
