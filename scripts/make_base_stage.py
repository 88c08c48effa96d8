#!/usr/bin/env python
"""Regenerate the base stage and every asset under stages/ (deterministic; the files are committed).

    python scripts/make_base_stage.py                       # procedural station -> stages/
    python scripts/make_base_stage.py --station ISS_2016.glb --units in --up-axis=-z --out out/stages_iss

An imported model's orientation and unit are its format's (glTF: +Y up, metres) or --up-axis /
--units (allo_usd.assets.importer); NASA's ISS_2016.glb breaks glTF's rule (inches, +Z nadir),
so it needs both given (--units auto reads its inches from its size).

Byte-identical across x86-64 machines: numpy's small products and norms (`@`, `np.dot`,
`np.linalg.norm`) go through OpenBLAS, which picks a kernel per CPU at load time, and the
AVX-512 kernels round the last bit differently from the AVX2 ones (measured: 7 of 97 files
differed on an AVX-512 EPYC). So this script pins OpenBLAS to its AVX2 ("Haswell") kernel
before numpy loads, on every x86-64 CPU that has AVX2 and FMA (`blas_pin`). Elsewhere the
files match to the last few ulps, and tests/test_base_stage.py compares them by value.
"""

from __future__ import annotations

import os
import platform
import sys


def blas_pin() -> dict[str, str]:
    """The environment that makes OpenBLAS round the same on every x86-64 CPU with AVX2, or {}."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return {}
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:
        return {}
    return {"OPENBLAS_CORETYPE": "Haswell"} if {"avx2", "fma"} <= set(flags) else {}


if __name__ == "__main__":  # before numpy is imported; importing this file (tests) changes nothing
    for _key, _value in blas_pin().items():
        os.environ.setdefault(_key, _value)

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402

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
