"""The direct .usda writer (allo_usd.usd.usda_writer) gives Sdf's ExportToString byte for byte:
numbers (doubles, floats rounded to float32, ints, bools) over random bit patterns and edge values,
the vector and quaternion types, token arrays, strings, relationships, prim metadata,
customLayerData and documentation, random prim trees, and every layer authoring writes for the
demo plan. Anything it does not know must go through Sdf (the direct writer returns None), never be
written differently."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from allo_usd.usd import usda_writer
from allo_usd.usd.usda_writer import Prim, fast_layer_text, layer_text, sdf_layer_text

pxr = pytest.importorskip("pxr")
from pxr import Gf, Sdf, Vt  # noqa: E402

RNG = np.random.default_rng(2626)


def _random_doubles(n: int) -> list[float]:
    """Finite doubles from random bit patterns (every exponent), plus values around the notation
    switches (1e-6, 1e15) and edge values."""
    bits = RNG.integers(0, 2 ** 63, n, dtype=np.int64) * np.where(RNG.random(n) < 0.5, 1, -1)
    values = bits.view(np.float64)
    values = values[np.isfinite(values)].tolist()
    scales = [10.0 ** e for e in range(-9, 19)]
    values += [float(RNG.uniform(-10, 10) * s) for s in scales for _ in range(200)]
    values += [float(x) for x in RNG.normal(size=2000)] + [float(x) for x in RNG.integers(-10 ** 17, 10 ** 17, 500)]
    values += [0.0, -0.0, 1.0, -1.0, 0.1, 1e-300, -1e-300, 5e-324, 1e22, 1e308, 1.7976931348623157e308,
               1e-6, 9.99999e-7, 1e-7, 1e15, 999999999999999.9, 1e14, 123456789012345.6, 0.5, 2.0 ** 52, 2.0 ** 53,
               math.pi, 1412.6442770198673, 146837867081.347, 0.0000012718199637825665]
    return values


def _sdf_array(type_name, values) -> list[str]:
    """Sdf's text of each element of a [type] array (the writer formats elements one at a time)."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    spec = Sdf.CreatePrimInLayer(layer, "/P")
    Sdf.AttributeSpec(spec, "a", type_name).default = values
    line = [l for l in layer.ExportToString().split("\n") if " a = [" in l][0]
    return line.split(" a = [", 1)[1].rstrip("]").split(", ")


def test_doubles_are_written_as_sdf_writes_them():
    values = _random_doubles(30000)
    want = _sdf_array(Sdf.ValueTypeNames.DoubleArray, Vt.DoubleArray(values))
    got = [usda_writer._double(v) for v in values]
    bad = [(v, g, w) for v, g, w in zip(values, got, want) if g != w]
    assert not bad, bad[:10]


def test_floats_are_written_as_sdf_writes_them():
    values = [v for v in _random_doubles(30000) if abs(v) < 3.4e38]
    values += [float(np.float32(v)) for v in values[:5000]] + [1.4e-45, -1.4e-45, 3.3999e38, 1e-46]
    want = _sdf_array(Sdf.ValueTypeNames.FloatArray, Vt.FloatArray(values))
    got = [usda_writer._float(v) for v in values]
    bad = [(v, g, w) for v, g, w in zip(values, got, want) if g != w]
    assert not bad, bad[:10]


def _value(rng: random.Random, type_name: str):
    d = lambda: rng.choice(_DOUBLES)   # noqa: E731
    base = type_name.removeprefix("uniform ")
    return {"bool": lambda: rng.random() < 0.5,
            "int": lambda: rng.randint(-2 ** 31, 2 ** 31 - 1),
            "int64": lambda: rng.choice([rng.randint(-2 ** 63, 2 ** 63 - 1), rng.randint(-5, 5)]),
            "double": d,
            "float": lambda: rng.choice(_FLOATS),
            "string": lambda: rng.choice(_STRINGS),
            "token": lambda: rng.choice(_STRINGS),
            "double3": lambda: Gf.Vec3d(d(), d(), d()),
            "quatd": lambda: Gf.Quatd(d(), Gf.Vec3d(d(), d(), d())),
            "int2": lambda: Gf.Vec2i(rng.randint(-2 ** 31, 2 ** 31 - 1), rng.randint(0, 4096)),
            "float2": lambda: Gf.Vec2f(rng.choice(_FLOATS), rng.choice(_FLOATS)),
            "token[]": lambda: [rng.choice(_STRINGS) for _ in range(rng.randint(1, 4))]}[base]()


_DOUBLES = _random_doubles(2000)
_FLOATS = [v for v in _DOUBLES if abs(v) < 3e38]
_PLAIN = ["", "x", "allo-usd scene s2031_d000_p41", "2031/0/41/crew_bag/white", "a b  c", "#;(){}[]<>@=,.!?*&^%$~`|"]
_ODD = ["quote\"inside", "it's", "back\\slash", "new\nline", "tab\there", "uni\u00e9\u4e2d", "\u00e9", 'both "\' q',
        "x" * 5000, "'''", '"""', "\x7f", "\x01"]
_STRINGS = _PLAIN + _ODD
_VARIANTS = ["white", "yellow", "straight", "v_2", "A"]
_TYPES = ["bool", "int", "int64", "double", "float", "string", "token", "double3", "quatd", "float2", "int2",
          "uniform int2", "uniform token[]", "token[]", "uniform double"]
_NAMES = ["a", "A", "b", "B", "a9", "a10", "a_b", "a:b", "aZ", "az", "x", "xformOp:orient", "xformOp:translate",
          "allo:seed", "allo:seedPath", "allo:sceneId", "Z9z", "_u", "inputs:intensity", "allo:render:seed"]
_PRIMS = ["/World", "/World/Camera", "/World/Sky/SunLight", "/World/Sky/Sun", "/World/Anomaly", "/Render/Settings",
          "/Render/Products/Image", "/World/Station/a/b", "/A9", "/A10", "/a"]


def _random_layer(rng: random.Random, plain: bool):
    """(prims, sublayers, custom, doc) with random structure; `plain`: only what the direct writer knows."""
    strings = _PLAIN if plain else _STRINGS
    prims = []
    for path in rng.sample(_PRIMS, rng.randint(0, len(_PRIMS))):
        names = rng.sample(_NAMES, rng.randint(0, 8))
        attrs = {}
        for n in names[: len(names) // 2 + 1] if names else []:
            t = rng.choice(_TYPES)
            v = _value(rng, t)
            if t.removeprefix("uniform ") in ("string", "token"):
                v = rng.choice(strings)
            elif t.endswith("token[]"):
                v = [rng.choice(strings) for _ in v]
            attrs[n] = (t, v)
        rels = {n: rng.sample(_PRIMS, rng.randint(1, 3)) for n in names[len(names) // 2 + 1:]}
        prims.append(Prim(path, attrs, api=tuple(rng.sample(["AlloSceneAPI", "AlloAnomalyAPI", "X"], rng.randint(0, 2))),
                          define=rng.choice(["", "", "Xform", "Scope"]),
                          reference=rng.choice(["", "../../../stages/anomalies/crew_bag.usda", "a.usda"]),
                          variants={k: rng.choice(_VARIANTS if plain else strings) for k in rng.sample(["variant", "Variant", "v2", "shade"],
                                                                                 rng.randint(0, 2))},
                          active=rng.choice([None, True, False]), rels=rels))
    sublayers = rng.sample(["../../../poses/s2031/d000_p41.usda", "../../../sky/d000.usda", "./base.usda",
                            "x y.usda"], rng.randint(0, 3))
    custom = {k: rng.choice([rng.randint(-2 ** 63, 2 ** 63 - 1), rng.randint(-100, 100), rng.choice(strings),
                             2 ** 31, -2 ** 31, 2 ** 31 - 1, -2 ** 31 - 1])
              for k in rng.sample(["seed", "seedPath", "sceneId", "sampleId", "day", "epoch", "Z", "a"], rng.randint(0, 4))}
    return prims, sublayers, custom, rng.choice([s for s in strings if s] if plain else strings)


@pytest.mark.parametrize("seed", range(40))
def test_random_plain_layers_are_written_directly_as_sdf_writes_them(seed):
    rng = random.Random(seed)
    for _ in range(25):
        args = _random_layer(rng, plain=True)
        fast = fast_layer_text(*args)
        assert fast is not None, args        # the direct writer knows everything here
        assert fast == sdf_layer_text(*args)


@pytest.mark.parametrize("seed", range(20))
def test_any_layer_is_written_as_sdf_writes_it(seed):
    """With odd strings in (quotes, backslashes, newlines, unicode, very long), layer_text still gives
    Sdf's bytes: the direct writer either writes the same or hands the layer to Sdf."""
    rng = random.Random(1000 + seed)
    for _ in range(25):
        args = _random_layer(rng, plain=False)
        try:
            want = sdf_layer_text(*args)
        except Exception:                    # Sdf refuses it (e.g. a variant name): so must layer_text
            with pytest.raises(Exception):
                layer_text(*args)
            continue
        assert layer_text(*args) == want
        fast = fast_layer_text(*args)
        assert fast is None or fast == want


@pytest.mark.parametrize("value", [np.float64(1.5), np.float32(1.5), 1, True, float("inf"), float("nan"), 1e39])
def test_values_of_other_kinds_go_through_sdf(value):
    prims = [Prim("/World", {"x": ("float", value)})]
    assert fast_layer_text(prims, [], {}, "d") is None


def test_empty_relationships_duplicate_paths_and_odd_names_go_through_sdf():
    assert fast_layer_text([Prim("/World", rels={"r": []})], [], {}, "d") is None
    assert fast_layer_text([Prim("/World"), Prim("/World")], [], {}, "d") is None
    assert fast_layer_text([Prim("/World", {"a b": ("int", 1)})], [], {}, "d") is None
    assert fast_layer_text([Prim("/World", rels={"r": ["/World/a b"]})], [], {}, "d") is None
    assert fast_layer_text([], ["a@b.usda"], {}, "d") is None
    assert fast_layer_text([], [], {"n": 2 ** 63}, "d") is None


@pytest.mark.slow
def test_every_layer_authoring_writes_is_written_directly(tmp_path, monkeypatch):
    """The demo plan's first scenes (normal and anomalous: scene, pose and sky layers): each layer's
    text is Sdf's, and none needed the Sdf fallback."""
    from allo_usd.plan.model import demo_plan
    from allo_usd.run.author import author

    calls = []
    real = usda_writer.layer_text

    def recording(prims, sublayers, custom, doc):
        calls.append((prims, sublayers, custom, doc))
        return real(prims, sublayers, custom, doc)

    monkeypatch.setattr(usda_writer, "layer_text", recording)
    author(demo_plan(), tmp_path / "tree", limit=9, progress=False, workers=1)
    assert len(calls) >= 9
    kinds = {doc.split()[1] for *_, doc in calls}
    assert {"scene", "camera", "sky"} <= kinds
    for args in calls:
        fast = fast_layer_text(*args)
        assert fast is not None, args[3]
        assert fast == sdf_layer_text(*args), args[3]


def test_double_repr_range_is_the_digit_layout_and_sdfs():
    """_double's repr route (1e-4 <= |x| < 1e15) writes what the digit layout it skips writes, and
    what Sdf writes, at the range's edges, whole numbers and random values of every magnitude; and
    _float's memo gives each value's own text (not a zero's sign for another zero)."""
    S = usda_writer

    def layout(x: float) -> str:
        """The digit layout (_digits, _shortest) for every finite double: the reference the repr
        route must equal."""
        if x == 0.0:
            return "-0" if str(x)[0] == "-" else "0"
        mantissa, _, e = repr(abs(x)).partition("e")
        digits, exp = S._digits(mantissa, int(e) if e else 0)
        return ("-" if x < 0 else "") + S._shortest(digits, exp)

    rng = np.random.default_rng(30)
    edges = [1e-4, np.nextafter(1e-4, 0), 1e15, np.nextafter(1e15, 0), 1e14, 123.0, -123.0, 0.5, 2.0 ** 53 + 2,
             100000000000000.5, 5e-324, -0.0, 0.0]
    values = [float(v) for v in [*edges, *(rng.normal(size=20000) * 10.0 ** rng.integers(-8, 18, 20000)),
                                 *range(-300, 300)]]
    assert [S._double(v) for v in values] == [layout(v) for v in values]
    layer = Sdf.Layer.CreateAnonymous(".usda")
    spec = Sdf.CreatePrimInLayer(layer, "/P")
    sample = values[:400]
    for i, v in enumerate(sample):
        Sdf.AttributeSpec(spec, f"a{i}", Sdf.ValueTypeNames.Double).default = v
    written = {}
    for line in layer.ExportToString().splitlines():
        if line.strip().startswith("double a"):
            name, _, text = line.strip()[len("double "):].partition(" = ")
            written[int(name[1:])] = text
    assert [written[i] for i in range(len(sample))] == [S._double(v) for v in sample]
    for v in (0.1, -0.1, 0.0, -0.0, 1e-50, -1e-50, 0.1):
        assert S._float(v) == S._float_text(v)
    assert (S._float(0.0), S._float(-0.0)) == ("0", "-0")
