"""Build a complete base stage (station, bodies, anomalies, rig) from the procedural station or a
real model file. Deterministic: the same source gives byte-identical files."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import write_base_stage


def station_and_fixtures(source: str | None, units: str = "auto"):
    """(station Asset, camera fixture points, provenance note) for 'procedural'/None or a model path."""
    if source in (None, "procedural"):
        from ..assets.station import build_station, station_fixture_points

        return build_station(), station_fixture_points(), "Procedural ISS-like station (allo_usd.assets.station)."
    from ..assets.importer import ISS_2016_ROTATION, import_mesh_report
    from ..rig import fixtures_from_mesh

    rotation = ISS_2016_ROTATION if Path(source).name == "ISS_2016.glb" else None
    report = import_mesh_report(source, units=units, name="Station", rotation=rotation)
    pts, tris = report.asset.triangle_soup()
    return report.asset, fixtures_from_mesh(pts, tris), (
        f"Imported from {Path(source).name} (unit {report.unit}, {report.triangles} triangles).")


def build_base_stage(out: Path, station_source: str | None = None, units: str = "auto") -> Path:
    """Write `out/base.usda` and every asset it references; returns the base stage path."""
    from ..assets.anomalies import ANOMALY_VARIANTS, build_anomaly
    from ..assets.bodies import build_bodies
    from ..rig import base_poses

    station, fixtures, doc = station_and_fixtures(station_source, units)
    pts, _ = station.triangle_soup()
    structure = np.concatenate([pts[:: max(1, len(pts) // 4000)], fixtures])
    poses = base_poses(fixtures, structure)
    anomalies = {name: {v: build_anomaly(name, v) for v in variants} for name, variants in ANOMALY_VARIANTS.items()}
    return write_base_stage(out, station, build_bodies(), anomalies, poses, station_doc=doc)
