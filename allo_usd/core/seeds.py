"""Seeds: every random choice of a scene comes from one hash of the plan seed and the scene's keys."""

from __future__ import annotations

import hashlib


def scene_seed(plan_seed: int, *keys) -> tuple[int, str]:
    """A stable 63-bit seed for one scene from the plan seed and the scene's keys, and its path."""
    path = "/".join(str(k) for k in (plan_seed, *keys))
    return int.from_bytes(hashlib.sha256(path.encode()).digest()[:8], "little") >> 1, path
