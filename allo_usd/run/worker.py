"""The render worker: what runs inside each worker process (local pool or Dask), and the only
module outside `blender/` that imports bpy, once per process, to keep it warm."""

from __future__ import annotations

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
from allo_usd.core.files import DISK_FULL_ERRNOS, sha256_file
from allo_usd.run.manifest import WORKDIR, output_paths
from allo_usd.usd.safety import ENV_ROOTS


# ---------------------------------------------------------------- the task (runs in a worker)

_BPY_LOCK = threading.Lock()  # bpy is one global state and not thread-safe: one render per process at a time
_SESSION = None  # this process's warm Blender session (allo_usd.blender.session), made by its first task


def render_task(layer: str, out_dir: str, threads: int | None = None, roots: str = "",
                before_render: Callable[[str], None] | None = None) -> dict:
    """Render one layer (forced: the parent decided it is not done) and checksum its outputs.

    Never raises for a bad layer or a full disk: returns {"status": "error", "kind": ...} so
    the parent can tell them apart from a crash, which it sees as a dead worker instead. Safe to
    call from several threads of one process (a Dask worker with --nthreads > 1): they take turns.
    `before_render(scene_name)`, if given, is called first, inside the lock (tests inject faults
    with it; it must be picklable: a module-level function or a partial of one).
    """
    with _BPY_LOCK:
        return _render_task(layer, out_dir, threads, roots, before_render)


def _render_task(layer: str, out_dir: str, threads: int | None, roots: str,
                 before_render: Callable[[str], None] | None) -> dict:
    global _SESSION
    _fix_bpy_path()
    from allo_usd.run.job import render_layer

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
        meta = render_layer(layer_p, out_p, force=True, threads=threads, workdir=render_workdir(out_p), session=_SESSION)
    except DiskFullError as exc:
        return error("disk_full", exc, prefix=False)
    except RenderFailedError as exc:  # not the layer's fault: retried
        return error("error", exc)
    except AlloError as exc:
        return error("layer", exc)
    except OSError as exc:
        if exc.errno in DISK_FULL_ERRNOS:
            return error("disk_full", DiskFullError(f"no space left on the device holding {out_p} ({exc}); free "
                                                    "space and re-run"), prefix=False)
        return error("error", exc)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which retries it
        return error("error", exc)
    files = {p.name: sha256_file(p) for p in output_paths(layer_p, out_p).values()}
    return {"status": "ok", "scene": scene, "layer": str(layer_p.resolve()), "layer_sha256": meta["layer_sha256"],
            "identity": meta["identity"],  # what the render read and the versions (allo_usd.run.manifest)
            "scene_id": (meta.get("scene") or {}).get("provenance", {}).get("sceneId", scene),
            "files": files, "render_seconds": meta["render_seconds"], "worker": f"{os.uname().nodename}:{os.getpid()}",
            "full_build": bool(_SESSION.last.full_build),
            "cores": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None}


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
    `log` for the block, then restore them (the single-layer `allo-usd render LAYER`)."""
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


def worker_main(conn, env: dict, parent_pid: int, cores: tuple[int, ...] | None = None,
                log: str | None = None, index: int = 0, before_render: Callable[[str], None] | None = None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C means
    _die_with_parent(parent_pid)
    if log:
        _send_output_to(Path(log))
        print(f"--- allo-usd render worker {index}, pid {os.getpid()}, started "
              f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')} ---", flush=True)
    if cores:  # before bpy: TBB sizes its pool from the affinity mask when it starts
        os.sched_setaffinity(0, cores)
    os.environ.update(env)
    _fix_bpy_path()
    import bpy  # noqa: F401 - warm: import once per worker, not per scene (its Session comes with the first task)

    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        conn.send(render_task(**msg, before_render=before_render))
