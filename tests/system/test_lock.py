"""requirements.lock (the same bytes on every machine): every dependency, transitive ones
included, pinned to one version with its sha256 hashes; in agreement with pyproject.toml's ranges; and
installed in this environment exactly as locked (else: `make env`). Those tests read files and package
metadata only: no network.

And `make env` itself (scripts/install_env.py): it installs wheels only, each checked against the lock's
hashes, and builds a venv again when its lock changed. Those tests run `make env` with VENV, LOCK and
PROJECT set to a scratch venv, a lock of two of the real lock's entries (idna, and setuptools to install
a tiny project with) and that tiny project: they fetch from the package index as `make env` does."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, distribution

import pytest
from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

from allo_usd.core.paths import ROOT

LOCK = ROOT / "requirements.lock"
PYPROJECT = ROOT / "pyproject.toml"
HASH = re.compile(r"--hash=sha256:([0-9a-f]{64})$")
FIX = "the environment differs from requirements.lock; fix: run `make env` (it reinstalls from the lock)"

pytestmark = pytest.mark.skipif(not LOCK.is_file(), reason="not a source checkout with requirements.lock")


def lock_entries() -> list[tuple[Requirement, list[str]]]:
    """(requirement, its sha256 hashes) per entry of the lock: comments dropped, continuation lines joined."""
    text = re.sub(r"\\\n", " ", LOCK.read_text())
    entries = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        assert not line.startswith("-"), f"requirements.lock: an option line {line!r}; the lock holds pins only"
        req, *options = line.split(" --")
        hashes = []
        for opt in options:
            m = HASH.match("--" + opt.strip())
            assert m, f"requirements.lock: {req.strip()}: {opt.strip()!r} is not a sha256 hash"
            hashes.append(m.group(1))
        entries.append((Requirement(req.strip()), hashes))
    return entries


def locked() -> dict[str, Version]:
    return {canonicalize_name(r.name): Version(next(iter(r.specifier)).version) for r, _ in lock_entries()}


def project() -> dict:
    return tomllib.loads(PYPROJECT.read_text())


def project_requirements() -> list[Requirement]:
    """pyproject's dependencies, its `test` extra and its build requirements (make env builds allo-usd
    without isolation, from the locked setuptools and wheel)."""
    p = project()
    return [Requirement(r) for r in (*p["project"]["dependencies"], *p["project"]["optional-dependencies"]["test"],
                                     *p["build-system"]["requires"])]


def test_every_entry_is_one_exact_version_with_hashes_and_no_name_twice():
    entries = lock_entries()
    assert len(entries) > 50, "requirements.lock lists every dependency, transitive ones included"
    names = [canonicalize_name(r.name) for r, _ in entries]
    assert len(names) == len(set(names)), f"named twice: {sorted({n for n in names if names.count(n) > 1})}"
    for req, hashes in entries:
        specs = list(req.specifier)
        assert len(specs) == 1 and specs[0].operator == "==" and "*" not in specs[0].version, \
            f"{req}: a lock entry is pinned with == to one version"
        assert not req.url and not req.extras, f"{req}: no URL, no extras (pip-compile --strip-extras)"
        assert hashes, f"{req} has no --hash=sha256: line; pip --require-hashes would refuse the lock"
        assert len(hashes) == len(set(hashes)), f"{req}: a hash listed twice"


def test_pyproject_ranges_hold_the_locked_versions():
    pins = locked()
    for req in project_requirements():
        name = canonicalize_name(req.name)
        assert name in pins, f"pyproject.toml requires {req}, which requirements.lock does not pin; fix: make lock"
        assert req.specifier.contains(pins[name], prereleases=True), \
            f"pyproject.toml requires {req}, requirements.lock pins {pins[name]}; fix: make lock (or the range)"
        for extra in req.extras:   # dask[distributed]: what the extra adds is locked too
            for sub in distribution(req.name).requires or []:
                sub = Requirement(sub)
                if sub.marker is not None and sub.marker.evaluate({**default_environment(), "extra": extra}) and \
                        not sub.marker.evaluate({**default_environment(), "extra": ""}):
                    assert canonicalize_name(sub.name) in pins, f"{req} needs {sub}, not in requirements.lock"


def test_the_lock_is_closed_under_dependencies():
    """Every requirement of every locked distribution (as installed, on this platform) is locked, at a
    version it accepts: installing the lock with --no-deps misses nothing (what `pip check` says)."""
    pins = locked()
    env = {**default_environment(), "extra": ""}
    problems = []
    for name, version in pins.items():
        try:
            requires = distribution(name).requires or []
        except PackageNotFoundError:
            continue   # reported by test_installed_versions_are_the_locked_ones
        for sub in map(Requirement, requires):
            if sub.marker is not None and not sub.marker.evaluate(env):
                continue
            got = pins.get(canonicalize_name(sub.name))
            if got is None or not sub.specifier.contains(got, prereleases=True):
                problems.append(f"{name} {version} needs {sub}; the lock has {got or 'nothing'}")
    assert not problems, "; ".join(problems) + "; fix: make lock"


def test_installed_versions_are_the_locked_ones():
    drift = []
    for name, version in sorted(locked().items()):
        try:
            have = distribution(name).version
        except PackageNotFoundError:
            drift.append(f"{name} {version} is not installed")
            continue
        if Version(have) != version:
            drift.append(f"{name} {have} is installed, the lock pins {version}")
    assert not drift, f"{FIX}: " + "; ".join(drift)


# ---------------------------------------------------------------- make env: wheels only, hash-checked, never stale

PROBE = """[build-system]
requires = ["setuptools>=68"]
build-backend = "setuptools.build_meta"

[project]
name = "lockprobe"
version = "0"

[tool.setuptools]
py-modules = []
"""


def lock_text(hashes: dict[str, list[str]]) -> str:
    """Lock entries for the given names (the real pins), with `hashes` in place of the real ones."""
    pins = locked()
    return "".join(f"{name}=={pins[name]} \\\n" + " \\\n".join(f"    --hash=sha256:{h}" for h in hs) + "\n"
                   for name, hs in hashes.items())


def real_hashes() -> dict[str, list[str]]:
    return {canonicalize_name(r.name): hs for r, hs in lock_entries()}


def tampered(h: str) -> str:
    return ("0" if h[0] != "0" else "1") + h[1:]


def make_env(venv, lock, project) -> subprocess.CompletedProcess:
    python = getattr(sys, "_base_executable", sys.executable)
    return subprocess.run(["make", "--no-print-directory", "-C", str(ROOT), "env", f"PYTHON={python}",
                           f"VENV={venv}", f"LOCK={lock}", f"PROJECT={project}"],
                          capture_output=True, text=True, timeout=300)


def installed(venv) -> set[str]:
    return {canonicalize_name(p.name.split("-")[0]) for p in (venv / "lib").glob("python*/site-packages/*.dist-info")}


def refused_naming(r: subprocess.CompletedProcess, package: str) -> str | None:
    """None if `make env` failed with a last line of its own naming the package and the fix."""
    ours = [line for line in r.stderr.splitlines() if line.startswith("make env: ")]
    if r.returncode != 0 and ours and package in ours[-1] and "fix: " in ours[-1] and "\n" not in ours[-1]:
        return None
    return f"exit {r.returncode}; stderr tail {r.stderr[-600:]!r}; stdout tail {r.stdout[-300:]!r}"


@pytest.fixture
def probe(tmp_path):
    (tmp_path / "proj").mkdir()
    (tmp_path / "proj" / "pyproject.toml").write_text(PROBE)
    return tmp_path / "proj"


def wheel_hash(name: str, tmp_path) -> str:
    """The sha256 of the wheel pip fetches for the locked `name` (the lock also holds its sdist's)."""
    d = tmp_path / "dl"
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary", ":all:",
                    "-d", str(d), f"{name}=={locked()[name]}"], check=True, capture_output=True, timeout=120)
    [whl] = d.glob("*.whl")
    return hashlib.sha256(whl.read_bytes()).hexdigest()


@pytest.mark.process
@pytest.mark.slow
def test_a_wheel_whose_hash_is_not_in_the_lock_fails_a_fresh_env_naming_the_package(tmp_path, probe):
    """idna's wheel hash altered, its source package's kept: pip must not fall back to building the source
    package (which fetches flit_core, a build backend outside the lock); make env fails naming idna."""
    hashes = real_hashes()
    wheel = wheel_hash("idna", tmp_path)
    assert wheel in hashes["idna"] and len(hashes["idna"]) > 1, "the test needs idna's wheel and sdist locked"
    lock = tmp_path / "tampered.lock"
    lock.write_text(lock_text({"idna": [tampered(h) if h == wheel else h for h in hashes["idna"]],
                               "setuptools": hashes["setuptools"]}))
    venv = tmp_path / "venv"
    r = make_env(venv, lock, probe)
    assert refused_naming(r, "idna") is None, refused_naming(r, "idna")
    assert not (venv / ".installed-stamp").exists(), "a failed build left a stamp: the next make env would trust it"
    assert not installed(venv) & {"idna", "flit-core"}, f"installed {sorted(installed(venv))}"


@pytest.mark.process
@pytest.mark.slow
def test_a_changed_lock_builds_the_env_again_and_a_tampered_one_fails(tmp_path, probe):
    """An existing venv is never trusted once its lock changed: both of idna's hashes altered, make env
    fails naming idna (pip would skip the installed idna without checking a hash); an unchanged lock is
    a no-op, a changed pyproject.toml installs the project again and keeps the rest."""
    hashes = real_hashes()
    good, bad = tmp_path / "good.lock", tmp_path / "bad.lock"
    good.write_text(lock_text({"idna": hashes["idna"], "setuptools": hashes["setuptools"]}))
    bad.write_text(lock_text({"idna": [tampered(h) for h in hashes["idna"]], "setuptools": hashes["setuptools"]}))
    venv = tmp_path / "venv"
    r = make_env(venv, good, probe)
    assert r.returncode == 0, r.stderr[-800:]
    first = installed(venv)
    marker = venv / "marker"
    marker.write_text("")
    r = make_env(venv, good, probe)
    assert r.returncode == 0 and "make env: " not in r.stdout + r.stderr, "an unchanged lock is a no-op"
    (probe / "pyproject.toml").write_text(PROBE.replace('version = "0"', 'version = "1"'))
    r = make_env(venv, good, probe)
    assert r.returncode == 0 and marker.exists(), f"a changed pyproject.toml rebuilt the venv: {r.stderr[-400:]}"
    again = {p.name for p in (venv / "lib").glob("python*/site-packages/lockprobe-*")}
    os.utime(bad, (0, 0))   # older than the stamp: a changed lock is seen by its content, not its time
    r = make_env(venv, bad, probe)
    assert refused_naming(r, "idna") is None, refused_naming(r, "idna")
    assert not (venv / ".installed-stamp").exists() and not marker.exists()
    assert {"idna", "setuptools", "lockprobe"} <= first, f"the first build installed {sorted(first)}"
    assert any(name.startswith("lockprobe-1.") for name in again), f"pyproject.toml's change not installed: {again}"


def test_the_stamp_decides_nothing_project_or_rebuild(tmp_path):
    from scripts import install_env as ie

    (tmp_path / "proj").mkdir()
    (tmp_path / "proj" / "pyproject.toml").write_text(PROBE)
    lock = tmp_path / "lock"
    lock.write_text("a==1\n")
    venv = tmp_path / "venv"
    want = ie.wanted(lock, tmp_path / "proj")
    assert ie.what_to_do(venv, want) == "rebuild"                      # no venv
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").touch()
    (venv / ie.STAMP).write_text("")                                   # a stamp of make env before this one
    assert ie.what_to_do(venv, want) == "rebuild"
    (venv / ie.STAMP).write_text(json.dumps(want))
    assert ie.what_to_do(venv, want) == "nothing"
    assert ie.what_to_do(venv, {**want, "pyproject_sha256": "0" * 64}) == "project"
    assert ie.what_to_do(venv, {**want, "lock_sha256": "0" * 64}) == "rebuild"
    assert ie.what_to_do(venv, {**want, "recipe": ie.RECIPE + 1}) == "rebuild"
    (venv / "bin" / "python").unlink()
    assert ie.what_to_do(venv, want) == "rebuild"
    with pytest.raises(ie.EnvError, match="not a Python venv"):         # never rm -rf a folder that is not a venv
        ie.check_removable(venv)
    (venv / "pyvenv.cfg").touch()
    ie.check_removable(venv)
    (venv / "lib").mkdir()
    (venv / "lib64").symlink_to("lib")
    ie.remove_venv(venv)
    assert not venv.exists()


def test_pip_failures_end_as_one_line_naming_the_package():
    from scripts import install_env as ie

    lock = LOCK
    mismatch = ("ERROR: THESE PACKAGES DO NOT MATCH THE HASHES FROM THE REQUIREMENTS FILE. If you have ...\n"
                "    idna==3.20 from https://example.invalid/idna-3.20-py3-none-any.whl (from -r requirements.lock"
                " (line 1)):\n        Expected sha256 00\n             Got        ab\n")
    line = ie.pip_failure(mismatch, lock)
    assert "idna==3.20" in line and "fix: " in line and "\n" not in line
    line = ie.pip_failure("ERROR: No matching distribution found for idna==3.20\n", lock)
    assert "idna==3.20" in line and "wheel" in line and "fix: " in line
    assert "fix: " in ie.pip_failure("ERROR: something else\n", lock)
