#!/usr/bin/env python
"""Regenerate the base stage and every asset under stages/ (deterministic; the files are committed).

    python scripts/make_base_stage.py                       # procedural station -> stages/
    python scripts/make_base_stage.py --station ISS.glb --out out/stages_iss   # imported model
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from allo_usd.assets.anomalies import ANOMALY_VARIANTS, build_anomaly
from allo_usd.assets.bodies import build_bodies
from allo_usd.author.base import write_base_stage
from allo_usd.paths import STAGES
from allo_usd.rig import base_poses, fixtures_from_mesh


def station_and_fixtures(source: str | None, units: str = "auto"):
    if source is None:
        from allo_usd.assets.station import build_station, station_fixture_points

        station = build_station()
        return station, station_fixture_points(), "Procedural ISS-like station (allo_usd.assets.station)."
    from allo_usd.assets.importer import ISS_2016_ROTATION, import_mesh_report

    rotation = ISS_2016_ROTATION if Path(source).name == "ISS_2016.glb" else None
    report = import_mesh_report(source, units=units, name="Station", rotation=rotation)
    pts, tris = report.asset.triangle_soup()
    return report.asset, fixtures_from_mesh(pts, tris), (
        f"Imported from {Path(source).name} (unit {report.unit}, {report.triangles} triangles).")


def build(out: Path, station_source: str | None = None, units: str = "auto") -> Path:
    station, fixtures, doc = station_and_fixtures(station_source, units)
    pts, _ = station.triangle_soup()
    structure = np.concatenate([pts[:: max(1, len(pts) // 4000)], fixtures])
    poses = base_poses(fixtures, structure)
    anomalies = {name: {v: build_anomaly(name, v) for v in variants} for name, variants in ANOMALY_VARIANTS.items()}
    return write_base_stage(out, station, build_bodies(), anomalies, poses, station_doc=doc)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=STAGES)
    ap.add_argument("--station", help="glTF/OBJ/STL model to use instead of the procedural station")
    ap.add_argument("--units", default="auto")
    args = ap.parse_args(argv)
    print(build(args.out, args.station, args.units))
    return 0


if __name__ == "__main__":
    sys.exit(main())
