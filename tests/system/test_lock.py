"""requirements.lock (the same bytes on every machine): every dependency, transitive ones
included, pinned to one version with its sha256 hashes; in agreement with pyproject.toml's ranges; and
installed in this environment exactly as locked (else: `make env`). Reads files and package metadata
only: no network."""

from __future__ import annotations

import re
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
