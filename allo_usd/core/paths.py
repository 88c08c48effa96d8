"""Where the package's shipped data lives: the base stage with its assets, and the schemas.

Both are package data (`allo_usd/stages`, `allo_usd/schemas`), found with importlib.resources so that
a non-editable install (a wheel) finds them exactly as a source checkout does. USD opens files by
path, so the package must be installed on disk (pip always does that), not imported from a zip.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def _package_dir() -> Path:
    root = files("allo_usd")
    if not isinstance(root, Path) or not (root / "stages").is_dir():
        raise ImportError(f"allo_usd's data (stages/, schemas/) is not on disk at {root}; USD opens files by "
                          "path, so install the package into a directory (pip install allo-usd), not a zip")
    return root


PACKAGE = _package_dir()
STAGES = PACKAGE / "stages"
SCHEMAS = PACKAGE / "schemas"
BASE_STAGE = STAGES / "base.usda"
# The source checkout (scripts/, tests/, docs/); only development tools use it, never the package.
ROOT = PACKAGE.parent
