"""Build a complete base stage (station, bodies, anomalies, rig) from the procedural station or a
real model file. Deterministic: the same source gives byte-identical files."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.usd.base_stage import write_base_stage


# Candidate camera positions sampled off the surface, from which `rig.base_poses` picks 50.
SURFACE_CANDIDATES = 200
# Procedural parts an arm camera is not mounted beside: the solar wings and radiators (large,
# thin panels that would otherwise take most area-weighted samples). Their geometry still counts
# for clearance and for what each view sees.
_NOT_FIXTURES = ("solar", "radiator")


def station_and_fixtures(source: str | None, units: str = "auto", up_axis: str = "auto"):
    """(station Asset, candidate camera positions, provenance note) for 'procedural'/None or a
    model path. Candidates: the procedural station's exterior fixture points plus samples 1-2.5 m
    off its modules and truss; for an imported model, samples 1-2.5 m off its whole surface.

    A model's orientation and units are the file's own (its format's rule, see
    allo_usd.assets.importer) or the `up_axis` / `units` given (a plan's [station], the `--up-axis`
    / `--units` options); never inferred from its file name, so a renamed copy imports the same."""
    from allo_usd.assets.mesh import Asset
    from allo_usd.scene.rig import fixtures_from_mesh

    if source in (None, "procedural"):
        from allo_usd.assets.station import build_station, station_fixture_points

        station = build_station()
        flat = build_station(articulated=False)   # the rest pose, merged as the rig was chosen from
        core = Asset("core", tuple(p for p in flat.parts if not p.name.startswith(_NOT_FIXTURES)),
                     flat.materials, flat.textures)
        samples = fixtures_from_mesh(*core.triangle_soup(), count=SURFACE_CANDIDATES)
        return (station, np.concatenate([station_fixture_points(), samples]),
                "Procedural ISS-like station (allo_usd.assets.station).")
    from allo_usd.assets.importer import import_mesh_report

    report = import_mesh_report(source, units=units, up_axis=up_axis, name="Station")
    pts, tris = report.asset.triangle_soup()
    return report.asset, fixtures_from_mesh(pts, tris, count=SURFACE_CANDIDATES, weight="triangle"), (
        f"Imported from {Path(source).name} (unit {report.unit}, up axis {report.source_up_axis}, "
        f"{report.triangles} triangles).")


def build_base_stage(out: Path, station_source: str | None = None, units: str = "auto",
                     up_axis: str = "auto", lens: CameraModel = DEFAULT_CAMERA, size: tuple[int, int] | None = None) -> Path:
    """Write `out/base.usda` and every asset it references; returns the base stage path. `lens`, `size`:
    the camera (core.camera_model) and image size the rig scores its views with (default Table I)."""
    from allo_usd.assets.anomalies import ANOMALY_VARIANTS, build_anomaly
    from allo_usd.assets.bodies import build_bodies
    from allo_usd.scene.rig import base_poses

    station, fixtures, doc = station_and_fixtures(station_source, units, up_axis)
    poses = base_poses(fixtures, *station.triangle_soup(), lens, size)
    anomalies = {name: {v: build_anomaly(name, v) for v in variants} for name, variants in ANOMALY_VARIANTS.items()}
    return write_base_stage(out, station, build_bodies(), anomalies, poses, station_doc=doc, lens=lens, size=size)
