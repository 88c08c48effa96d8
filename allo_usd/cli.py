"""The `allo-usd` command line."""

from __future__ import annotations

from pathlib import Path

import typer

from allo_usd.core.errors import AlloError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Author, record and render the ALLO lunar-orbit anomaly dataset as USD layers.")
asset_app = typer.Typer(no_args_is_help=True, help="Convert real meshes into USD assets.")
app.add_typer(asset_app, name="asset")


@app.command()
def render(source: Path = typer.Argument(..., metavar="PLAN_OR_DIR_OR_LAYER",
                                         help="A scene layer (.usda), a directory of them, or a plan (.toml/.yaml)."),
           out: Path = typer.Option(Path("out/render"), "--out", help="Output directory."),
           force: bool = typer.Option(False, help="Re-render a single layer even if its outputs exist."),
           workers: int = typer.Option(0, "--workers",
                                       help="Local worker processes (default: the cores this process may use)."),
           scheduler: str = typer.Option(None, "--scheduler", help="Dask scheduler address (tcp://host:8786)."),
           threads: int = typer.Option(0, "--threads", help="Cycles threads per worker (default: cores // workers)."),
           retries: int = typer.Option(2, "--retries", help="Retries of a task whose worker crashed."),
           save_blend: Path = typer.Option(None, "--save-blend", metavar="FILE",
                                           help="A single layer only: also save the Blender scene it builds as "
                                                "FILE (.blend), to open what Blender got.")):
    """Render scene layers: RGB PNG, linear EXR, 3-class mask PNG and a metadata JSON per scene.

    One .usda layer renders in this process. A directory renders all its scene layers (searched
    recursively; an authored plan's scenes/) on a local pool (--workers) or a Dask cluster
    (--scheduler), resuming from OUT/manifest.jsonl; failures go to OUT/failed.jsonl and Blender's
    output to OUT/logs/. A plan is authored into OUT/layers first, then rendered into OUT/renders.
    With --save-blend FILE a single layer is rendered (even if done) and its Blender scene saved.
    """
    from allo_usd.run.dispatch import author_and_dispatch, dispatch
    from allo_usd.run.worker import output_to

    suffix = source.suffix.lower()
    single = suffix == ".usda" and source.is_file() and scheduler is None and not workers
    if save_blend is not None and not single:
        raise AlloError("--save-blend saves the Blender scene of one layer: pass a single .usda layer (without "
                        "--workers or --scheduler)")
    if single:
        from allo_usd.run.job import render_layer

        with output_to(out / "logs" / "render.log"):  # Blender's own prints
            meta = render_layer(source, out, force=force, threads=threads or None, save_blend=save_blend)
        typer.echo(f"{source} -> {out}: {meta['render_seconds']:.2f} s, classes {meta['class_pixels']}")
        if save_blend is not None:
            typer.echo(f"Blender scene saved as {save_blend}")
        return
    kwargs = dict(workers=workers or None, scheduler=scheduler, threads=threads or None, retries=retries)
    if source.is_file() and suffix in (".toml", ".yaml", ".yml"):
        summary = author_and_dispatch(source, out, **kwargs)
    elif source.is_dir() or (source.is_file() and suffix == ".usda"):
        summary = dispatch(source, out, **kwargs)
    else:
        raise AlloError(f"{source} does not exist or is not a .usda layer, a directory of layers or a plan "
                        "(.toml/.yaml); check the path")
    typer.echo(f"{source} -> {out}: {summary}")
    for row in summary.failed:
        typer.echo(f"  failed {row['scene']}: {row['reason']}", err=True)
    if summary.interrupted:
        raise SystemExit(130)
    if summary.failed:
        raise SystemExit(1)


@app.command()
def demo(out: Path = typer.Option(Path("out/demo"), "--out"),
         width: int = 480, height: int = 270, samples: int = 32):
    """Author and render the small demo dataset (2 normal, 2 anomalous scenes) and a contact sheet."""
    from allo_usd.run.demo import run_demo

    try:
        sheet = run_demo(out, (width, height), samples)
    except KeyboardInterrupt:
        typer.echo(f"interrupted: finished scenes are kept under {out}; re-run the same command to render the "
                   "rest", err=True)
        raise SystemExit(130) from None
    typer.echo(f"contact sheet: {sheet}")


@app.command()
def sky(out: Path = typer.Option(Path("out/sky"), "--out"), year: int = 2030, days: int = 365):
    """Write a year's sky table (CSV) and plot (PNG): distance, irradiance, eclipses, angular sizes."""
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.sky.report import write_sky_report

    s = compute_sky(default_epochs(year, days), Orbit())
    out.mkdir(parents=True, exist_ok=True)
    write_sky_report(s, out / f"sky_{year}.csv", out / f"sky_{year}.png")
    typer.echo(f"wrote {out / f'sky_{year}.csv'} and {out / f'sky_{year}.png'}")


@asset_app.command("import")
def asset_import(file: Path = typer.Argument(..., help="glTF/GLB, OBJ or STL file."),
                 out: Path = typer.Option(Path("out/assets"), "--out", help="Directory for the USD asset."),
                 units: str = typer.Option("auto", help="The file's unit: m, cm, mm, in, ft, or auto (glTF: "
                                           "metres; an absurd size for a station is read as inches)."),
                 up_axis: str = typer.Option("auto", "--up-axis", help="The file axis that points up: x, y, z, "
                                             "-x, -y, -z, or auto (the format's: glTF and OBJ y, STL z)."),
                 label: str = typer.Option("station", help="Class label: station or anomaly.")):
    """Convert a real mesh (through trimesh) into a USD asset in metres, Z up.

    The orientation and unit are the format's (glTF is +Y up and metres by specification) or
    --up-axis / --units; never guessed from the file name (NASA's ISS_2016.glb: --up-axis=-z)."""
    from allo_usd.assets.importer import import_mesh_report
    from allo_usd.usd.asset import write_asset

    report = import_mesh_report(file, units=units, up_axis=up_axis)
    path = write_asset(report.asset, out, label)
    typer.echo(f"{file} -> {path} (unit {report.unit}, up axis {report.source_up_axis}, "
               f"{report.triangles} triangles)")


@app.command()
def inspect(layer: Path = typer.Argument(..., help="Scene layer (.usda)."),
            as_json: bool = typer.Option(False, "--json", help="Print JSON instead of text.")):
    """Describe a scene from its USD layer alone: identity, seed, sky, camera, anomaly, render, layer stack."""
    import json

    from allo_usd.usd.inspect import describe, format_description

    d = describe(layer)
    typer.echo(json.dumps(d, indent=2) if as_json else format_description(d))


@app.command()
def diff(a: Path = typer.Argument(..., help="First scene layer."), b: Path = typer.Argument(..., help="Second."),
         full: bool = typer.Option(False, help="Compare every prim, not only those the non-shared layers touch.")):
    """List composed values that differ between two scene layers (exit 1 if any differ, like diff)."""
    from allo_usd.usd.inspect import diff as diff_layers
    from allo_usd.usd.inspect import format_diff

    rows = diff_layers(a, b, full=full)
    typer.echo(format_diff(rows))
    if rows:
        raise typer.Exit(1)


@app.command()
def dataset(render_dirs: list[Path] = typer.Argument(..., help="Render directories (NAME.json + files)."),
            out: Path = typer.Option(..., "--out", help="Dataset directory."),
            category: str = typer.Option("allo", help="MVTec category name."),
            copy: bool = typer.Option(False, "--copy", help="Copy files instead of hard-linking them.")):
    """Assemble renders into an MVTec-AD-style tree, 3-class masks, a manifest and contact sheets.

    Re-runs add only new or re-rendered scenes. Ctrl-C stops after the scene in hand (exit 130);
    the manifest always lists every file in the tree. Mask-only renders are left out (no image)."""
    import warnings

    from allo_usd.output.dataset import assemble, read_manifest

    with warnings.catch_warnings(record=True) as notes:
        warnings.simplefilter("always")
        try:
            manifest = assemble(render_dirs, out, link=not copy, category=category, progress=True)
        except KeyboardInterrupt as exc:
            _notes(notes)
            typer.echo(f"interrupted: {exc or 'before any file was placed; re-run the same command'}", err=True)
            raise SystemExit(130) from None
    _notes(notes)
    rows = [r for r in read_manifest(manifest) if r["category"] == category]
    counts = {k: sum(1 for r in rows if (r["split"], r["kind"]) == k) for k in
              (("train", "good"), ("test", "good"), ("test", "anomaly"))}
    typer.echo(f"{out / category}: " + ", ".join(f"{s}/{k} {n}" for (s, k), n in counts.items())
               + f"; manifest {manifest}")


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
           out: Path = typer.Option(Path("out/dataset"), "--out", help="Output directory for the layers."),
           limit: int = typer.Option(None, "--limit", help="Author only the first N scenes of the plan "
                                     "(and the reserve scenes that top up their skipped depths)."),
           workers: int = typer.Option(None, "--workers", help="Processes (default: 2 for large plans)."),
           progress: bool = typer.Option(True, help="Show a progress bar.")):
    """Author a plan's scene layers over shared sky and camera-sample layers (resumes; skips done).

    Anomalous depths that the placement check skips are topped up from reserve placements of the
    same seed, asset and variant, so each reaches its planned count (allo_usd.run.author). With
    --limit N the quotas are those of the first N scenes, and their skipped depths are topped up
    too. Ends with planned vs authored counts (also in OUT/counts.csv); exits 1 if an asset stays
    short because its reserve groups ran out (anomalies.reserve_groups_per_slot).
    """
    from allo_usd.run.author import AuthoringInterrupted, author as author_tree, summary_lines
    from allo_usd.plan.io import load_plan

    try:
        plan = load_plan(plan_file)
        done = author_tree(plan, out, limit=limit, progress=progress, workers=workers)
    except AuthoringInterrupted as exc:
        typer.echo(f"{exc}", err=True)
        raise SystemExit(130) from None
    except KeyboardInterrupt:  # before the first scene: nothing but finished files was written
        typer.echo("interrupted before authoring began; re-run the same command", err=True)
        raise SystemExit(130) from None
    typer.echo(f"{len(done.paths)} scene layers under {out / 'scenes'}; skipped depths in {out / 'skipped.csv'}, "
               f"planned vs authored in {out / 'counts.csv'}")
    topup = plan.anomalies.reserve_groups_per_slot > 0
    for line in summary_lines(done.counts, topup):
        typer.echo(line, err=line.startswith("SHORT"))
    if done.short and topup:
        raise SystemExit(1)


def main() -> None:
    try:
        app()
    except AlloError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
