"""The `allo-usd` command line."""

from __future__ import annotations

import errno
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import allo_usd
from allo_usd.core.interrupts import Held

# a Ctrl-C while the command line loads (typer: ~0.3 s) ends it with exit 130 (_loaded); the console
# script's hold began in allo_usd/__init__.py
_LOADING = allo_usd._LOADING if allo_usd._LOADING.active else Held().start()

import typer  # noqa: E402 - after the hold above

from allo_usd.core.errors import AlloError  # noqa: E402
from allo_usd.core.files import ensure_output_dir, ensure_output_file  # noqa: E402
from allo_usd.core.limits import MAX_SIDE_PX, MIN_SIDE_PX, resolution_problem  # noqa: E402
from allo_usd.plan.settings import PASSES  # noqa: E402
from allo_usd.usd.tree import (COUNTS_CSV, LAYER_FOLDER_DIRS, POSE_DIR, SCENE_DIR, SKIPPED_CSV, SKY_DIR,  # noqa: E402
                               STAGE_DIR)

if TYPE_CHECKING:
    from allo_usd.run.options import JobOptions, RunOptions

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode="markdown",
                  help="Author, record and render the ALLO lunar-orbit anomaly dataset as USD layers.")
asset_app = typer.Typer(no_args_is_help=True, rich_markup_mode="markdown", help="Convert real meshes into USD assets.")
app.add_typer(asset_app, name="asset")

TREE_HELP = (f"An authored tree (the OUT of `allo-usd author`) whose {SCENE_DIR}/, {SKY_DIR}/, {POSE_DIR}/ and "
             f"{STAGE_DIR}/ your layer may read, for a layer of your own outside the tree that sublayers one of its "
             "scene layers (repeatable; nothing else of OUT is granted). The demo's OUT/layers is granted its "
             f"scene layers, {', '.join(d + '/' for d in LAYER_FOLDER_DIRS[:-1])} and {LAYER_FOLDER_DIRS[-1]}/. "
             "ALLO_ASSET_ROOTS lists further allowed "
             "directories.")


# ---------------------------------------------------------------- numbers given on the command line
# Every numeric option is parsed here, not by typer (whose error is a box that does not say what was
# given): the text as given must be a finite number in the option's range, else one AlloError line
# that prints it ("--timeout nan is not a number of seconds > 0; fix: ...").

MAX_PROCESSES = 1024   # --workers and --threads: more is a typo (each render worker is a Blender process)
MAX_RETRIES = 100


def _as_given(text) -> str:
    shown = str(text).strip()
    return shown if len(shown) <= 40 else shown[:40] + "..."


def _whole(option: str, low, high, fix: str):
    """A typer parser: the text given as a whole number in low..high (high None: no upper bound; a
    function: a bound from a module not worth importing for --help), else an AlloError that prints
    the text."""
    def parse(text):
        bottom, top = (low() if callable(low) else low), (high() if callable(high) else high)
        if isinstance(text, int) and not isinstance(text, bool):
            value = text   # the option's default
        else:
            try:
                value = int(str(text).strip(), 10)
            except ValueError:
                value = None
        if value is None or value < bottom or (top is not None and value > top):
            sign = "negative: " if value is not None and value < 0 else ""
            span = f"from {bottom} to {top}" if top is not None else f">= {bottom}"
            raise AlloError(f"{option} {_as_given(text)} is {sign}not a whole number {span}; fix: {fix}")
        return value
    return parse


def _timeout_seconds(text):
    """--timeout: seconds, finite and > 0 (NaN would turn the limit off: it compares false with every
    time); leaving the option out keeps the default limit from each layer's size."""
    try:
        value = float(str(text).strip())
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        sign = "negative: " if value < 0 else ""
        raise AlloError(f"--timeout {_as_given(text)} is {sign}not a number of seconds > 0; fix: give the seconds one "
                        "scene may take on a worker (e.g. --timeout 600), or leave --timeout out for 120 s + 5e-5 s "
                        "per pixel x sample of each layer")
    return value


def _real(option: str, low: float, high: float, fix: str):
    """A typer parser: the text given as a finite number in low..high, else an AlloError that prints the text."""
    def parse(text):
        if isinstance(text, (int, float)) and not isinstance(text, bool):
            value = float(text)   # a default
        else:
            try:
                value = float(str(text).strip())
            except ValueError:
                value = math.nan
        if not (math.isfinite(value) and low <= value <= high):
            sign = "negative: " if value < 0 else ""
            raise AlloError(f"{option} {_as_given(text)} is {sign}not a number from {low:g} to {high:.0f}; fix: {fix}")
        return value
    return parse


def _target_options():
    """`--target-psnr DB` and `--time-limit S` (render, demo): the target mode for this run (allo_usd.plan.settings)."""
    from allo_usd.plan.settings import TARGET_PSNR_DB, TIME_LIMIT_S

    return (typer.Option(None, "--target-psnr", metavar="DB", show_default=False,
                         parser=_real("--target-psnr", 0.0, TARGET_PSNR_DB[1], "give the PSNR in dB the render should "
                                      "reach, e.g. 40, or 0 for fixed samples"),
                         help="Render to a quality: spend samples in rounds of two independent halves until the "
                              "estimated PSNR of the delivered image (8-bit sRGB, against the converged image) "
                              "reaches DB (0-100; 0: fixed samples), or the samples or --time-limit stop "
                              "it; the JSON records which. Replaces the layers' allo:render:targetPsnr for this run (demo: authored into its layers)."),
            typer.Option(None, "--time-limit", metavar="S", show_default=False,
                         parser=_real("--time-limit", TIME_LIMIT_S[0], TIME_LIMIT_S[1], "give the seconds one render "
                                      "may spend reaching its target, e.g. 60, or 0 for no limit"),
                         help="With a target: stop spending samples after S seconds (0: no limit). Replaces the "
                              "layers' allo:render:timeLimit for this run."))


TARGET_OPTION, TIME_LIMIT_OPTION = _target_options()


def _render_samples_max() -> int:
    from allo_usd.usd.reader_bounds import RENDER_SAMPLES

    return RENDER_SAMPLES[1]


def _sky_bounds() -> tuple[int, int, int]:
    """(first year, last year, most days) a sky table may ask for: inside DE421's coverage."""
    from allo_usd.sky.ephemeris_range import DE421_END_TDB_JD, DE421_END_UTC, DE421_START_TDB_JD, DE421_START_UTC

    return int(DE421_START_UTC[:4]) + 1, int(DE421_END_UTC[:4]), int(DE421_END_TDB_JD - DE421_START_TDB_JD)


def _tree_option():
    return typer.Option(None, "--tree", metavar="OUT", help=TREE_HELP, show_default=False)


DEVICE_HELP = ("The Cycles device: auto (a GPU when Cycles finds one: OptiX, CUDA, HIP, oneAPI or Metal; else the CPU, "
               "with a one-line note), cpu (never looks for a GPU) or gpu (an error when there is none). Not part of "
               "the layer; each render's JSON records the device used.")


def _device_option(default: str | None, more: str = ""):
    return typer.Option(default, "--device", metavar="auto|cpu|gpu", help=DEVICE_HELP + more,
                        show_default=default is not None)


def _show_device_notes() -> None:
    """The device notices this process's renders printed into their log, once each, on stderr."""
    from allo_usd.blender.device import noticed

    for text in noticed():
        typer.echo(f"note: {text}", err=True)


@app.command()
def render(source: Path = typer.Argument(..., metavar="PLAN_OR_DIR_OR_LAYER",
                                         help="A scene layer (.usda, .usdc or .usd), a packed scene (.usdz, "
                                              "`allo-usd pack`), a directory of layers, or a plan (.toml/.yaml)."),
           out: Path = typer.Option(Path("out/render"), "--out", help="Output directory."),
           force: bool = typer.Option(False, help="Re-render a single layer even if its outputs exist, and "
                                      "replace an existing --save-blend FILE (a regular file only)."),
           workers: int = typer.Option(0, "--workers", show_default=False, metavar="N",
                                       parser=_whole("--workers", 0, MAX_PROCESSES, "pass 0 (or leave it out) for "
                                                     "one worker per usable core, or a number of worker processes"),
                                       help="Local worker processes. Default (or 0): one per core this process may "
                                            "use; a single layer without --workers renders in this process."),
           scheduler: str = typer.Option(None, "--scheduler", show_default=False,
                                         help="Dask scheduler address (tcp://host:8786). Default: a local pool."),
           threads: int = typer.Option(0, "--threads", show_default=False, metavar="N",
                                       parser=_whole("--threads", 0, MAX_PROCESSES, "pass 0 (or leave it out) for "
                                                     "the usable cores // workers, or Cycles threads per worker"),
                                       help="Cycles threads per worker. Default (or 0): the usable cores // workers "
                                            "(a single layer: all of them)."),
           retries: int = typer.Option(2, "--retries", metavar="N",
                                       parser=_whole("--retries", 0, MAX_RETRIES, "give how many more times a "
                                                     "scene whose worker crashed or timed out is tried, e.g. 2"),
                                       help="Retries of a task whose worker crashed or timed out."),
           verify: bool = typer.Option(False, "--verify", show_default=False,
                                       help="Read and checksum every finished output instead of trusting the size, mtime "
                                            "and inode its manifest row recorded, and render again what fails (after "
                                            "a disk error, or a tree copied without its mtimes; a single layer is "
                                            "always checked this way)."),
           timeout: float = typer.Option(None, "--timeout", metavar="SECONDS", show_default=False,
                                         parser=_timeout_seconds,
                                         help="Time limit of one scene on a worker (seconds > 0), after which the "
                                              "worker is killed and the scene retried. Default: 120 s + 5e-5 s per "
                                              "pixel x sample of the layer."),
           save_blend: Path = typer.Option(None, "--save-blend", metavar="FILE", show_default=False,
                                           help="A single layer only: also save the Blender scene it builds as "
                                                "FILE (.blend), to open what Blender got. An existing FILE is "
                                                "replaced only with --force; a link or a non-file never."),
           trees: list[Path] = _tree_option(),
           device: str = _device_option(None, " Default: a plan's render.device, else auto."),
           passes: str = typer.Option(None, "--passes", metavar="P1,P2", show_default=False,
                                      help="The passes to write this run, replacing what the layers order: a comma "
                                           "list of " + ", ".join(PASSES) + ". A single layer records them in its "
                                           "JSON; a plan's layers are authored with them."),
           target_psnr: float = TARGET_OPTION, time_limit: float = TIME_LIMIT_OPTION,
           estimate: bool = typer.Option(False, "--estimate", help=(
               "Also estimate each fixed-sample render's error (its estimated PSNR in the JSON's accuracy and the "
               "manifest's est_psnr_db) from one more render of the same settings with another seed: twice the "
               "time, the image unchanged. A finished single layer without an estimate renders again; in a "
               "directory or plan, renders already done are kept (--force renders them again). A render to a "
               "target (--target-psnr) always has its estimate."))):
    """Render scene layers: per scene the passes its layer orders (default RGB PNG, linear EXR, 3-class
    mask PNG; docs/formats/render_outputs.md, Passes) and a metadata JSON.

    One layer renders in this process. A directory renders all its scene layers (searched
    recursively; an authored plan's scenes/) on a local pool (--workers) or a Dask cluster
    (--scheduler), resuming from OUT/manifest.jsonl; failures go to OUT/failed.jsonl and Blender's
    output to OUT/logs/. A plan is authored into OUT/layers first, then rendered into OUT/renders.
    With --save-blend FILE a single layer is rendered (even if done) and its Blender scene saved.
    Each scene on a worker has a time limit (--timeout); past it the scene is retried, then failed.
    A layer reads only files in its own folder, the package's stages/ and, for a scene layer of an
    authored tree, that tree's authored folders; --tree OUT grants a tree to a layer of your own.
    A packed scene (.usdz, `allo-usd pack`) renders as its layer would and reads only its own files.
    --device picks the Cycles device (auto, cpu, gpu); the JSON of each render records it.
    --target-psnr DB renders to a quality instead of a fixed number of samples (a single layer or a plan).
    """
    from allo_usd.run.options import RunOptions
    from allo_usd.usd.safety import trees_granted

    with trees_granted(trees or ()):
        # the one value the rest reads; built and checked here (passes, device, numbers, --scheduler)
        _render(source, out, RunOptions.from_cli(force=force, workers=workers, scheduler=scheduler, threads=threads,
                                                 retries=retries, timeout=timeout, verify=verify,
                                                 save_blend=save_blend, device=device, passes=passes,
                                                 target_psnr=target_psnr, time_limit=time_limit,
                                                 estimate=estimate))


def _render(source: Path, out: Path, options: RunOptions) -> None:
    """`allo-usd render` with its options as one RunOptions (allo_usd.run.options; RunOptions.from_cli
    checked them): one layer in this process (_render_one), else a directory, a layer on workers or
    a plan through the dispatcher. Checks what depends on the source first."""
    import dataclasses
    import warnings

    from allo_usd.usd.sniff import LAYER_SUFFIXES

    job = options.job
    suffix = source.suffix.lower()
    is_layer = suffix in (*LAYER_SUFFIXES, ".usdz") and source.exists() and not source.is_dir()  # .usdz: a pack
    single = is_layer and options.scheduler is None and not options.workers
    if job.save_blend is not None and not single:
        raise AlloError("--save-blend saves the Blender scene of one layer: pass a single .usda layer (or .usdc, "
                        ".usd; without --workers or --scheduler)")
    if job.save_blend is not None:   # before anything is written or rendered (allo_usd.blender.debug)
        from allo_usd.blender.debug import check_blend_target

        job = dataclasses.replace(job, save_blend=check_blend_target(job.save_blend, replace=job.force))
    if not (source.is_dir() or is_layer or (source.is_file() and suffix in (".toml", ".yaml", ".yml"))):
        raise AlloError(f"{source} does not exist or is not a layer (.usda, .usdc, .usd, or a .usdz package), a "
                        "directory of layers or a plan (.toml/.yaml); check the path")
    if job.passes is not None and (source.is_dir() or (is_layer and not single)):
        raise AlloError("--passes overrides the passes of a single layer (rendered in this process) or of a plan's "
                        "layers; a directory's layers record their own: render a plan with --passes, or set "
                        "quality.passes in the plan and author the layers again")
    if (job.target_psnr is not None or job.time_limit is not None) and (source.is_dir() or (is_layer and not single)):
        raise AlloError("--target-psnr and --time-limit override the target of a single layer (rendered in this "
                        "process) or of a plan's layers; a directory's layers record their own: render a plan with "
                        "--target-psnr, or set quality.target_psnr in the plan and author the layers again")
    ensure_output_dir(out)
    if single:
        _render_one(source, out, job)
        return
    from allo_usd.run.dispatch import author_and_dispatch, dispatch
    from allo_usd.run.scheduler import connect_scheduler

    # connected before the scan: an unreachable scheduler is one line within SCHEDULER_CONNECT_S
    client = None if options.scheduler is None else connect_scheduler(options.scheduler)
    options = dataclasses.replace(options, scheduler=client, job=job)
    try:
        with warnings.catch_warnings(record=True) as notes:
            warnings.simplefilter("always")
            if source.is_dir() or is_layer:
                summary = dispatch(source, out, options=options)   # job.device None: auto
            else:
                summary = author_and_dispatch(source, out, options)   # job.device None: the plan's
    finally:
        if client is not None:
            client.close()
    _notes(notes)
    typer.echo(f"{source} -> {out}: {summary}")
    for row in summary.failed:
        typer.echo(f"  failed {row['scene']}: {row['reason']}", err=True)
    if summary.interrupted:
        typer.echo(f"interrupted: finished scenes are kept under {out}; re-run the same command to render the rest",
                   err=True)
        raise SystemExit(130)
    if summary.failed:
        raise SystemExit(1)


def _accuracy_text(meta) -> str:
    """", estimated 40.3 dB, at least 39.1 dB (target 40, stopped by target)" of a render that estimated its
    accuracy, else "". The two PSNRs pass the manifest's check (accuracy_columns: finite, 0..200 dB)."""
    from allo_usd.output.annotations import accuracy_columns

    columns = accuracy_columns(meta)
    est, low = columns["est_psnr_db"], columns["est_psnr_low_db"]
    if est == "":
        return ""
    acc = meta.accuracy if isinstance(meta.accuracy, dict) else {}
    target, why = acc.get("target_psnr_db"), acc.get("stopped_by")
    aimed = isinstance(target, (int, float)) and not isinstance(target, bool) and math.isfinite(target) and target
    more = ", ".join(x for x in (f"target {target:g}" if aimed else "",
                                 f"stopped by {why}" if why in ("target", "samples", "seconds") else "") if x)
    return (f", estimated {est:.1f} dB" + (f", at least {low:.1f} dB" if low != "" else "")
            + (f" ({more})" if more else ""))


def _render_one(layer: Path, out: Path, job: JobOptions) -> None:
    """One layer in this process as `job` (a JobOptions; device None: auto) says, under the same output
    lock as a directory render; a full disk (our writers' ENOSPC, or OpenEXR's RuntimeError for one) is
    a DiskFullError."""
    from allo_usd.core.files import RunLock
    from allo_usd.run.dispatch import LOCK
    from allo_usd.run.job import render_record
    from allo_usd.run.worker import disk_full_error, output_to, own_run_tmpdir
    from allo_usd.usd.sniff import refusal

    why = refusal(layer)  # the rule find_layers applies to a layer named on the command line
    if why:
        raise AlloError(why)
    with RunLock(out, LOCK, "render"):
        workdir = own_run_tmpdir(out)  # temporaries (Blender's too) under OUT/.allo-tmp: a kill leaves none elsewhere
        try:
            with output_to(out / "logs" / "render.log"):  # Blender's own prints
                meta = render_record(layer, out, job, workdir=workdir)
        except (OSError, RuntimeError) as exc:
            full = disk_full_error(exc, out)
            if full is None:
                raise
            raise full from None
    _show_device_notes()
    typer.echo(f"{layer} -> {out}: {meta.render_seconds:.2f} s, classes {meta.class_pixels}" + _accuracy_text(meta))
    if job.save_blend is not None:
        typer.echo(f"Blender scene saved as {job.save_blend}")


@app.command()
def pack(layer: Path = typer.Argument(..., help="Scene layer (.usda, .usdc or .usd)."),
         out: Path = typer.Option(..., "--out", metavar="SCENE.usdz", help="The package to write (.usdz)."),
         force: bool = typer.Option(False, "--force", help="Replace SCENE.usdz if it exists as a regular file (never "
                                    "a symbolic link or anything else)."),
         trees: list[Path] = _tree_option()):
    """Pack one scene into one file: the layer and every layer, asset and texture it composes, as a USD
    package (.usdz) that opens anywhere and renders the same images and masks (`allo-usd render
    SCENE.usdz`). To send one sample to a colleague or attach it to a bug report.

    The layer passes the render's sandbox first; a file it names outside its roots, or in metadata
    only, is refused. The package is written whole or not at all; an existing SCENE.usdz is
    replaced only with --force."""
    from allo_usd.usd.pack import pack as pack_scene
    from allo_usd.usd.safety import trees_granted

    with trees_granted(trees or ()):
        done = pack_scene(layer, out, replace=force)
    typer.echo(f"{layer} -> {out}: {done['files']} files, {done['bytes']:,} bytes; render it with "
               f"`allo-usd render {out} --out DIR`")


@app.command()
def demo(out: Path = typer.Option(Path("out/demo"), "--out",
                                  help="Output directory: the plan, its layers, the renders and the contact sheet."),
         width: int = typer.Option(480, metavar="PIXELS", help="Image width in pixels.",
                                   parser=_whole("--width", MIN_SIDE_PX, MAX_SIDE_PX, "give an image width in pixels, "
                                                 "e.g. --width 480")),
         height: int = typer.Option(270, metavar="PIXELS", help="Image height in pixels.",
                                    parser=_whole("--height", MIN_SIDE_PX, MAX_SIDE_PX, "give an image height in "
                                                  "pixels, e.g. --height 270")),
         samples: int = typer.Option(32, metavar="N", help="Cycles samples per pixel.",
                                     parser=_whole("--samples", 1, _render_samples_max, "give Cycles samples per "
                                                   "pixel, e.g. --samples 32")),
         device: str = _device_option("auto"),
         target_psnr: float = TARGET_OPTION, time_limit: float = TIME_LIMIT_OPTION):
    """Author and render the small demo dataset (2 normal, 2 anomalous scenes) and a contact sheet.
    With --target-psnr DB the layers ask for the target mode, --samples being its cap."""
    from allo_usd.blender.device import check_device
    from allo_usd.plan.settings import target_problem
    from allo_usd.run.demo import run_demo

    device = check_device(device)
    why = resolution_problem(width, height)
    if why:
        raise AlloError(f"--width {width} --height {height}: {why}")
    why = target_problem(target_psnr or 0.0, time_limit or 0.0, "--target-psnr", "--time-limit")
    if why:
        raise AlloError(why)
    ensure_output_dir(out)
    try:
        sheet = run_demo(out, (width, height), samples, device=device, target_psnr=target_psnr or 0.0,
                         time_limit=time_limit or 0.0)
    except KeyboardInterrupt:
        typer.echo(f"interrupted: finished scenes are kept under {out}; re-run the same command to render the "
                   "rest", err=True)
        raise SystemExit(130) from None
    finally:
        _show_device_notes()
    typer.echo(f"contact sheet: {sheet}")


@app.command()
def sky(out: Path = typer.Option(Path("out/sky"), "--out", help="Output directory for SKY_YEAR.csv and .png."),
        year: int = typer.Option(2030, metavar="YEAR", help="The year whose 1 January (00:00 UTC) starts the table.",
                                 parser=_whole("--year", lambda: _sky_bounds()[0], lambda: _sky_bounds()[1],
                                               "give a year the ephemeris (DE421) covers, e.g. --year 2030")),
        days: int = typer.Option(365, metavar="N", help="Days in the table, one row per day at 00:00 UTC.",
                                 parser=_whole("--days", 1, lambda: _sky_bounds()[2],
                                               "give the number of days in the table, e.g. --days 365"))):
    """Write a year's sky table (CSV) and plot (PNG): distance, irradiance, eclipses, angular sizes."""
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.sky.report import write_sky_report

    ensure_output_dir(out)
    s = compute_sky(default_epochs(year, days), Orbit())
    write_sky_report(s, out / f"sky_{year}.csv", out / f"sky_{year}.png")
    typer.echo(f"wrote {out / f'sky_{year}.csv'} and {out / f'sky_{year}.png'}")


@asset_app.command("import")
def asset_import(file: Path = typer.Argument(..., help="glTF/GLB, OBJ, STL or USD file."),
                 out: Path = typer.Option(Path("out/assets"), "--out", help="Directory for the USD asset."),
                 units: str = typer.Option("auto", help="The file's unit: m, cm, mm, in, ft, or auto (glTF: "
                                           "metres; an absurd size for a station is read as inches; USD: the "
                                           "file's metersPerUnit)."),
                 up_axis: str = typer.Option("auto", "--up-axis", help="The file axis that points up: x, y, z, "
                                             "-x, -y, -z, or auto (the format's: glTF and OBJ y, STL z; USD: the "
                                             "file's upAxis)."),
                 label: str = typer.Option("station", help="Class label: station or anomaly.")):
    """Convert a real mesh into a USD asset in metres, Z up (the importer a plan's own hazards use).

    The orientation and unit are the format's (glTF is +Y up and metres by specification; USD
    says both) or --up-axis / --units; never guessed from the file name (NASA's ISS_2016.glb:
    --up-axis=-z). The result must measure what its label may (anomaly: 1 cm to 20 m, as a plan's
    own hazards; station: 1 cm to 500 m): a size outside is a unit mistake, named with the unit read."""
    from allo_usd.assets.importer import check_options

    units, up_axis = check_options(units, up_axis)   # before anything is read: the allowed values, named
    ensure_output_dir(out)
    from allo_usd.usd.asset import write_asset
    from allo_usd.usd.hazard import SIZE_M, STATION_SIZE_M, check_size, import_model

    asset, info = import_model(file, None, units, up_axis, what="model")
    fmt = info["format"]
    read_as = ("" if units != "auto" else " (the file's metersPerUnit)" if fmt == "usd"
               else " (--units auto: guessed from its size)" if info["unit"] != "m"
               else " (glTF's unit by specification)" if fmt == "gltf"
               else f" (--units auto: an {fmt.upper()} file does not say its unit)")
    hazard = label == "anomaly"
    extent = check_size(asset, file, file.stem, info["unit"], "model", SIZE_M if hazard else STATION_SIZE_M,
                        "a hazard near the station" if hazard else "a station", "--units mm, cm, in, ...", read_as)
    path = write_asset(asset, out, label)
    typer.echo(f"{file} -> {path} (unit {info['unit']}, up axis {info['upAxis']}, {info['triangles']} triangles, "
               + (f"{info['droppedTriangles']} dropped (non-finite, out of range or zero area), "
                  if info["droppedTriangles"] else "")
               + " x ".join(f"{e:.4g}" for e in extent) + " m)")


@app.command()
def inspect(layer: Path = typer.Argument(..., help="Scene layer (.usda, .usdc or .usd)."),
            as_json: bool = typer.Option(False, "--json", help="Print JSON instead of text."),
            trees: list[Path] = _tree_option()):
    """Describe a scene from its USD layer alone: identity, seed, sky, camera, anomaly, render, layer stack."""
    import json

    from allo_usd.usd.inspect import describe, format_description
    from allo_usd.usd.safety import trees_granted

    with trees_granted(trees or ()):
        d = describe(layer)
    typer.echo(json.dumps(d, indent=2) if as_json else format_description(d))


@app.command()
def diff(a: Path = typer.Argument(..., help="First scene layer."),
         b: Path = typer.Argument(..., help="Second scene layer."),
         full: bool = typer.Option(False, help="Compare every prim, not only those the non-shared layers touch."),
         trees: list[Path] = _tree_option()):
    """List composed values that differ between two scene layers (exit 1 if any differ, like diff)."""
    from allo_usd.usd.inspect import diff as diff_layers
    from allo_usd.usd.inspect import format_diff
    from allo_usd.usd.safety import trees_granted

    with trees_granted(trees or ()):
        rows = diff_layers(a, b, full=full)
    typer.echo(format_diff(rows))
    if rows:
        raise typer.Exit(1)


@app.command()
def dataset(render_dirs: list[Path] = typer.Argument(..., help="Render directories (NAME.json + files)."),
            out: Path = typer.Option(..., "--out", help="Dataset directory."),
            category: str = typer.Option("allo", help="MVTec category name."),
            copy: bool = typer.Option(False, "--copy", help="Copy files instead of hard-linking them."),
            defects: str = typer.Option("per-asset", "--defects", metavar="per-asset|merged",
                                        help="Anomalous test images: `per-asset` puts each anomaly asset in its "
                                             "own folder, test/ASSET/ with masks in ground_truth/ASSET/ (as MVTec "
                                             "AD has one folder per defect type); `merged` puts them all in "
                                             "test/anomaly/ and ground_truth/anomaly/. A re-run with the other "
                                             "choice moves the files.")):
    """Assemble renders into an MVTec-AD-style tree, 3-class masks, a manifest and contact sheets.

    Re-runs add only new or re-rendered scenes. Ctrl-C stops after the scene in hand (exit 130);
    the manifest always lists every file in the tree. Mask-only renders are left out (no image).
    A render whose JSON contradicts itself or names files outside its folder is left out with a
    note; no renders, or renders of different resolutions, stop the run (exit 2)."""
    ensure_output_dir(out)
    import warnings
    from collections import Counter

    from allo_usd.output.dataset import RefusedRenders, assemble, read_manifest

    with warnings.catch_warnings(record=True) as notes:
        warnings.simplefilter("always")
        try:
            manifest = assemble(render_dirs, out, link=not copy, category=category, progress=sys.stderr.isatty(),
                                defects=defects)
        except KeyboardInterrupt as exc:
            _notes(notes)
            typer.echo(f"interrupted: {str(exc) or 'before any file was placed; re-run the same command'}",
                       err=True)   # a bare KeyboardInterrupt says nothing (and is truthy)
            raise SystemExit(130) from None
    _notes(notes)
    folders = Counter("/".join(r["image"].split("/")[1:3]) for r in read_manifest(manifest)
                      if r["category"] == category)   # SPLIT/FOLDER: train/good, test/good, test/<defect>
    order = sorted(folders, key=lambda k: (k != "train/good", k != "test/good", k))
    typer.echo(f"{out / category}: " + ", ".join(f"{k} {folders[k]}" for k in order) + f"; manifest {manifest}")
    from allo_usd.output.dataset import summary_line

    typer.echo(summary_line(out))   # COCO, BOP, passes (allo_usd.output.dataset)
    if any(issubclass(w.category, RefusedRenders) for w in notes):
        raise SystemExit(1)  # like `render` with failures: the rest is assembled, the refused ones are named


def _notes(caught) -> None:
    """The library's warnings (UserWarning: scenes left out, files cleaned up) as plain notes."""
    for w in caught:
        if issubclass(w.category, UserWarning):
            typer.echo(f"note: {w.message}", err=True)


@app.command("plan")
def plan_cmd(out: Path = typer.Option(..., "--out", help="Plan file to write (.toml, .yaml or .yml)."),
             paper: bool = typer.Option(False, "--paper", help="The ALLO paper's Table II plan (51,409 scenes)."),
             demo: bool = typer.Option(False, "--demo", help="A tiny plan: 2 days, 3 poses, 1 anomaly.")):
    """Write a dataset plan file (the paper's, or a tiny demo one) to edit and author."""
    ensure_output_file(out)
    from allo_usd.core.errors import PlanError
    from allo_usd.plan.model import demo_plan, paper_plan
    from allo_usd.plan.enumeration import count_scenes
    from allo_usd.plan.io import save_plan

    if paper == demo:
        raise PlanError("choose exactly one of --paper or --demo")
    plan = paper_plan() if paper else demo_plan()
    save_plan(plan, out)
    typer.echo(f"wrote {out}: {count_scenes(plan)} scenes (only the fields the plan sets; "
               f"quality.preset fills the quality fields it leaves out)")


@app.command()
def author(plan_file: Path = typer.Argument(..., help="Plan file (.toml or .yaml)."),
           out: Path = typer.Option(Path("out/layers"), "--out", help="Output directory for the layers (the authored "
                                    "tree; `allo-usd dataset` writes the dataset)."),
           limit: int = typer.Option(None, "--limit", show_default=False, metavar="N",
                                     parser=_whole("--limit", 0, None, "give the number of scenes to author, 0 or "
                                                   "more, or leave --limit out for every scene"),
                                     help="Author only the first N scenes of the plan (and the reserve scenes that "
                                          "top up their skipped depths). Default: every scene."),
           workers: int = typer.Option(None, "--workers", show_default=False, metavar="N",
                                       parser=_whole("--workers", 1, MAX_PROCESSES, "give the number of authoring "
                                                     "processes, or leave --workers out for 2 on large plans, "
                                                     "else 1"),
                                       help="Processes. Default: 2 for large plans, else 1."),
           replace: bool = typer.Option(False, "--replace", help="OUT was authored from another plan: delete "
                                        f"its layers ({SCENE_DIR}/, {SKY_DIR}/, {POSE_DIR}/, {STAGE_DIR}/, the CSVs) "
                                        "and author this one."),
           progress: bool = typer.Option(True, help="Show a progress bar.")):
    """Author a plan's scene layers over shared sky and camera-sample layers (resumes; skips done).

    Anomalous depths that the placement check skips are topped up from reserve placements of the
    same seed, asset and variant, so each reaches its planned count (allo_usd.run.topup). With
    --limit N the quotas are those of the first N scenes, and their skipped depths are topped up
    too. Ends with planned vs authored counts (also in OUT/counts.csv); exits 1 if an asset stays
    short because its reserve groups ran out (anomalies.reserve_groups_per_slot).

    OUT remembers its plan (OUT/plan.toml): a different plan is refused unless --replace. One
    author run at a time per OUT; a second one is refused (exit 2).
    """
    ensure_output_dir(out)
    from allo_usd.run.author import AuthoringInterrupted, author as author_tree
    from allo_usd.run.ledgers import summary_lines
    from allo_usd.plan.io import load_plan

    try:
        plan = load_plan(plan_file)
        done = author_tree(plan, out, limit=limit, progress=progress, workers=workers, replace=replace)
    except AuthoringInterrupted as exc:
        typer.echo(f"{exc}", err=True)
        raise SystemExit(130) from None
    except KeyboardInterrupt:  # before the first scene: nothing but finished files was written
        typer.echo("interrupted before authoring began; re-run the same command", err=True)
        raise SystemExit(130) from None
    typer.echo(f"{len(done.paths)} scene layers under {out / SCENE_DIR}; skipped depths in {out / SKIPPED_CSV}, "
               f"planned vs authored in {out / COUNTS_CSV}")
    topup = plan.anomalies.reserve_groups_per_slot > 0
    for line in summary_lines(done.counts, topup):
        typer.echo(line, err=line.startswith("SHORT"))
    if done.short and topup:
        raise SystemExit(1)


_PXR_COMMANDS = {"render", "inspect", "diff", "demo", "author", "asset", "pack"}


def version_line() -> str:
    """`allo-usd X (bpy Y, usd-core Z)`: the installed distributions' versions, from package metadata
    (allo_usd.output.identity.render_versions: bpy is not imported)."""
    from importlib.metadata import PackageNotFoundError, version

    from allo_usd.output.identity import render_versions

    versions = render_versions()
    try:
        mine = version("allo-usd")
    except PackageNotFoundError:
        mine = f"{versions['allo_usd']} (not installed: run from a source checkout)"
    return f"allo-usd {mine} (bpy {versions['bpy']}, usd-core {versions['usd-core']})"


def _print_version(value: bool) -> None:
    if value:
        typer.echo(version_line())
        raise typer.Exit()


@app.callback()
def _before_command(ctx: typer.Context,
                    version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                                 help="Print the versions of allo-usd, bpy and usd-core, and exit.")
                    ) -> None:
    # pxr's module loader swallows a Ctrl-C that lands while it loads (allo_usd.usd.sniff.load_pxr)
    if ctx.invoked_subcommand in _PXR_COMMANDS:
        from allo_usd.usd.sniff import load_pxr

        load_pxr()


_OS_FIXES = {errno.EACCES: "fix its permissions or choose another path",
             errno.EPERM: "fix its permissions or choose another path",
             errno.EROFS: "it is on a read-only file system: choose another path",
             errno.ENOSPC: "free space and re-run (finished outputs are kept)",
             errno.EDQUOT: "free space (the disk quota is spent) and re-run (finished outputs are kept)",
             errno.ENOENT: "check the path",
             errno.ENOTDIR: "a part of the path is a file, not a directory: check the path",
             errno.EISDIR: "it is a directory: pass a file",
             errno.ENAMETOOLONG: "use a shorter path",
             errno.ELOOP: "it is a symlink loop: check the path"}


def _os_error_line(exc: OSError) -> str | None:
    """One line for an OSError a user's path or disk caused, or None (then it is a bug: traceback)."""
    fix = _OS_FIXES.get(exc.errno)
    if fix is None or (exc.filename is None and exc.errno not in (errno.ENOSPC, errno.EDQUOT)):
        return None
    where = f" {exc.filename}" if exc.filename is not None else ""
    return f"error: cannot use{where}: {exc.strerror or exc}; {fix}"


_INTERRUPTED = ("interrupted (Ctrl-C): finished outputs are kept, temporaries removed; re-run the same command to "
                "go on")


def one_line(message: str) -> str:
    """A message of several lines (a plan's list of problems) as one line: one error, one line."""
    lines = [line.strip() for line in message.splitlines() if line.strip()]
    return " ".join(line if i == len(lines) - 1 or line.endswith(":") else line.rstrip(";") + ";"
                    for i, line in enumerate(lines))


def main() -> None:
    try:
        app()
    except KeyboardInterrupt:
        typer.echo(_INTERRUPTED, err=True)
        raise SystemExit(130) from None
    except SystemExit as exc:
        # typer ends a command that a Ctrl-C stopped with a silent Exit(130): say what happened
        ctx = exc.__context__
        if exc.code == 130 and ctx is not None and isinstance(ctx.__cause__, KeyboardInterrupt):
            typer.echo(_INTERRUPTED, err=True)
        raise
    except Exception as exc:
        if _SIGINTS:   # a library turned the Ctrl-C into another error: it was still a Ctrl-C
            typer.echo(_INTERRUPTED, err=True)
            raise SystemExit(130) from None
        if isinstance(exc, AlloError):
            typer.secho(f"error: {one_line(str(exc))}", fg=typer.colors.RED, err=True)
            raise SystemExit(2) from None
        line = _os_error_line(exc) if isinstance(exc, OSError) else None
        if line is None:
            raise
        typer.secho(line, fg=typer.colors.RED, err=True)
        raise SystemExit(2) from None


_SIGINTS: list[int] = []   # SIGINTs that reached Python's handler during the command (_noted_sigint)


def _noted_sigint(signum, frame):
    """Python's SIGINT handler (a KeyboardInterrupt), noting that one came: a C extension that takes
    numpy's C API as it loads turns a KeyboardInterrupt raised inside its import into "ImportError:
    numpy.core.multiarray failed to import", and a bare `except:` around an optional import turns it
    into the next import's error (skyfield's iokit: "No module named 'urlparse'"). The libraries
    this package loads lazily are imported with SIGINT held (core.interrupts); main() ends any other
    such error that follows a Ctrl-C as the Ctrl-C it was (exit 130, the one line), not a traceback."""
    _SIGINTS.append(signum)
    raise KeyboardInterrupt


def console() -> None:
    """The `allo-usd` command (its console script, and `python -m allo_usd.cli`): main(), then the
    process ends at once with SIGINT only noted (_exit_held). main() alone (a caller's process) returns
    or raises SystemExit as before."""
    said = True                     # main() prints the "interrupted" line itself when it ends with 130
    try:
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    except KeyboardInterrupt:       # a Ctrl-C on main()'s way out, after its own handling
        code, said = 130, False
    while True:
        try:
            _exit_held(code, said)  # never returns
        except KeyboardInterrupt:   # a Ctrl-C that came before the hold, raised as _exit_held began
            if code in (0, None):
                code, said = 130, False


def _exit_held(code, said: bool = True) -> None:
    """End the process with `code` (a SystemExit's: None is 0, a message is printed and 1), a SIGINT
    only noted from the first line on. Python's own shutdown after a command (module teardown, about
    0.3 s with USD, numpy and embree loaded) puts back the default SIGINT action, so a Ctrl-C landing
    there killed the process by the signal (status -2, no message) after its work was done. Noted, a
    Ctrl-C that comes before the end turns a success into 130 with the one line, as at any other
    moment. What shutdown does that matters runs first, in its order: threads joined (threading's
    exit hooks), atexit handlers, the standard streams flushed. A process that loaded bpy ends through
    Python's shutdown, as before: Blender removes its session's temporary folder in C exit handlers."""
    import signal

    came: list[int] = []
    signal.signal(signal.SIGINT, lambda *_: came.append(1))   # one already due runs this handler, not Python's
    try:
        _due()
    except KeyboardInterrupt:       # raised by Python's handler just before the line above
        came.append(1)
    import atexit
    import os
    import threading

    if isinstance(code, str):
        print(code, file=sys.stderr)
        code = 1
    code = 0 if code is None else int(code)

    def verdict(code: int) -> int:
        """`code`, or 130 (the one line said) for a success that a Ctrl-C came into."""
        if came and code == 0:
            code = 130
            typer.echo(_INTERRUPTED, err=True)
        elif code == 130 and not said:
            typer.echo(_INTERRUPTED, err=True)
        return code

    if "bpy" in sys.modules:        # Blender removes its session's temporary folder in its own C exit
        raise SystemExit(verdict(code))   # handlers, which os._exit would skip: Python's shutdown, as before
    threading._shutdown()           # what Python's shutdown runs first: non-daemon threads joined, executors' hooks
    atexit._run_exitfuncs()
    code = verdict(code)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):   # a closed or broken pipe: nothing more can be said
            pass
    os._exit(code)


def _due() -> None:
    """Nothing: a Python call, at whose start Python runs the signal handlers that are due."""


def _loaded() -> None:
    """Put back the SIGINT handler held while this module loaded. A Ctrl-C that came meanwhile ends
    `allo-usd` (the console script, or `python -m allo_usd.cli`) with the one line and exit 130;
    imported by anything else, the module hands it to the handler it displaced (Python's: a
    KeyboardInterrupt), as if nothing had held it."""
    command = __name__ == "__main__" or Path(sys.argv[0] if sys.argv else "").name == "allo-usd"
    if _LOADING.release(deliver=not command):
        typer.echo(_INTERRUPTED, err=True)
        raise SystemExit(130)
    if command:
        import signal

        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, _noted_sigint)


_loaded()

if __name__ == "__main__":
    console()
