#!/usr/bin/env python
"""Regenerate the base stage and every asset under stages/ (deterministic; the files are committed).

    python scripts/make_base_stage.py                       # procedural station -> stages/
    python scripts/make_base_stage.py --station ISS.glb --out out/stages_iss   # imported model
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from allo_usd.author.build_stage import build_base_stage as build
from allo_usd.paths import STAGES


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
