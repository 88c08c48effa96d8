"""Files written whole or not at all: atomic writers, checksums, run locks and the one relative-path rule."""

from __future__ import annotations

import errno
import os
import re
import tempfile
from contextlib import contextmanager
from pathlib import Path

from allo_usd.core.errors import AlloError, DiskFullError


def relpath(target: Path, start: Path) -> str:
    rel = os.path.relpath(Path(target).resolve(), Path(start).resolve())
    return rel if rel.startswith(".") else f"./{rel}"


def write_text_atomic(path: Path, text: str) -> Path:
    """Write to a temporary name beside `path`, then rename: a reader never sees a partial file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)  # no space, or the user's quota is spent


def temp_name_re(pid: int | None = None) -> re.Pattern:
    """Names of atomic_path temporaries: `.NAME.PID.XXXXXXXX.EXT` (mkstemp's 8 random characters),
    those of writer `pid` only when given. Without a pid it also matches the names of earlier
    versions, which had no pid. The pid lets a dispatcher remove a dead worker's temporaries
    without touching those its live workers are writing."""
    who = r".+" if pid is None else rf".+\.{int(pid)}"
    return re.compile(rf"^\.{who}\.[a-z0-9_]{{8}}(\.[A-Za-z0-9]+)?$")


@contextmanager
def atomic_path(path: Path, suffix: str = ""):
    """Yield a temporary path beside `path` (named for this process, see temp_name_re); on success
    rename it over `path`, else remove it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=suffix or path.suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if exc.errno in DISK_FULL_ERRNOS:
            raise DiskFullError(f"no space left on the device while writing {path}; free space and re-run "
                            "(finished outputs are kept and will be skipped)") from exc
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
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
