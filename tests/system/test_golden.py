"""Golden layers: the demo plan's first scenes must author byte for byte as committed.

Compared: a normal scene, an anomalous scene, their pose layers and their day's sky layer
(tests/support/golden/; tests/support/goldens.py says how to regenerate them).
"""

from __future__ import annotations

import re

import pytest

from tests.support.goldens import FILES, GOLDEN, author_demo


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    out = tmp_path_factory.mktemp("golden") / "tree"
    author_demo(out)
    return out


@pytest.mark.parametrize("name", FILES)
def test_layer_matches_golden(tree, name):
    got, want = (tree / name).read_bytes(), (GOLDEN / name).read_bytes()
    assert got == want, f"{name} differs from tests/support/golden/{name}; if intended: python -m tests.support.goldens"


@pytest.mark.parametrize("name", FILES)
def test_golden_has_no_absolute_paths(name):
    text = (GOLDEN / name).read_text()
    assert not re.search(r"@/|@[A-Za-z]:[\\/]", text), f"{name} has an absolute asset path"
    assert "/tmp/" not in text and "/work/" not in text and "/home/" not in text, name
