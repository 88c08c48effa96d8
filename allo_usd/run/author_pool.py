"""Where authoring runs: in this process (one worker), or on a spawn-based process pool whose
workers each build their own `AuthorContext` once. Both take tasks alike (`submit`, `stop`,
`in_flight`, `chunks`), so the driver (allo_usd.run.author.drive) does not know which it has.
"""

from __future__ import annotations

import os
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path

from allo_usd.core.interrupts import children_start_deaf, ignore_sigint
from allo_usd.plan.model import Plan
from allo_usd.run.samples import AuthorContext

CHUNK_SAMPLES = 48         # planned anomaly placements per pool task
CHUNK_NORMAL = 256         # normal camera samples per pool task
CHUNK_RESERVE = 1          # reserve groups per pool task (each walk decides as soon as one is back)

_ctx = None  # the per-process authoring context (set by _init)


def _init(plan_json: str, out_dir: str, sky, stop) -> None:
    global _ctx
    ignore_sigint()  # started with SIGINT blocked (_Pool.submit); the parent handles Ctrl-C and tells us through `stop`
    _ctx = AuthorContext(Plan.model_validate_json(plan_json), Path(out_dir), sky, stop)


def _in_worker(fn, *args):
    return fn(_ctx, *args)


class InlineRunner:
    """Runs each task at once in this process (one worker)."""

    in_flight = 1
    chunks = (1, 1, 1)  # (planned placements, normal samples, reserve groups) per task

    def __init__(self, ctx: AuthorContext):
        self.ctx = ctx

    def submit(self, fn, *args) -> Future:
        f = Future()
        f.set_result(fn(self.ctx, *args))
        return f

    def stop(self) -> None:
        pass


class _Pool:
    """A spawn-based process pool; each worker builds its own `AuthorContext` once."""

    chunks = (CHUNK_SAMPLES, CHUNK_NORMAL, CHUNK_RESERVE)

    def __init__(self, pool: ProcessPoolExecutor, stop, workers: int):
        self.pool, self._stop, self.in_flight = pool, stop, 2 * workers

    def submit(self, fn, *args) -> Future:
        with children_start_deaf():  # the pool starts its workers here: a Ctrl-C meanwhile is the parent's alone
            return self.pool.submit(_in_worker, fn, *args)

    def stop(self) -> None:
        self._stop.set()


@contextmanager
def open_runner(ctx: AuthorContext, plan: Plan, out_dir: Path, sky, workers: int):
    """The runner of a run: an InlineRunner over `ctx` for one worker, else a pool of `workers`
    processes, stopped at once (not after their queued chunks) when the block ends in an error or Ctrl-C."""
    if workers <= 1:
        yield InlineRunner(ctx)
        return
    import multiprocessing as mp

    mpctx = mp.get_context("spawn")
    stop = mpctx.Event()
    with _single_threaded_numerics(), _caller_main_hidden(), \
            ProcessPoolExecutor(workers, mp_context=mpctx, initializer=_init,
                                initargs=(plan.model_dump_json(), str(out_dir), sky, stop)) as pool:
        try:
            yield _Pool(pool, stop, workers)
        except BaseException:  # a failed task or Ctrl-C: stop the workers now, not after their queued chunks
            stop.set()
            pool.shutdown(wait=True, cancel_futures=True)
            raise


_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextmanager
def _caller_main_hidden():
    """While the pool lives, spawned workers do not run the caller's script. multiprocessing's spawn
    re-imports `__main__` in every child (from its __spec__ name or its __file__), so a script without
    an `if __name__ == "__main__":` guard would author again in each worker, recursively. The workers
    need nothing from it (their functions and initializer live in this package), so the two
    attributes spawn reads are hidden while workers start, and put back after."""
    import sys

    main = sys.modules.get("__main__")
    saved = {k: main.__dict__[k] for k in ("__spec__", "__file__") if main is not None and k in main.__dict__}
    if main is not None:
        main.__dict__.pop("__file__", None)
        if "__spec__" in saved:
            main.__spec__ = None
    try:
        yield
    finally:
        if main is not None:
            main.__dict__.update(saved)


@contextmanager
def _single_threaded_numerics():
    """One BLAS thread per worker process. Each worker multiplies large ray arrays; with BLAS's
    default of one thread per core, 2 workers on 2 cores oversubscribe and the paper plan takes
    146 s instead of 73 s (measured). Spawned workers inherit the environment when they start,
    which happens inside this block; a value the user set is kept."""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    for k in _THREAD_VARS:
        os.environ.setdefault(k, "1")
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
