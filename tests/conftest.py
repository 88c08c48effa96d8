"""Shared fixtures (a tiny base stage built in a temp dir, two tiny renders of it) and the unit tier.

Helper functions live in tests/support/helpers.py. `pytest --unit` (`make test-unit`) runs the
unit tier: every test outside tests/system/ that is not marked `render`, `slow`, `process` or `bpy`, and
it fails any test of that tier that starts a process or imports bpy, so that the tier stays the
inner loop that answers in about a minute. `make test` runs everything."""

from __future__ import annotations

import contextlib
import multiprocessing.process
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from allo_usd.assets.bodies import build_bodies
from allo_usd.scene.spec import CameraPose
from allo_usd.usd.base_stage import write_base_stage
from allo_usd.core.geometry import look_at

from tests.support.helpers import CAM_POS, tiny_anomalies, tiny_station

# A runner started in the background by a non-interactive shell (`cmd &`, `nohup cmd &`) inherits
# SIGINT ignored, and so would every process the tests start: the Ctrl-C tests would then wait for
# a stop that never comes. The tests send real SIGINTs, so they run with Python's own handler.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def tiny_base(tmp_path_factory):
    root = tmp_path_factory.mktemp("stages")
    poses = [CameraPose(i, "train" if i <= 40 else "test", CAM_POS + [0, i * 0.1, 0],
                        look_at(CAM_POS + [0, i * 0.1, 0], [0, 0, 0])) for i in (1, 2, 41)]
    return write_base_stage(root, tiny_station(), build_bodies(), tiny_anomalies(), poses)


@pytest.fixture(scope="session")
def rendered(tiny_base, tmp_path_factory):
    """A normal and an anomalous scene over the tiny base stage, rendered once for every test that
    reads them (test_render, test_camera_record): {"normal"|"anomaly": (layer, meta, render dir)}."""
    from allo_usd.run.job import render_layer
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    root = tmp_path_factory.mktemp("render")
    out = {}
    for name, anomaly in (("normal", False), ("anomaly", True)):
        layer = write_scene_layer(make_spec(anomaly=anomaly), root / "layers" / f"{name}.usda", tiny_base)
        out[name] = (layer, render_layer(layer, root / "renders"), root / "renders")
    return out


@pytest.fixture(scope="session", autouse=True)
def _allow_test_asset_roots(tmp_path_factory):
    """Test layers live in pytest's temp dirs, over a tiny base stage in another temp dir: allow
    that tree as an asset root (allo_usd.usd.safety), for this process and the workers it spawns."""
    import os

    from allo_usd.usd.safety import ENV_ROOTS

    old = os.environ.get(ENV_ROOTS)
    os.environ[ENV_ROOTS] = str(tmp_path_factory.getbasetemp())
    yield
    if old is None:
        os.environ.pop(ENV_ROOTS, None)
    else:
        os.environ[ENV_ROOTS] = old


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 1 MiB tmpfs (a real file system that fills up); skipped where mounting is not permitted.
    Always unmounted, lazily if a process still holds it."""
    mnt = tmp_path / "tmpfs"
    mnt.mkdir()
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m,mode=0755", "tmpfs", str(mnt)],
                           capture_output=True, text=True)
    except FileNotFoundError:
        pytest.skip("no `mount` command here: cannot make a small tmpfs to fill")
    if r.returncode != 0:
        pytest.skip(f"mounting a tmpfs is not permitted here (needs root or CAP_SYS_ADMIN): {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        if subprocess.run(["umount", str(mnt)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


# ---------------------------------------------------------------- the unit tier

TESTS = Path(__file__).resolve().parent
UNIT_EXCLUDED_MARKS = ("render", "slow", "process", "bpy")


def pytest_addoption(parser):
    parser.addoption("--unit", action="store_true", default=False,
                     help="the unit tier: no tests/system/, nothing marked render, slow, process or bpy; a test of "
                          "the tier that starts a process or imports bpy fails")


def in_unit_tier(item) -> bool:
    return (TESTS / "system") not in Path(str(item.fspath)).parents and \
        not any(item.get_closest_marker(m) for m in UNIT_EXCLUDED_MARKS)


def pytest_collection_modifyitems(config, items):
    if not config.getoption("--unit"):
        return
    keep = [i for i in items if in_unit_tier(i)]
    config.hook.pytest_deselected(items=[i for i in items if not in_unit_tier(i)])
    items[:] = keep


class _UnitTierBreach(BaseException):
    """Raised (not an Exception, so that no `except Exception` in the code under test swallows it)
    where a unit-tier test starts a process or imports bpy."""


def _refuse(what: str):
    def refuse(*args, **kwargs):
        raise _UnitTierBreach(f"a unit-tier test {what}: mark it @pytest.mark.process (or bpy, or render if it "
                              f"renders) so that `make test-unit` leaves it to `make test`")
    return refuse


class _NoBpy:
    """A meta-path finder that refuses to import bpy (loading Blender costs seconds)."""

    def find_spec(self, name, path=None, target=None):
        if name == "bpy" or name.startswith("bpy."):
            _refuse("imports bpy")()
        return None


@contextlib.contextmanager
def _unit_tier_guard():
    """No process and no bpy while a unit-tier test sets up its fixtures (a session fixture first
    used by it included) and runs."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(subprocess.Popen, "__init__", _refuse("starts a process (subprocess)"))
        patch.setattr(multiprocessing.process.BaseProcess, "start", _refuse("starts a process (multiprocessing)"))
        finder = _NoBpy()
        sys.meta_path.insert(0, finder)
        try:
            yield
        finally:
            sys.meta_path.remove(finder)


def _guarded(item):
    return _unit_tier_guard() if item.config.getoption("--unit") else contextlib.nullcontext()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    with _guarded(item):
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    with _guarded(item):
        yield
