"""`make env`: build .venv from requirements.lock, wheels only, every file checked against the lock's sha256
hashes, and never trust a venv built from another lock.

    python3.11 -m scripts.install_env [--venv .venv] [--lock requirements.lock] [--project .]

Run by the Makefile with the interpreter the venv is made from (not the venv's: it may not exist yet),
so it uses the standard library only. The stamp, VENV/.installed-stamp, records the sha256 of the lock
and of PROJECT/pyproject.toml that the venv was built from, and RECIPE (how it was built):

- stamp matches and the venv's python is there: nothing to do (silent; `make test` runs this every time);
- the lock (or RECIPE) differs, or there is no stamp (a venv of unknown origin, or a build that did not
  finish): the venv is removed and built again from scratch. pip skips an installed distribution whose
  version matches without checking any hash, and the lock's hashes are those of the wheel files, not of
  installed files, so an existing venv cannot be verified against the lock without fetching every wheel
  again; a fresh build costs the same and also drops what the lock no longer lists;
- only pyproject.toml differs: allo-usd itself is installed again (its entry points), nothing else.

The stamp is removed before a build starts and written after it ends, so a failed or interrupted build
is built again by the next `make env`. The lock is installed with `--require-hashes --only-binary :all:
--no-deps --force-reinstall`: a wheel whose hash is not in the lock fails (pip cannot fall back to the
source package, whose build would fetch a build backend from outside the lock), and nothing the venv
came with is kept unchecked. allo-usd is then installed editable with `--no-build-isolation --no-index`
from the venv's own (locked) setuptools: nothing outside the lock is fetched.

A failure ends with one line (after pip's own output) naming the package and the fix; exit 1 (130 on
Ctrl-C)."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

RECIPE = 1   # bump when the way the venv is built changes: every venv is then built again
STAMP = ".installed-stamp"
PREFIX = "make env: "


class EnvError(Exception):
    """One line for the user: what went wrong and the fix."""


def sha256(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise EnvError(f"cannot read {path} ({exc.strerror}); fix: run make env in a checkout that has it") from None


def wanted(lock: Path, project: Path) -> dict:
    return {"recipe": RECIPE, "lock_sha256": sha256(lock), "pyproject_sha256": sha256(project / "pyproject.toml")}


def recorded(venv: Path) -> dict | None:
    """The stamp's record, or None when there is none or it is not one this script wrote."""
    try:
        data = json.loads((venv / STAMP).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def python_of(venv: Path) -> Path:
    return venv / "bin" / "python"


def what_to_do(venv: Path, want: dict) -> str:
    """'nothing', 'project' (install allo-usd again) or 'rebuild' (the venv from scratch)."""
    have = recorded(venv)
    if have is None or not python_of(venv).exists() or \
            any(have.get(k) != want[k] for k in ("recipe", "lock_sha256")):
        return "rebuild"
    return "nothing" if have == want else "project"


def check_removable(venv: Path) -> None:
    """Only a venv (a pyvenv.cfg at its top) or an empty folder is ever removed."""
    if venv.is_symlink() or (venv.exists() and not venv.is_dir()):
        raise EnvError(f"{venv} is not a folder; fix: remove it or set VENV=another/path")
    if venv.is_dir() and not (venv / "pyvenv.cfg").is_file() and any(venv.iterdir()):
        raise EnvError(f"{venv} is not a Python venv (no pyvenv.cfg), so it is not replaced; "
                       "fix: remove it or set VENV=another/path")


def remove_venv(venv: Path) -> None:
    """Remove a venv, its pyvenv.cfg last: a removal cut short leaves a folder check_removable still accepts."""
    if not venv.exists():
        return
    for child in venv.iterdir():
        if child.name == "pyvenv.cfg":
            continue
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()
    (venv / "pyvenv.cfg").unlink(missing_ok=True)
    venv.rmdir()


def check_python() -> None:
    if sys.version_info[:2] != (3, 11):
        raise EnvError("allo-usd needs Python 3.11 (bpy==5.0.1); set PYTHON=/path/to/python3.11")


def run(cmd: list[str]) -> tuple[int, str]:
    """Run cmd, passing its output through, and return (exit status, its output)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace")
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:
        sys.stdout.write(line)
        lines.append(line)
    sys.stdout.flush()
    return proc.wait(), "".join(lines)


def pip_failure(output: str, lock: Path) -> str:
    """One line from pip's output: the package it failed on, and the fix."""
    restore = f"fix: restore {lock.name} (git checkout {lock.name}) or regenerate it with make lock, then run make env"
    if "DO NOT MATCH THE HASHES" in output:
        names = re.findall(r"^ {4}(\S+?==\S+?) from ", output, re.M)
        which = ", ".join(dict.fromkeys(names)) or "a package"
        return (f"the file pip fetched for {which} matches none of its sha256 hashes in {lock.name} "
                f"(the lock was changed, or the file was); nothing was installed from it; {restore}")
    if "are missing from some requirements" in output or "must have their versions pinned" in output:
        return f"{lock.name} has an entry without an == pin and its sha256 hashes (see above); {restore}"
    m = re.search(r"No matching distribution found for (\S+)", output)
    if m:
        return (f"no wheel of {m.group(1)} for this platform (make env installs wheels only and builds "
                f"nothing from source); fix: pin a version with a Linux x86-64 Python 3.11 wheel (make lock), "
                f"then run make env")
    return f"pip could not install {lock.name} (its reason is above); {restore}"


def build(venv: Path, lock: Path, project: Path, want: dict, action: str) -> None:
    stamp = venv / STAMP
    if action == "rebuild":
        check_python()
        check_removable(venv)
        print(f"{PREFIX}building {venv} from {lock} (wheels only, every file checked against its sha256)",
              flush=True)
        remove_venv(venv)
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        rc, out = run([str(python_of(venv)), "-m", "pip", "install", "--quiet", "--require-hashes",
                       "--only-binary", ":all:", "--no-deps", "--force-reinstall", "-r", str(lock)])
        if rc != 0:
            raise EnvError(pip_failure(out, lock) + f" ({venv} stays unfinished until then)")
    else:
        print(f"{PREFIX}{project / 'pyproject.toml'} changed: installing it into {venv} again", flush=True)
        stamp.unlink()
    rc, out = run([str(python_of(venv)), "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                   "--no-index", "-e", str(project)])
    if rc != 0:
        raise EnvError(f"installing {project} into {venv} failed (pip's reason is above); fix: correct "
                       f"{project / 'pyproject.toml'}, then run make env")
    tmp = venv / (STAMP + ".tmp")
    tmp.write_text(json.dumps(want, indent=1) + "\n")
    os.replace(tmp, stamp)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--venv", type=Path, default=Path(".venv"))
    p.add_argument("--lock", type=Path, default=Path("requirements.lock"))
    p.add_argument("--project", type=Path, default=Path("."))
    args = p.parse_args(argv)
    try:
        want = wanted(args.lock, args.project)
        action = what_to_do(args.venv, want)
        if action != "nothing":
            build(args.venv, args.lock, args.project, want, action)
    except EnvError as exc:
        print(f"{PREFIX}{exc}", file=sys.stderr)
        return 1
    except subprocess.CalledProcessError as exc:
        print(f"{PREFIX}{' '.join(map(str, exc.cmd))} failed (exit {exc.returncode}, its reason is above); "
              f"fix: remove {args.venv} and run make env again", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PREFIX}interrupted; {args.venv} is built again by the next make env", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
