"""The one file writer, the one directory writer, the one relative-path rule and the one seed hash."""

from __future__ import annotations

import errno
import hashlib
import os
import subprocess
import sys

import pytest

from allo_usd.core.errors import DiskFullError
from allo_usd.core.files import atomic_directory, atomic_path, relpath, temp_name_re, write_text_atomic
from allo_usd.core.seeds import key_hash, scene_seed


def test_atomic_path_renames_on_success_and_removes_on_failure(tmp_path):
    target = tmp_path / "a" / "out.png"
    with atomic_path(target) as tmp:
        assert temp_name_re(os.getpid()).match(tmp.name) and tmp.suffix == ".png"
        tmp.write_bytes(b"x")
    assert target.read_bytes() == b"x" and oct(target.stat().st_mode & 0o777) == "0o644"
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("killed")
    assert target.read_bytes() == b"x" and os.listdir(target.parent) == ["out.png"]


def test_a_full_disk_is_a_disk_full_error(tmp_path):
    with pytest.raises(DiskFullError), atomic_path(tmp_path / "f.json"):
        raise OSError(errno.ENOSPC, "No space left on device")
    assert os.listdir(tmp_path) == []


def test_write_text_atomic(tmp_path):
    p = write_text_atomic(tmp_path / "t.csv", "a,b\n", newline="")
    assert p.read_text() == "a,b\n" and os.listdir(tmp_path) == ["t.csv"]


def test_atomic_directory_replaces_whole_or_not_at_all(tmp_path):
    dest = tmp_path / "stages"
    with atomic_directory(dest) as tmp:
        assert temp_name_re(os.getpid()).match(tmp.name)
        (tmp / "base.usda").write_text("1")
    assert (dest / "base.usda").read_text() == "1"
    with pytest.raises(RuntimeError), atomic_directory(dest) as tmp:
        (tmp / "base.usda").write_text("2")
        raise RuntimeError("killed")
    assert (dest / "base.usda").read_text() == "1" and sorted(os.listdir(tmp_path)) == ["stages"]
    with atomic_directory(dest) as tmp:
        (tmp / "other").write_text("3")
    assert os.listdir(dest) == ["other"]


def test_atomic_directory_removes_dead_writers_leftovers_only(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    old = tmp_path / f".stages.{'ab' * 16}.tmp"                 # an earlier version's
    gone = tmp_path / f".stages.{dead_pid}.abcd1234"            # a killed writer's
    live = tmp_path / f".stages.{os.getppid()}.abcd1234"        # a running process's
    other = tmp_path / f".poses.{dead_pid}.abcd1234"            # another destination's
    for d in (old, gone, live, other):
        d.mkdir()
    with atomic_directory(tmp_path / "stages"):
        pass
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other.name, "stages"])


def test_relpath_rule(tmp_path):
    (tmp_path / "real" / "sky").mkdir(parents=True)
    (tmp_path / "link").symlink_to(tmp_path / "real")
    assert relpath(tmp_path / "real" / "sky" / "d000.usda", tmp_path / "real") == "./sky/d000.usda"
    assert relpath(tmp_path / "real" / "base.usda", tmp_path / "real" / "sky") == "../base.usda"
    # a resolved and an unresolved path of the same tree still relate
    assert relpath(tmp_path / "real" / "base.usda", tmp_path / "link" / "sky") == "../base.usda"


def test_one_seed_hash():
    old = int.from_bytes(hashlib.sha256(b"2031/a/3").digest()[:8], "little")
    assert key_hash(2031, "a", 3) == old
    assert scene_seed(2031, "a", 3) == (old >> 1, "2031/a/3")
