"""Render many scene layers on a local pool of worker processes or a Dask cluster, so that a run
can be killed, crash a worker or fill the disk at any moment and a re-run finishes the rest.

The local pool is our own rather than concurrent.futures: a dead worker breaks a whole
ProcessPoolExecutor, while here the parent knows which task each worker held and retries that
one alone. How the two backends stay crash-safe is described in docs/guide/dispatch.md.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from allo_usd.core.errors import AlloError, DiskFullError
from allo_usd.core.files import RunLock, ensure_output_dir, read_whole_small
from allo_usd.core.threads import in_threads
from allo_usd.core.timefmt import seconds_text
from allo_usd.output.checksums import remember_sha256
from allo_usd.output.render_outputs import check_output_names
from allo_usd.run.options import JobOptions, RunOptions, check_timeout, run_options
from allo_usd.run.scheduler import connect_scheduler, load_distributed
from allo_usd.run.render_index import (MANIFEST, append_jsonl, append_rows, clean_stale, compact_manifest, prefetch,
                                       resume_check)
from allo_usd.run.worker import WorkerProcess, check_hook, render_task
from allo_usd.usd.safety import ENV_ROOTS, roots_cached, tree_roots
from allo_usd.usd.sniff import refusal
from allo_usd.usd.tree import POSE_DIR, SCENE_DIR, SKY_DIR, STAGE_DIR, SUPPORT_DIRS, TREE_PLAN

Hook = Callable[[str], None]

FAILED = "failed.jsonl"
# The default time limit of one scene (per attempt; dispatch(timeout=None), `render --timeout 0`):
# TIMEOUT_BASE_S + TIMEOUT_S_PER_PIXEL_SAMPLE * pixels * samples of the layer's own render settings.
# The base covers a worker's first Blender scene build, the denoiser and the writes; the per
# pixel-sample cost is ~3.5x what one Cycles thread took on this (loaded) machine (docs/reliability/reliability.md, section 5).
TIMEOUT_BASE_S = 120.0
TIMEOUT_S_PER_PIXEL_SAMPLE = 5e-5
TIMEOUT_FALLBACK_COST = 1920 * 1080 * 256  # a layer that names no resolution or samples: the paper's full render
STARTUP_S = 300.0  # more time for a worker that has not yet taken its task (still importing bpy)
LOCK = ".allo-dispatch.lock"
LOGS = "logs"


@dataclass
class Summary:
    rendered: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: list[dict] = field(default_factory=list)
    interrupted: bool = False
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)  # workers' one-line notices (a GPU-less `auto`), each once

    def __str__(self) -> str:
        s = (f"{len(self.rendered)} rendered, {len(self.skipped)} skipped (already done), "
             f"{len(self.failed)} failed in {self.seconds:.1f} s")
        return s + (" (interrupted)" if self.interrupted else "")


# ---------------------------------------------------------------- which layers

def _read_candidate(path: Path) -> tuple[bool, bytes | None]:
    """(refused, its bytes when it is a small regular file): the refusal check (never opened when
    refused), then one read of the whole layer, entered in file_sha256's cache for the resume check.
    Safe in a thread: the sniff that may need pxr happens in the caller's (_is_scene_layer)."""
    from allo_usd.usd.sniff import HEAD_BYTES, refusal

    if refusal(path):
        return True, None
    whole = read_whole_small(path, HEAD_BYTES)   # a scene layer is a few KB: read once, sniffed and checksummed
    if whole is None:
        return False, None
    data, st = whole
    remember_sha256(path, st, data)   # the resume check's checksum of the layer (checksums.file_sha256's cache)
    return False, data


def _is_scene_layer(path: Path, read: tuple[bool, bytes | None] | None = None) -> bool | None:
    """The one rule for what `render DIR` renders (allo_usd.usd.sniff.is_scene_layer: a layer whose
    own layer metadata holds customLayerData.allo.sceneId, or a layer over one); `read`: _read_candidate's answer."""
    from allo_usd.usd.sniff import is_scene_layer

    refused, data = _read_candidate(path) if read is None else read
    if refused:
        return None
    return is_scene_layer(path) if data is None else is_scene_layer(path, data)


def _scene_layers_under(root: Path) -> list[Path]:
    """Every scene layer (.usda, .usdc, .usd; _is_scene_layer) and scene package (.usdz: `allo-usd
    pack`) below `root`, recursively, skipping
    hidden directories. In an authored tree the support folders are not even searched: in a plan's
    tree (plan.toml beside scenes/) only scenes/ is; in a tree that holds stages/base.usda (the
    demo's OUT/layers) not its sky/, poses/, stages/, schema/ and hazards/ (shared sublayers, the
    base stage's assets, the schema plugin; a paper plan has ~39,000 pose layers not worth opening).
    A layer name that is not a regular file (a FIFO, a device) is kept unopened: the dispatcher
    records it as a failed layer."""
    from allo_usd.usd.safety import is_authored_tree
    from allo_usd.usd.sniff import LAYER_SUFFIXES

    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        if SCENE_DIR in dirnames and (here / TREE_PLAN).is_file():
            dirnames[:] = [SCENE_DIR]
        else:
            support = SUPPORT_DIRS if is_authored_tree(here) else ()
            dirnames[:] = [d for d in dirnames if not d.startswith(".") and d not in support]
        found += [here / f for f in filenames
                  if f.lower().endswith((*LAYER_SUFFIXES, ".usdz")) and not f.startswith(".")]
    # A name that is not a regular file is kept (never opened): dispatch records it in failed.jsonl.
    found.sort()
    reads = in_threads(_read_candidate, found)
    return [p for p, read in zip(found, reads) if _is_scene_layer(p, read) is not False]


def find_layers(source: str | Path | list) -> list[Path]:
    """A directory (its scene layers, recursively), a single layer, or a list of layers.
    Raises AlloError when there is nothing to render."""
    if isinstance(source, (list, tuple)):
        layers = [Path(p) for p in source]
        if not layers:
            raise AlloError("no layers to render (an empty list); pass scene layers, their directory or a plan")
    else:
        source = Path(source)
        if source.is_dir():
            with roots_cached():   # one allowed_roots per folder for the scan's refusal checks (the caller's block's)
                layers = _scene_layers_under(source)
            if not layers:
                raise AlloError(f"no scene layers under {source} (a scene layer is a .usda whose customLayerData "
                                f"holds allo.sceneId, or a layer whose subLayers reach one; {SKY_DIR}/, {POSE_DIR}/ and {STAGE_DIR}/ layers are shared "
                                f"sublayers, not scenes); author a plan there with `allo-usd author PLAN --out "
                                f"{source}`, or pass the directory that holds the scene layers")
        elif os.path.exists(source):
            layers = [source]
        else:
            raise AlloError(f"{source} is neither a layer nor a directory of layers; check the path")

    stems: dict[str, Path] = {}
    for p in layers:
        if p.stem in stems:
            raise AlloError(f"two layers share the name {p.stem!r} ({stems[p.stem]}, {p}); outputs are named "
                            "after the layer, so rename one")
        stems[p.stem] = p
    check_output_names(layers)  # no output name of one layer may be another's (allo_usd.output.render_outputs)
    for p in ([] if isinstance(source, Path) and source.is_dir() else layers):  # named by the caller
        why = refusal(p)
        if why:
            raise AlloError(why)
    return layers


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, as Blender's TBB sees it), not the machine's."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def core_sets(workers: int, threads: int, cores: list[int] | None = None) -> list[tuple[int, ...] | None]:
    """Disjoint cores for each worker, or None for all when `workers * threads` exceeds them."""
    if cores is None:
        cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if workers * threads > len(cores) or workers < 1 or threads < 1:
        return [None] * max(workers, 0)
    return [tuple(cores[i * threads:(i + 1) * threads]) for i in range(workers)]


class _Worker:
    """One local worker: its own `python -m allo_usd.run.worker` process (never the caller's
    `__main__` again, so an unguarded script works), and the task it holds."""

    def __init__(self, env: dict, cores: tuple[int, ...] | None = None, index: int = 0,
                 out_dir: Path | None = None, before_render: Hook | None = None):
        self.cores, self.index = cores, index
        self.log = None if out_dir is None else Path(out_dir) / LOGS / f"worker-{index}.log"
        self.proc = WorkerProcess(env=env, parent_pid=os.getpid(), cores=cores,
                                  log=None if self.log is None else str(self.log), index=index,
                                  before_render=before_render, out_dir=None if out_dir is None else str(out_dir))
        self.conn = self.proc.conn
        self.task: _Task | None = None
        self.sent: float = 0.0              # when the task was sent (monotonic)
        self.started: float | None = None   # when the worker said it took it

    def kill(self) -> None:
        self.proc.kill()
        self.proc.join(5)
        self.proc.close()  # its connection and pidfd


def time_limit(layer: Path, timeout: float | None = None) -> float:
    """Seconds one attempt at `layer` may take: `timeout` when given (> 0, check_timeout), else the
    default formula from the layer's pixels and samples (TIMEOUT_BASE_S + TIMEOUT_S_PER_PIXEL_SAMPLE * cost)."""
    timeout = check_timeout(timeout)
    if timeout is not None:
        return timeout
    from allo_usd.usd.sniff import render_cost

    cost = render_cost(layer)
    return TIMEOUT_BASE_S + TIMEOUT_S_PER_PIXEL_SAMPLE * (cost[0] * cost[1] if cost else TIMEOUT_FALLBACK_COST)


def _timeout_reason(limit: float) -> str:
    return (f"no result within the time limit of {seconds_text(limit)}; the worker was killed (raise the limit "
            "with `render --timeout SECONDS`, or check the layer's sublayers: a FIFO or a hung mount blocks a reader)")


@dataclass
class _Task:
    layer: Path
    attempts: int = 0
    reasons: list[str] = field(default_factory=list)
    limit: float | None = None  # seconds per attempt (time_limit), worked out when first sent

    @property
    def scene(self) -> str:
        return self.layer.stem


def _death_reason(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        hint = " (out of memory?)" if -code == signal.SIGKILL else ""
        return f"worker died with {name}{hint}"
    return f"worker exited with status {code}"


PROGRESS_INTERVAL_S = 30.0  # at most one progress line per this many seconds when stderr is not a terminal


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    return f"{h}h{rest // 60:02d}m" if h else f"{rest // 60}m{rest % 60:02d}s"


class _Run:
    """Book-keeping shared by both backends: manifest, failures, progress, retries.

    Progress: a tqdm bar on a terminal (`progress` None and stderr a TTY, or True); where stderr is
    not a terminal (a pipe, nohup, a CI log) and `progress` is None, one plain line at most every
    `interval` seconds (done, failed, rate, ETA; also while a long scene renders, so a log shows
    the run is alive) and a final line when the run ends (not before an error's or Ctrl-C's own
    one line); `progress` False: nothing."""

    def __init__(self, out_dir: Path, total: int, retries: int, progress: bool | None, summary: Summary,
                 interval: float = PROGRESS_INTERVAL_S):
        from tqdm.auto import tqdm

        self.out_dir, self.retries, self.summary = out_dir, retries, summary
        tty = sys.stderr.isatty()
        disable = (not tty) if progress is None else not progress
        self.bar = tqdm(total=total, unit="scene", desc="render", disable=disable, dynamic_ncols=True,
                        file=sys.stderr)
        self.lines = progress is None and not tty  # plain progress lines instead of the bar
        self.total, self.interval = total, interval
        self.t0 = self.last = time.monotonic()

    def line(self, final: bool = False) -> str:
        """One progress line: scenes done of all (rendered, already done, failed), time, rate, ETA."""
        s, elapsed = self.summary, time.monotonic() - self.t0
        worked = len(s.rendered) + len(s.failed)   # this run's scenes (the skipped ones cost nothing)
        text = (f"render: {worked + len(s.skipped)}/{self.total + len(s.skipped)} scenes done ({len(s.rendered)} "
                f"rendered, {len(s.skipped)} already done, {len(s.failed)} failed), {_duration(elapsed)}")
        if worked and elapsed > 0:
            rate = worked / elapsed
            text += f", {rate * 3600:.0f} scenes/h"
            if not final and worked < self.total:
                text += f", ETA {_duration((self.total - worked) / rate)}"
        elif not final and self.total:
            text += ", ETA after the first scene"
        return text

    def poll(self) -> None:
        """Print a progress line when `interval` seconds passed since the last (plain lines only)."""
        if self.lines and time.monotonic() - self.last >= self.interval:
            self.last = time.monotonic()
            print(self.line(), file=sys.stderr, flush=True)

    def ok(self, task: _Task, result: dict) -> None:
        row = {k: v for k, v in result.items() if k not in ("status", "device_notice")}
        self.note(result.get("device_notice"))
        row.update(attempts=task.attempts, finished=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        append_jsonl(self.out_dir / MANIFEST, row)
        self.summary.rendered.append(task.scene)
        self._tick()

    def fail(self, task: _Task, kind: str, reason: str) -> None:
        row = {"scene": task.scene, "layer": str(task.layer), "kind": kind, "reason": reason,
               "attempts": task.attempts, "reasons": task.reasons,
               "time": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        self.summary.failed.append(row)
        try:
            append_jsonl(self.out_dir / FAILED, row)
        finally:
            self._tick()

    def note(self, text: str | None) -> None:
        """Show a worker's notice once per run (every worker of an `auto` run without a GPU sends it)."""
        if text and text not in self.summary.notes:
            self.summary.notes.append(text)
            self.bar.write(f"note: {text}", file=sys.stderr)

    def retry_or_fail(self, task: _Task, kind: str, reason: str) -> bool:
        """True if the task should run again."""
        task.reasons.append(reason)
        if task.attempts <= self.retries:
            return True
        self.fail(task, kind, f"{reason} (after {task.attempts} attempts)")
        return False

    def settle(self, task: _Task, result: dict) -> bool:
        """Record a worker's result; True if the task should run again. A bad layer is never
        retried; a full disk stops the run (DiskFullError), and so does a device the worker's machine
        does not have (`--device gpu` without a GPU: DeviceError); other errors retry up to the limit."""
        if result["status"] == "ok":
            self.ok(task, result)
            return False
        if result["kind"] == "layer":
            self.fail(task, "layer", result["message"])
            return False
        if result["kind"] == "disk_full":
            try:
                self.fail(task, "disk_full", result["message"])
            except DiskFullError:
                pass  # failed.jsonl cannot grow on a full disk; the exception below says it all
            raise DiskFullError(result["message"])
        if result["kind"] == "device":
            from allo_usd.blender.device import DeviceError

            self.fail(task, "device", result["message"])
            raise DeviceError(result["message"])
        return self.retry_or_fail(task, "error", result["message"])

    def _tick(self) -> None:
        self.bar.set_postfix(ok=len(self.summary.rendered), failed=len(self.summary.failed), refresh=False)
        self.bar.update(1)
        self.poll()

    def close(self, last_line: bool = True) -> None:
        """Close the bar; print the final plain line when `last_line` (a run that ended: an error or
        Ctrl-C says what happened in its own one line)."""
        self.bar.close()
        if self.lines and last_line:
            print(self.line(final=True), file=sys.stderr, flush=True)


def _run_local(tasks: list[_Task], out_dir: Path, workers: int, job: JobOptions, run: _Run, env: dict,
               before_render: Hook | None = None, timeout: float | None = None) -> None:
    """The tasks on `workers` local worker processes, each rendering with `job` (its threads: the
    cores given to each worker)."""
    from multiprocessing.connection import wait

    check_hook(before_render)  # one line now, not a worker death per attempt
    pending = deque(tasks)
    n = min(workers, len(tasks))
    pool = [_Worker(env, cores, i, out_dir, before_render) for i, cores in enumerate(core_sets(n, job.threads))]

    def replace(i: int, w: _Worker) -> None:
        w.kill()
        clean_stale(out_dir, pid=w.proc.pid)  # its half-written temporaries, not its neighbours'
        # after the cleanup: a reused pid keeps its files
        pool[i] = _Worker(env, w.cores, w.index, out_dir, before_render)

    try:
        while pending or any(w.task for w in pool):
            for w in pool:
                if w.task is None and pending:
                    w.task = pending.popleft()
                    w.task.attempts += 1
                    if w.task.limit is None:
                        w.task.limit = time_limit(w.task.layer, timeout)
                    w.sent, w.started = time.monotonic(), None
                    w.conn.send({"layer": str(w.task.layer), "out_dir": str(out_dir), "options": job,
                                 "roots": env.get(ENV_ROOTS, "")})
            busy = [w for w in pool if w.task]
            wait([w.conn for w in busy] + [w.proc.sentinel for w in busy if w.proc.sentinel is not None], timeout=1.0)
            run.poll()
            for i, w in enumerate(pool):
                if w.task is None:
                    continue
                result, dead = None, False
                while result is None and not dead and w.conn.poll():
                    try:
                        msg = w.conn.recv()
                    except (EOFError, OSError):
                        dead = True
                        break
                    if msg.get("status") == "started":  # the worker took the task: its clock starts
                        w.started = time.monotonic()
                    else:
                        result = msg
                if result is None and not dead:
                    dead = not w.proc.is_alive()
                late = result is None and not dead and time.monotonic() > (
                    w.started + w.task.limit if w.started is not None else w.sent + STARTUP_S + w.task.limit)
                if result is None and not dead and not late:
                    continue
                task, w.task = w.task, None
                if late:
                    w.proc.kill()  # SIGKILL: a render stuck in C (a FIFO sublayer, a hung mount) ignores the rest
                    replace(i, w)
                    if run.retry_or_fail(task, "timeout", _timeout_reason(task.limit)):
                        pending.appendleft(task)
                elif dead:
                    w.proc.join(5)
                    reason = f"{_death_reason(w.proc.exitcode)}; its output is in {w.log}"
                    replace(i, w)
                    if run.retry_or_fail(task, "crash", reason):
                        pending.appendleft(task)
                elif run.settle(task, result):
                    pending.appendleft(task)
    finally:
        for w in pool:
            w.kill()


# ---------------------------------------------------------------- Dask

def _hold_one_death_per_attempt(client, hold: bool) -> bool:
    """Set the scheduler's allowed-failures to 0 while a run holds it (restore it when the last
    hold is released): a task whose worker dies then errs with KilledWorker at once, and our
    retry bound counts worker deaths. The function is pickled by value, so the scheduler needs
    no allo_usd. Returns False (with a warning) where the scheduler refuses to run it."""

    def swap(hold, dask_scheduler=None):
        holds = getattr(dask_scheduler, "_allo_dispatch_holds", 0)
        if hold:
            if holds == 0:
                dask_scheduler._allo_saved_allowed_failures = dask_scheduler.allowed_failures
            dask_scheduler.allowed_failures = 0
            dask_scheduler._allo_dispatch_holds = holds + 1
        else:
            dask_scheduler._allo_dispatch_holds = holds = max(holds - 1, 0)
            if holds == 0:
                dask_scheduler.allowed_failures = getattr(dask_scheduler, "_allo_saved_allowed_failures",
                                                          dask_scheduler.allowed_failures)
        return dask_scheduler.allowed_failures

    try:
        client.run_on_scheduler(swap, hold)
        return True
    except Exception as exc:  # noqa: BLE001 - a scheduler that forbids run_on_scheduler
        if hold:
            print(f"warning: could not set the Dask scheduler's allowed-failures to 0 ({type(exc).__name__}: {exc}); "
                  "each attempt may cost several worker deaths; start the scheduler with "
                  "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=0", file=sys.stderr)
        return False


def _run_dask(tasks: list[_Task], out_dir: Path, scheduler, job: JobOptions, run: _Run, env: dict,
              before_render: Hook | None = None, timeout: float | None = None) -> None:
    """The tasks on a Dask cluster, each rendering with `job`. Each attempt's clock starts when the
    scheduler first lists it as processing on a worker; past its limit the future is cancelled, the
    worker restarted (the stuck thread holds that process's bpy lock) and the attempt counted as a
    timeout."""
    load_distributed()
    from distributed import Client, as_completed

    client = scheduler if isinstance(scheduler, Client) else connect_scheduler(scheduler)
    roots = env.get(ENV_ROOTS, "")
    held = False
    try:
        held = _hold_one_death_per_attempt(client, True)
        futures: dict = {}
        started: dict = {}  # future key -> (monotonic time it was first seen processing, worker address)

        def submit(task: _Task) -> None:
            task.attempts += 1
            if task.limit is None:
                task.limit = time_limit(task.layer, timeout)
            fut = client.submit(render_task, str(task.layer), str(out_dir), job, roots, before_render,
                                pure=False, retries=0,
                                key=f"allo-render-{task.scene}-{task.attempts}-{os.getpid()}-{time.time_ns()}")
            futures[fut] = task
            completed.add(fut)

        completed = as_completed()
        for t in tasks:
            submit(t)
        try:
            while futures:
                done = completed.next_batch(block=False)
                if not done:
                    time.sleep(0.25)
                run.poll()
                for fut in done:
                    if fut not in futures:  # cancelled after its time ran out
                        continue
                    task = futures.pop(fut)
                    started.pop(fut.key, None)
                    try:
                        result = fut.result()
                    except Exception as exc:  # noqa: BLE001 - KilledWorker, a lost connection, ...
                        if run.retry_or_fail(task, "crash", f"{type(exc).__name__}: {exc}"):
                            submit(task)
                        continue
                    if run.settle(task, result):
                        submit(task)
                for fut, task in _overdue(client, futures, started):
                    del futures[fut]
                    worker = started.pop(fut.key)[1]
                    client.cancel([fut], force=True)
                    _restart_worker(client, worker)
                    if run.retry_or_fail(task, "timeout", _timeout_reason(task.limit)):
                        submit(task)
        finally:
            if futures:
                client.cancel(list(futures), force=True)
    finally:
        if held:
            _hold_one_death_per_attempt(client, False)
        if client is not scheduler:
            client.close()


def _overdue(client, futures: dict, started: dict) -> list:
    """Futures past their task's limit, counted from when each was first seen processing (noted in
    `started`); the scheduler's processing list is asked only while some future has no start yet."""
    now = time.monotonic()
    if any(f.key not in started for f in futures):
        try:
            processing = client.processing()
        except Exception:  # noqa: BLE001 - a scheduler that does not answer this time: ask again next second
            processing = {}
        where = {key: addr for addr, keys in processing.items() for key in keys}
        for f in futures:
            if f.key not in started and f.key in where:
                started[f.key] = (now, where[f.key])
    return [(f, t) for f, t in futures.items() if f.key in started and now - started[f.key][0] > t.limit]


def _restart_worker(client, address: str) -> None:
    """Restart the Dask worker at `address` (through its nanny); warn when that is not possible."""
    try:
        client.restart_workers([address], timeout=120, raise_for_error=True)
    except Exception as exc:  # noqa: BLE001 - no nanny, or the restart failed: the run goes on without it
        print(f"warning: could not restart the Dask worker {address} after a timeout ({type(exc).__name__}: {exc}); "
              "its stuck render keeps that process busy: restart it by hand", file=sys.stderr)


# ---------------------------------------------------------------- entry point

def dispatch(source, out_dir: str | Path, workers: int | None = None, scheduler=None, threads: int | None = None,
             retries: int = 2, progress: bool | None = None, extra_roots: tuple = (),
             before_render: Hook | None = None, timeout: float | None = None, trees: tuple = (),
             device: str = "auto", progress_interval: float = PROGRESS_INTERVAL_S, verify: bool = False, *,
             options: RunOptions | None = None) -> Summary:
    """Render every scene layer of `source` (directory, layer or list) into `out_dir`.

    The options of the run are `options` (a RunOptions, as the command line builds it) or, without
    it, the keywords workers, scheduler, threads, retries, timeout, device, verify and progress,
    which build one (allo_usd.run.options.run_options; an option given both ways is an AlloError).
    A run renders each layer's own passes: a RunOptions whose job sets passes or save_blend is
    refused; its job's force is not read (what is done is the resume rule's to say).

    `workers` local processes (default: the cores this process may use) with `threads` Cycles
    threads each (default: cores // workers), or the Dask cluster at `scheduler` (an address or
    a Client). Returns a Summary; raises DiskFullError when the disk fills (after stopping
    cleanly) and AlloError when `source` holds no scene layer. `before_render(scene_name)` is
    called in the worker before each render (a picklable function; tests inject faults with it).
    `timeout` is the limit of one attempt in seconds (None or 0: time_limit's formula per layer);
    an attempt past it is killed and retried like a crash, then recorded with kind "timeout".
    `trees` are authored trees (the OUT of `allo-usd author`) whose four authored folders the
    layers may also read, as `render --tree OUT` grants them (allo_usd.usd.safety.tree_roots: a
    LayerError for a folder that is not an authored tree); `extra_roots` are further directories.
    `device` is the Cycles device of every worker: 'auto' (a GPU when Cycles finds one, else the CPU
    with a notice, in Summary.notes and shown once), 'cpu' or 'gpu' (a machine without a GPU stops
    the run with DeviceError); see allo_usd.blender.device.
    `progress` None shows a bar on a terminal and, where stderr is not one (a pipe, nohup, a CI log),
    a plain line at most every `progress_interval` seconds and a final one; True the bar, False nothing.
    A scene is skipped when done by the rule every entry point shares (allo_usd.run.render_index.is_done,
    resume_check: a verified manifest row, else its render JSON); one another entry point rendered
    (render_layer, the demo) gets its manifest row from its JSON. A row's outputs are trusted on their
    recorded size, mtime and inode (the quick check: nothing is read); `verify` reads and checksums
    every output instead, re-renders what fails and records the stat of what passes (after a disk
    error, or a tree copied without its mtimes).
    """
    t0 = time.perf_counter()
    # checked as it is built: the device, workers >= 0, the timeout (NaN would turn the limit off)
    options = run_options(options, workers=workers, scheduler=scheduler, threads=threads, retries=retries,
                          progress=progress, timeout=timeout, device=device, verify=verify)
    for name in ("passes", "save_blend", "target_psnr", "time_limit"):
        if getattr(options.job, name) is not None:
            raise AlloError(f"options.job.{name}: a run renders each layer's own passes and target and saves no "
                            f"Blender scene; fix: render one layer with allo_usd.render_layer({name}=...), or leave "
                            "it None")
    job = options.job   # device None renders as auto (run.job.render_record)
    out_dir = Path(os.path.abspath(out_dir))  # workers elsewhere (Dask) must see the same paths
    extra_roots = (*extra_roots, *(r for t in trees for r in tree_roots(t, "trees=")))
    roots_seen: dict = {}   # allowed_roots, real paths and refusals of this decision (a worker checks afresh)
    with roots_cached(roots_seen):
        layers = [p if (a := os.path.abspath(p)) == str(p) else Path(a) for p in find_layers(source)]
    ensure_output_dir(out_dir, "output directory")
    # a layer's own folder (not its link target's: a link to /etc/passwd must not make /etc a root)
    roots = sorted({os.path.realpath(f) for f in {p.parent for p in layers}} | {str(Path(r).resolve()) for r in extra_roots})
    prior = os.environ.get(ENV_ROOTS, "")
    env = {ENV_ROOTS: os.pathsep.join([*roots, *([prior] if prior else [])])}
    summary = Summary()
    with RunLock(out_dir, LOCK, "render"):
        clean_stale(out_dir)
        (out_dir / FAILED).unlink(missing_ok=True)  # failures of this run only; earlier ones are retried
        done = compact_manifest(out_dir)
        tasks, unusable, caught_up = [], [], []
        with roots_cached(roots_seen):
            prefetch(layers, done)   # the shared inputs' checksums, several reads in flight
            for layer in layers:
                why = refusal(layer)
                if why:  # found by the scan: never opened, recorded as failed
                    unusable.append((_Task(layer), why))
                    continue
                # is_done's rule: the manifest row's quick check (every byte with `verify`), else the render's JSON
                finished, row = resume_check(layer, out_dir, done.get(layer.stem), options.verify)
                if finished:
                    summary.skipped.append(layer.stem)
                    if row is not None:  # the index catches up: a scene another entry point rendered, or new stat
                        caught_up.append(row if "finished" in row else
                                         {**row, "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
                else:
                    tasks.append(_Task(layer))
        append_rows(out_dir / MANIFEST, caught_up)  # one write and one fsync, before anything renders
        run = _Run(out_dir, len(tasks) + len(unusable), options.retries, options.progress, summary, progress_interval)
        ended = False  # the run's last progress line only for a run that ended (not for an error's one line)
        for task, why in unusable:
            run.fail(task, "layer", why)
        try:
            if tasks and options.scheduler is not None:
                _run_dask(tasks, out_dir, options.scheduler, job, run, env, before_render, options.timeout)
            elif tasks:
                cores = usable_cores()
                n = max(1, options.workers or cores)
                job = dataclasses.replace(job, threads=job.threads or max(1, cores // n))
                _run_local(tasks, out_dir, n, job, run, env, before_render, options.timeout)
            ended = True
        except KeyboardInterrupt:
            summary.interrupted = True
        finally:
            run.close(last_line=ended)
            if tasks:   # temporaries of writers killed during this run (none ran: none to clean)
                clean_stale(out_dir)
            try:
                if tasks or caught_up:   # rows were appended (a resume with nothing to do leaves it as it was)
                    compact_manifest(out_dir)
            except DiskFullError:
                pass  # the appended manifest is valid as it is; compaction waits for the next run
    summary.seconds = time.perf_counter() - t0
    return summary


def aimed_plan(plan, job: JobOptions):
    """`plan` with the job's target and time limit (`render PLAN --target-psnr --time-limit`) in its quality,
    so its layers are authored with them; the pair checked as the plan's own would be."""
    if job.target_psnr is None and job.time_limit is None:
        return plan
    from allo_usd.run.job import aimed_target

    target_psnr, time_limit = aimed_target(plan.quality, job)   # the plan's Quality carries the same two fields
    update = {"target_psnr": target_psnr, "time_limit": time_limit}
    return plan.model_copy(update={"quality": plan.quality.model_copy(update=update)})


def author_and_dispatch(plan_path: Path, out_dir: Path, options: RunOptions | None = None, **kwargs) -> Summary:
    """A plan file: author its layers into OUT/layers (with the job's passes, target and time limit
    instead of the plan's quality.passes, target_psnr and time_limit, when set), then render them into OUT/renders on the job's device (None, as when
    `options` is left out: the plan's render.device). `kwargs` are dispatch's other keywords
    (before_render, extra_roots, progress_interval)."""
    from allo_usd.plan.io import load_plan
    from allo_usd.run.author import author_plan

    options = RunOptions(job=JobOptions(device=None)) if options is None else options
    layers_dir = Path(out_dir) / "layers"
    plan = load_plan(Path(plan_path))
    passes = options.job.passes
    if passes is not None:
        plan = plan.model_copy(update={"quality": plan.quality.model_copy(update={"passes": list(passes)})})
    plan = aimed_plan(plan, options.job)
    job = dataclasses.replace(options.job, device=options.job.device or plan.render.device, passes=None,
                              target_psnr=None, time_limit=None)
    layers = author_plan(plan, layers_dir)
    # the tree's authored folders, not all of OUT (OUT/renders and whatever else lies there)
    return dispatch(list(layers) if layers else layers_dir, Path(out_dir) / "renders", trees=(layers_dir,),
                    options=dataclasses.replace(options, job=job), **kwargs)


__all__ = ["Summary", "dispatch", "author_and_dispatch", "find_layers", "core_sets", "usable_cores"]
