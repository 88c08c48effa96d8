"""Files written whole or not at all: the one file writer (atomic_path) and the one directory
writer (atomic_directory), checksums, run locks and the one relative-path rule."""

from __future__ import annotations

import errno
import glob
import itertools
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


def folder_realpath(folder, folders: dict | None) -> str:
    """os.path.realpath(folder), kept in `folders` (a caller's memo for one run or one decision, None:
    none) under ("realpath", FOLDER): the first answer stands while the memo lives."""
    if folders is None:
        return os.path.realpath(folder)
    key = ("realpath", os.fspath(folder))
    real = folders.get(key)
    if real is None:
        real = folders[key] = os.path.realpath(key[1])
    return real


def memo_realpath(path, folders: dict | None) -> str:
    """os.path.realpath(path), the same string, from one lstat where it can: a path whose last
    component is no symbolic link resolves as its folder's real path (folder_realpath, memoised in
    `folders`) joined with its name; realpath itself lstats every component (a 51,409-scene run
    resolves each file several times). A link, a name that is "", "." or "..", or one that lstat
    cannot see resolves in full. The path is made absolute without being normalised, as realpath
    takes it (a link is resolved before the ".." after it). One rule for authoring's TreeLinks,
    the dispatcher's decision (usd.safety.real_path) and a dataset run (output.dataset_files)."""
    if folders is None:
        return os.path.realpath(path)
    p = os.fspath(path)
    p = p if os.path.isabs(p) else os.path.join(os.getcwd(), p)
    folder, name = os.path.split(p)
    if name in ("", ".", ".."):
        return os.path.realpath(p)
    try:
        if stat.S_ISLNK(os.lstat(p).st_mode):
            return os.path.realpath(p)
    except OSError:
        return os.path.realpath(p)
    return os.path.join(folder_realpath(folder, folders), name)


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
    fd, tmp = _open_temp_beside(path, suffix)
    os.close(fd)
    return tmp


_TEMP_SERIAL = itertools.count()  # this process's temporaries: `.NAME.PID.SERIAL.EXT`, SERIAL 8 hex digits
_TEMP_FLAGS = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


def _open_temp_beside(path: Path, suffix: str = "") -> tuple[int, Path]:
    """temp_beside's file, still open: (descriptor, path). Made as tempfile.mkstemp makes it (created
    exclusively, links not followed, mode 0o600), named by a per-process serial instead of random
    letters, the folder made only when the create finds it missing: authoring writes ~92,000 files,
    and mkstemp's names and a mkdir each cost a third of a layer's writing."""
    folder = os.path.dirname(os.fspath(path))
    for tmp in _temp_names(path, suffix):
        try:
            return os.open(tmp, _TEMP_FLAGS, 0o600), Path(tmp)
        except FileExistsError:
            continue   # a name left by an earlier process of this pid: the next serial
        except FileNotFoundError:
            if folder and not os.path.isdir(folder):
                Path(folder).mkdir(parents=True, exist_ok=True)
                continue
            raise
    raise FileExistsError(errno.EEXIST, "no free temporary name", os.fspath(path))


def _temp_names(path, suffix: str = ""):
    """Up to 1,000 temporary names beside `path` for this process (temp_name_re's form: `.NAME.PID.SERIAL`
    and `suffix` or `path`'s suffix), each a new serial."""
    folder, name = os.path.split(os.fspath(path))
    ext = suffix or os.path.splitext(name)[1]
    for _ in range(1000):
        yield os.path.join(folder, f".{name}.{os.getpid()}.{next(_TEMP_SERIAL) & 0xFFFFFFFF:08x}{ext}")


_UNNAMED_FLAGS = getattr(os, "O_TMPFILE", 0) | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0)
_NO_UNNAMED = (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOTSUP, errno.ENOSYS)   # no O_TMPFILE there
_unnamed = {"ok": hasattr(os, "O_TMPFILE"), "root": None, "folders": set()}   # this process's findings


def _open_unnamed_beside(path: Path) -> int | None:
    """A descriptor of a new file without a name in `path`'s folder (made when the open finds it
    missing), or None where there are none: not Linux, a file system without O_TMPFILE (remembered
    per folder), or /proc not there to link one in (remembered for the process). Creating a named
    temporary and renaming it costs two directory updates where linking an unnamed file costs one:
    about a quarter of a small layer's writing on ext4, for ~92,000 layers a paper-plan run."""
    if not _unnamed["ok"]:
        return None
    folder = os.path.dirname(os.fspath(path)) or "."
    if folder in _unnamed["folders"]:
        return None
    for _ in range(2):
        try:
            return os.open(folder, _UNNAMED_FLAGS, 0o600)
        except FileNotFoundError:
            Path(folder).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            if exc.errno in _NO_UNNAMED:
                _unnamed["folders"].add(folder)
                return None
            raise
    return None


def _link_unnamed(fd: int, path: Path) -> bool:
    """Give the written unnamed file `fd` the name `path`: linkat through /proc/self/fd (the only
    unprivileged way; the root folder's descriptor as src_dir_fd makes os.link call linkat with
    AT_SYMLINK_FOLLOW). An existing `path` is replaced as rename replaces it: the file is linked
    under a temporary name, then renamed over it. False (nothing named) where /proc cannot be used,
    and the caller writes through a named temporary instead."""
    if _unnamed["root"] is None:
        _unnamed["root"] = os.open("/", os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    source = f"/proc/self/fd/{fd}"
    try:
        os.link(source, path, src_dir_fd=_unnamed["root"])
        return True
    except FileExistsError:
        pass
    except (FileNotFoundError, PermissionError, NotADirectoryError):
        _unnamed["ok"] = False      # no /proc here (or it hides descriptors): named temporaries from now on
        return False
    except OSError as exc:
        if exc.errno != errno.EXDEV:
            raise
        _unnamed["folders"].add(os.path.dirname(os.fspath(path)) or ".")   # a mount that will not link it
        return False
    for tmp in _temp_names(path):
        try:
            os.link(source, tmp, src_dir_fd=_unnamed["root"])
            break
        except FileExistsError:
            continue
    else:
        raise FileExistsError(errno.EEXIST, "no free temporary name", path)
    commit_temp(Path(tmp), path, None)
    return True


def _failed(exc: BaseException, tmp: Path, path: Path) -> None:
    """Remove the temporary, and raise a full disk as DiskFullError (other errors propagate)."""
    if Path(tmp).is_dir():
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        Path(tmp).unlink(missing_ok=True)
    if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
        raise _disk_full(path) from exc


def _disk_full(path) -> DiskFullError:
    return DiskFullError(f"no space left on the device while writing {path}; free space and re-run "
                         "(finished outputs are kept and will be skipped)")


def _fill(fd: int, data: bytes, mode: int) -> None:
    """Make the new file `fd` `mode` and write all of `data` into it."""
    os.fchmod(fd, mode)
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


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
    """Write `text` whole or not at all (a reader never sees a partial file); `open_args` as for open().
    Without them the text is written as UTF-8 through write_bytes_atomic's one descriptor (authoring
    writes ~92,000 files: a second open in text mode cost as much as building a layer), the same bytes
    on every machine whatever its locale."""
    if not open_args:
        return write_bytes_atomic(path, text.encode("utf-8"))
    with atomic_path(path) as tmp:
        with open(tmp, "w", **open_args) as f:
            f.write(text)
    return Path(path)


def write_bytes_atomic(path: Path, data: bytes, mode: int = 0o644) -> Path:
    """Write `data` whole or not at all: into a file without a name in `path`'s folder (O_TMPFILE),
    made `mode`, then linked in as `path` (`_link_unnamed`); where the file system or platform has
    no unnamed files, into atomic_path's temporary through the descriptor that created it, then
    renamed over `path`. A full disk raises DiskFullError; a write cut short leaves nothing (an
    unnamed file vanishes when its descriptor closes)."""
    path = Path(path)
    try:
        fd = _open_unnamed_beside(path)
        if fd is not None:
            try:
                _fill(fd, data, mode)
                if _link_unnamed(fd, path):
                    return path
            finally:
                os.close(fd)
        fd, tmp = _open_temp_beside(path)
    except OSError as exc:   # no inode, block or quota left for the file, its folder or its name
        if exc.errno in DISK_FULL_ERRNOS:
            raise _disk_full(path) from exc
        raise
    try:
        try:
            _fill(fd, data, mode)
        finally:
            os.close(fd)
    except BaseException as exc:
        _failed(exc, tmp, path)
        raise
    commit_temp(tmp, path, None)
    return path


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
    """Hex SHA-256 of a file, read in 1 MiB chunks (checksums in manifests). Opened as the read gate
    opens (non-blocking, then checked as a regular file that is no pseudo-file): a FIFO or a device
    put in a checked file's place is an InputRefused naming the rule, not a hang or endless bytes."""
    import hashlib

    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _refuse(path, "not_regular", _NOT_REGULAR, "file", "", None)
        real = _opened_real(fd)
        if real is not None and _pseudo_root(real):
            raise _refuse(path, "pseudo", _pseudo_reason(real), "file", "", None)
        h = hashlib.sha256()
        first = True
        while chunk := os.read(fd, 1 << 20):
            if first and st.st_size == 0:   # reported empty, yet it yields bytes
                raise _refuse(path, "pseudo", _ZERO_YIELDS, "file", "", None)
            first = False
            h.update(chunk)
    finally:
        os.close(fd)
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


# ------------------------------------------------------------------ the read gate
#
# Every file the project reads from a user (a pose file, a render record NAME.json, a plan, and,
# through allo_usd.usd.dependencies, every layer and texture a scene names) passes one rule, checked
# by os.stat before anything is opened: missing or unreadable, outside the allowed roots (where the
# caller has roots), not a regular file (a FIFO would block its reader, a device such as /dev/zero
# never ends, a directory is no file), or more than `limit` bytes. A file that passes is then read
# through a non-blocking descriptor, checked again as a regular file (a swap between the stat and the
# open), for at most limit + 1 bytes: one that grew past the bound meanwhile is refused too. JSON
# nested deeper than MAX_JSON_DEPTH is refused: json.loads's RecursionError on a few thousand levels,
# or the parsed value's depth (read_user_json). A refusal names the file and the rule, never the
# file's content.
#
# Pseudo-files are refused too: a regular file whose real path lies under /proc, /sys or /dev (the
# kernel makes their bytes up: /proc/self/environ is the process's environment, and reports a size of
# 0), and any file whose stat says 0 bytes but which yields a byte when read (the one case where the
# gate opens a file before deciding: a regular file, opened non-blocking, one byte read). Each read
# checks the descriptor again (its real path, and its reported size against the bytes it yields), so
# a file swapped for a pseudo-file after the check is refused as well.

MAX_JSON_DEPTH = 64   # a render record nests 5 levels, a pose file 3
MAX_RECORD_BYTES = 4 << 20   # a render record NAME.json (allo_usd.run.job writes a few KB)


class InputRefused(AlloError, ValueError):
    """A user's file the read gate refused. `kind` names the rule (missing, unreadable, outside,
    not_regular, pseudo, too_big, grew, not_utf8, too_deep, not_json), `reason` is the text that follows the
    file's name ("is too big (N bytes > LIMIT)"); the message is one line with the fix."""

    def __init__(self, message: str, kind: str, reason: str):
        super().__init__(message)
        self.kind, self.reason = kind, reason


def _bound(limit: int) -> str:
    """A byte bound in words: 256 MiB, 64 KiB or 1,000 bytes."""
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if limit >= 1 << shift and limit % (1 << shift) == 0:
            return f"{limit >> shift:,} {unit}"
    return f"{limit:,} bytes"


def _inside_roots(real: str, roots) -> bool:
    real_path = Path(real)
    for r in roots:
        r = Path(os.path.realpath(r))
        if real_path == r or r in real_path.parents:
            return True
    return False


def input_problem(path: str | Path, limit: int, roots=None) -> tuple[str, str] | None:
    """(kind, reason) of why `path` may not be read as a bounded regular file, or None if it may
    (the gate's rule, module comment above). os.stat only (symlinks followed): nothing is opened.
    `roots`: directories the file's real path must lie in (None: no such rule)."""
    real = None
    if roots is not None:
        real = os.path.realpath(path)
        if not _inside_roots(real, roots):
            return "outside", (f"resolves to {real}, outside {', '.join(str(r) for r in roots)} (a symbolic link "
                               "out of its folder)")
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "missing", "does not exist"
    except OSError as exc:
        return "unreadable", f"cannot be read ({exc.strerror})"
    if not stat.S_ISREG(st.st_mode):
        return "not_regular", _NOT_REGULAR
    real = real or os.path.realpath(path)
    if _pseudo_root(real):
        return "pseudo", _pseudo_reason(real)
    if st.st_size > limit:
        return "too_big", f"is too big ({st.st_size:,} bytes > {_bound(limit)} allowed)"
    if st.st_size == 0 and _yields_bytes(path):
        return "pseudo", _ZERO_YIELDS
    return None


PSEUDO_ROOTS = ("/proc", "/sys", "/dev")   # file systems whose files the kernel makes up (or devices)
_NOT_REGULAR = "is not a regular file (a directory, FIFO, device or socket)"
_ZERO_YIELDS = ("is a pseudo-file: its size is 0 but it yields bytes when read (the kernel makes its content up, "
                "e.g. under /proc), and is never read")


def _pseudo_root(real: str) -> str | None:
    """The pseudo-filesystem root (PSEUDO_ROOTS) the real path `real` lies under, or None."""
    return next((r for r in PSEUDO_ROOTS if real == r or real.startswith(r + "/")), None)


def _pseudo_reason(real: str) -> str:
    return (f"is a pseudo-file: it resolves to {real}, under {_pseudo_root(real)}, whose files the kernel makes up "
            "(never read)")


def _yields_bytes(path) -> bool:
    """Does the file at `path` (a regular file by os.stat, of size 0) yield a byte when read? Opened
    non-blocking and checked as a regular file first, so nothing can block. False if it cannot be
    opened (the read that follows says why)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return False
    try:
        return stat.S_ISREG(os.fstat(fd).st_mode) and os.read(fd, 1) != b""
    except OSError:
        return False
    finally:
        os.close(fd)


def _opened_real(fd: int) -> str | None:
    """The real path of what the descriptor `fd` has open (/proc/self/fd; one readlink), or None
    where that cannot be asked (no /proc, an unnamed file)."""
    try:
        real = os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return None
    return real if real.startswith("/") else None


class _Pseudo(Exception):
    """_read_regular met a pseudo-file (its real path, or "" for a size-0 file that yields bytes)."""

    def __init__(self, real: str):
        super().__init__(real)
        self.real = real


def file_problem(path: str | Path, limit: int) -> str | None:
    """Why `path` may not be read as a bounded regular file, or None if it may: input_problem's
    reason without roots ("cannot be read (...)" for a missing file too). The text follows the path
    in a message ("PATH is not a regular file ..."); the caller adds the fix."""
    found = input_problem(path, limit)
    if found is None:
        return None
    kind, reason = found
    return "cannot be read (No such file or directory)" if kind == "missing" else reason


_RULE_FIX = {"pseudo": "point it at a file on disk (copy what you mean to use into one)"}   # when the caller has none


def _refuse(path, kind: str, reason: str, what: str, fix, error):
    if isinstance(fix, dict):
        hint = fix[kind] if kind in fix else _RULE_FIX.get(kind, fix.get("", ""))
    else:
        hint = fix or _RULE_FIX.get(kind, "")
    message = f"{what} {path} {reason}" + (f"; fix: {hint}" if hint else "")
    if error is None:
        return InputRefused(message, kind, reason)
    return error(message)


def _bounded_read(path: str | Path, limit: int) -> bytes | None:
    """At most limit + 1 bytes of a regular file, read through a non-blocking descriptor; None when
    what was opened is not a regular file (swapped after the stat)."""
    return _read_regular(os.open(path, os.O_RDONLY | os.O_NONBLOCK), limit + 1)


def _read_regular(fd: int, count: int) -> bytes | None:
    """At most `count` bytes from the open descriptor `fd` (closed after), or None if it is not a
    regular file: the one bounded read of _bounded_read and read_head. A pseudo-file (what is open
    lies under PSEUDO_ROOTS, or it reports 0 bytes and yields some) raises _Pseudo, its content
    unread past the first byte: checked on the descriptor, so a swap after the gate's check is caught."""
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):   # replaced between the stat and the open
            return None
        real = _opened_real(fd)
        if real is not None and _pseudo_root(real):
            raise _Pseudo(real)
        chunks, size = [], 0
        while size < count:
            chunk = os.read(fd, min(count - size, 1 << 20) if size or st.st_size else 1)
            if not chunk:
                break
            if not size and st.st_size == 0:   # reported empty, yet it yields bytes
                raise _Pseudo("")
            chunks.append(chunk)
            size += len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_user_bytes(path: str | Path, limit: int, what: str, fix: str | dict = "", roots=None,
                    error: type[Exception] | None = None) -> bytes:
    """The bytes of a user's file through the read gate (module comment above), or a one-line
    error "WHAT PATH REASON; fix: FIX" (`fix` may map a kind to its own fix, "" the default): an
    `error` instance when given (PlanError, LayerError), else InputRefused."""
    found = input_problem(path, limit, roots)
    if found is not None:
        raise _refuse(path, *found, what, fix, error)
    try:
        data = _bounded_read(path, limit)
    except _Pseudo as exc:
        raise _refuse(path, "pseudo", _pseudo_reason(exc.real) if exc.real else _ZERO_YIELDS, what, fix,
                      error) from None
    except FileNotFoundError:
        raise _refuse(path, "missing", "does not exist", what, fix, error) from None
    except OSError as exc:
        raise _refuse(path, "unreadable", f"cannot be read ({exc.strerror})", what, fix, error) from None
    if data is None:
        raise _refuse(path, "not_regular", _NOT_REGULAR, what, fix, error)
    if len(data) > limit:
        raise _refuse(path, "grew", f"is too big (it grew past {_bound(limit)} while it was read)", what, fix, error)
    return data


def read_user_text(path: str | Path, limit: int, what: str, fix: str | dict = "", roots=None,
                   error: type[Exception] | None = None) -> str:
    """read_user_bytes decoded as UTF-8 (a byte-order mark is dropped); bytes that are not UTF-8
    are refused naming the first bad byte's offset."""
    data = read_user_bytes(path, limit, what, fix, roots, error)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise _refuse(path, "not_utf8", f"is not UTF-8 text (byte {exc.start} is not)", what, fix, error) from None


_JSON_STRING = re.compile(r'"(?:[^"\\\n]|\\.)*"')


def json_too_deep(text: str, max_depth: int = MAX_JSON_DEPTH) -> int | None:
    """The line where JSON `text` nests arrays and objects deeper than `max_depth`, or None. Brackets
    inside strings do not count. A scan, not a parse (numpy over the text's bytes: 16 MB of '['
    in well under a second), so it is safe to ask before json.loads, which recurses."""
    if text.count("[") + text.count("{") <= max_depth:
        return None
    import numpy as np

    blank = _JSON_STRING.sub(lambda m: " " * len(m.group()), text).encode()   # brackets are ASCII bytes
    codes = np.frombuffer(blank, dtype=np.uint8)
    at = np.flatnonzero((codes == 0x5B) | (codes == 0x7B) | (codes == 0x5D) | (codes == 0x7D))
    depth = np.cumsum(np.where((codes[at] == 0x5B) | (codes[at] == 0x7B), 1, -1).astype(np.int8), dtype=np.int32)
    over = np.flatnonzero(depth > max_depth)
    if over.size == 0:
        return None
    return blank.count(b"\n", 0, int(at[over[0]])) + 1


def _nests_over(value, max_depth: int) -> bool:
    """Does a parsed JSON value nest arrays and objects deeper than `max_depth`? (the depth
    json_too_deep counts: the outermost array or object is level 1)"""
    stack = [(value, 1)]
    while stack:
        v, depth = stack.pop()
        children = v.values() if isinstance(v, dict) else v
        if depth > max_depth:
            return True
        stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))
    return False


def read_user_json(path: str | Path, limit: int, what: str, fix: str | dict = "", roots=None,
                   error: type[Exception] | None = None, max_depth: int = MAX_JSON_DEPTH):
    """read_user_text parsed as JSON, refused when nested deeper than `max_depth` (kind too_deep,
    naming the line) or when it is not JSON (kind not_json, naming line and column).

    Parsed first: json.loads raises RecursionError on deep nesting (its C scanner counts its
    recursion) and nothing else is at risk in a text already bounded by `limit`, so a record is
    parsed once and its depth read from the parsed value; the bracket scan (json_too_deep, ~2 ms
    a render record) runs only for a text that is refused, to name the line."""
    import json

    text = read_user_text(path, limit, what, fix, roots, error)

    def too_deep():
        line = json_too_deep(text, max_depth)
        where = f" (at line {line})" if line is not None else ""
        return _refuse(path, "too_deep", f"nests values over {max_depth} levels deep{where}", what, fix, error)

    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        if json_too_deep(text, max_depth) is not None:   # deep before it is broken: depth is the rule it breaks
            raise too_deep() from None
        raise _refuse(path, "not_json", f"is not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})",
                      what, fix, error) from None
    except RecursionError:
        raise too_deep() from None
    if isinstance(value, (dict, list)) and text.count("[") + text.count("{") > max_depth \
            and _nests_over(value, max_depth):
        raise too_deep()
    return value


def read_own_record(path: str | Path, limit: int = 1 << 20):
    """A JSON record this project wrote into its own tree (a marker such as stages/station_source.json,
    versions.json), read through the gate: its parsed value, or None when it is missing, refused (a
    FIFO, a pseudo-file, too big, too deep) or not JSON. The caller decides what None means (usually:
    a record that does not match)."""
    try:
        return read_user_json(path, limit, "record")
    except InputRefused:
        return None


def record_shown(recorded, keys, limit: int = 300) -> str | None:
    """What a message may show of a record read back from a tree: only its values under `keys` (the
    fields the project writes there), cut to `limit` characters; None when it is no JSON object. A
    record replaced by some other JSON file shows nothing of that file's own fields."""
    if not isinstance(recorded, dict):
        return None
    text = repr({k: recorded[k] for k in keys if k in recorded})
    return text if len(text) <= limit else text[:limit - 3] + "..."


def read_head(path: Path, limit: int = 16384) -> bytes | None:
    """At most `limit` bytes from the start of a regular file (symlinks followed); None for
    anything else (a FIFO, a device, a socket, a directory), which is never opened for reading
    past a non-blocking open: a FIFO named like a layer cannot block the caller, and a symlink
    to /dev/zero or a huge sparse file costs `limit` bytes, not the whole file. A pseudo-file
    (the gate's rule: under /proc, /sys or /dev, or of size 0 yet yielding bytes) is None too."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        return _read_regular(fd, limit)
    except _Pseudo:
        return None


def read_whole_small(path: str | Path, limit: int) -> tuple[bytes, os.stat_result] | None:
    """The whole of a regular file of at most `limit` bytes and the stat those bytes were read at
    (the descriptor's, the same before and after the read), or None for anything else (bigger,
    not a regular file, a pseudo-file, changed during the read, unreadable). read_head's rule for
    what is opened: the dispatcher's scan reads a scene layer once, to sniff it and to checksum it.
    A size-0 file that yields bytes is refused by the size check below (its bytes differ from its
    size)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        before = os.fstat(fd)
        if not stat.S_ISREG(before.st_mode) or before.st_size > limit:
            return None
        real = _opened_real(fd)
        if real is not None and _pseudo_root(real):
            return None
        data = os.read(fd, limit + 1)
        after = os.fstat(fd)
    except OSError:
        return None
    finally:
        os.close(fd)
    if len(data) != before.st_size or (after.st_size, after.st_mtime_ns) != (before.st_size, before.st_mtime_ns):
        return None
    return data, after


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
