"""One read gate for every file read from a user (core.files.read_user_bytes/_text/_json):
a FIFO, a device (/dev/zero), a directory or a link out of the allowed folder is refused by os.stat
before any open, an oversized file says "too big (N bytes > LIMIT)", and JSON nested deeper than
MAX_JSON_DEPTH is refused by a bracket scan before json.loads could raise RecursionError. Used for pose
files, render records NAME.json in `dataset` and in the resume check, and plan files. Also: a layer's
bad allo:split is refused by the reader, as `dataset` refuses it.

Commands that would hang on a FIFO if the gate let it through run in a subprocess with a timeout, so
a regression fails, not hangs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from allo_usd.core.errors import LayerError, PlanError
from allo_usd.core.files import (MAX_JSON_DEPTH, MAX_RECORD_BYTES, InputRefused, file_problem, json_too_deep,
                                 read_user_json, read_user_text)
from allo_usd.plan.posefile import MAX_POSE_FILE_BYTES, read_pose_file

from tests.support.helpers import ROOT
from tests.support.renders import fake_render

HANG = 90   # seconds: far above what any of these commands takes, far below forever
POSE_HEADER = "name,split,x,y,z,qw,qx,qy,qz\n"


def _cli(*args, timeout: float = HANG) -> subprocess.CompletedProcess:
    """`allo-usd ARGS` in a subprocess; a hang is a test failure (TimeoutExpired), not a stuck run."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", "from allo_usd.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=timeout)


def _lines(r: subprocess.CompletedProcess) -> list[str]:
    return [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith("reading ")]


def _sparse(path: Path, size: int, head: bytes = b"") -> Path:
    with open(path, "wb") as f:   # no disk used
        f.write(head)
        f.truncate(size)
    return path


def _deep(levels: int) -> str:
    return "[" * levels + "]" * levels


# ---------------------------------------------------------------------------------------------
# The gate itself


@pytest.mark.process
def test_the_gate_refuses_a_fifo_without_opening_it(tmp_path):
    fifo = tmp_path / "r.json"
    os.mkfifo(fifo)
    code = ("from allo_usd.core.files import read_user_json, InputRefused\n"
            f"try:\n    read_user_json({str(fifo)!r}, 1000, 'render record', 'fix it')\n"
            "except InputRefused as e:\n    print(e.kind, '|', e)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=HANG,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.stdout.startswith("not_regular | render record ") and "is not a regular file" in r.stdout, r
    assert "; fix: fix it" in r.stdout


@pytest.mark.parametrize("target", ["/dev/zero", "DIR"])
def test_the_gate_refuses_devices_and_directories(tmp_path, target):
    link = tmp_path / "x.json"
    link.symlink_to(tmp_path if target == "DIR" else target)
    with pytest.raises(InputRefused) as err:
        read_user_json(link, 1 << 20, "render record")
    assert err.value.kind == "not_regular" and str(link) in str(err.value)


def test_an_oversized_file_is_too_big_not_missing(tmp_path):
    big = _sparse(tmp_path / "big.json", MAX_RECORD_BYTES + 1, b"{}")
    with pytest.raises(InputRefused) as err:
        read_user_json(big, MAX_RECORD_BYTES, "render record", {"too_big": "remove it", "": "other"})
    assert err.value.kind == "too_big"
    assert f"is too big ({MAX_RECORD_BYTES + 1:,} bytes > 4 MiB allowed); fix: remove it" in str(err.value)
    assert file_problem(big, MAX_RECORD_BYTES).startswith("is too big (")


def test_a_link_out_of_the_allowed_folder_is_refused(tmp_path):
    inside, outside = tmp_path / "in", tmp_path / "out"
    inside.mkdir(), outside.mkdir()
    (outside / "secret.json").write_text("{}")
    (inside / "r.json").symlink_to(outside / "secret.json")
    with pytest.raises(InputRefused) as err:
        read_user_json(inside / "r.json", 1000, "render record", roots=(inside,))
    assert err.value.kind == "outside" and str(outside / "secret.json") in str(err.value)
    (inside / "ok.json").write_text('{"a": 1}')
    assert read_user_json(inside / "ok.json", 1000, "render record", roots=(inside,)) == {"a": 1}


def test_deep_json_is_refused_by_depth_not_recursion_error(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("\n" + _deep(200_000))
    with pytest.raises(InputRefused) as err:
        read_user_json(deep, 1 << 20, "render record")
    assert err.value.kind == "too_deep" and f"over {MAX_JSON_DEPTH} levels deep (at line 2)" in str(err.value)
    ok = tmp_path / "ok.json"
    ok.write_text(json.dumps({"s": "[" * 500, "v": json.loads(_deep(MAX_JSON_DEPTH - 1))}))   # brackets in strings
    assert read_user_json(ok, 1 << 20, "render record")["s"] == "[" * 500
    assert json_too_deep(_deep(MAX_JSON_DEPTH)) is None and json_too_deep(_deep(MAX_JSON_DEPTH + 1)) == 1
    assert json_too_deep('["\\"[[[", ' + _deep(MAX_JSON_DEPTH - 1) + "]") is None   # an escaped quote in a string


def test_text_that_is_not_utf8_names_the_byte(tmp_path):
    f = tmp_path / "x.toml"
    f.write_bytes(b"name = 1\n\xff")
    with pytest.raises(InputRefused, match=r"x.toml is not UTF-8 text \(byte 9 is not\)"):
        read_user_text(f, 1000, "plan")


# ---------------------------------------------------------------------------------------------
# Pose files


@pytest.mark.process
def test_a_fifo_pose_file_fails_author_at_once(tmp_path):
    fifo = tmp_path / "poses.csv"
    os.mkfifo(fifo)
    plan = tmp_path / "plan.toml"
    plan.write_text(f'name = "fifo"\n\n[poses]\nfile = "{fifo}"\n')
    r = _cli("author", plan, "--out", tmp_path / "out", "--no-progress")
    lines = _lines(r)
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert f"pose file {fifo} is not a regular file" in lines[0] and "fix: " in lines[0]


def test_a_pose_file_linked_to_dev_zero_is_refused_unread(tmp_path):
    link = tmp_path / "poses.csv"
    link.symlink_to("/dev/zero")
    with pytest.raises(PlanError, match="is not a regular file.*fix: point poses.file at a regular"):
        read_pose_file(link)
    big = _sparse(tmp_path / "big.csv", MAX_POSE_FILE_BYTES + 1, POSE_HEADER.encode())
    with pytest.raises(PlanError, match=r"big.csv is too big \("):
        read_pose_file(big)


def test_deep_pose_json_is_one_plan_error_naming_its_line(tmp_path):
    f = tmp_path / "poses.json"
    f.write_text('[\n{"name": "a", "split": "train", "position": ' + _deep(100_000) + "}]\n")
    with pytest.raises(PlanError) as err:
        read_pose_file(f)
    message = str(err.value)
    assert message.startswith(f"pose file {f}:2: values nested over {MAX_JSON_DEPTH} levels deep") and "fix:" in message
    assert "\n" not in message


# ---------------------------------------------------------------------------------------------
# Render records


@pytest.mark.process
def test_dataset_refuses_hostile_render_records_with_notes_and_keeps_the_rest(tmp_path):
    renders = tmp_path / "renders"
    fake_render(renders, "ok")
    os.mkfifo(renders / "fifo.json")
    (renders / "zero.json").symlink_to("/dev/zero")
    (renders / "deep.json").write_text(_deep(100_000))
    _sparse(renders / "big.json", MAX_RECORD_BYTES + 1, b"{}")
    r = _cli("dataset", renders, "--out", tmp_path / "ds")
    notes = " ".join(_lines(r))
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    for name, why in (("fifo", "is not a regular file"), ("zero", "resolves to /dev/zero, outside"),
                      ("deep", f"nests values over {MAX_JSON_DEPTH} levels deep"),
                      ("big", f"is too big ({MAX_RECORD_BYTES + 1:,} bytes")):
        assert f"{renders / name}.json: {why}" in notes, (name, notes)
    assert "4 render(s) refused" in notes
    assert [p.name for p in (tmp_path / "ds").rglob("*ok.png")], "the good record is assembled"


@pytest.mark.process
def test_an_oversized_record_alone_is_named_too_big_not_no_record(tmp_path):
    renders = tmp_path / "renders"
    renders.mkdir()
    _sparse(renders / "big.json", MAX_RECORD_BYTES + 1, b"{}")
    r = _cli("dataset", renders, "--out", tmp_path / "ds")
    text = " ".join(_lines(r))
    assert r.returncode in (1, 2) and "too big" in text and "no NAME.json render record" not in text, r.stderr


@pytest.mark.process
def test_the_resume_check_reads_a_fifo_record_as_not_done(tmp_path):
    """manifest._meta (render's "is it done?") on a FIFO NAME.json: {} at once, so the scene renders again."""
    fifo = tmp_path / "scene.json"
    os.mkfifo(fifo)
    (tmp_path / "zero.json").symlink_to("/dev/zero")
    (tmp_path / "deep.json").write_text(_deep(100_000))
    code = ("from allo_usd.run.render_index import _meta\n"
            f"print([_meta(p) for p in ({str(fifo)!r}, {str(tmp_path / 'zero.json')!r}, "
            f"{str(tmp_path / 'deep.json')!r})])\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=HANG,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0 and r.stdout.strip() == "[{}, {}, {}]", r


# ---------------------------------------------------------------------------------------------
# A layer's split: refused when read, as dataset refuses it


def test_a_bad_split_is_refused_by_the_reader_as_dataset_refuses_it(tiny_base, tmp_path):
    from pxr import Sdf

    from allo_usd.core.scene_labels import label_problem
    from allo_usd.usd.read import read_scene
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    assert read_scene(layer).meta["split"] == "train"
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    sdf.GetAttributeAtPath("/World.allo:split").default = "../../escaped"
    sdf.Save()
    with pytest.raises(LayerError) as err:
        read_scene(layer)
    message = str(err.value)
    assert "split '../../escaped' is not one of train, test" in message and "allo:split is train or test" in message
    assert label_problem({"split": "../../escaped", "variant": "normal"}) in message   # the dataset's own words


@pytest.mark.process
def test_render_refuses_a_bad_split_and_records_nothing(tiny_base, tmp_path):
    from pxr import Sdf

    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    layer = write_scene_layer(make_spec(), tmp_path / "s.usda", tiny_base)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    sdf.GetAttributeAtPath("/World.allo:split").default = "validation"
    sdf.Save()
    r = _cli("render", layer, "--out", tmp_path / "out", "--device", "cpu", timeout=300)
    lines = _lines(r)
    assert r.returncode == 2 and len(lines) == 1 and "split 'validation'" in lines[0], r.stderr
    assert not list((tmp_path / "out").glob("*.json")) if (tmp_path / "out").exists() else True
