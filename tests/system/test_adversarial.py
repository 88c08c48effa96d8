"""The adversarial corpus (tests/support/adversarial_corpus.py) through the real tool.

Hostile, malformed and extreme layers go through the local pool beside good ones, as
`allo-usd render DIR` run in a subprocess (under strace when it can attach): every bad layer ends
as one line in failed.jsonl (a layer error, or the per-task timeout), nothing hangs, no process
opens a file outside the roots, the canary the outside files hold shows up nowhere, and every good
scene's files are byte-identical to a clean run. Hostile plans, render records and command lines
end as one line on stderr with exit status 2. Each subprocess runs under an address-space limit
(a /dev/zero read must not take the machine down) and a wall-clock bound (a hang fails the test).
All case failures are collected and reported together, one line per case.
"""

from __future__ import annotations

import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from allo_usd.core.errors import AlloError
from allo_usd.run.dispatch import FAILED, dispatch
from allo_usd.output.render_outputs import output_paths
from allo_usd.run.render_index import is_done, load_manifest
from allo_usd.usd.safety import ENV_ROOTS

from tests.support.helpers import make_spec

pytestmark = pytest.mark.render

TASK_TIMEOUT = 20          # seconds a worker may spend on one scene (dispatch(timeout=...), --timeout)
RUN_TIMEOUT = 150          # seconds a whole `allo-usd render DIR` run may take before it counts as hung
CLI_TIMEOUT = 30           # seconds a plan, dataset or command-line case may take
MEMORY_LIMIT = 8 << 30     # address space of every subprocess (bpy workers need ~2-3 GB of it)
CLI = [sys.executable, "-c", "from allo_usd.cli import main; main()"]
IMAGE_SUFFIXES = (".png", ".exr")


from tests.support import adversarial_corpus as C  # noqa: E402


# ---------------------------------------------------------------- running a command, traced and bounded

def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def strace_works() -> bool:
    if not shutil.which("strace"):
        return False
    try:
        r = subprocess.run(["strace", "-f", "-qq", "--seccomp-bpf", "-e", "trace=openat", "-o", os.devnull, "true"],
                           capture_output=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return r.returncode == 0


@dataclass
class Ran:
    argv: list[str]
    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    trace: Path | None = None

    @property
    def hung(self) -> bool:
        return self.rc is None

    def opened(self, forbidden) -> list[str]:
        """strace lines in which a process opened (or blocked opening) one of `forbidden`."""
        if self.trace is None or not self.trace.is_file():
            return []
        names = {str(p) for p in forbidden}
        hits = []
        for line in self.trace.read_text(errors="replace").splitlines():
            m = re.search(r'open(?:at2?)?\((?:[^,]*, )?"([^"]*)"', line)
            if m and m.group(1) in names and not re.search(r"= -1 E", line):
                hits.append(line)
        return hits


def run_cli(args, env: dict, timeout: float, trace: Path | None = None) -> Ran:
    cmd = [*CLI, *map(str, args)]
    if trace is not None:
        cmd = ["strace", "-f", "-qq", "--seccomp-bpf", "-e", "trace=open,openat,openat2", "-o", str(trace), *cmd]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, errors="replace",
                            env=env, start_new_session=True, preexec_fn=_limit_memory)
    try:
        out, err = proc.communicate(timeout=timeout)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        rc = None
    return Ran(list(map(str, args)), rc, out, err, time.monotonic() - t0, trace)


INSTALL_TIMEOUT = 240     # seconds a `make env` of an install case may take (its `before` run included)
ROOT_DIR = Path(__file__).resolve().parents[2]


def run_make(case) -> Ran:
    """`make -C ROOT` with the case's `before` arguments (which must succeed), then its own."""
    python = getattr(sys, "_base_executable", sys.executable)
    t0 = time.monotonic()
    for args in ([case.before] if case.before else []) + [case.argv]:
        r = subprocess.run(["make", "--no-print-directory", "-C", str(ROOT_DIR), *args, f"PYTHON={python}"],
                           capture_output=True, text=True, errors="replace", timeout=INSTALL_TIMEOUT)
        if args is case.before and r.returncode != 0:
            return Ran(list(args), r.returncode, r.stdout, "the `before` run failed: " + r.stderr,
                       time.monotonic() - t0)
    return Ran(list(case.argv), r.returncode, r.stdout, r.stderr, time.monotonic() - t0)


def install_refused(ran: Ran, case) -> str | None:
    """None if `make env` failed with a last line of its own naming idna and the fix, leaving no stamp."""
    ours = [line for line in ran.stderr.splitlines() if line.startswith("make env: ")]
    venv = Path(next(a for a in case.argv if a.startswith("VENV=")).removeprefix("VENV="))
    if ran.rc not in (0, None) and ours and "idna" in ours[-1] and "fix: " in ours[-1] \
            and not (venv / ".installed-stamp").exists():
        return None
    return f"exit {ran.rc}; stderr tail {ran.stderr[-300:]!r}"


def one_line_error(ran: Ran) -> str | None:
    """None if the command ended with exit 2 and one stderr line 'error: ...', else what it did."""
    if ran.hung:
        return f"hung (killed after {ran.seconds:.0f} s)"
    lines = [line for line in ran.stderr.splitlines() if line.strip()]
    if ran.rc == 2 and len(lines) == 1 and lines[0].startswith("error: "):
        return None
    tail = " | ".join(lines[-3:])[:300]
    return f"exit {ran.rc}, {len(lines)} stderr line(s): {tail}"


def refused_with_a_note(ran: Ran, case) -> str | None:
    """None if the command ended with exit 1 and one stderr line 'note: ...' naming the refused record."""
    if ran.hung:
        return f"hung (killed after {ran.seconds:.0f} s)"
    lines = [line for line in ran.stderr.splitlines() if line.strip()]
    if ran.rc == 1 and len(lines) == 1 and lines[0].startswith("note: ") and str(case.paths[0]) in lines[0]:
        return None
    tail = " | ".join(lines[-3:])[:300]
    return f"exit {ran.rc}, {len(lines)} stderr line(s): {tail}"


def recomputed_with_a_note(ran: Ran) -> str | None:
    """None if the command ended with exit 0, its stderr only 'note: ...' lines, one naming records.json
    (the dataset's cache refused and recomputed: the dataset assembled all the same)."""
    if ran.hung:
        return f"hung (killed after {ran.seconds:.0f} s)"
    lines = [line for line in ran.stderr.splitlines() if line.strip()]
    if ran.rc == 0 and all(line.startswith("note: ") for line in lines) and any("records.json" in line
                                                                               for line in lines):
        return None
    tail = " | ".join(lines[-3:])[:300]
    return f"exit {ran.rc}, {len(lines)} stderr line(s): {tail}"


def model_warned(ran: Ran, case) -> str | None:
    """None if the command ended with exit 0, its stderr only 'note: ...' lines, one naming the BOP model
    it could not read, and no PLY was written from it."""
    if ran.hung:
        return f"hung (killed after {ran.seconds:.0f} s)"
    lines = [line for line in ran.stderr.splitlines() if line.strip()]
    plys = list(Path(case.argv[3]).rglob("obj_*.ply"))
    if ran.rc == 0 and all(line.startswith("note: ") for line in lines) and \
            any("BOP model" in line for line in lines) and not plys:
        return None
    tail = " | ".join(lines[-3:])[:300]
    return f"exit {ran.rc}, {len(lines)} stderr line(s), {len(plys)} PLY: {tail}"


# ---------------------------------------------------------------- the corpus and the runs

@dataclass
class Runs:
    root: Path
    cases: dict
    canary: str
    env: dict
    traced: bool
    clean: Path
    ran: dict = field(default_factory=dict)    # run name -> Ran
    outs: dict = field(default_factory=dict)   # run name -> output directory
    problems: dict = field(default_factory=dict)  # case name -> what went wrong


@pytest.fixture(scope="module")
def runs(tiny_base, tmp_path_factory) -> Runs:
    tmp = tmp_path_factory.mktemp("adversarial")
    root = tmp / "corpus"
    cases = {c.name: c for c in C.make_corpus(root, base=tiny_base,
                                              spec=lambda seed, sid, anomaly: make_spec(seed=seed, scene_id=sid,
                                                                                        anomaly=anomaly, samples=2))}
    canary = (root / C.CANARY_FILE).read_text()
    # Only the tiny base stage is a root beyond what each run grants itself (conftest allows all of
    # pytest's temp dirs, which would hold the outside files too).
    env = {**os.environ, ENV_ROOTS: str(Path(tiny_base).parent), C.CANARY_ENV: canary}
    r = Runs(root, cases, canary, env, strace_works(), tmp / "clean")

    good = [c.paths[0] for c in cases.values() if c.cls == "good"]
    summary = dispatch(good, r.clean, workers=2, threads=1, progress=False)
    assert sorted(summary.rendered) == sorted(p.stem for p in good), summary.failed

    jobs = {"pool": (["render", root / "pool", "--out", tmp / "out_pool", "--workers", 2, "--threads", 1,
                      "--timeout", TASK_TIMEOUT], RUN_TIMEOUT),
            "scan": (["render", root / "scan", "--out", tmp / "out_scan", "--workers", 1, "--threads", 1,
                      "--timeout", TASK_TIMEOUT], RUN_TIMEOUT)}
    for c in cases.values():
        if c.run in ("single", "plan", "dataset", "cli"):
            jobs[c.name] = (list(c.argv), CLI_TIMEOUT)
    r.outs = {"pool": tmp / "out_pool", "scan": tmp / "out_scan"}
    for c in cases.values():
        if c.run == "single":
            r.outs[c.name] = Path(c.argv[1]).parent / "out"
            jobs[c.name] = (list(c.argv) + ["--out", r.outs[c.name]], CLI_TIMEOUT)
    traces = tmp / "traces"
    traces.mkdir()

    for c in cases.values():
        if c.run == "install":
            jobs[c.name] = (c, INSTALL_TIMEOUT)

    def go(name):
        args, timeout = jobs[name]
        if isinstance(args, C.Case):
            return name, run_make(args)
        return name, run_cli(args, env, timeout, traces / f"{name}.strace" if r.traced else None)

    with ThreadPoolExecutor(2) as pool:  # the pool run beside the light command-line cases
        r.ran = dict(pool.map(go, sorted(jobs, key=lambda n: (n not in ("pool", "scan"), not n.startswith("install_")))))
    return r


def _failed_rows(out: Path) -> list[dict]:
    path = out / FAILED
    return [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []


def _check_layer_case(case, rows: list[dict], out: Path) -> str | None:
    mine = [row for row in rows if row["scene"] == case.name]
    if len(mine) != 1:
        return f"{len(mine)} rows in failed.jsonl" + (" (rendered)" if (out / f"{case.name}.json").is_file() else "")
    row = mine[0]
    reason = str(row["reason"])
    timed_out = row["kind"] == "timeout" or "timed out" in reason or "timeout" in reason.lower()
    # a FAILS case may also time out on one attempt (a loaded machine) and end as a layer error on the retry
    earlier_timeout = any("time limit" in str(r) or "timed out" in str(r) for r in row.get("reasons") or [])
    if "\n" in reason:
        return f"a reason of several lines: {reason[:200]!r}"
    if list(out.glob(f"{case.name}.*")) or (out / f"{case.name}_mask.png").exists():
        return "left outputs behind"
    if case.expect == C.LAYER_ERROR and not (row["kind"] == "layer" and row["attempts"] <= 1):  # 0: refused unopened
        return f"kind {row['kind']!r} after {row['attempts']} attempt(s): {reason[:200]}"
    if case.expect == C.TIMEOUT and not timed_out:
        return f"kind {row['kind']!r}, not a timeout: {reason[:200]}"
    if case.expect == C.FAILS and not (row["kind"] == "layer" and (row["attempts"] <= 1 or earlier_timeout) or timed_out):
        return f"kind {row['kind']!r} after {row['attempts']} attempt(s): {reason[:200]}"
    if case.name == "syntax_error" and not re.search(r"syntax_error\.usda:\d+:\d+", reason):
        return f"the reason does not name file:line:col: {reason[:200]}"
    return None


def _check_good(case, out: Path, clean: Path) -> str | None:
    layer = case.paths[0]
    if not is_done(layer, out, load_manifest(out)):
        return "not rendered (or its outputs do not verify)"
    for path in output_paths(layer, clean).values():
        if path.suffix in IMAGE_SUFFIXES and path.read_bytes() != (out / path.name).read_bytes():
            return f"{path.name} differs from the clean run"
    return None


def _report(problems: dict) -> str:
    return "\n".join(f"{name}: {what}" for name, what in sorted(problems.items()))


def test_pool_and_scan_runs_end_every_bad_layer_as_one_line(runs):
    """Layer-level cases in pool/ and the hostile files the directory scan meets in scan/: both runs
    finish, each bad layer is one failed.jsonl row (a layer error or a timeout), each good scene
    renders byte-identical to the clean run."""
    problems = {}
    for run in ("pool", "scan"):
        ran, out = runs.ran[run], runs.outs[run]
        if ran.hung:
            problems[f"<{run} run>"] = f"hung: killed after {ran.seconds:.0f} s; stderr tail {ran.stderr[-300:]!r}"
            continue
        if ran.rc != 1 or "Traceback" in ran.stderr:
            problems[f"<{run} run>"] = f"exit {ran.rc} (1 expected: some failed); stderr tail {ran.stderr[-400:]!r}"
        rows = _failed_rows(out)
        for case in runs.cases.values():
            if case.run != run:
                continue
            what = _check_good(case, out, runs.clean) if case.cls == "good" else _check_layer_case(case, rows, out)
            if what:
                problems[case.name] = what
    assert not problems, "\n" + _report(problems)


def test_command_line_cases_end_as_one_line_exit_2(runs):
    """Hostile plans, render records and command lines: exit 2 with one 'error: ...' line, fast."""
    problems = {}
    for case in runs.cases.values():
        if case.run not in ("single", "plan", "dataset", "cli"):
            continue
        ran = runs.ran[case.name]
        what = (refused_with_a_note(ran, case) if case.expect == C.CLI_REFUSED
                else recomputed_with_a_note(ran) if case.expect == C.CACHE_RECOMPUTED
                else model_warned(ran, case) if case.expect == C.MODEL_WARNED else one_line_error(ran))
        if case.expect == C.CLI_OK_OR_ERROR and what and ran.rc == 0:
            what = None
        if what:
            problems[case.name] = what
    # a dataset never writes outside its --out (the split "../../escaped")
    out = runs.root / "dataset_out" / "escaped_split"
    escaped = [str(p) for p in runs.root.parent.rglob("escaped") if out not in p.parents]
    if escaped:
        problems["dataset_escaped_split"] = f"wrote outside the dataset: {escaped}"
    # an edited cache never reaches the annotation files (the bbox, /etc/passwd, the injected camera)
    for case in runs.cases.values():
        if case.expect == C.CACHE_RECOMPUTED:
            made = Path(case.argv[3])
            coco, cams = made / "annotations" / "instances_test.json", list(made.rglob("scene_camera.json"))
            text = "".join(p.read_text() for p in [coco, *cams] if p.is_file())
            if not coco.is_file() or "/etc/passwd" in text or "INJECTED" in text or '"bbox":[0,0,1,1]' in text:
                problems[case.name] = "the edited cache reached the annotation files (or they are missing)"
    hostname = Path("/etc/hostname")
    if hostname.is_file():
        data = hostname.read_bytes()
        copied = [str(p) for p in (runs.root / "dataset_out").rglob("*") if p.is_file() and p.read_bytes() == data]
        if copied:
            problems["dataset_hostname_files"] = f"/etc/hostname copied into the dataset: {copied}"
    assert not problems, "\n" + _report(problems)


def test_install_cases_fail_naming_the_package(runs):
    """`make env` with a tampered requirements.lock fails, fresh venv or existing, its last line naming
    the package and the fix, and leaves no stamp that the next `make env` would trust."""
    problems = {}
    for case in runs.cases.values():
        if case.run == "install":
            what = install_refused(runs.ran[case.name], case)
            if what:
                problems[case.name] = what
    assert not problems, "\n" + _report(problems)


def test_nothing_outside_the_roots_is_opened_or_leaked(runs):
    """The canary (held by every outside file, and by the environment) is nowhere in what the runs
    wrote or printed; under strace, no process opened an outside file or a hostile link."""
    problems = {}
    for name, ran in runs.ran.items():
        if runs.canary.lower() in (ran.stdout + ran.stderr).lower():   # in any case: a parser may lower it
            problems[f"<{name} output>"] = "the canary is on stdout/stderr"
    for out in [*runs.outs.values(), runs.root / "plan_out", runs.root / "dataset_out", runs.root / "cli_out"]:
        if not out.is_dir():
            continue
        for path in out.rglob("*"):
            if path.is_file() and not path.is_symlink() and path.stat().st_size < 64 << 20 \
                    and runs.canary.encode() in path.read_bytes():
                problems[str(path.relative_to(runs.root.parent))] = "holds the canary"
    if runs.traced:
        for case in runs.cases.values():
            ran = runs.ran.get(case.run if case.run in ("pool", "scan") else case.name)
            hits = ran.opened(case.forbidden) if ran and case.forbidden else []
            if hits:
                problems[case.name] = f"opened outside the roots: {hits[0][:200]}"
    assert not problems, "\n" + _report(problems)
    if not runs.traced:
        pytest.skip("strace cannot attach here (ptrace restricted): the open() check did not run")


def test_colliding_output_names_are_refused_or_kept_apart(runs, tmp_path):
    """a.usda beside a_mask.usda (a's mask and a_mask's image are both a_mask.png), Sc beside sc:
    refused before rendering, or rendered with no file shared, each scene verifying."""
    problems = {}
    for case in (c for c in runs.cases.values() if c.run == "names"):
        out = tmp_path / case.name
        try:
            summary = dispatch(case.paths[0].parent, out, workers=1, threads=1, progress=False)
        except AlloError as exc:
            if "\n" in str(exc) or (out.is_dir() and any(out.glob("*.png"))):
                problems[case.name] = f"refused, but not cleanly: {exc}"
            continue
        names = [set(p.name for p in output_paths(layer, out).values()) for layer in case.paths]
        shared = set.intersection(*names)
        manifest = load_manifest(out)
        if shared:
            problems[case.name] = f"scenes share output files {sorted(shared)}"
        elif summary.failed or not all(is_done(layer, out, manifest) for layer in case.paths):
            problems[case.name] = f"not every scene rendered and verifies: {summary}"
    assert not problems, "\n" + _report(problems)


def test_editing_a_shared_sublayer_renders_the_scene_again(runs, tmp_path):
    case = runs.cases["stale_resume"]
    layer, sky = case.paths
    out = tmp_path / "out"
    first = dispatch(layer.parent, out, workers=1, threads=1, progress=False)
    assert first.rendered == ["scene"], first
    before = (out / "scene.png").read_bytes()
    sky.write_text(sky.read_text().replace("float inputs:intensity = 1361", "float inputs:intensity = 0"))
    second = dispatch(layer.parent, out, workers=1, threads=1, progress=False)
    assert second.rendered == ["scene"] and not second.skipped, \
        f"stale_resume: the scene was not rendered again after its sky layer changed: {second}"
    assert (out / "scene.png").read_bytes() != before
