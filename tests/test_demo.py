"""What `make run` does, at 64x36: real scenes over the committed stage, rendered and valid."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from allo_usd.demo import run_demo

from test_validation import validation_errors

pytestmark = pytest.mark.render


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    run_demo(out, resolution=(64, 36), samples=2)
    return out


def test_demo_renders_two_normal_and_two_anomalous(demo_dir):
    metas = [json.loads(p.read_text()) for p in sorted((demo_dir / "renders").glob("*.json"))]
    assert len(metas) == 4
    kinds = sorted(m["scene"]["variant"] for m in metas)
    assert kinds == ["anomaly", "anomaly", "normal", "normal"]
    for m in metas:
        mask = np.asarray(Image.open(demo_dir / "renders" / m["files"]["mask"]))
        assert mask.shape == (36, 64)
        assert (mask == 1).any(), "every demo pose looks at the station"
        assert ((mask == 2).any()) == (m["scene"]["variant"] == "anomaly")
        assert m["scene"]["provenance"]["seed"] == m["scene"]["seed"]
    sheet = Image.open(demo_dir / "contact_sheet.png")
    assert sheet.size[0] > 128 and sheet.size[1] > 4 * 36


def test_every_demo_layer_validates(demo_dir):
    layers = sorted((demo_dir / "layers").glob("*.usda"))
    assert len(layers) == 4
    for layer in layers:
        assert layer.stat().st_size <= 6144  # opinions only: a few KB, never geometry
        assert validation_errors(layer) == [], layer.name
