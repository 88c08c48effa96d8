"""Regenerate the base stage and every asset under stages/ (deterministic; the files are committed).

    python -m scripts.make_base_stage                       # procedural station -> stages/
    python -m scripts.make_base_stage --station ISS_2016.glb --units in --up-axis=-z --out out/stages_iss

An imported model's orientation and unit are its format's (glTF: +Y up, metres) or --up-axis /
--units (allo_usd.assets.importer); NASA's ISS_2016.glb breaks glTF's rule (inches, +Z nadir),
so it needs both given (--units auto reads its inches from its size).

Byte-identical on every x86-64 machine, whatever its BLAS kernel or SIMD features: every value that
reaches a file is computed with allo_usd.core.fixedmath (no BLAS, no libm or SVML transcendentals),
so no environment pin is needed (scripts/check_determinism.py shows it; docs/reliability/determinism.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from allo_usd.usd.build_stage import build_base_stage as build
from allo_usd.core.paths import STAGES


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=STAGES)
    ap.add_argument("--station", help="glTF/OBJ/STL model to use instead of the procedural station")
    ap.add_argument("--units", default="auto", help="the model's unit: m, cm, mm, in, ft or auto")
    ap.add_argument("--up-axis", default="auto", help="the model axis pointing up: x, y, z, -x, -y, -z or auto "
                                                      "(the format's: glTF and OBJ y, STL z)")
    args = ap.parse_args(argv)
    print(build(args.out, args.station, args.units, args.up_axis))
    return 0


if __name__ == "__main__":
    sys.exit(main())
