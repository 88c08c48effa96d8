"""The render job's target mode, without Blender (the render itself is a stand-in that records what it
was asked for): the layer's target, or the run's override, reaches the render; the JSON records the
target used, the layer's and the render's accuracy; a render without a target writes the JSON it wrote
before; and the done rule re-renders a changed or overridden target."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from allo_usd.core.errors import AlloError
from allo_usd.output.identity import done_record, render_identity
from allo_usd.run import job as job_module
from allo_usd.run.job import render_record
from allo_usd.run.options import JobOptions
from allo_usd.usd.scene_layer import write_scene_layer

from tests.support.helpers import make_spec

ESTIMATE = {"mode": "target", "target_psnr_db": 40.0, "estimated_psnr_db": 40.6, "samples": 48, "rounds": 3,
            "stopped_by": "target", "estimator": "two halves"}


@pytest.fixture
def fake_blender(monkeypatch):
    """render_record with Blender stood in for: each render's RenderDesc is kept in `asked`, and the
    render returns flat images (and ESTIMATE as its accuracy when the layer asks for a target)."""
    from allo_usd.blender import device
    from allo_usd.blender.render import RenderResult

    asked = []

    def render(desc, *args, **kwargs):
        asked.append(desc.render)
        w, h = desc.render.resolution
        return RenderResult(rgb=np.full((h, w, 3), 0.25, np.float32), mask=np.zeros((h, w), np.uint8), depth=None,
                            seconds=0.5, ids=np.zeros((h, w), np.uint16), objects=(),
                            accuracy=dict(ESTIMATE) if desc.render.target_psnr > 0 else None)

    monkeypatch.setattr(job_module, "import_held", lambda name: None)
    monkeypatch.setattr(job_module, "_render", render)
    monkeypatch.setattr(device, "select", lambda requested: device.Device(requested))
    monkeypatch.setattr(device, "record", lambda used: {"used": "CPU"})
    monkeypatch.setattr(device, "cycles_cpu", lambda: {"kernel": "stand-in"})
    return asked


def _layer(tiny_base, tmp_path, name="s", **render):
    spec = make_spec()
    return write_scene_layer(replace(spec, render=replace(spec.render, **render)), tmp_path / "layers" / f"{name}.usda",
                             tiny_base)


def test_a_layer_without_a_target_renders_and_records_as_before(fake_blender, tiny_base, tmp_path):
    layer, out = _layer(tiny_base, tmp_path), tmp_path / "out"
    meta = render_record(layer, out)
    assert fake_blender[-1].target_psnr == 0.0 and fake_blender[-1].time_limit == 0.0
    written = json.loads((out / "s.json").read_text())
    assert not {"target", "layer_target", "accuracy"} & set(written)   # the JSON holds what it held before
    assert meta.identity == render_identity(meta.inputs)                  # and its identity is the old formula
    assert done_record(layer, out) is not None


def test_a_layers_target_reaches_the_render_and_the_record(fake_blender, tiny_base, tmp_path):
    layer, out = _layer(tiny_base, tmp_path, target_psnr=40.0, time_limit=90.0), tmp_path / "out"
    meta = render_record(layer, out)
    assert (fake_blender[-1].target_psnr, fake_blender[-1].time_limit) == (40.0, 90.0)
    target = {"target_psnr": 40.0, "time_limit": 90.0}
    assert meta.target == meta.layer_target == target and meta.accuracy == ESTIMATE
    written = json.loads((out / "s.json").read_text())
    assert written["target"] == target and written["accuracy"] == ESTIMATE
    assert meta.identity == render_identity(meta.inputs, target=target) != render_identity(meta.inputs)
    assert done_record(layer, out) is not None   # the layer's own target: done, skipped next time
    render_record(layer, out)
    assert len(fake_blender) == 1


def test_a_target_override_renders_again_and_is_never_done(fake_blender, tiny_base, tmp_path):
    layer, out = _layer(tiny_base, tmp_path), tmp_path / "out"
    render_record(layer, out)
    meta = render_record(layer, out, JobOptions(target_psnr=42.0))   # done without a target: rendered anyway
    assert len(fake_blender) == 2 and fake_blender[-1].target_psnr == 42.0
    assert meta.target == {"target_psnr": 42.0, "time_limit": 0.0} and meta.layer_target is None
    assert done_record(layer, out) is None            # not the layer's own render: the next plain run redoes it
    render_record(layer, out)
    assert len(fake_blender) == 3 and fake_blender[-1].target_psnr == 0.0
    # a time limit alone stops the layer's own target; --target-psnr 0 renders the layer's fixed samples
    aimed = _layer(tiny_base, tmp_path, name="t", target_psnr=40.0)
    meta = render_record(aimed, out, JobOptions(time_limit=30.0))
    assert meta.target == {"target_psnr": 40.0, "time_limit": 30.0} and meta.layer_target == {"target_psnr": 40.0,
                                                                                                "time_limit": 0.0}
    assert render_record(aimed, out, JobOptions(target_psnr=0.0)).target is None


def test_a_record_whose_target_was_edited_is_not_done(fake_blender, tiny_base, tmp_path):
    layer, out = _layer(tiny_base, tmp_path, target_psnr=40.0), tmp_path / "out"
    render_record(layer, out)
    record = json.loads((out / "s.json").read_text())
    for change in ({"target_psnr": 30.0, "time_limit": 0.0}, None, "40", [40]):
        edited = {**record, "target": change, "layer_target": change}
        (out / "s.json").write_text(json.dumps(edited))
        assert done_record(layer, out) is None, change   # the identity no longer holds


def test_a_time_limit_without_any_target_is_one_line_before_the_render(fake_blender, tiny_base, tmp_path):
    layer = _layer(tiny_base, tmp_path)
    with pytest.raises(AlloError, match=r"^--time-limit 30 is given without --target-psnr: .*fix: give --target-psnr "
                                        r"too \(e\.g\. 40\) or drop --time-limit$"):
        render_record(layer, tmp_path / "out", JobOptions(time_limit=30.0))
    assert fake_blender == [] and not (tmp_path / "out" / "s.json").exists()
