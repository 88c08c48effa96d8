"""An output tree as authoring holds it: one writer at a time (`tree_lock`), the plan it was made
from (`check_tree_plan`; `replace_tree` clears it for another plan), its own base stage
(`with_tree_stage`) and pose-file copy (`with_tree_poses`), and `open_tree`, which does all of that
and yields the authoring context over the tree. Its names and paths are allo_usd.usd.tree's.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
import time
from contextlib import contextmanager, suppress
from dataclasses import asdict
from pathlib import Path

from allo_usd.core.camera_model import DEFAULT_CAMERA
from allo_usd.core.errors import AlloError, DiskFullError, LayerError, PlanError
from allo_usd.core.files import atomic_directory, file_problem
from allo_usd.core.provenance import record_tree_versions
from allo_usd.plan.io import save_plan
from allo_usd.plan.model import Plan
from allo_usd.run.samples import AuthorContext
from allo_usd.usd.tree import (BASE_STAGE_FILE, LAYER_DIRS, POSE_INPUTS, STAGE_DIR, STATION_MARKER, TREE_ENTRIES,
                               TREE_LOCK, TREE_PLAN, tree_base_stage)

_TRASH = re.compile(r"^\.replaced\.[a-z0-9_]{8}$")   # a replace's trash (mkdtemp), left if the run was killed
# Plan fields the tree checks by content, not by name: the base stage's path and the station's
# source (stages/ must be a byte copy of the plan's stage, or built from the same model file).
# `render.device` is not compared at all: it says how to render, not what (plan.model.Render);
# any other field of `render` is compared like the rest.
UNCOMPARED = {"base_stage": True, "station": True, "render": {"device"}}


def with_tree_stage(plan: Plan, out_dir: Path) -> Plan:
    """The plan, pointed at the output tree's own base stage `out_dir/stages/base.usda`, made before
    any worker starts. A procedural station's tree gets a byte copy of the plan's base stage and its
    assets; a station that is a model file gets a base stage built from it (into a temporary
    directory, then renamed, with `stages/station_source.json` naming the file and its sha256; a tree
    built from another station is refused). Scene layers then refer only to files inside the tree,
    so the tree can be moved or copied as a whole and re-authoring elsewhere gives the same bytes
    (for a model-built stage, on machines whose OpenBLAS rounds alike: scripts/make_base_stage.py
    pins that kernel for the committed stage)."""
    from allo_usd.usd.compose import copy_base_stage

    base = tree_base_stage(out_dir)
    if plan.station.source == "procedural":
        copy_base_stage(plan.resolve_base_stage(), out_dir)
        return plan.model_copy(update={"base_stage": str(base.resolve())})
    source = Path(plan.station.source)
    problem = file_problem(source, 1 << 40)   # missing, unreadable, a name too long, not a regular file
    if problem:
        raise PlanError(f"station.source: {str(source)[:200]} {problem}; fix: give the path of a glTF/OBJ/STL "
                        "model, or 'procedural'")
    from allo_usd.core.files import sha256_file

    made_from = {"source": source.name, "sha256": sha256_file(source), "units": plan.station.units,
                 "up_axis": plan.station.up_axis}
    lens, size = plan.camera_model()   # the rig scores its views through the plan's camera
    if lens != DEFAULT_CAMERA:
        made_from["camera"] = {**asdict(lens), "resolution": list(size)}
    marker = base.parent / STATION_MARKER
    if base.is_file():
        from allo_usd.core.files import read_own_record, record_shown

        recorded = read_own_record(marker)   # through the gate: a FIFO or a pseudo-file is no record
        if recorded != made_from:
            shown = record_shown(recorded, made_from) or "another station"   # the record's own fields only
            raise PlanError(f"{base.parent} was built from {shown}, not from {made_from}; "
                            f"fix: author this plan into a new output directory (or delete that {STAGE_DIR}/ folder)")
    else:
        from allo_usd.usd.build_stage import build_base_stage

        with atomic_directory(base.parent) as tmp:  # replaces an incomplete build of an older version
            build_base_stage(tmp, str(source), plan.station.units, plan.station.up_axis, lens, size)
            (tmp / STATION_MARKER).write_text(json.dumps(made_from, indent=1, sort_keys=True) + "\n")
    return plan.model_copy(update={"base_stage": str(base.resolve())})


@contextmanager
def tree_lock(out_dir: Path):
    """Hold the tree's lock (RunLock on `TREE_LOCK`) for the block. The holder writes its pid into
    the lock file and empties it on release (so a finished tree's bytes do not depend on who
    wrote it); a second run is refused with one line naming the holder."""
    from allo_usd.core.errors import AlloError
    from allo_usd.core.files import RunLock

    lock = RunLock(out_dir, TREE_LOCK, "author")
    try:
        lock.__enter__()
    except AlloError:
        from allo_usd.core.files import read_head

        # the holder's own line ("pid N, since TIME"), shown only in that form: the lock file is never quoted
        head = (read_head(lock.path, 200) or b"").decode("utf-8", "replace").strip()
        holder = head if re.fullmatch(r"pid \d+, since [0-9T:.+\- Z]{1,40}", head) else ""
        raise AlloError(f"another author run{f' ({holder})' if holder else ''} is writing to {Path(out_dir)}; "
                        f"wait for it to finish, then re-run to resume (or stop it), or author into "
                        f"another --out") from None
    try:
        os.ftruncate(lock.fd, 0)
        os.pwrite(lock.fd, f"pid {os.getpid()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode(), 0)
        yield
    finally:
        try:
            os.ftruncate(lock.fd, 0)
        finally:
            lock.__exit__(None, None, None)


def plan_fields(plan: Plan) -> dict:
    """The plan as flat `section.field` -> value (JSON types), the fields a tree compares."""
    flat = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict):
            for k in sorted(value):
                walk(f"{prefix}.{k}" if prefix else k, value[k])
        else:
            flat[prefix] = value

    walk("", plan.model_dump(mode="json", exclude=UNCOMPARED))
    return flat


def _shown(field: str, value) -> str:
    if field == "quality.resolution" and isinstance(value, list) and len(value) == 2:
        return f"{value[0]}x{value[1]}"
    return json.dumps(value, separators=(",", ":"))


def plan_differences(recorded: Plan, given: Plan) -> list[str]:
    """'field RECORDED in the tree, GIVEN in this plan' for each field where the plans differ (the
    validated models, so formatting, field order and omitted defaults do not count)."""
    a, b = plan_fields(recorded), plan_fields(given)
    return [f"{k} {_shown(k, a.get(k))} in the tree, {_shown(k, b.get(k))} in the plan given"
            for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def _refuse(out_dir: Path, why: str) -> PlanError:
    return PlanError(f"{out_dir} {why}; fix: author into a fresh --out, or pass --replace (replace=True) to "
                     f"delete this tree's layers and author the plan given")


def check_tree_plan(plan: Plan, out_dir: Path) -> bool:
    """Refuse to author `plan` into a tree made from another plan; True if the tree already records
    this plan (then plan.toml is kept as first written). `--limit` is not part of the plan, so the
    same plan with another limit resumes."""
    from allo_usd.plan.io import load_plan

    record = out_dir / TREE_PLAN
    if not record.is_file():
        found = [n for n in LAYER_DIRS if (out_dir / n).is_dir()]
        if found:
            raise _refuse(out_dir, f"holds authored layers ({', '.join(found)}/) but no {TREE_PLAN}, so the plan "
                                   "they were made from is unknown")
        return False
    try:
        recorded = load_plan(record)
    except PlanError as exc:
        raise _refuse(out_dir, f"records its plan in {record}, which cannot be read "
                               f"({str(exc).splitlines()[0]})") from None
    diff = plan_differences(recorded, plan)
    if diff:
        more = f" (and {len(diff) - 1} more: {'; '.join(diff[1:4])}{'; ...' if len(diff) > 4 else ''})" \
            if len(diff) > 1 else ""
        raise _refuse(out_dir, f"was authored from another plan: {diff[0]}{more}")
    return True


def replace_tree(out_dir: Path) -> list[str]:
    """Remove what authoring wrote under `out_dir` (TREE_ENTRIES; plan.toml is rewritten after),
    nothing else: each entry is renamed into one hidden trash directory (a symlink moves as a
    link, its target untouched), which is then deleted. Only a folder that is a tree (plan.toml or
    stages/base.usda at its top) is touched. Returns the names removed."""
    out_dir = Path(out_dir)
    for stale in out_dir.iterdir():   # a replace killed before it emptied its trash
        if _TRASH.match(stale.name) and stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
    present = [n for n in TREE_ENTRIES if os.path.lexists(out_dir / n)]
    if not present:
        return []
    if not (out_dir / TREE_PLAN).is_file() and not tree_base_stage(out_dir).is_file():
        raise PlanError(f"{out_dir} holds {', '.join(present)} but is not an authored tree (no {TREE_PLAN}, no "
                        f"{STAGE_DIR}/{BASE_STAGE_FILE}), so --replace leaves it alone; fix: author into a fresh "
                        "--out, or remove those entries yourself")
    trash = Path(tempfile.mkdtemp(dir=out_dir, prefix=".replaced."))
    for name in present:
        os.rename(out_dir / name, trash / name)
    shutil.rmtree(trash)
    return present


def with_tree_poses(plan: Plan, out_dir: Path) -> tuple[Plan, Path | None]:
    """The plan pointed at the tree's byte copy of its pose file, `out_dir/inputs/<name>` (written
    atomically if missing), and the copy if this call wrote it (else None). A tree whose copy differs
    from the plan's pose file (sha256) is refused, so pose layers of old poses never mix with new ones."""
    if plan.poses.file is None:
        return plan, None
    from allo_usd.core.files import read_user_bytes, sha256_file, write_bytes_atomic
    from allo_usd.plan.posefile import MAX_POSE_FILE_BYTES

    src = Path(plan.poses.file)
    pose_file = plan.poses.pose_file()   # read and checked (PlanError naming FILE:LINE)
    data = read_user_bytes(src, MAX_POSE_FILE_BYTES, "pose file", "re-run when it is no longer replaced",
                           error=PlanError)   # the gate again: a file swapped for a FIFO since is refused, not read
    now = hashlib.sha256(data).hexdigest()
    if now != pose_file.sha256:
        raise PlanError(f"pose file {src} changed while it was read; fix: re-run when it is no longer edited")
    dest = Path(out_dir) / POSE_INPUTS / src.name
    wrote = None
    if dest.is_file():
        had = sha256_file(dest)
        if had != now:
            raise PlanError(f"pose file {src} changed since {out_dir} was authored from it (sha256 {had[:12]}... in "
                            f"the tree's copy {dest}, {now[:12]}... now); its pose layers were made from the old "
                            "poses; fix: restore the pose file (the tree's copy is the old one), or author into a "
                            "fresh --out, or pass --replace")
    else:
        write_bytes_atomic(dest, data)
        wrote = dest
    return plan.model_copy(update={"poses": plan.poses.model_copy(update={"file": str(dest.resolve())})}), wrote


def _broken_stage(stage: Path, exc: BaseException, copy: Path | None = None) -> LayerError:
    """The one error for a base stage that cannot be read (pxr's own message reduced to its last line)."""
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[-1].strip()
    also = f", and delete the tree's copy {copy} (or author with --replace)" if copy is not None else ""
    return LayerError(f"base stage {stage} cannot be read ({first[:300]}); fix: regenerate it (`make stage`, "
                      f"i.e. scripts/make_base_stage.py) or restore stages/ (git checkout stages){also}, then re-run")


def _stage_source(plan: Plan) -> Path:
    return plan.resolve_base_stage() if plan.station.source == "procedural" else Path(plan.station.source)


@contextmanager
def open_tree(plan: Plan, out_dir: Path, replace: bool = False):
    """Hold `out_dir` (tree_lock) as a tree for `plan` and yield the authoring context over it: the
    plan must be the one the tree records (check_tree_plan; `replace` first removes the tree's
    layers: replace_tree); the tree's own base stage (with_tree_stage), read whole before any
    scene (its rig, the station and the plan's anomaly assets: a broken stage is one LayerError
    naming it and the fix); `plan.toml` (the tree's record, and its root for allo_usd.usd.safety)
    and the sky of every plan day. `author` and `author_scene` start here."""
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit
    from allo_usd.usd.compose import copy_schema
    from allo_usd.usd.hazard import write_hazards

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tree_lock(out_dir):
        if replace:
            replace_tree(out_dir)   # plan.toml is rewritten below
        same = not replace and check_tree_plan(plan, out_dir)
        source, stages = _stage_source(plan), tree_base_stage(out_dir).parent
        had_stages = stages.exists()
        given = plan
        try:
            plan = with_tree_stage(plan, out_dir)
            write_hazards(plan, out_dir)   # the plan's own hazards, converted into OUT/hazards
        except (AlloError, KeyboardInterrupt):
            raise
        except Exception as exc:  # pxr's Tf.ErrorException (a RuntimeError) and the like
            raise _broken_stage(source, exc) from None
        plan, new_copy = with_tree_poses(plan, out_dir)
        ctx = AuthorContext(plan, out_dir, compute_sky(plan.dates.epochs(), Orbit(perilune_epoch=plan.perilune_epoch)))
        try:
            ctx.read_stage()
        except (DiskFullError, KeyboardInterrupt):
            raise
        except PlanError:   # a pose-file pose inside the station: nothing is kept of this run
            if new_copy is not None:
                new_copy.unlink()
                with suppress(OSError):
                    new_copy.parent.rmdir()   # if this run made it
            raise
        except Exception as exc:  # LayerError "re-author it" is a scene layer's fix, not a stage's
            if not had_stages:    # the copy this run made from a broken stage: do not keep it
                shutil.rmtree(stages, ignore_errors=True)
            raise _broken_stage(source, exc, stages if had_stages else None) from None
        copy_schema(out_dir)   # for other USD tools (allo_usd.usd.compose); this process uses the package's
        if not same:
            save_plan(given, out_dir / TREE_PLAN)
        record_tree_versions(out_dir)   # versions.json: the library versions of each run (never in a layer)
        yield ctx
