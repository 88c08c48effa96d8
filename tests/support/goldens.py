"""The golden layers: the demo plan's first scenes, committed under tests/support/golden/ (paths
relative to the output tree) and compared byte for byte by tests/system/test_golden.py.

Authoring is meant to be deterministic (same plan and seed, same bytes), so any change to the
layer text shows up there. After an intended change to the layer text, regenerate with
`python -m tests.support.goldens` from the repository's root, and review the diff of
tests/support/golden/ before committing it.
"""

from __future__ import annotations

from pathlib import Path

GOLDEN = Path(__file__).resolve().parent / "golden"
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
    regenerate()
