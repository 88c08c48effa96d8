"""The render worker: what runs inside each worker process (local pool or Dask), and the only
module outside `blender/` that imports bpy, once per process, to keep it warm."""

from __future__ import annotations

import dataclasses
import os
import re
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

from allo_usd.core.errors import AlloError, DiskFullError, RenderFailedError
from allo_usd.core.files import DISK_FULL_ERRNOS
from allo_usd.run.options import JobOptions
from allo_usd.run.render_index import WORKDIR, manifest_row
from allo_usd.usd.safety import ENV_ROOTS


# ---------------------------------------------------------------- the task (runs in a worker)

_BPY_LOCK = threading.Lock()  # bpy is one global state and not thread-safe: one render per process at a time
_SESSION = None  # this process's warm Blender session (allo_usd.blender.session), made by its first task


def render_task(layer: str, out_dir: str, options: JobOptions | None = None, roots: str = "",
                before_render: Callable[[str], None] | None = None) -> dict:
    """Render one layer as `options` says (a JobOptions, pickled with the task: its device, 'auto',
    'cpu' or 'gpu', is probed once per process, allo_usd.blender.device; its threads are this worker's
    share of the cores), forced (the parent decided it is not done), and checksum its outputs.
    `roots` is the run's ALLO_ASSET_ROOTS.

    Never raises for a bad layer, a full disk or a missing GPU: returns {"status": "error", "kind":
    ...} ("layer", "disk_full", "device", "error") so the parent can tell them apart from a crash,
    which it sees as a dead worker instead. Safe to
    call from several threads of one process (a Dask worker with --nthreads > 1): they take turns.
    `before_render(scene_name)`, if given, is called first, inside the lock (tests inject faults
    with it; it must be picklable: a module-level function or a partial of one).
    """
    with _BPY_LOCK:
        return _render_task(layer, out_dir, JobOptions() if options is None else options, roots, before_render)


def _render_task(layer: str, out_dir: str, options: JobOptions, roots: str,
                 before_render: Callable[[str], None] | None) -> dict:
    global _SESSION
    _fix_bpy_path()
    from allo_usd.run.job import render_record

    if roots:
        os.environ[ENV_ROOTS] = roots
    layer_p, out_p = Path(layer), Path(out_dir)
    scene = layer_p.stem

    def error(kind: str, exc: BaseException, prefix: bool = True) -> dict:
        return {"status": "error", "kind": kind, "scene": scene,
                "message": f"{type(exc).__name__}: {exc}" if prefix else str(exc)}

    try:
        if before_render is not None:
            before_render(scene)
        if _SESSION is None:
            from allo_usd.blender.session import Session

            _SESSION = Session()  # one Blender scene per process, patched from scene to scene
        meta = render_record(layer_p, out_p, dataclasses.replace(options, force=True), workdir=render_workdir(out_p),
                             session=_SESSION, index=False)  # the parent writes the manifest row
    except DiskFullError as exc:
        return error("disk_full", exc, prefix=False)
    except RenderFailedError as exc:  # not the layer's fault: retried
        return error("error", exc)
    except AlloError as exc:
        from allo_usd.blender.device import DeviceError

        if isinstance(exc, DeviceError):  # this machine cannot render as asked: the run stops
            return error("device", exc, prefix=False)
        return error("layer", exc)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which retries it unless the disk is full
        full = disk_full_error(exc, out_p)
        return error("disk_full", full, prefix=False) if full is not None else error("error", exc)
    return {"status": "ok", **manifest_row(layer_p, out_p, meta),   # the row the dispatcher appends
            "worker": f"{os.uname().nodename}:{os.getpid()}", "full_build": bool(_SESSION.last.full_build),
            "device_notice": meta.device.get("notice"),  # the dispatcher shows it once per run
            "cores": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None}


_FULL_WORDS = tuple(os.strerror(e).lower() for e in DISK_FULL_ERRNOS) + ("no space", "disk full", "quota exceeded")


def disk_full_error(exc: BaseException, out_dir: Path) -> DiskFullError | None:
    """`exc` as a DiskFullError when it means the device is full, else None: our writers' own
    DiskFullError, an OSError with ENOSPC/EDQUOT, or a RuntimeError from a C++ writer (OpenEXR:
    'Failed to write pixel data ... No space left on device') that says so, or that failed to
    write while the device holding `out_dir` has no free blocks left."""
    if isinstance(exc, DiskFullError):
        return exc
    said = " ".join(str(exc).split())  # OpenEXR's messages span lines
    full = f"no space left on the device holding {out_dir} ({said}); free space and re-run (finished outputs are kept)"
    if isinstance(exc, OSError):
        return DiskFullError(full) if exc.errno in DISK_FULL_ERRNOS else None
    if not isinstance(exc, RuntimeError):
        return None
    text = str(exc).lower()
    if any(w in text for w in _FULL_WORDS):
        return DiskFullError(full)
    if "write" in text:
        try:
            if os.statvfs(out_dir).f_bavail == 0:
                return DiskFullError(full)
        except OSError:
            pass
    return None


def render_workdir(out_dir: Path) -> Path:
    """This process's own directory for Blender's render files (removed if the process dies)."""
    d = out_dir / WORKDIR / str(os.getpid())
    d.mkdir(parents=True, exist_ok=True)
    return d


# ---------------------------------------------------------------- worker output

def _send_output_to(log: Path) -> None:
    """Point this process's stdout and stderr at `log` (appending), at the file-descriptor level:
    Blender prints from C ("Saved: ...", "CUEW initialization failed"), past sys.stdout."""
    try:
        log.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    except OSError:  # a full or read-only disk: the output is not worth failing for
        fd = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)


def _flush_c_stdio() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass


@contextmanager
def output_to(log: Path):
    """Send this process's stdout and stderr (file descriptors, so Blender's C output too) to
    `log` for the block, then restore them (the single-layer `allo-usd render LAYER`, the demo, and
    the public allo_usd.render_layer and render_scene)."""
    _flush_c_stdio()  # what C printed before the block stays where it was going
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    saved = os.dup(1), os.dup(2)
    try:
        _send_output_to(Path(log))
        yield Path(log)
    finally:
        _flush_c_stdio()
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


# ---------------------------------------------------------------- local pool

def _die_with_parent(parent_pid: int) -> None:
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass

    def watch():
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(1.0)

    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=watch, daemon=True).start()


_BPY_SCRIPTS = re.compile(r"[/\\]bpy[/\\]\d+\.\d+[/\\]scripts")


def _fix_bpy_path() -> None:
    """A spawned child inherits its parent's sys.path; if the parent had imported bpy, that holds
    bpy's bundled scripts/modules, whose `bpy` package shadows the real module: drop them."""
    if "bpy" not in sys.modules:
        sys.path[:] = [p for p in sys.path if not _BPY_SCRIPTS.search(p)]


def own_tmpdir(out_dir: Path) -> Path:
    """Point this process's temporary directory (TMPDIR, and Python's tempfile) at
    OUT/.allo-tmp/PID/tmp, before bpy is imported: Blender makes its session folder
    (blender_XXXXXX) there, and a worker that is killed (as every pool worker is at the end of a
    run) cannot remove it itself; the dispatcher removes OUT/.allo-tmp/PID instead."""
    tmp = render_workdir(Path(out_dir)) / "tmp"
    tmp.mkdir(parents=True, exist_ok=True)
    os.environ["TMPDIR"] = str(tmp)
    import tempfile

    tempfile.tempdir = None  # computed again from TMPDIR
    return tmp


def own_run_tmpdir(out_dir: Path) -> Path:
    """For a layer rendered in this process (`allo-usd render LAYER`), under the output lock: what a
    killed run left in OUT/.allo-tmp removed (no other run can own it: clean_stale), then this
    process's temporary directory pointed at OUT/.allo-tmp/PID/tmp (own_tmpdir), before bpy is
    imported: Blender makes its session folder (blender_XXXXXX) when bpy loads, and a SIGKILL leaves
    it behind; here the next run into OUT removes it, where in the system temp dir it stayed for
    good. When the process ends, Blender removes its folder (its exit handler, registered when bpy
    loads, runs before this one's) and OUT/.allo-tmp goes. Returns the render file's workdir.
    With bpy already loaded (a caller's own process) its session folder is elsewhere: the render
    file alone goes under OUT."""
    import atexit

    from allo_usd.run.render_index import clean_stale

    clean_stale(out_dir)
    if "bpy" not in sys.modules:
        own_tmpdir(out_dir)
    atexit.register(_remove_run_tmpdir, Path(out_dir), os.getpid())
    return render_workdir(Path(out_dir))


def _remove_run_tmpdir(out_dir: Path, pid: int) -> None:
    import shutil

    if os.getpid() != pid:   # a forked child inherits the handler: the folder is its parent's
        return
    shutil.rmtree(out_dir / WORKDIR / str(pid), ignore_errors=True)
    try:
        (out_dir / WORKDIR).rmdir()   # only if empty
    except OSError:
        pass


def worker_main(conn, env: dict, parent_pid: int, cores: tuple[int, ...] | None = None,
                log: str | None = None, index: int = 0, before_render: Callable[[str], None] | bytes | None = None,
                out_dir: str | None = None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C means
    _die_with_parent(parent_pid)
    if log:
        _send_output_to(Path(log))
        print(f"--- allo-usd render worker {index}, pid {os.getpid()}, started "
              f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')} ---", flush=True)
    if isinstance(before_render, bytes):  # pickled by WorkerProcess: unpickled here, so a failure is in the log
        import pickle

        before_render = pickle.loads(before_render)
    if cores:  # before bpy: TBB sizes its pool from the affinity mask when it starts
        os.sched_setaffinity(0, cores)
    os.environ.update(env)
    if out_dir:
        own_tmpdir(Path(out_dir))
    _fix_bpy_path()
    import bpy  # noqa: F401 - warm: import once per worker, not per scene (its Session comes with the first task)

    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        conn.send({"status": "started"})  # the parent's time limit for this task starts now
        conn.send(render_task(**msg, before_render=before_render))


# ---------------------------------------------------------------- starting a local worker

def check_hook(before_render: Callable[[str], None] | None) -> None:
    """A local worker is a fresh `python -m allo_usd.run.worker` that never imports the caller's
    `__main__` (a script need not guard itself), so a `before_render` hook must live in a module
    it can import: refuse one defined in `__main__`, at once and in one line."""
    fn = before_render
    while fn is not None and hasattr(fn, "func"):  # functools.partial, possibly nested
        fn = fn.func
    if fn is not None and getattr(fn, "__module__", None) == "__main__":
        raise AlloError(f"before_render={getattr(fn, '__qualname__', fn)!r} is defined in __main__, which local "
                        "render workers never import; move it into a module of its own and import it from there")


class WorkerProcess:
    """A local pool worker, started as its own program: `python -m allo_usd.run.worker FD`, with FD
    one end of a socket pair that both sides wrap in a multiprocessing Connection (pickled
    messages, as a Pipe). The child never imports the caller's `__main__` (multiprocessing's spawn
    does, so an unguarded script ran itself again in every worker). Its first message is the
    parent's sys.path and worker_main's arguments; the hook travels pickled and is unpickled after
    the worker's output went to its log. Offers the part of multiprocessing.Process the
    dispatcher uses: pid, sentinel (a pidfd, or None where there is none: the connection's EOF
    then tells of a death), is_alive, kill, join, exitcode."""

    def __init__(self, *, env: dict, parent_pid: int, cores: tuple[int, ...] | None, log: str | None, index: int,
                 before_render: Callable[[str], None] | None, out_dir: str | None):
        import pickle
        import socket
        import subprocess
        from multiprocessing.connection import Connection
        from multiprocessing.spawn import get_executable

        start = {"sys_path": list(sys.path), "env": env, "parent_pid": parent_pid, "cores": cores, "log": log,
                 "index": index, "out_dir": out_dir,  # a hook that does not pickle fails here, before a start
                 "before_render": None if before_render is None else pickle.dumps(before_render)}
        from allo_usd.core.interrupts import children_start_deaf

        ours, theirs = socket.socketpair()
        try:
            with children_start_deaf():  # a Ctrl-C while it starts waits, then is dropped: no traceback from it
                self.popen = subprocess.Popen(
                    [get_executable(), *subprocess._args_from_interpreter_flags(), "-m", "allo_usd.run.worker",
                     str(theirs.fileno())],
                    pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        self.conn = Connection(ours.detach())
        self.pid = self.popen.pid
        try:
            self.sentinel = os.pidfd_open(self.pid)
        except (AttributeError, OSError):
            self.sentinel = None
        try:
            self.conn.send(start)
        except OSError:
            pass  # it died at start-up: the dispatcher sees a dead worker

    @property
    def exitcode(self) -> int | None:
        return self.popen.poll()

    def is_alive(self) -> bool:
        return self.popen.poll() is None

    def kill(self) -> None:
        if self.popen.poll() is None:
            try:
                self.popen.kill()
            except ProcessLookupError:
                pass

    def join(self, timeout: float | None = None) -> None:
        import subprocess

        try:
            self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass

    def close(self) -> None:
        """The connection and the pidfd (after kill and join)."""
        self.conn.close()
        if self.sentinel is not None:
            os.close(self.sentinel)
            self.sentinel = None


def _child_main(fd: int) -> None:
    """The worker side of WorkerProcess: the parent's sys.path first (so that the modules it names,
    a hook's too, import here as there), then worker_main."""
    from multiprocessing.connection import Connection

    os.set_inheritable(fd, False)  # Blender's own subprocesses must not hold the parent's line open
    conn = Connection(fd)
    try:
        start = conn.recv()
    except (EOFError, OSError):
        return
    sys.path[:] = start.pop("sys_path")
    worker_main(conn, **start)


if __name__ == "__main__":  # `python -m allo_usd.run.worker FD` (WorkerProcess), started with SIGINT blocked
    from allo_usd.core.interrupts import ignore_sigint

    ignore_sigint()  # the parent decides what Ctrl-C means
    from allo_usd.run.worker import _child_main as _main  # the module under its own name: one copy of its state

    _main(int(sys.argv[1]))
