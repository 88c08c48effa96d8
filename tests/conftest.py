"""Shared fixtures: a tiny base stage built in a temp dir (fast). Helper functions live in
helpers.py."""

from __future__ import annotations

import pytest

from allo_usd.assets.bodies import build_bodies
from allo_usd.scene.spec import CameraPose
from allo_usd.usd.base_stage import write_base_stage
from allo_usd.core.geometry import look_at

from helpers import CAM_POS, tiny_anomalies, tiny_station


@pytest.fixture(scope="session")
def tiny_base(tmp_path_factory):
    root = tmp_path_factory.mktemp("stages")
    poses = [CameraPose(i, "train" if i <= 40 else "test", CAM_POS + [0, i * 0.1, 0],
                        look_at(CAM_POS + [0, i * 0.1, 0], [0, 0, 0])) for i in (1, 2, 41)]
    return write_base_stage(root, tiny_station(), build_bodies(), tiny_anomalies(), poses)


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
