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


@pytest.mark.process
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


def test_write_bytes_atomic_links_an_unnamed_file_and_replaces_an_existing_one(tmp_path):
    from allo_usd.core import files

    target = tmp_path / "deep" / "layer.usda"
    files.write_bytes_atomic(target, b"first")
    assert target.read_bytes() == b"first" and oct(target.stat().st_mode & 0o777) == "0o644"
    files.write_bytes_atomic(target, b"second", mode=0o600)
    assert target.read_bytes() == b"second" and oct(target.stat().st_mode & 0o777) == "0o600"
    assert os.listdir(target.parent) == ["layer.usda"]                   # no temporary left either way
    if files._unnamed["ok"]:                                              # Linux with O_TMPFILE here: no name was made
        made = []
        real_open = os.open

        def spy(p, flags, *a, **k):
            made.append(flags & os.O_CREAT)
            return real_open(p, flags, *a, **k)

        os.open = spy
        try:
            files.write_bytes_atomic(tmp_path / "deep" / "other.usda", b"3")
        finally:
            os.open = real_open
        assert made == [0]


@pytest.mark.parametrize("refusal", [errno.EOPNOTSUPP, errno.EISDIR, errno.ENOSYS])
def test_write_bytes_atomic_falls_back_to_a_named_temporary(tmp_path, monkeypatch, refusal):
    """Without unnamed files in a folder (the file system refuses O_TMPFILE: EOPNOTSUPP; a kernel that
    predates it reads the flag as O_DIRECTORY: EISDIR; a FUSE or emulation layer: ENOSYS), across
    mounts, or without /proc to link one, the named temporary and rename of atomic_path write the
    file, whole."""
    from allo_usd.core import files

    monkeypatch.setattr(files, "_unnamed", {"ok": True, "root": None, "folders": set()})
    real_open = os.open

    def no_tmpfile(p, flags, *a, **k):
        if flags & getattr(os, "O_TMPFILE", 0) == getattr(os, "O_TMPFILE", -1):
            raise OSError(refusal, os.strerror(refusal), p)
        return real_open(p, flags, *a, **k)

    monkeypatch.setattr(os, "open", no_tmpfile)
    files.write_bytes_atomic(tmp_path / "a.usda", b"named")
    assert (tmp_path / "a.usda").read_bytes() == b"named" and os.listdir(tmp_path) == ["a.usda"]
    assert str(tmp_path) in files._unnamed["folders"]                   # not asked again for this folder
    monkeypatch.setattr(os, "open", real_open)
    if not hasattr(os, "O_TMPFILE"):
        return
    real_link = os.link

    def no_proc(src, dst, **k):
        if str(src).startswith("/proc/self/fd/"):
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", src)
        return real_link(src, dst, **k)

    def other_mount(src, dst, **k):
        raise OSError(errno.EXDEV, "Invalid cross-device link", src)

    monkeypatch.setattr(os, "link", other_mount)
    files.write_bytes_atomic(tmp_path / "mnt" / "c.usda", b"other mount")
    assert (tmp_path / "mnt" / "c.usda").read_bytes() == b"other mount" and os.listdir(tmp_path / "mnt") == ["c.usda"]
    assert str(tmp_path / "mnt") in files._unnamed["folders"] and files._unnamed["ok"] is True
    monkeypatch.setattr(os, "link", no_proc)
    files.write_bytes_atomic(tmp_path / "sub" / "b.usda", b"no proc")
    assert (tmp_path / "sub" / "b.usda").read_bytes() == b"no proc" and os.listdir(tmp_path / "sub") == ["b.usda"]
    assert files._unnamed["ok"] is False


def test_write_bytes_atomic_on_a_full_disk_leaves_nothing(tmp_path, monkeypatch):
    from allo_usd.core import files

    (tmp_path / "kept.usda").write_bytes(b"old")

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "write", full)
    for name in ("kept.usda", "new.usda"):
        with pytest.raises(DiskFullError, match="free space"):
            files.write_bytes_atomic(tmp_path / name, b"x" * 100)
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["kept.usda"] and (tmp_path / "kept.usda").read_bytes() == b"old"


@pytest.mark.parametrize("unnamed", [True, False])
def test_write_bytes_atomic_without_an_inode_left_is_a_disk_full_error(tmp_path, monkeypatch, unnamed):
    """ENOSPC (or EDQUOT) when the file itself is created, not only while it is written."""
    from allo_usd.core import files

    monkeypatch.setattr(files, "_unnamed", {"ok": unnamed, "root": None, "folders": set()})

    def no_inode(p, flags, *a, **k):
        raise OSError(errno.ENOSPC if unnamed else errno.EDQUOT, "No space left on device", p)

    monkeypatch.setattr(os, "open", no_inode)
    with pytest.raises(DiskFullError, match="free space"):
        files.write_bytes_atomic(tmp_path / "a.usda", b"x")
    monkeypatch.undo()
    assert os.listdir(tmp_path) == []



# ---------------------------------------------------------------------------------------------
# Pseudo-files and the read gate: a file the kernel makes up is refused unread, its content never shown

def _environment_entries() -> list[str]:
    """This process's environment as /proc/self/environ holds it (the text a leak would show)."""
    with open("/proc/self/environ", "rb") as f:
        return [e.decode(errors="replace") for e in f.read().split(b"\0") if len(e) >= 8]


needs_proc = pytest.mark.skipif(not os.path.exists("/proc/self/environ"), reason="no /proc here")


@needs_proc
@pytest.mark.parametrize("target", ["/proc/self/environ", "/proc/self/mounts",
                                    "/sys/kernel/mm/transparent_hugepage/enabled"])
def test_the_gate_refuses_a_link_to_a_pseudo_file_by_its_real_path(tmp_path, target):
    from allo_usd.core.files import InputRefused, file_problem, read_head, read_user_bytes, read_user_text, \
        read_whole_small, sha256_file

    if not os.path.isfile(target):
        pytest.skip(f"no {target} here")
    link = tmp_path / "poses.csv"
    link.symlink_to(target)
    for read in (lambda: read_user_bytes(link, 1 << 20, "pose file"), lambda: read_user_text(link, 1 << 20, "plan"),
                 lambda: sha256_file(link)):
        with pytest.raises(InputRefused) as err:
            read()
        msg = str(err.value)
        assert err.value.kind == "pseudo" and "is a pseudo-file" in msg and "fix: point it at a file on disk" in msg
        assert str(link) in msg and "\n" not in msg
        assert not [e for e in _environment_entries() if e in msg], msg
    assert "pseudo-file" in file_problem(link, 1 << 20)
    assert read_head(link) is None and read_whole_small(link, 1 << 20) is None


@needs_proc
def test_a_file_of_size_zero_that_yields_bytes_is_a_pseudo_file(tmp_path, monkeypatch):
    """The second rule, for pseudo-files outside /proc, /sys and /dev: a file stat reports empty that
    yields a byte when read. Shown on /proc/self/environ with the real-path rule switched off."""
    from allo_usd.core import files
    from allo_usd.core.files import InputRefused, read_head, read_user_bytes, read_whole_small, sha256_file

    assert os.stat("/proc/self/environ").st_size == 0
    monkeypatch.setattr(files, "PSEUDO_ROOTS", ())
    link = tmp_path / "plan.toml"
    link.symlink_to("/proc/self/environ")
    assert files.input_problem(link, 1 << 20)[0] == "pseudo"
    with pytest.raises(InputRefused) as err:
        read_user_bytes(link, 1 << 20, "plan")
    assert err.value.kind == "pseudo" and "its size is 0 but it yields bytes" in str(err.value)
    assert not [e for e in _environment_entries() if e in str(err.value)]
    with pytest.raises(InputRefused, match="size is 0 but it yields bytes"):
        sha256_file(link)
    assert read_head(link) is None and read_whole_small(link, 1 << 20) is None
    monkeypatch.setattr(files, "input_problem", lambda *a, **k: None)   # a swap after the check: the read refuses it
    with pytest.raises(InputRefused, match="size is 0 but it yields bytes"):
        read_user_bytes(link, 1 << 20, "plan")


def test_an_empty_file_and_a_devices_kind_are_as_before(tmp_path):
    """An honest empty file is read as empty; a device under /dev stays "not a regular file"."""
    from allo_usd.core.files import InputRefused, read_head, read_user_bytes, read_whole_small, sha256_file

    empty = tmp_path / "empty.csv"
    empty.write_bytes(b"")
    assert read_user_bytes(empty, 10, "pose file") == b"" and read_head(empty) == b""
    assert read_whole_small(empty, 10)[0] == b"" and sha256_file(empty) == hashlib.sha256(b"").hexdigest()
    with pytest.raises(InputRefused) as err:
        read_user_bytes("/dev/null", 10, "pose file")
    assert err.value.kind == "not_regular"
