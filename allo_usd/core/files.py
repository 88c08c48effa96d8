"""Files written whole or not at all: the one file writer (atomic_path) and the one directory
writer (atomic_directory), checksums, run locks and the one relative-path rule."""

from __future__ import annotations

import errno
import glob
import os
import re
import shutil
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path

from allo_usd.core.errors import AlloError, DiskFullError


def relpath(target: Path, start: Path) -> str:
    """The one rule for a path written into a layer or shown beside one: `target` relative to the
    directory `start`, both made absolute with symlinks resolved (so a resolved path and an
    unresolved one of the same file still relate), POSIX separators, and anchored with "./" when
    it does not start with "." (USD would read a bare name as a search path)."""
    rel = Path(os.path.relpath(Path(target).resolve(), Path(start).resolve())).as_posix()
    return rel if rel.startswith(".") else f"./{rel}"


DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)  # no space, or the user's quota is spent


def temp_name_re(pid: int | None = None) -> re.Pattern:
    """Names of atomic_path temporaries: `.NAME.PID.XXXXXXXX.EXT` (mkstemp's 8 random characters;
    atomic_directory's have no .EXT),
    those of writer `pid` only when given. Without a pid it also matches the names of earlier
    versions, which had no pid. The pid lets a dispatcher remove a dead worker's temporaries
    without touching those its live workers are writing."""
    who = r".+" if pid is None else rf".+\.{int(pid)}"
    return re.compile(rf"^\.{who}\.[a-z0-9_]{{8}}(\.[A-Za-z0-9]+)?$")


def temp_beside(path: Path, suffix: str = "") -> Path:
    """A new, empty temporary file beside `path`, named for this process (temp_name_re) and ending
    in `suffix` or `path`'s suffix (some writers choose the format by it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=suffix or path.suffix)
    os.close(fd)
    return Path(tmp)


def _failed(exc: BaseException, tmp: Path, path: Path) -> None:
    """Remove the temporary, and raise a full disk as DiskFullError (other errors propagate)."""
    if Path(tmp).is_dir():
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        Path(tmp).unlink(missing_ok=True)
    if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
        raise DiskFullError(f"no space left on the device while writing {path}; free space and re-run "
                            "(finished outputs are kept and will be skipped)") from exc


def commit_temp(tmp: Path, path: Path, mode: int | None = 0o644) -> None:
    """Rename a temporary of temp_beside over `path`, made `mode` first (None keeps it: a hard link
    shares its mode with its source); on failure remove it."""
    try:
        if mode is not None:
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException as exc:
        _failed(exc, tmp, path)
        raise


@contextmanager
def atomic_path(path: Path, suffix: str = "", mode: int | None = 0o644):
    """The one file writer: yield a temporary path beside `path` (temp_beside); on success rename it
    over `path`, else remove it. A full disk raises DiskFullError."""
    tmp = temp_beside(path, suffix)
    try:
        yield tmp
    except BaseException as exc:
        _failed(exc, tmp, path)
        raise
    commit_temp(tmp, path, mode)


def write_text_atomic(path: Path, text: str, **open_args) -> Path:
    """Write `text` whole or not at all (a reader never sees a partial file); `open_args` as for open()."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", **open_args) as f:
            f.write(text)
    return Path(path)


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


# a directory temporary after ".DEST": ".PID.XXXXXXXX" (atomic_directory) or ".<32 hex>.tmp" (earlier versions)
_DIR_TEMP = re.compile(r"^\.(?:(\d+)\.[a-z0-9_]{8}|[0-9a-f]{32}\.tmp)$")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


@contextmanager
def atomic_directory(dest: Path):
    """The one directory writer: yield a new temporary directory beside `dest` (named like
    atomic_path's temporaries); on success replace `dest` by it (an existing `dest` is removed
    first), else remove it. A killed run leaves nothing under the final name; the leftovers of dead
    writers of the same `dest` are removed first."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    for stale in dest.parent.glob(f".{glob.escape(dest.name)}.*"):
        m = _DIR_TEMP.match(stale.name[len(dest.name) + 1:])
        if m and stale.is_dir() and (m.group(1) is None or not _alive(int(m.group(1)))):
            shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}.{os.getpid()}."))
    try:
        os.chmod(tmp, 0o755)  # mkdtemp makes 0700; a tree is meant to be shared
        yield tmp
        if dest.exists():
            shutil.rmtree(dest)
        os.replace(tmp, dest)
    except BaseException as exc:
        _failed(exc, tmp, dest)
        raise


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB chunks (checksums in manifests)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class RunLock:
    """One writer per output directory: an exclusive, non-blocking flock on `out_dir/name`, held for
    the block (released by the kernel if the process dies). A second run gets a clear error."""

    def __init__(self, out_dir: Path, name: str, what: str):
        self.path, self.what = Path(out_dir) / name, what

    def __enter__(self):
        import fcntl

        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self.fd)
            raise AlloError(f"another {self.what} run is writing to {self.path.parent}; wait for it or use "
                            "another --out") from None
        return self

    def __exit__(self, *exc):
        os.close(self.fd)


def file_problem(path: str | Path, limit: int) -> str | None:
    """Why `path` may not be read as a bounded regular file, or None if it may: missing or
    unreadable, not a regular file (a FIFO would block its reader, a device never ends), or more
    than `limit` bytes. Uses os.stat only (symlinks followed): nothing is opened. The text follows
    the path in a message ("PATH is not a regular file ..."); the caller adds the fix."""
    try:
        st = os.stat(path)
    except OSError as exc:
        return f"cannot be read ({exc.strerror})"
    if not stat.S_ISREG(st.st_mode):
        return "is not a regular file (a directory, FIFO, device or socket)"
    if st.st_size > limit:
        return f"holds {st.st_size:,} bytes, over the {limit >> 20:,} MiB allowed"
    return None


def read_head(path: Path, limit: int = 16384) -> bytes | None:
    """At most `limit` bytes from the start of a regular file (symlinks followed); None for
    anything else (a FIFO, a device, a socket, a directory), which is never opened for reading
    past a non-blocking open: a FIFO named like a layer cannot block the caller, and a symlink
    to /dev/zero or a huge sparse file costs `limit` bytes, not the whole file."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # replaced between the stat and the open
            return None
        chunks, size = [], 0
        while size < limit:
            chunk = os.read(fd, limit - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def _nearest_existing(path: Path) -> Path:
    for p in (path, *path.parents):
        if os.path.lexists(p):
            return p
    return path


def ensure_output_dir(path: Path, what: str = "--out") -> Path:
    """Make sure `path` is a directory this process can write, before any work is spent on it:
    create it (with its parents) and write and remove a probe file in it. Raises AlloError naming
    the path and the fix (it is a file, a parent is a file, it cannot be created or written),
    or DiskFullError when the probe finds the device full."""
    path = Path(path)
    if os.path.lexists(path) and not path.is_dir():
        raise AlloError(f"{what} {path} exists and is not a directory; pass a directory (or remove the file)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        base = _nearest_existing(path.parent)
        why = exc.strerror or type(exc).__name__
        if base.exists() and not base.is_dir():
            why = f"{base} is a file"
        raise AlloError(f"{what} {path} cannot be created ({why}); choose a directory you can write") from None
    try:
        fd, probe = tempfile.mkstemp(dir=path, prefix=".allo-write-probe.")
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        if exc.errno in DISK_FULL_ERRNOS:
            raise DiskFullError(f"no space left on the device holding {what} {path}; free space or choose another "
                                "directory") from None
        raise AlloError(f"{what} {path} cannot be written ({exc.strerror or exc}); fix its permissions or choose "
                        "another directory") from None
    return path


def ensure_output_file(path: Path, what: str = "--out") -> Path:
    """Make sure the file `path` can be written: not a directory, and its directory writable
    (ensure_output_dir on the parent, which is created if missing)."""
    path = Path(path)
    if path.is_dir():
        raise AlloError(f"{what} {path} is a directory; pass a file name")
    ensure_output_dir(path.parent, f"{what} {path.name}'s directory")
    return path
