"""The package installs like one: a wheel built from the source holds the base stage and the
schemas, installs (non-editable) into a fresh environment, registers the schema from there and
runs `allo-usd demo` from a folder that has nothing to do with the checkout.

The fresh environment gets the wheel alone (`--no-deps`); the dependencies (bpy, usd-core, ...)
come from the environment running the tests, made visible through a .pth file that lists its
site-packages. A .pth line adds a directory but runs none of the .pth files inside it, so the
running environment's editable allo_usd (a .pth finder) cannot shadow the wheel; every subprocess
checks that allo_usd is imported from inside the fresh environment anyway.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from allo_usd.core.paths import ROOT, SCHEMAS, STAGES

pytestmark = pytest.mark.slow

BUILD_REQUIRES = ("setuptools>=68", "wheel")   # pyproject's [build-system]; the `test` extra has them too
SKIP_DIRS = {".git", ".venv", ".lock-tool", "out", "build", "dist", "__pycache__", ".pytest_cache", ".hypothesis"}


def _env() -> dict:
    """The subprocesses' environment: nothing that points Python or USD at the checkout."""
    drop = {"PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PYTHONUSERBASE", "VIRTUAL_ENV", "ALLO_ASSET_ROOTS"}
    return {k: v for k, v in os.environ.items() if k not in drop and not k.startswith("PXR_")}


def _run(cmd: list, cwd: Path, timeout: int = 600) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{cmd} failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


def _copy_source(dest: Path) -> Path:
    """The checkout's tracked and untracked-but-not-ignored files (or, without git, the tree minus
    environments and outputs), so building leaves no build/ or egg-info in the checkout."""
    listed = None
    if (ROOT / ".git").exists() and shutil.which("git"):
        r = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-co", "--exclude-standard", "-z"],
                           capture_output=True)
        if r.returncode == 0:
            listed = [f for f in r.stdout.decode().split("\0") if f]
    if listed is None:
        listed = [str(p.relative_to(ROOT)) for p in ROOT.rglob("*")
                  if p.is_file() and not SKIP_DIRS & set(p.relative_to(ROOT).parts)
                  and not any(part.endswith(".egg-info") for part in p.relative_to(ROOT).parts)]
    for f in listed:
        if (ROOT / f).is_file():   # (a deleted, not yet committed file is still listed)
            (dest / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, dest / f)
    return dest


def _has_build_requires() -> bool:
    from importlib.metadata import PackageNotFoundError, version

    try:
        setuptools, _ = version("setuptools"), version("wheel")
    except PackageNotFoundError:
        return False
    return int(setuptools.split(".")[0]) >= 68


def _build_python(tmp: Path) -> Path:
    """An interpreter that can build the wheel without build isolation: the running one when it
    has the build requirements (`make test`'s environment: the `test` extra), else a fresh
    environment that gets them from the package index."""
    if _has_build_requires():
        return Path(sys.executable)
    venv = tmp / "build-env"
    _run([sys.executable, "-m", "venv", venv], tmp)
    python = venv / "bin" / "python"
    _run([python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", *BUILD_REQUIRES], tmp)
    return python


def _site_packages(venv: Path) -> Path:
    python = venv / "bin" / "python"
    r = _run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], venv)
    return Path(r.stdout.strip())


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(the wheel, the fresh environment it is installed in)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = _copy_source(tmp / "src")
    python = _build_python(tmp)
    _run([python, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--quiet",
          "--disable-pip-version-check", "--wheel-dir", tmp / "dist", src], tmp)
    wheel, = (tmp / "dist").glob("allo_usd-*.whl")
    venv = tmp / "fresh"
    _run([sys.executable, "-m", "venv", venv], tmp)
    _run([venv / "bin" / "python", "-m", "pip", "install", "--no-deps", "--no-index", "--quiet",
          "--disable-pip-version-check", wheel], tmp)
    # after the install, so that pip never sees (nor offers to replace) the running environment's allo-usd
    user = [site.getusersitepackages()] if site.ENABLE_USER_SITE else []
    deps = [p for p in dict.fromkeys([*site.getsitepackages(), *user]) if Path(p).is_dir()]
    (_site_packages(venv) / "_allo_usd_test_deps.pth").write_text("".join(f"{p}\n" for p in deps))
    return wheel, venv


def test_the_wheel_holds_the_package_data(installed):
    wheel, _ = installed
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"allo_usd/stages/base.usda", "allo_usd/schemas/alloUsd/plugInfo.json",
            "allo_usd/schemas/alloUsd/generatedSchema.usda", "allo_usd/cli.py"} <= names
    # the checkout keeps them at its top (stages/, schemas/); the wheel maps them into the package
    assert STAGES == ROOT / "stages" and SCHEMAS == ROOT / "schemas"
    shipped = {"allo_usd/" + p.relative_to(ROOT).as_posix() for d in (STAGES, SCHEMAS) for p in d.rglob("*")
               if p.is_file() and "__pycache__" not in p.parts}
    assert len(shipped) >= 70 and shipped <= names, sorted(shipped - names)[:5]
    assert {n.split("/")[0] for n in names} == {"allo_usd", wheel.name.split("-")[0] + "-" +
                                                  wheel.name.split("-")[1] + ".dist-info"}   # no tests/, scripts/
    print(f"\nwheel {wheel.name}: {wheel.stat().st_size / 1e6:.2f} MB, {len(names)} files")


def test_the_installed_package_registers_the_schema_from_where_it_is(installed, tmp_path):
    _, venv = installed
    probe = r"""
import json, sys
from pathlib import Path
import allo_usd
from allo_usd.core.paths import BASE_STAGE
from allo_usd.usd import schema
schema.register()
from pxr import Plug, Usd
plugin = Plug.Registry().GetPluginWithName("alloUsd")
print(json.dumps({"package": allo_usd.__file__, "base_stage": str(BASE_STAGE), "plugin": plugin.path,
                  "prefix": sys.prefix, "defined": [n for n in schema.API_SCHEMAS
                                                   if Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(n)]}))
"""
    report = json.loads(_run([venv / "bin" / "python", "-c", probe], tmp_path).stdout)
    fresh = venv.resolve()
    for key in ("package", "base_stage", "plugin"):
        assert fresh in Path(report[key]).resolve().parents, (key, report[key])   # not the checkout's
    assert Path(report["base_stage"]).is_file()
    from allo_usd.usd.schema import API_SCHEMAS

    assert report["defined"] == list(API_SCHEMAS)


def test_allo_usd_demo_runs_from_an_unrelated_folder(installed, tmp_path):
    _, venv = installed
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    _run([venv / "bin" / "allo-usd", "demo", "--out", "demo", "--width", "64", "--height", "36", "--samples", "2"],
         elsewhere, timeout=1200)
    out = elsewhere / "demo"
    layers = sorted((out / "layers").glob("*.usda"))
    assert len(layers) == 4
    for layer in layers:
        meta = json.loads((out / "renders" / f"{layer.stem}.json").read_text())
        for f in meta["files"].values():
            assert (out / "renders" / f).is_file(), f
        assert {"rgb", "mask"} <= set(meta["files"])
    assert (out / "contact_sheet.png").is_file() and (out / "layers" / "stages" / "base.usda").is_file()
    assert (out / "layers" / "schema" / "plugInfo.json").is_file()


def test_pyproject_lists_every_code_package():
    """pyproject.toml lists the packages (the data folders are mapped in beside them), so a new
    subpackage left out of the list would be missing from the wheel: the list must match allo_usd/."""
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    code = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "allo_usd").rglob("__init__.py")
            if "__pycache__" not in p.parts}
    assert set(config["packages"]) == code | {"allo_usd.stages", "allo_usd.schemas"}
    assert config["package-dir"] == {"allo_usd.stages": "stages", "allo_usd.schemas": "schemas"}
