"""A Ctrl-C while a library loads lazily, mid-command, is held until the import is complete and then
raised as a KeyboardInterrupt (exit 130 at the command line), never lost or turned into another
error: embreex's Cython modules take numpy's C API as they load (a KeyboardInterrupt there came out
as "ImportError: numpy.core.multiarray failed to import", seen in a CI run of test_sigint),
skyfield's iokit tries urllib under a bare `except:` (it came out as "No module named 'urlparse'"),
OpenEXR and scipy.ndimage are C extensions that take numpy, and distributed is a large import with
optional modules. Each case sends SIGINT to a fresh process the moment the import machinery starts
looking for the library, then checks that the interrupt was raised after the library was fully in."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

HOOK = """
import importlib.abc, os, signal, sys
TRIGGER = {trigger!r}
class Hook(importlib.abc.MetaPathFinder):
    fired = False
    def find_spec(self, name, path, target=None):
        if name == TRIGGER and not Hook.fired:
            Hook.fired = True
            os.kill(os.getpid(), signal.SIGINT)   # Python raises it at its next instruction: inside the import
        return None
sys.meta_path.insert(0, Hook())
assert TRIGGER not in sys.modules
try:
{call}
    print("finished")
except KeyboardInterrupt:
    print("interrupted", Hook.fired, all(m in sys.modules for m in {loaded!r}))
"""

CASES = {
    "embreex": ("embreex.rtcore_scene", ["embreex.rtcore_scene", "embreex.mesh_construction"],
                "    import numpy as np\n    from allo_usd.scene.raycast import RayScene\n"
                "    RayScene([(np.eye(3), np.array([[0, 1, 2]]), 1)])"),
    "skyfield": ("skyfield.iokit", ["skyfield.api", "skyfield.iokit"],
                 "    from allo_usd.sky.ephemeris import load_de421\n    load_de421()"),
    "OpenEXR": ("OpenEXR", ["OpenEXR"], "    from allo_usd.output.annotation_files import read_depth_exr\n"
                "    read_depth_exr('missing.exr')"),
    "scipy.ndimage": ("scipy.ndimage", ["scipy.ndimage"],
                      "    import numpy as np\n    from allo_usd.output.contact import outlined\n"
                      "    mask = np.zeros((8, 8), bool)\n    mask[3:5, 3:5] = True\n"
                      "    outlined(np.zeros((8, 8, 3), np.uint8), mask, (8, 8))"),
    "distributed": ("distributed", ["distributed", "distributed.comm.registry"],
                    "    from allo_usd.run.scheduler import scheduler_problem\n    scheduler_problem('tcp://h:8786')"),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.process
def test_a_ctrl_c_while_a_library_loads_is_raised_once_it_is_loaded(case):
    trigger, loaded, call = CASES[case]
    script = HOOK.format(trigger=trigger, loaded=loaded, call=call)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "interrupted True True", (done.stdout, done.stderr[-3000:])


CONVERTED = """
import importlib.abc, os, signal, sys
sys.argv = ["allo-usd", "author", "plan.toml", "--out", "out", "--no-progress"]


def _tick():
    pass


class Hook(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == {trigger!r}:
            sys.meta_path.remove(self)
            try:
                os.kill(os.getpid(), signal.SIGINT)
                _tick()                                   # Python runs its handler here: a KeyboardInterrupt
            except KeyboardInterrupt:                     # what a Cython module's import_array makes of it
                raise ImportError("numpy.core.multiarray failed to import")
        return None


from allo_usd.cli import console   # the command line's own imports (no numpy yet)
assert "numpy" not in sys.modules
sys.meta_path.insert(0, Hook())
console()
"""


@pytest.mark.process
def test_a_ctrl_c_a_library_turned_into_another_error_still_ends_the_command_with_130(tmp_path):
    """The safety net behind the held imports: numpy's own import (the author command's first) is made
    to turn a Ctrl-C into the ImportError a C extension makes of it; the command ends with the one
    line and exit 130 (before: a traceback and exit 1)."""
    done = subprocess.run([sys.executable, "-c", CONVERTED.format(trigger="numpy.random")], cwd=tmp_path,
                          env={**__import__("os").environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 130, done.stderr[-3000:]
    assert done.stderr.strip().splitlines()[-1].startswith("interrupted (Ctrl-C)"), done.stderr[-3000:]
    assert "Traceback" not in done.stderr and "ImportError" not in done.stderr
