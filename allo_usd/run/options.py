"""The render options, as two frozen values built once and read where they are used.

`JobOptions` is how one scene is rendered: device, Cycles threads, passes, force and save_blend.
`run.job.render_record` reads it, and the dispatcher pickles it to every worker with each task
(`run.worker.render_task`; local workers and Dask workers alike), so it holds plain fields only.

`RunOptions` is how a run of many scenes goes: workers, scheduler, retries, timeout, verify and
progress, around the `JobOptions` of its scenes (`job`). Only the dispatcher's own process reads
it (`run.dispatch.dispatch`), so `scheduler` may also be a distributed Client or cluster object.

Two values, not one, because the two halves go to different places: what a worker needs travels
with every task and nothing else does (a Client does not pickle, and a worker has no use for
retries or a progress bar); and a single layer rendered in the caller's process
(`allo-usd render LAYER`, `allo_usd.render_layer`) needs only the job's half.

The command line builds one RunOptions from its options (`RunOptions.from_cli`, with the command
line's messages); the API builds them from its keyword arguments (`run_options`, `JobOptions(...)`).
Each value checks itself when built: the device (allo_usd.blender.device.check_device), the
passes (canonicalised, allo_usd.plan.settings.canonical_passes), the number of workers and the
time limit (check_timeout).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path

from allo_usd.core.errors import AlloError


def check_timeout(timeout, name: str = "timeout=") -> float | None:
    """`timeout` as seconds (finite and > 0), or None for time_limit's formula (None, or 0 from the
    API); anything else (NaN, which compares false with every limit and so turned the limit off, an
    infinity, a negative number, a bool or a string) is an AlloError that prints what was given."""
    number = isinstance(timeout, numbers.Real) and not isinstance(timeout, bool)
    if timeout is None or (number and timeout == 0):
        return None
    if not number or not (math.isfinite(timeout) and timeout > 0):
        raise AlloError(f"{name}{timeout!r} is not a number of seconds > 0; fix: give the seconds one attempt at a "
                        "scene may take, or None for the limit from each layer's size")
    return float(timeout)


@dataclass(frozen=True)
class JobOptions:
    """How one scene is rendered (run.job.render_record).

    `device`: 'auto', 'cpu' or 'gpu' (checked and lower-cased; allo_usd.blender.device), or None:
    not chosen, which renders as 'auto' except for a plan, whose render.device then decides
    (run.dispatch.author_and_dispatch). `threads` overrides the layer's allo:render:threads for this
    process (None: the layer's). `passes` replaces the passes the layer orders (canonicalised to
    PASSES order; None: the layer's). `force` renders a scene even when it is done and lets
    `save_blend` replace an existing file; `save_blend` also saves the built Blender scene there.
    `target_psnr` and `time_limit` replace the layer's allo:render:targetPsnr / timeLimit for this run
    (None: the layer's; target 0: fixed samples): the JSON records both targets, and a render to
    another target than its layer's is never skipped as done. `estimate`: a fixed-sample render also
    estimates its own error (one more render of the same settings; its image is unchanged); a finished
    render without an estimate is then not done.
    """
    device: str | None = "auto"
    threads: int | None = None
    passes: tuple[str, ...] | None = None
    force: bool = False
    save_blend: Path | None = None
    target_psnr: float | None = None
    time_limit: float | None = None
    estimate: bool = False

    def __post_init__(self):
        from allo_usd.plan.settings import target_problem

        # each on its own: a time limit alone may stop the layer's own target (the pair is checked at the render)
        problem = ((self.target_psnr is not None and target_problem(self.target_psnr, 0.0))
                   or (self.time_limit is not None and target_problem(1.0, self.time_limit)))
        if problem:
            raise AlloError(problem)
        if self.passes is not None:
            from allo_usd.plan.settings import canonical_passes

            object.__setattr__(self, "passes", canonical_passes(self.passes))
        if self.device is not None:
            from allo_usd.blender.device import check_device

            object.__setattr__(self, "device", check_device(self.device))


@dataclass(frozen=True)
class RunOptions:
    """How a run of many scenes goes (run.dispatch.dispatch), and its scenes' `job`.

    `workers` local worker processes (None or 0: one per usable core), or the Dask cluster at
    `scheduler` (an address; from the API also a distributed Client or cluster). `retries` more
    attempts at a scene whose worker crashed or timed out. `timeout` seconds per attempt (None or 0:
    each layer's limit from its size; checked by check_timeout, 0 becomes None). `verify` checksums
    every finished output instead of trusting its manifest row's stat. `progress` None shows a bar
    on a terminal and plain lines elsewhere, True the bar, False nothing. A run renders each layer's
    own passes, and what it skips is decided by the resume rule, not by `job.force`.
    """
    job: JobOptions = field(default_factory=JobOptions)
    workers: int | None = None
    scheduler: object = None
    retries: int = 2
    timeout: float | None = None
    verify: bool = False
    progress: bool | None = None

    def __post_init__(self):
        if self.workers is not None and self.workers < 0:
            raise AlloError(f"workers={self.workers}: pass a number of worker processes >= 1 (or 0 for one per core)")
        object.__setattr__(self, "timeout", check_timeout(self.timeout))

    @classmethod
    def from_cli(cls, *, force: bool = False, workers: int = 0, scheduler: str | None = None, threads: int = 0,
                 retries: int = 2, timeout: float | None = None, verify: bool = False, save_blend: Path | None = None,
                 device: str | None = None, passes: str | None = None, target_psnr: float | None = None,
                 time_limit: float | None = None, estimate: bool = False) -> "RunOptions":
        """The value `allo-usd render` builds from its options, with the command line's messages:
        `passes` as given ("rgb,mask"), `device` None when --device was left out (a plan's
        render.device decides), 0 for the default of --workers and --threads. Checks, in this order:
        the passes, the device, negative numbers (the command line's parsers refuse them first), a
        malformed --scheduler address (one line before anything starts; an unreachable one is the
        dispatcher's)."""
        job = JobOptions(device=device, threads=threads or None, force=force, save_blend=save_blend,
                         passes=None if passes is None else [p.strip() for p in passes.split(",") if p.strip()],
                         target_psnr=target_psnr, time_limit=time_limit, estimate=bool(estimate))
        for name, value in (("--workers", workers), ("--threads", threads), ("--retries", retries),
                            ("--timeout", timeout or 0)):
            if value < 0:
                raise AlloError(f"{name} {value:g} is negative; pass 0 for the default or a positive number")
        if scheduler is not None:
            from allo_usd.run.scheduler import SCHEDULER_FIX, scheduler_problem

            why = scheduler_problem(scheduler)
            if why:
                raise AlloError(f"--scheduler {why}; {SCHEDULER_FIX}")
        return cls(job=job, workers=workers or None, scheduler=scheduler, retries=retries, timeout=timeout or None,
                   verify=verify)


# dispatch's keyword arguments that are options, with their defaults (a keyword -> RunOptions or JobOptions field)
RUN_KEYWORDS = {"workers": None, "scheduler": None, "retries": 2, "timeout": None, "verify": False, "progress": None}
JOB_KEYWORDS = {"threads": None, "device": "auto"}


def run_options(options: RunOptions | None = None, **keywords) -> RunOptions:
    """`options`, or the RunOptions that dispatch's option keywords (RUN_KEYWORDS, JOB_KEYWORDS) spell;
    an option given both ways is an AlloError."""
    if options is None:
        job = JobOptions(**{k: keywords.pop(k) for k in JOB_KEYWORDS if k in keywords})
        return RunOptions(job=job, **keywords)
    defaults = {**RUN_KEYWORDS, **JOB_KEYWORDS}
    beside = [k for k, v in keywords.items() if v is not defaults[k] and v != defaults[k]]
    if beside:
        raise AlloError(f"{', '.join(f'{k}=' for k in beside)} given beside options=; fix: set "
                        f"{'it' if len(beside) == 1 else 'them'} in the RunOptions (or its job) instead")
    return options


__all__ = ["JobOptions", "RunOptions", "check_timeout", "run_options"]
