"""Fuzz the reader: 500 mutated scene layers each give a clear AlloError (or a valid scene).

Every mutation except random garbage is invalid by construction and must be rejected with an
`AlloError` that names the problem and the fix; garbage bytes may land somewhere harmless (a
comment, a string), so those may also read successfully, but never raise anything else. A share
of the same layers then goes through the dispatcher beside good ones: good layers render intact,
every bad one is recorded in failed.jsonl with the reader's own message.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from PIL import Image

from allo_usd.usd.scene_layer import write_scene_layer
from allo_usd.usd.description import SceneDescription
from allo_usd.core.errors import AlloError
from allo_usd.usd.read import read_scene

from tests.support.helpers import make_spec

N_CASES = 500


def _sub(pattern: str, repl: str):
    def mutate(text: str, rng) -> str:
        out, n = re.subn(pattern, repl, text, count=1)
        assert n == 1, pattern
        return out
    return mutate


def _sub_nth(pattern: str, repl: str):
    """Replace one of the pattern's occurrences, chosen at random."""
    def mutate(text: str, rng) -> str:
        hits = list(re.finditer(pattern, text))
        assert hits, pattern
        m = hits[int(rng.integers(len(hits)))]
        return text[:m.start()] + repl + text[m.end():]
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
FAR_CAMERAS = ["(1e300, 8, 5)", "(15, 2e4, 5)", "(0, 0, -1e13)"]  # beyond 10 km (or 1e12 m) of the station
INVALID = {
    # wrong attribute types
    "samples_type": _sub(r"int allo:render:samples = \d+", 'string allo:render:samples = "many"'),
    "resolution_type": _sub(r"uniform int2 resolution = \(\d+, \d+\)", 'uniform string resolution = "big"'),
    "intensity_type": _sub(r"float inputs:intensity = \S+", 'string inputs:intensity = "bright"'),
    "translate_type": _sub(r"double3 xformOp:translate = \(15, 8, 5\)", 'string xformOp:translate = "here"'),
    "exposure_type": _sub(r"float exposure = \S+", "bool exposure = 1"),
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
    "exposure_nan": lambda t, rng: _sub(r"float exposure = \S+",
                                        f"float exposure = {rng.choice(BAD_NUMBERS + ['1e3', '-1e3'])}")(t, rng),
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
    # values that are finite and well typed but absurd (USD itself would accept them silently)
    "orient_zero": _sub_nth(r"quatd xformOp:orient = \([^)]*\)", "quatd xformOp:orient = (0, 0, 0, 0)"),
    "camera_far": lambda t, rng: _sub(r"double3 xformOp:translate = \(15, 8, 5\)",
                                      f"double3 xformOp:translate = {rng.choice(FAR_CAMERAS)}")(t, rng),
    "body_far": lambda t, rng: _sub(r"double3 xformOp:translate = \(0, 0, -7000000\)",
                                    f"double3 xformOp:translate = (0, 0, {rng.choice(['-2e12', '1e300'])})")(t, rng),
    "resolution_huge": lambda t, rng: _sub(r"uniform int2 resolution = \(\d+, \d+\)",
                                           "uniform int2 resolution = ({}, {})".format(
                                               *rng.choice([(16384, 16384), (8193, 36), (8192, 8192)])))(t, rng),
}
KINDS = sorted(INVALID) + ["garbage"] * 6
NAMES = {"orient_zero": "xformOp:orient = (0, 0, 0, 0)", "camera_far": "/World/Camera is at (",
         "body_far": "/World/Sky/Moon is at (", "resolution_huge": ".resolution = ("}  # what the message names
REMEDY = re.compile(r"fix|restore|re-author|regenerate|choose|move|rename")  # ... and how to put it right


def mutated_layers(text: str):
    """(index, kind, bytes) of the N_CASES mutations of a valid layer's text, in a seeded order."""
    rng = np.random.default_rng(20300101)
    for i in range(N_CASES):
        kind = KINDS[i % len(KINDS)]
        if kind == "garbage":
            yield i, kind, _garbage(text, rng).encode("latin-1")
        else:
            yield i, kind, INVALID[kind](text, rng).encode()


@pytest.fixture(scope="module")
def valid_layer(tiny_base, tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    return write_scene_layer(make_spec(anomaly=True), root / "layers" / "valid.usda", tiny_base)


def test_valid_layer_reads(valid_layer):
    assert isinstance(read_scene(valid_layer), SceneDescription)


@pytest.mark.slow
def test_500_mutated_layers_give_clear_errors(valid_layer):
    text = valid_layer.read_text()
    failures = []
    for i, kind, data in mutated_layers(text):
        path = valid_layer.parent / f"mut_{i:03d}.usda"
        path.write_bytes(data)
        try:
            read_scene(path)
        except AlloError as exc:
            message = str(exc)
            if not REMEDY.search(message):
                failures.append((i, kind, f"no fix named: {message}"))
            if kind in NAMES and NAMES[kind] not in message:
                failures.append((i, kind, f"does not name {NAMES[kind]!r}: {message}"))
        except Exception as exc:  # noqa: BLE001 - the point is to catch everything else
            failures.append((i, kind, f"{type(exc).__name__}: {exc}"))
        else:
            if kind != "garbage":
                failures.append((i, kind, "accepted an invalid layer"))
        finally:
            path.unlink()
    assert not failures, failures[:10]


@pytest.mark.render
def test_dispatch_a_share_of_the_fuzzed_layers(valid_layer, tiny_base, tmp_path):
    """Every 9th of the first 450 fuzzed layers (50, every kind of mutation) goes through the local
    pool beside good layers: the good ones render and verify, every bad one is in failed.jsonl
    (once, not retried) with the message the reader gives in this process; the parent lives on."""
    from allo_usd.run.dispatch import FAILED, dispatch
    from allo_usd.run.render_index import is_done, load_manifest

    batch = valid_layer.parent.parent / "batch"  # beside layers/: relative sublayer paths still resolve
    batch.mkdir(exist_ok=True)
    layers = [write_scene_layer(make_spec(seed=s, scene_id=f"good_{s}", samples=2, anomaly=s == 2),
                                batch / f"good_{s}.usda", tiny_base) for s in (1, 2, 3)]
    for i, kind, data in mutated_layers(valid_layer.read_text()):
        if i % 9 == 0 and i < 450:  # 9 is prime to len(KINDS): all kinds come up
            layers.append(batch / f"mut_{i:03d}_{kind}.usda")
            layers[-1].write_bytes(data)
    assert len(layers) == 3 + 50 and {p.stem.split("_", 2)[2] for p in layers[3:]} >= set(INVALID)
    expected = {}
    for p in layers:
        try:
            read_scene(p)
            expected[p.stem] = None
        except AlloError as exc:
            expected[p.stem] = f"{type(exc).__name__}: {exc}"
    good = sorted(s for s, e in expected.items() if e is None)
    assert {"good_1", "good_2", "good_3"} <= set(good) and len(good) < 10

    out = tmp_path / "out"
    summary = dispatch(layers, out, workers=2, progress=False)
    assert sorted(summary.rendered) == good
    failed = {r["scene"]: r for r in map(json.loads, (out / FAILED).read_text().splitlines())}
    assert set(failed) == {s for s, e in expected.items() if e is not None}
    for scene, row in failed.items():
        assert (row["kind"], row["attempts"], row["reason"]) == ("layer", 1, expected[scene]), scene
        assert not list(out.glob(f"{scene}*"))
    variants = [r["reason"] for s, r in failed.items() if s.endswith("unknown_variant")]
    assert variants and all("is not one of ['blue', 'red']" in r for r in variants)
    done = load_manifest(out)
    for p in layers:
        if p.stem in good:
            assert is_done(p, out, done)
            rgb = np.asarray(Image.open(out / f"{p.stem}.png"))
            assert rgb.shape == (36, 64, 3) and rgb.max() > 0
    assert (np.asarray(Image.open(out / "good_2_mask.png")) == 2).any()  # its anomaly is in the mask
