"""The `allo-usd` command line."""

from __future__ import annotations

from pathlib import Path

import typer

from .errors import AlloError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Author, record and render the ALLO lunar-orbit anomaly dataset as USD layers.")
asset_app = typer.Typer(no_args_is_help=True, help="Convert real meshes into USD assets.")
app.add_typer(asset_app, name="asset")


@app.command()
def render(layer: Path = typer.Argument(..., help="Scene layer (.usda) to render."),
           out: Path = typer.Option(Path("out/render"), "--out", help="Output directory."),
           force: bool = typer.Option(False, help="Re-render even if outputs exist.")):
    """Render one scene layer: RGB PNG, linear EXR, 3-class mask PNG and a metadata JSON."""
    from .job import render_layer

    meta = render_layer(layer, out, force=force)
    typer.echo(f"{layer} -> {out}: {meta['render_seconds']:.2f} s, classes {meta['class_pixels']}")


@app.command()
def demo(out: Path = typer.Option(Path("out/demo"), "--out"),
         width: int = 480, height: int = 270, samples: int = 32):
    """Author and render the small demo dataset (2 normal, 2 anomalous scenes) and a contact sheet."""
    from .demo import run_demo

    sheet = run_demo(out, (width, height), samples)
    typer.echo(f"contact sheet: {sheet}")


@app.command()
def sky(out: Path = typer.Option(Path("out/sky"), "--out"), year: int = 2030, days: int = 365):
    """Write a year's sky table (CSV) and plot (PNG): distance, irradiance, eclipses, angular sizes."""
    from .sky import Orbit, compute_sky, default_epochs
    from .sky_report import write_sky_report

    s = compute_sky(default_epochs(year, days), Orbit())
    out.mkdir(parents=True, exist_ok=True)
    write_sky_report(s, out / f"sky_{year}.csv", out / f"sky_{year}.png")
    typer.echo(f"wrote {out / f'sky_{year}.csv'} and {out / f'sky_{year}.png'}")


@asset_app.command("import")
def asset_import(file: Path = typer.Argument(..., help="glTF/GLB, OBJ or STL file."),
                 out: Path = typer.Option(Path("out/assets"), "--out", help="Directory for the USD asset."),
                 units: str = typer.Option("auto", help="m, cm, mm, in, ft or auto."),
                 label: str = typer.Option("station", help="Class label: station or anomaly.")):
    """Convert a real mesh (through trimesh) into a USD asset in metres, Z up."""
    from .assets.importer import import_mesh_report
    from .author.asset import write_asset

    report = import_mesh_report(file, units=units)
    path = write_asset(report.asset, out, label)
    typer.echo(f"{file} -> {path} (unit {report.unit}, {report.triangles} triangles)")


def main() -> None:
    try:
        app()
    except AlloError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
