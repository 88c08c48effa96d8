"""The library versions that computed a file's bytes, recorded beside what they made: a render's
JSON (`libraries`) and an authored tree's `versions.json` (TREE_VERSIONS). Never inside a USD layer:
layers stay byte-identical across machines and versions.

Versions come from package metadata (importlib.metadata), so nothing is imported: the parent process
never imports bpy. `lock_sha256` names the environment as a whole: the SHA-256 of the checkout's
`requirements.lock` (the exact versions, with hashes, that `make env` installs) when running from a
source checkout that has one, None in an installed wheel (which ships no lock).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

# Distributions whose code computes values written to files: the renderer and USD, the numerics
# (rig, placement, ray casts, sensor noise), the sky (ephemeris and its data), the image writers,
# the plan's parsing and writing, the plots.
LIBRARIES = ("allo-usd", "bpy", "usd-core", "numpy", "scipy", "trimesh", "embreex", "rtree", "skyfield", "jplephem",
             "skyfield-data", "OpenEXR", "Pillow", "pydantic", "pydantic-core", "PyYAML", "tomli-w", "matplotlib",
             "contourpy", "kiwisolver")
LOCK_FILE = "requirements.lock"   # at the top of a source checkout (`make lock` writes it)
TREE_VERSIONS = "versions.json"   # at the top of an authored tree (record_tree_versions)
_MAX_RECORD = 1 << 20             # a versions.json larger than this is not read (replaced)


def installed_version(name: str) -> str | None:
    """The installed version of distribution `name` (any spelling pip accepts), or None."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return None


def lock_path() -> Path | None:
    """The checkout's requirements.lock, or None when the package is not run from a source checkout
    that holds one (an installed wheel carries its data inside the package: allo_usd.core.paths)."""
    from allo_usd.core.paths import DATA, PACKAGE

    path = DATA / LOCK_FILE
    return path if DATA != PACKAGE and path.is_file() else None


@functools.cache
def _versions() -> tuple[tuple[str, str | None], ...]:
    from allo_usd.core.files import sha256_file

    lock = lock_path()
    return (*((n, installed_version(n)) for n in LIBRARIES), ("lock_sha256", None if lock is None else sha256_file(lock)))


def library_versions() -> dict[str, str | None]:
    """{distribution: installed version (None if missing)} for LIBRARIES, plus `lock_sha256`; read once
    per process (a fresh dict each call)."""
    return dict(_versions())


def _recorded_runs(path: Path) -> list[dict]:
    from allo_usd.core.files import read_own_record

    record = read_own_record(path, _MAX_RECORD)   # through the read gate; None when refused or not JSON
    runs = record.get("runs") if isinstance(record, dict) else None
    return [r for r in runs if isinstance(r, dict)] if isinstance(runs, list) else []


def record_tree_versions(tree: Path) -> Path:
    """Record in `tree/versions.json` the versions this authoring run uses: {"runs": [library_versions(),
    ...]}, oldest first. A run whose versions equal the last entry adds nothing (a resume with the same
    environment leaves the file's bytes as they were); a run with other versions is appended, never
    refused, so a tree resumed with other versions says which versions wrote into it. A record that
    cannot be read is replaced by this run's. Written atomically (allo_usd.core.files)."""
    from allo_usd.core.files import write_text_atomic

    path = Path(tree) / TREE_VERSIONS
    now = library_versions()
    runs = _recorded_runs(path)
    if runs and runs[-1] == now:
        return path
    record = {"note": "library versions of each authoring run that wrote into this tree, oldest first (a run "
                      "with the same versions as the last one is not repeated); allo_usd.core.provenance",
              "runs": [*runs, now]}
    return write_text_atomic(path, json.dumps(record, indent=1, sort_keys=True) + "\n")
