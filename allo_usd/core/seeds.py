"""Seeds: every random choice comes from one hash of the plan seed and the keys of what it decides."""

from __future__ import annotations

import hashlib


def key_path(*keys) -> str:
    """The keys joined by "/" (recorded with a scene as its seed path)."""
    return "/".join(str(k) for k in keys)


def key_hash(*keys) -> int:
    """The one seed hash: the first 8 bytes of SHA-256 of key_path(*keys), little-endian (64 bits)."""
    return int.from_bytes(hashlib.sha256(key_path(*keys).encode()).digest()[:8], "little")


def scene_seed(plan_seed: int, *keys) -> tuple[int, str]:
    """A stable 63-bit seed for one scene from the plan seed and the scene's keys, and its path."""
    return key_hash(plan_seed, *keys) >> 1, key_path(plan_seed, *keys)
