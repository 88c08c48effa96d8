"""Ctrl-C kept out of libraries that swallow it.

Some libraries catch a KeyboardInterrupt and carry on: pxr's module loader prints it as a warning
while it imports its C++ modules' wrappers; bpy's import (Blender's start-up) does the same and
leaves numpy half-loaded; trimesh wraps its optional imports (scipy, its path and voxel packages)
and several loader steps in `except BaseException`. A Ctrl-C landing there was lost: the command
ran on to exit 0. Their calls run inside `interrupt_held()`, which only notes a SIGINT and delivers
it once the call is over, so the command stops right after the call (docs/reliability/reliability.md, "Ctrl-C
is never swallowed").
"""

from __future__ import annotations

import importlib
import signal
import threading
from contextlib import contextmanager


class Held:
    """SIGINT noted, not acted on, from `start()` to `release()`: for a span that is not one block
    (the command line's own imports, cli.py). Only the main thread owns SIGINT: elsewhere, and where
    the handler was set outside Python (getsignal is None), nothing is held."""

    def __init__(self):
        self.caught: list[int] = []
        self.previous = None
        self.active = False

    def start(self) -> "Held":
        if threading.current_thread() is threading.main_thread():
            previous = signal.getsignal(signal.SIGINT)
            if previous is not None:
                self.previous, self.active = previous, True
                signal.signal(signal.SIGINT, lambda sig, frame: self.caught.append(sig))
        return self

    def release(self, deliver: bool = True) -> bool:
        """Put the previous handler back; True if a SIGINT came meanwhile, then (with `deliver`) handed
        to that handler at once (Python's default raises KeyboardInterrupt here; SIG_IGN drops it)."""
        if not self.active:
            return False
        self.active = False
        signal.signal(signal.SIGINT, self.previous)
        came = bool(self.caught)
        if came and deliver and self.previous is not signal.SIG_IGN:
            signal.raise_signal(signal.SIGINT)   # its Python handler runs before raise_signal returns
        return came


@contextmanager
def interrupt_held():
    """Hold SIGINT for the block (Held) and deliver it after the block to the handler that was there
    before (Python's default raises KeyboardInterrupt; `dataset`'s notes "stop after this scene").
    Nestable: an inner block hands its note to the outer one."""
    held = Held().start()
    try:
        yield
    finally:
        held.release()


@contextmanager
def children_start_deaf():
    """Processes started inside the block (a pool's workers) begin with SIGINT blocked, until they
    call `ignore_sigint`. A Ctrl-C at the terminal reaches every process of its group; a worker
    whose interpreter was still starting (site, its module's imports) printed the KeyboardInterrupt's
    traceback above the command's one line. A blocked signal is inherited through fork and exec and
    only waits: the worker drops it as it starts ignoring SIGINT (the parent decides what Ctrl-C
    means). In this thread SIGINT waits too until the block ends, then arrives as usual (as
    multiprocessing starts its resource tracker)."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def ignore_sigint() -> None:
    """In a worker started inside `children_start_deaf`: SIGINT ignored from now on, one that came
    while it started dropped (a pending signal whose action is to ignore it is discarded), and
    SIGINT unblocked (its own threads and children start as any others)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def import_held(name: str):
    """`importlib.import_module(name)` with SIGINT held (interrupt_held): a Ctrl-C during the import
    stops the command after it, instead of being swallowed and leaving the library half-loaded."""
    with interrupt_held():
        return importlib.import_module(name)
