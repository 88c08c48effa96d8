"""The render options as values (allo_usd.run.options): each checks itself as it is built, with the
messages the command line and the API print; both pickle as the workers receive them; and the
`allo-usd render` options and the fields agree, each exception named with its reason."""

from __future__ import annotations

import dataclasses
import inspect
import math
import pickle
import re
from pathlib import Path

import pytest

from allo_usd import cli
from allo_usd.blender.device import DeviceError
from allo_usd.core.errors import AlloError
from allo_usd.run.options import JobOptions, RunOptions, run_options

# `allo-usd render` parameters that are no option of a render: what to render, where, and the trees
# whose folders the sandbox grants (cli.render wraps the whole command in safety.trees_granted)
CLI_ONLY = {"source": "the input", "out": "the output directory", "trees": "granted by safety.trees_granted"}
# fields with no `allo-usd render` option: the nesting, and the progress display the command line
# leaves to dispatch (a bar on a terminal, plain lines where stderr is not one)
FIELD_ONLY = {"job": "RunOptions' JobOptions", "progress": "None: chosen from stderr"}


def _fields(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def test_every_render_option_is_a_field_and_every_field_an_option_or_named():
    options = set(inspect.signature(cli.render).parameters) - set(CLI_ONLY)
    fields = (_fields(RunOptions) | _fields(JobOptions)) - set(FIELD_ONLY)
    assert options == fields
    assert set(inspect.signature(RunOptions.from_cli).parameters) == options   # the CLI builds it from all of them
    assert set(FIELD_ONLY) <= _fields(RunOptions) | _fields(JobOptions)


def test_the_job_checks_its_device_and_puts_its_passes_in_order():
    job = JobOptions(device=" CPU", passes=["mask", "rgb"])
    assert (job.device, job.passes) == ("cpu", ("rgb", "mask"))
    assert JobOptions(device=None).device is None   # not chosen: auto, or a plan's render.device
    with pytest.raises(DeviceError, match=r"^--device 'tpu' is not a render device; fix: use one of auto, cpu, gpu$"):
        JobOptions(device="tpu")
    with pytest.raises(AlloError, match=r"unknown render pass\(es\) 'zdepth'; choose from rgb, exr, mask"):
        JobOptions(passes=["rgb", "zdepth"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        job.force = True


def test_the_run_checks_workers_and_its_time_limit():
    with pytest.raises(AlloError, match=r"^workers=-1: pass a number of worker processes >= 1"):
        RunOptions(workers=-1)
    for bad in (math.nan, math.inf, -1.0, "10", True):
        with pytest.raises(AlloError, match="not a number of seconds > 0"):
            RunOptions(timeout=bad)
    assert RunOptions(timeout=0).timeout is None and RunOptions(timeout=5).timeout == 5.0


@pytest.mark.parametrize("name", ["workers", "threads", "retries", "timeout"])
def test_the_command_lines_value_says_a_negative_number_in_its_words(name):
    with pytest.raises(AlloError, match=rf"^--{name} -2 is negative; pass 0 for the default or a positive number$"):
        RunOptions.from_cli(**{name: -2})


def test_the_command_lines_value_reads_zero_as_the_default_and_splits_the_passes():
    options = RunOptions.from_cli(workers=0, threads=0, timeout=None, passes=" mask, rgb,", force=True)
    assert options == RunOptions(job=JobOptions(device=None, passes=("rgb", "mask"), force=True))
    assert options.workers is None and options.job.threads is None and options.timeout is None


def test_both_values_pickle_as_the_workers_receive_them(tmp_path):
    job = JobOptions(device="gpu", threads=3, passes=("rgb", "depth"), force=True, save_blend=tmp_path / "s.blend")
    run = RunOptions(job=job, workers=2, scheduler="tcp://host:8786", retries=0, timeout=60, verify=True)
    for value in (job, run, JobOptions(), RunOptions()):
        again = pickle.loads(pickle.dumps(value))
        assert again == value and type(again) is type(value)
    assert isinstance(pickle.loads(pickle.dumps(job)).save_blend, Path)


def test_the_api_keywords_build_the_value_and_none_goes_beside_it():
    built = run_options(workers=2, threads=1, device="cpu", retries=0, timeout=None, verify=True, progress=False)
    assert built == RunOptions(job=JobOptions(device="cpu", threads=1), workers=2, retries=0, verify=True,
                               progress=False)
    assert run_options(built, workers=None, retries=2, device="auto") is built   # the defaults: nothing beside
    with pytest.raises(AlloError, match=r"^workers=, device= given beside options="):
        run_options(built, workers=3, device="gpu")


def test_a_run_refuses_a_job_that_only_one_layer_can_do(tmp_path):
    from allo_usd.run.dispatch import dispatch

    for job in (JobOptions(passes=("mask",)), JobOptions(save_blend=tmp_path / "x.blend"), JobOptions(target_psnr=40),
                JobOptions(time_limit=5)):
        with pytest.raises(AlloError, match=r"^options\.job\.(passes|save_blend|target_psnr|time_limit): a run renders"):
            dispatch(tmp_path, tmp_path / "out", options=RunOptions(job=job))
    with pytest.raises(AlloError, match="beside options="):
        dispatch(tmp_path, tmp_path / "out", workers=2, options=RunOptions())
    assert not (tmp_path / "out").exists()


def test_the_worker_and_the_job_take_the_one_value():
    from allo_usd.run.job import render_record
    from allo_usd.run.worker import render_task

    assert list(inspect.signature(render_task).parameters) == ["layer", "out_dir", "options", "roots",
                                                               "before_render"]
    assert list(inspect.signature(render_record).parameters) == ["layer", "out_dir", "options", "workdir",
                                                                 "session", "index"]


@pytest.mark.parametrize("given,needle", [
    (dict(target_psnr=math.nan), "target_psnr nan is not a PSNR in dB"),
    (dict(target_psnr=-1), "target_psnr -1 is not a PSNR in dB"), (dict(target_psnr=101), "target_psnr 101 is not"),
    (dict(target_psnr="40"), "target_psnr '40' is not"), (dict(target_psnr=True), "target_psnr True is not"),
    (dict(time_limit=math.inf), "time_limit inf is not a number of seconds"),
    (dict(time_limit=-2), "time_limit -2 is not"), (dict(time_limit=2e6), "time_limit 2e+06 is not"),
])
def test_the_job_checks_its_target_and_time_limit_each_on_its_own(given, needle):
    with pytest.raises(AlloError, match="^" + re.escape(needle)) as info:
        JobOptions(**given)
    assert "fix:" in str(info.value) and "\n" not in str(info.value)
    # accepted: a target alone, 0 (fixed samples), and a time limit alone (it may stop the layer's own target)
    assert JobOptions(target_psnr=40).target_psnr == 40 and JobOptions(target_psnr=0).target_psnr == 0
    assert JobOptions(time_limit=60).time_limit == 60
