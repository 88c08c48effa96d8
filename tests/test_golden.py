"""Golden layers: the demo plan's first scenes must author byte for byte as committed.

Authoring is meant to be deterministic (same plan and seed, same bytes), so any change to the
layer text shows up here. Compared: a normal scene, an anomalous scene, their pose layers and
their day's sky layer (tests/golden/, paths relative to the output tree).

After an intended change to the layer text, regenerate with: python tests/test_golden.py
(and review the diff of tests/golden/ before committing it).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

GOLDEN = Path(__file__).parent / "golden"
LIMIT = 7  # the demo plan's 6 normal scenes, then its first anomalous one
FILES = (
    "sky/d000.usda",
    "poses/s2030/d000_p01.usda",
    "poses/s2030/d000_p41_power_drill-yellow.usda",
    "scenes/train/normal/s2030_d000_p01.usda",
    "scenes/test/anomaly/s2030_d000_p41_power_drill-yellow_z0.usda",
)


def author_demo(out_dir: Path) -> None:
    from allo_usd.plan.model import demo_plan
    from allo_usd.run.author import author

    author(demo_plan(), out_dir, limit=LIMIT, progress=False, workers=1)


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    out = tmp_path_factory.mktemp("golden") / "tree"
    author_demo(out)
    return out


@pytest.mark.parametrize("name", FILES)
def test_layer_matches_golden(tree, name):
    got, want = (tree / name).read_bytes(), (GOLDEN / name).read_bytes()
    assert got == want, f"{name} differs from tests/golden/{name}; if intended: python tests/test_golden.py"


@pytest.mark.parametrize("name", FILES)
def test_golden_has_no_absolute_paths(name):
    text = (GOLDEN / name).read_text()
    assert not re.search(r"@/|@[A-Za-z]:[\\/]", text), f"{name} has an absolute asset path"
    assert "/tmp/" not in text and "/work/" not in text and "/home/" not in text, name


def regenerate() -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "tree"
        author_demo(out)
        for name in FILES:
            dst = GOLDEN / name
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes((out / name).read_bytes())
            print(f"wrote {dst}")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    regenerate()
