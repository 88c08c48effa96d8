"""USD's own validation (every registered validator) reports no errors on what we author.

In usd-core 26.x the old Python ComplianceChecker is gone: `usdchecker` runs these same
UsdValidation validators, so this is the compliance check."""

from __future__ import annotations

from pxr import Usd, UsdValidation

from allo_usd.usd import schema
from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.core.paths import BASE_STAGE

from tests.support.helpers import make_spec


def validation_errors(path, warnings: bool = False) -> list[str]:
    """Errors (and, with `warnings`, warnings too) that all registered validators find on `path`."""
    schema.register()
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) > 10
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors
            if e.GetType() == UsdValidation.ValidationErrorType.Error
            or (warnings and e.GetType() == UsdValidation.ValidationErrorType.Warn)]


def test_committed_base_stage_validates():
    assert validation_errors(BASE_STAGE, warnings=True) == []


def test_scene_layer_validates_as_a_stage(tiny_base, tmp_path):
    layer = write_scene_layer(make_spec(anomaly=True), tmp_path / "s.usda", tiny_base)
    assert validation_errors(layer, warnings=True) == []


def test_validation_catches_a_broken_stage(tmp_path):
    bad = tmp_path / "bad.usda"
    bad.write_text('#usda 1.0\n(\n    upAxis = "Q"\n)\n\ndef Mesh "M"\n{\n    point3f[] points = [(0, 0, 0)]\n}\n')
    assert validation_errors(bad), "validators should reject an invalid upAxis / missing defaultPrim"
