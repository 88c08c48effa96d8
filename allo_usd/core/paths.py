"""Where the package's shipped data lives: the base stage with its assets, and the schemas.

In the repository they sit at the top, beside `allo_usd/` (`stages/`, `schemas/`), where a reader
of the project finds them. A wheel maps them into the package (`allo_usd/stages`, `allo_usd/schemas`:
pyproject.toml's `package-dir`), so an installed package carries its own copy. Both are found from
the package's location, so a non-editable install (a wheel) finds them exactly as a source checkout
or an editable install does. USD opens files by path, so the package must be installed on disk
(pip always does that), not imported from a zip.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

_MARKERS = ("stages/base.usda", "schemas/alloUsd/plugInfo.json")


def _data_root() -> tuple[Path, Path]:
    """(the package directory, the directory holding stages/ and schemas/): the package itself in an
    installed wheel, the checkout's top in a source checkout (recognised by its pyproject.toml, so an
    unrelated `stages/` beside an installed package is never taken)."""
    root = files("allo_usd")
    if not isinstance(root, Path):
        raise ImportError(f"allo_usd is not on disk at {root}; USD opens files by path, so install the "
                          "package into a directory (pip install allo-usd), not a zip")
    for cand, needs in ((root, None), (root.parent, root.parent / "pyproject.toml")):
        if all((cand / m).is_file() for m in _MARKERS) and (needs is None or needs.is_file()):
            return root, cand
    raise ImportError(f"allo_usd's data (stages/, schemas/) is neither in the package at {root} (a wheel) nor "
                      f"at the top of a source checkout ({root.parent}); reinstall the package, or restore "
                      "stages/ and schemas/ in the checkout (git checkout -- stages schemas)")


PACKAGE, DATA = _data_root()   # DATA holds stages/ and schemas/ (the package in a wheel, the checkout top)
STAGES = DATA / "stages"
SCHEMAS = DATA / "schemas"
BASE_STAGE = STAGES / "base.usda"
# The source checkout (scripts/, tests/, docs/); only development tools use it, never the package.
ROOT = PACKAGE.parent
