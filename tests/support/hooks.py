"""Faults the dispatcher tests inject into render workers through `dispatch(..., before_render=...)`.

Each hook is called in the worker process with the scene's name before it renders. They are
module-level (picklable by reference; spawned and Dask workers inherit sys.path, so `hooks`
imports there too) and take their settings through functools.partial.
"""

from __future__ import annotations

import errno
import os
import signal
import time
from pathlib import Path

_WRITER = None  # allo_usd.run.job's own EXR writer, kept while a hook replaces it


def crash_on(scenes, scene: str) -> None:
    """Die with SIGSEGV, as a crashing Blender would, before rendering one of `scenes`."""
    if scene in scenes:
        os.kill(os.getpid(), signal.SIGSEGV)


def crash_after(scenes, out_dir: Path, others, scene: str, timeout: float = 300.0) -> None:
    """Like crash_on, but only once every scene in `others` is in out_dir's manifest (its result
    reached the run), so the death cannot take a task of theirs with it."""
    if scene not in scenes:
        return
    from allo_usd.run.render_index import load_manifest

    deadline = time.monotonic() + timeout
    while not set(others) <= set(load_manifest(out_dir)) and time.monotonic() < deadline:
        time.sleep(0.05)
    os.kill(os.getpid(), signal.SIGSEGV)


def _set_exr_writer(writer) -> None:
    """Put `writer` in place of allo_usd.run.job.write_rgb_exr (None: the original back)."""
    global _WRITER
    from allo_usd.run import job

    if _WRITER is None:
        _WRITER = job.write_rgb_exr
    job.write_rgb_exr = writer or _WRITER


def full_disk_on(scenes, scene: str) -> None:
    """While one of `scenes` is written, its EXR hits ENOSPC half-way (a temporary is left)."""
    from allo_usd.core.files import atomic_path

    def full_disk(path, *args, **kwargs):
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"partial EXR")
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))

    _set_exr_writer(full_disk if scene in scenes else None)


def _hang(markers: Path, name: str) -> None:
    """Say where this worker stopped (a file the test waits for), then wait to be killed."""
    (Path(markers) / name).write_text(str(os.getpid()))
    while True:
        time.sleep(60)


def pause_at(markers: Path, before, mid_write, scene: str) -> None:
    """Stop for good at a well-defined point, for a test to SIGKILL the run there: before
    rendering a scene in `before`, or, for a scene in `mid_write`, after its PNG is complete and
    while its EXR's temporary is half written. Marker files `markers/SCENE.before` and
    `markers/SCENE.mid_write` say the worker got there."""
    from allo_usd.core.files import atomic_path

    if scene in before:
        _hang(markers, f"{scene}.before")

    def half_written(path, *args, **kwargs):
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"half an EXR")
            _hang(markers, f"{scene}.mid_write")

    _set_exr_writer(half_written if scene in mid_write else None)
