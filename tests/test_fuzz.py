"""Fuzz the reader: 500 mutated scene layers each give a clear AlloError (or a valid scene), fast.

Every mutation except random garbage is invalid by construction and must be rejected with an
`AlloError` that names the problem; garbage bytes may land somewhere harmless (a comment, a
string), so those may also read successfully, but never raise anything else. A small batch with
a few bad layers then goes through the dispatcher: good layers render, bad ones are recorded.
"""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest

from allo_usd.author.scene import write_scene_layer
from allo_usd.description import SceneDescription
from allo_usd.errors import AlloError
from allo_usd.read import read_scene

from conftest import make_spec

N_CASES = 500


def _sub(pattern: str, repl: str):
    def mutate(text: str, rng) -> str:
        out, n = re.subn(pattern, repl, text, count=1)
        assert n == 1, pattern
        return out
    return mutate


def _truncate(text: str, rng) -> str:
    return text[: int(rng.integers(0, text.rindex("}")))]


def _garbage(text: str, rng) -> str:
    data = text.encode()
    kind = int(rng.integers(3))
    noise = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
    if kind == 0:
        return noise.decode("latin-1")
    i = int(rng.integers(0, len(data)))
    if kind == 1:
        data = data[:i] + noise + data[i:]
    else:
        data = data[:i] + noise + data[i + len(noise):]
    return data.decode("latin-1")


BAD_NUMBERS = ["nan", "inf", "-inf"]
INVALID = {
    # wrong attribute types
    "samples_type": _sub(r"int allo:render:samples = \d+", 'string allo:render:samples = "many"'),
    "resolution_type": _sub(r"uniform int2 resolution = \(\d+, \d+\)", 'uniform string resolution = "big"'),
    "intensity_type": _sub(r"float inputs:intensity = \S+", 'string inputs:intensity = "bright"'),
    "translate_type": _sub(r"double3 xformOp:translate = \(15, 8, 5\)", 'string xformOp:translate = "here"'),
    "exposure_type": _sub(r"float allo:render:exposure = \S+", "bool allo:render:exposure = 1"),
    "orient_type": _sub(r"quatd xformOp:orient = \(1, 0, 0, 0\)", "int xformOp:orient = 3"),
    # non-finite transforms and values
    "camera_nan": lambda t, rng: _sub(r"double3 xformOp:translate = \(15, 8, 5\)",
                                      f"double3 xformOp:translate = ({rng.choice(BAD_NUMBERS)}, 8, 5)")(t, rng),
    "anomaly_nan": lambda t, rng: _sub(r"double3 xformOp:translate = \(8, 4, 2.5\)",
                                       f"double3 xformOp:translate = (8, {rng.choice(BAD_NUMBERS)}, 2.5)")(t, rng),
    "orient_nan": lambda t, rng: _sub(r"quatd xformOp:orient = \(1, 0, 0, 0\)",
                                      f"quatd xformOp:orient = ({rng.choice(BAD_NUMBERS)}, 0, 0, 0)")(t, rng),
    "scale_inf": lambda t, rng: _sub(r"double3 xformOp:scale = \(1737400, 1737400, 1737400\)",
                                     f"double3 xformOp:scale = (1, {rng.choice(BAD_NUMBERS)}, 1)")(t, rng),
    "sun_nan": lambda t, rng: _sub(r"float inputs:intensity = \S+",
                                   f"float inputs:intensity = {rng.choice(BAD_NUMBERS)}")(t, rng),
    "exposure_nan": lambda t, rng: _sub(r"float allo:render:exposure = \S+",
                                        f"float allo:render:exposure = {rng.choice(BAD_NUMBERS + ['0', '-1'])}")(t, rng),
    # missing files
    "missing_sublayer": _sub(r"@([^@]*)base\.usda@", r"@\1gone.usda@"),
    "missing_reference": _sub(r"@([^@]*)anomalies/Crate\.usda@", r"@\1anomalies/Gone.usda@"),
    "outside_sublayer": _sub(r"@([^@]*)base\.usda@", "@/usr/share/outside.usda@"),
    # unknown anomaly variant
    "unknown_variant": lambda t, rng: _sub(r'string variant = "blue"',
                                           f'string variant = "{rng.choice(["purple", "", "Blue", "x" * 40])}"')(t, rng),
    # absurd render settings
    "resolution": lambda t, rng: _sub(r"uniform int2 resolution = \(\d+, \d+\)",
                                      "uniform int2 resolution = ({}, {})".format(
                                          *rng.choice([(0, 36), (-64, 36), (100000, 36), (64, 2 ** 31 - 1)])))(t, rng),
    "samples": lambda t, rng: _sub(r"int allo:render:samples = \d+",
                                   f"int allo:render:samples = {rng.choice([0, -1, 10 ** 9])}")(t, rng),
    "bounces": lambda t, rng: _sub(r"int allo:render:maxBounces = \d+",
                                   f"int allo:render:maxBounces = {rng.choice([-1, 100000])}")(t, rng),
    "threads": _sub(r"int allo:render:threads = \d+", "int allo:render:threads = -4"),
    "adaptive": lambda t, rng: _sub(r"float allo:render:adaptiveThreshold = \S+",
                                    f"float allo:render:adaptiveThreshold = {rng.choice(['nan', '-1', '5'])}")(t, rng),
    "truncated": _truncate,
}
KINDS = sorted(INVALID) + ["garbage"] * 6


@pytest.fixture(scope="module")
def valid_layer(tiny_base, tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    return write_scene_layer(make_spec(anomaly=True), root / "layers" / "valid.usda", tiny_base)


def test_valid_layer_reads(valid_layer):
    assert isinstance(read_scene(valid_layer), SceneDescription)


def test_500_mutated_layers_give_clear_errors_fast(valid_layer):
    text = valid_layer.read_text()
    rng = np.random.default_rng(20300101)
    failures, t0 = [], time.perf_counter()
    for i in range(N_CASES):
        kind = KINDS[i % len(KINDS)]
        mutated = _garbage(text, rng) if kind == "garbage" else INVALID[kind](text, rng)
        path = valid_layer.parent / f"mut_{i:03d}.usda"
        path.write_bytes(mutated.encode("latin-1") if kind == "garbage" else mutated.encode())
        try:
            read_scene(path)
        except AlloError as exc:
            if not str(exc):
                failures.append((i, kind, "empty message"))
        except Exception as exc:  # noqa: BLE001 - the point is to catch everything else
            failures.append((i, kind, f"{type(exc).__name__}: {exc}"))
        else:
            if kind != "garbage":
                failures.append((i, kind, "accepted an invalid layer"))
        finally:
            path.unlink()
    seconds = time.perf_counter() - t0
    assert not failures, failures[:10]
    assert seconds < 30.0, f"{N_CASES} reads took {seconds:.1f} s"


@pytest.mark.render
def test_dispatch_batch_with_bad_layers(valid_layer, tiny_base, tmp_path):
    from allo_usd.dispatch import dispatch

    layers = tmp_path / "layers"
    good = [write_scene_layer(make_spec(seed=s, scene_id=f"good_{s}"), layers / f"good_{s}.usda", tiny_base)
            for s in (1, 2)]
    text = good[0].read_text()
    (layers / "bad_truncated.usda").write_text(text[: len(text) // 2])
    (layers / "bad_variant.usda").write_text(
        write_scene_layer(make_spec(anomaly=True, scene_id="bad_variant"), layers / "bad_variant.usda",
                          tiny_base).read_text().replace('string variant = "blue"', 'string variant = "purple"'))
    (layers / "bad_nan.usda").write_text(text.replace("(15, 8, 5)", "(nan, 8, 5)").replace("good_1", "bad_nan"))
    out = tmp_path / "out"
    summary = dispatch(layers, out, workers=2, progress=False)
    assert sorted(summary.rendered) == ["good_1", "good_2"]
    failed = {r["scene"]: r for r in map(json.loads, (out / "failed.jsonl").read_text().splitlines())}
    assert set(failed) == {"bad_truncated", "bad_variant", "bad_nan"}
    assert all(r["kind"] == "layer" and r["attempts"] == 1 for r in failed.values())
    assert "purple" in failed["bad_variant"]["reason"]
    assert (out / "good_1.png").is_file() and not (out / "bad_nan.png").exists()
