"""Small dataset plans for the authoring tests, and a tree opened with plain usd-core."""

from __future__ import annotations

import json
from pathlib import Path

from allo_usd.core.paths import BASE_STAGE
from allo_usd.plan.model import AnomalyChoice, Anomalies, Dates, Plan, Poses, Quality


def tiny_plan() -> Plan:
    return Plan(name="tiny", dates=Dates(days=2), poses=Poses(train=[1, 2], test=[41]),
                anomalies=Anomalies(assets=[AnomalyChoice(id="power_drill")], depths=[0, 1, 2, 3, 4]),
                quality=Quality(resolution=(64, 36), samples=4), base_stage=str(BASE_STAGE))


def small_plan(resolution=(160, 90), days: int = 1, train=(1,), base_stage: Path = BASE_STAGE, **kw) -> Plan:
    return Plan(name="tree", dates=Dates(days=days), poses=Poses(train=list(train), test=[41]),
                anomalies=Anomalies(assets=[AnomalyChoice(id="power_drill")], depths=[0]),
                quality=Quality(resolution=resolution, samples=4), base_stage=str(base_stage), **kw)


PLAIN_USD = r"""
import json, os, sys
from pxr import Usd, UsdValidation
root = os.path.realpath(sys.argv[1])
validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
report = {"validators": len(validators), "layers": {}}
for path in sys.argv[2:]:
    stage = Usd.Stage.Open(path)
    used = [layer.realPath for layer in stage.GetUsedLayers() if not layer.anonymous]
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    report["layers"][path] = {
        "composition_errors": [str(e) for e in stage.GetCompositionErrors()],
        "outside": [u for u in used if os.path.commonpath([root, os.path.realpath(u)]) != root],
        "used": len(used),
        "anomaly_loaded": (len(stage.GetPrimAtPath("/World/Anomaly").GetAllChildren()) > 0
                           if stage.GetPrimAtPath("/World/Anomaly") else None),
        "validation_errors": [f"{e.GetName()}: {e.GetMessage()}" for e in errors
                              if e.GetType() == UsdValidation.ValidationErrorType.Error]}
report["allo_usd_imported"] = any(m.startswith("allo_usd") for m in sys.modules)
print(json.dumps(report))
"""


def plain_usd_report(root: Path, layers: list[Path]) -> dict:
    """Open each layer with usd-core alone, in a fresh process: no allo_usd import, no plugin path
    or asset-root variables, run from an unrelated directory. Returns what it found."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k in ("PATH", "HOME", "LANG", "TMPDIR")}
    proc = subprocess.run([sys.executable, "-c", PLAIN_USD, str(root), *map(str, layers)], env=env,
                          cwd=Path(root).anchor, capture_output=True, text=True, check=True)
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["validators"] > 10 and report["allo_usd_imported"] is False
    return report
