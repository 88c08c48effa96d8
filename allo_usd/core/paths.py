"""Where the project's shipped files live (the package is installed editable from the repo)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent
STAGES = ROOT / "stages"
SCHEMAS = ROOT / "schemas"
BASE_STAGE = STAGES / "base.usda"
