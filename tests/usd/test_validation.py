"""USD's own validation (every registered validator) reports no errors on what we author.

In usd-core 26.x the old Python ComplianceChecker is gone: `usdchecker` runs these same
UsdValidation validators, so this is the compliance check."""

from __future__ import annotations

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.core.paths import BASE_STAGE

from tests.support.helpers import make_spec
from tests.support.validation import validation_errors


def test_committed_base_stage_validates():
    assert validation_errors(BASE_STAGE, warnings=True) == []


def test_scene_layer_validates_as_a_stage(tiny_base, tmp_path):
    layer = write_scene_layer(make_spec(anomaly=True), tmp_path / "s.usda", tiny_base)
    assert validation_errors(layer, warnings=True) == []


def test_validation_catches_a_broken_stage(tmp_path):
    bad = tmp_path / "bad.usda"
    bad.write_text('#usda 1.0\n(\n    upAxis = "Q"\n)\n\ndef Mesh "M"\n{\n    point3f[] points = [(0, 0, 0)]\n}\n')
    assert validation_errors(bad), "validators should reject an invalid upAxis / missing defaultPrim"
