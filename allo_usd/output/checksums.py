"""File checksums, cached per process: a render's identity, its record's output checksums and the
dispatcher's resume check all hash the same files (a tree's shared sky, pose and base layers once
per resume check, not once per scene). The cache is keyed by (real path, mtime_ns, size, inode,
device), so a changed file is hashed again.
"""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

from allo_usd.core.files import sha256_file

_SHA256: dict[tuple, str] = {}
_SHA256_BOUND = 1 << 20  # entries (~200 B each); a paper plan's resume needs ~100,000


def file_sha256(path: str | Path, fresh: bool = False) -> str | None:
    """SHA-256 of a regular file, cached per process by (path, mtime_ns, size, inode, device); None
    for a missing or non-regular file (never opened: a FIFO or a device would block or never end).
    One os.stat per call (it follows symbolic links: a link pointed elsewhere changes the inode).
    `fresh` reads the bytes even when the cache holds this stat (`render --verify`: a file edited
    in place with its mtime put back keeps its stat, not its bytes)."""
    return hashed(path, fresh)[0]


def hashed(path: str | Path, fresh: bool = False) -> tuple[str | None, os.stat_result | None]:
    """file_sha256 and the os.stat it was keyed by (None, None for a missing or non-regular file),
    so that a manifest row records the stat of exactly the bytes it checksums."""
    path = os.path.abspath(path)
    try:
        st = os.stat(path)
    except OSError:
        return None, None
    if not stat.S_ISREG(st.st_mode):
        return None, None
    digest = None if fresh else _SHA256.get(_cache_key(path, st))
    if digest is None:
        try:
            digest = sha256_file(Path(path))
        except OSError:
            return None, None
        remember_digest(path, st, digest)
    return digest, st


def _cache_key(path: str, st: os.stat_result) -> tuple:
    return path, st.st_mtime_ns, st.st_size, st.st_ino, st.st_dev


def remember_digest(path: str | Path, st: os.stat_result, digest: str) -> None:
    """Enter `digest`, the checksum of the file at `path` as it was at `st`, into file_sha256's
    cache (bounded: cleared when full)."""
    if len(_SHA256) >= _SHA256_BOUND:
        _SHA256.clear()
    _SHA256[_cache_key(os.path.abspath(path), st)] = digest


def remember_sha256(path: str | Path, st: os.stat_result, data: bytes) -> None:
    """remember_digest of `data`, the whole of the file at `path` as read at `st`
    (core.files.read_whole_small): the dispatcher's scan reads each scene layer once, to sniff it
    and to checksum it for the resume check."""
    remember_digest(path, st, hashlib.sha256(data).hexdigest())
