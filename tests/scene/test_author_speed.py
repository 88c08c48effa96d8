"""The shortcuts that keep authoring the paper plan fast give exactly the values of the code they
stand in for (issue 26): fixedmath's scalar path is the vectorised path bit for bit, its by-column
matmul is the broadcast sum bit for bit, and compose.TreeLinks is core.files.relpath, symlinks
and ".." included. tests/core/test_fixedmath.py checks fixedmath against the C library and a Python
transcription; tests/system/test_golden.py and tests/system/test_determinism.py check whole authored layers."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from allo_usd.core import fixedmath as fm
from allo_usd.core.errors import AlloError
from allo_usd.core.files import relpath
from allo_usd.usd.compose import TreeLinks

RNG = np.random.default_rng(26)
N = 6000


def _bits(a) -> list[int]:
    return np.asarray(a, dtype=np.float64).reshape(-1).view(np.int64).tolist()


def _edges(*values) -> np.ndarray:
    return np.array(values, dtype=np.float64)


ANGLES = np.concatenate([RNG.uniform(-7, 7, N), RNG.uniform(-8e5, 8e5, N), RNG.normal(0, 1e-8, N),
                         np.arange(-400, 401) * (math.pi / 4),   # where the reduction's later stages run
                         _edges(0.0, -0.0, 2.0 ** -27, -(2.0 ** -27), 2.0 ** -28, 5e-324, fm.REDUCTION_LIMIT * 0.999)])
UNIT = np.concatenate([RNG.uniform(-1, 1, N), 1 - RNG.uniform(0, 1e-9, N), -1 + RNG.uniform(0, 1e-9, N),
                       _edges(0.0, -0.0, 0.5, -0.5, 0.975, -0.975, 1.0, -1.0, 2.0 ** -27, 2.0 ** -58, 1e-300)])
POSITIVE = np.concatenate([np.exp(RNG.uniform(-700, 700, N)), RNG.uniform(0.6, 1.5, N),
                           _edges(1.0, 2.0, 0.5, 5e-324, 1e308, math.sqrt(0.5), 1 - 2.0 ** -53)])
REAL = np.concatenate([RNG.uniform(-3, 3, N), RNG.standard_cauchy(N) * 1e3,
                       _edges(0.0, -0.0, 0.4375, 0.6875, 1.1875, 2.4375, -2.4375, 1e300, -5e-324)])
ONE_ARG = {"sin": ANGLES, "cos": ANGLES, "tan": np.concatenate([ANGLES[:2 * N], np.arange(-40, 41) * (math.pi / 2)]),
           "arcsin": UNIT, "arccos": UNIT, "arctan": REAL, "log": POSITIVE, "log2": POSITIVE}


@pytest.mark.parametrize("name", sorted(ONE_ARG))
def test_a_scalar_gets_the_bits_of_the_vectorised_path(name):
    f, x = getattr(fm, name), ONE_ARG[name]
    vectorised = f(x)
    assert _bits([f(float(v)) for v in x]) == _bits(vectorised)   # Python floats
    assert _bits([f(v) for v in x]) == _bits(vectorised)          # numpy float64 scalars
    assert all(type(f(float(v))) is float for v in x[:50])


@pytest.mark.parametrize("name", ["arctan2", "hypot"])
def test_two_argument_scalars_get_the_bits_of_the_vectorised_path(name):
    f = getattr(fm, name)
    y = np.concatenate([RNG.normal(size=N), RNG.normal(size=N) * 1e-300, RNG.normal(size=N) * 1e300,
                        _edges(0.0, -0.0, 1.0, -1.0, 0.0, -0.0, 1e308, -1e308, 3.0)])
    x = np.concatenate([RNG.normal(size=N), RNG.normal(size=N), RNG.normal(size=N) * 1e-300,
                        _edges(1.0, 1.0, -1.0, -1.0, -1.0, -2.0, 1e-308, 1e-308, 4.0)])
    assert _bits([f(float(a), float(b)) for a, b in zip(y, x)]) == _bits(f(y, x))


def test_special_scalars_still_take_the_vectorised_path():
    """inf, nan, a zero divisor and out-of-range arguments are decided exactly as before."""
    for name in ("sin", "cos", "tan", "arctan", "arcsin", "arccos", "log", "log2"):
        f = getattr(fm, name)
        for v in (math.inf, -math.inf, math.nan, 1.5, -1.5, 0.0, -0.0, -2.0):
            got, want = f(v), f(np.array([v]))[0]
            assert _bits(got) == _bits(want) or (math.isnan(got) and math.isnan(want)), (name, v)
    for a, b in [(1.0, 0.0), (-1.0, -0.0), (0.0, 0.0), (1e308, 1e-308), (math.inf, 1.0), (1.0, math.nan)]:
        got, want = fm.arctan2(a, b), fm.arctan2(np.array([a]), np.array([b]))[0]
        assert _bits(got) == _bits(want) or (math.isnan(got) and math.isnan(want)), (a, b)
    with pytest.raises(AlloError, match="reduce the angle"):
        fm.cos(1e7)
    with pytest.raises(AlloError, match="reduce the angle"):
        fm.tan(-1e7)


def _broadcast_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = a[:, 0, None] * b[0, None, :]
    for i in range(1, a.shape[1]):
        out = out + a[:, i, None] * b[i, None, :]
    return out


@pytest.mark.parametrize("rows", [fm._ROWS_BY_COLUMN - 1, fm._ROWS_BY_COLUMN, 5000])
@pytest.mark.parametrize("inner, cols", [(3, 3), (3, 1), (1, 4), (4, 2)])
def test_matmul_by_column_is_the_broadcast_sum(rows, inner, cols):
    a, b = RNG.normal(size=(rows, inner)) * 1e3, RNG.normal(size=(inner, cols))
    a[0, 0], a[1, 0], b[0, 0] = -0.0, 1e-320, -0.0
    got = fm.matmul(a, b)
    assert got.shape == (rows, cols) and got.flags.c_contiguous
    assert _bits(got) == _bits(_broadcast_matmul(a, b))


def test_norm_of_a_small_vector_is_the_numpy_sum():
    for v in [RNG.normal(size=n) * s for n in (1, 3, 4, 16) for s in (1.0, 1e-200, 1e200)] + \
             [np.zeros(3), _edges(-0.0), _edges(np.inf, 1.0), RNG.normal(size=(3, 3))]:
        flat = v.reshape(-1)
        with np.errstate(over="ignore"):
            s = flat[0] * flat[0]
            for k in range(1, flat.size):
                s = s + flat[k] * flat[k]
        assert _bits(fm.norm(v)) == _bits(np.sqrt(s)) and type(fm.norm(v)) is float
    assert math.isnan(fm.norm(_edges(np.nan, 1.0)))
    assert fm.norm(np.ones(3), keepdims=True).shape == (1,)


def test_tree_links_are_relpath_through_symlinks_and_dot_dots(tmp_path, monkeypatch):
    real = tmp_path / "real"
    for d in ("scenes/test/anomaly", "poses/s2030", "sky", "stages/anomalies", "elsewhere"):
        (real / d).mkdir(parents=True)
    for f in ("poses/s2030/d000_p01.usda", "sky/d000.usda", "stages/base.usda", "elsewhere/target.usda"):
        (real / f).write_text("#usda 1.0\n")
    os.symlink(real, tmp_path / "tree")                                          # the whole tree linked
    os.symlink(real / "elsewhere" / "target.usda", real / "sky" / "d001.usda")  # a layer that is a link
    os.symlink(real / "elsewhere", real / "stages" / "anomalies" / "linked")    # a linked directory
    monkeypatch.chdir(tmp_path)
    links = TreeLinks()
    starts = [tmp_path / "tree" / "scenes" / "test" / "anomaly", real / "scenes" / "test" / "anomaly",
              "tree/scenes/test/anomaly", "tree/stages/anomalies/linked/.."]
    targets = [real / "poses/s2030/d000_p01.usda", tmp_path / "tree/sky/d000.usda", "tree/sky/d001.usda",
               "tree/stages/base.usda", "tree/stages/anomalies/linked/../base.usda", "tree/scenes/missing.usda",
               tmp_path / "tree/stages/anomalies/linked/target.usda"]
    for _ in range(2):   # a second time from the cache
        for start in starts:
            for target in targets:
                assert links.relpath(target, start) == relpath(target, start), (target, start)
