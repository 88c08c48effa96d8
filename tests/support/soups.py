"""Triangle soups for the ray-casting and placement tests: random blobs with degenerate triangles,
and the tiny station as one RayScene. Each draws from its own seeded generator, so a test gets the
same scene whatever ran before it."""

from __future__ import annotations

import numpy as np

from allo_usd.scene import raycast
from allo_usd.scene.raycast import RayScene

from tests.support.helpers import tiny_station


def blob(n_tris: int = 400, seed: int = 0, centre=(0.0, 0.0, 0.0), spread=(0.2, 2.0)) -> RayScene:
    """A random triangle soup around `centre` (one owner, id 2), scaled by a factor drawn from
    `spread`; its first ten triangles have zero area (no normal)."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n_tris * 3, 3)) * rng.uniform(*spread) + np.asarray(centre)
    pts[:30] = pts[0]
    return RayScene([(pts, np.arange(len(pts)).reshape(-1, 3), 2)])


def station_scene() -> RayScene:
    """The tiny station's triangles, owner id 1."""
    pts, tris = tiny_station().triangle_soup()
    return RayScene([(pts, tris, 1)])


def numpy_path(monkeypatch, fn):
    """`fn()` with raycast's few-ray path switched off (fans made inside `fn` carry no rows): the
    reference the Python-float path for up to `_FEW` rays must equal bit for bit."""
    with monkeypatch.context() as m:
        m.setattr(raycast, "_FEW", 0)
        return fn()
