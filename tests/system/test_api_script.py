"""The public API from a user's own script: the README's Python API block
runs without an `if __name__ == "__main__":` guard (local render workers never import the caller's
`__main__`), and the in-process renders keep Blender's own output off the terminal, in a log file."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import allo_usd

README = Path(__file__).resolve().parents[2] / "docs" / "guide" / "api.md"
# Blender's own log lines ("00:02.023  render           | Saved: '...'"), and what the GPU probe prints
BLENDER_LINE = re.compile(r"^\d\d:\d\d\.\d{3}\s+\w+\s+\|", re.M)
BLENDER_WORDS = ("Saved:", "CUEW", "HIPEW")


def _tiny_plan(path: Path) -> Path:
    """The demo plan (16 scenes) at 64x36 px, 1 sample, no denoiser."""
    plan = allo_usd.demo_plan()
    quality = plan.quality.model_copy(update={"resolution": (64, 36), "samples": 1, "denoise": False})
    return allo_usd.save_plan(plan.model_copy(update={"quality": quality}), path)


def readme_api_block(guard: bool = False) -> str:
    """The README's Python API block; without its `if __name__ == "__main__":` guard unless `guard`."""
    text = README.read_text()
    start = text.index("```python\n", text.index("**Python API**")) + len("```python\n")
    code = text[start:text.index("```", start)]
    if guard:
        return code
    head, sep, body = code.partition('if __name__ == "__main__":\n')
    return head + textwrap.dedent(body) if sep else code


def _blender_output(text: str) -> list[str]:
    return BLENDER_LINE.findall(text) + [w for w in BLENDER_WORDS if w in text]


def test_readme_block_runs_as_an_unguarded_script(tmp_path):
    _tiny_plan(tmp_path / "plan.toml")
    code = readme_api_block()
    assert "__main__" not in code and "workers=2" in code
    script = tmp_path / "script.py"
    script.write_text(code + 'print("SUMMARY", summary)\n')
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    out = tmp_path / "out" / "renders"
    failed = out / "failed.jsonl"
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert not (failed.is_file() and failed.read_text().strip()), failed.read_text()[:3000]
    tree = [p for p in (tmp_path / "out" / "tree" / "scenes").rglob("*.usda")]
    assert len(tree) == 16
    done = [p.stem for p in out.glob("*.json")]
    assert sorted(done) == sorted(p.stem for p in tree)
    counts = re.search(r"SUMMARY (\d+) rendered, (\d+) skipped \(already done\), (\d+) failed", proc.stdout)
    assert counts and int(counts[1]) + int(counts[2]) == 16 and counts[3] == "0", proc.stdout[-3000:]
    assert (tmp_path / "out" / "dataset").is_dir()
    # the script ran once: the workers never imported it (they would have authored and rendered again)
    assert json.loads((out / f"{tree[0].stem}.json").read_text())["files"]
    assert not _blender_output(proc.stdout + proc.stderr), (proc.stdout + proc.stderr)[-3000:]


RENDER_IN_PROCESS = """
import sys
import allo_usd
layer, out = sys.argv[1:3]
meta = allo_usd.render_layer(layer, out)
result = allo_usd.render_scene(allo_usd.read_scene(layer))
print("DONE", meta["resolution"], result.rgb.shape, flush=True)
"""


def test_in_process_renders_keep_blender_off_the_terminal(tmp_path):
    plan = allo_usd.load_plan(_tiny_plan(tmp_path / "plan.toml"))
    layer = allo_usd.author_plan(plan, tmp_path / "tree", limit=1, progress=False).paths[0]
    out, tmp = tmp_path / "renders", tmp_path / "tmp"
    tmp.mkdir()
    proc = subprocess.run([sys.executable, "-c", RENDER_IN_PROCESS, str(layer), str(out)], capture_output=True,
                          text=True, timeout=600, env={**os.environ, "TMPDIR": str(tmp)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "DONE [64, 36] (36, 64, 3)" in proc.stdout
    assert not _blender_output(proc.stdout), proc.stdout
    assert not _blender_output(proc.stderr), proc.stderr
    log = (out / "logs" / "render.log").read_text()
    assert "Saved:" in log and BLENDER_LINE.search(log), log
    scene_log = tmp / f"allo-usd-{os.getuid()}" / "render.log"  # render_scene's default: no output directory
    assert "Saved:" in scene_log.read_text()
    if "Cycles finds no GPU" in log:  # the notice is ours: shown once on the terminal as well
        assert proc.stderr.count("note: --device auto") == 1, proc.stderr


def test_a_hook_from_main_is_refused_in_one_line():
    from allo_usd.run.worker import check_hook

    def hook(scene):
        pass

    hook.__module__ = "__main__"
    with pytest.raises(allo_usd.AlloError, match="defined in __main__.*move it into a module"):
        check_hook(hook)
    import functools

    from tests.support import hooks  # tests/support/hooks.py: importable by reference, accepted

    check_hook(functools.partial(hooks.crash_on, {"s1"}))
    check_hook(None)


@pytest.mark.slow
def test_author_plan_with_a_process_pool_from_an_unguarded_script(tmp_path):
    """`author_plan(..., workers=2)` starts a spawn pool; its workers must not run the caller's
    unguarded script again (each would author again, recursively, and the pool would break)."""
    script = tmp_path / "author_it.py"
    script.write_text(textwrap.dedent("""
        import sys
        from pathlib import Path
        import allo_usd
        print("script body ran", flush=True)
        out = Path(sys.argv[1])
        allo_usd.author_plan(allo_usd.demo_plan(), out, limit=7, progress=False, workers=2)
        print("authored", len(list((out / "scenes").rglob("*.usda"))))
    """))
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "tree")], capture_output=True, text=True,
                       cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert r.stdout.count("script body ran") == 1 and "authored 7" in r.stdout
    import __main__
    assert hasattr(__main__, "__file__") or hasattr(__main__, "__spec__")   # nothing left hidden here
