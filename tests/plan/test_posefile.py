"""A plan's own poses (README, Your own poses): the pose file's formats and every error with its line,
the plan's pose numbers, and trees authored from file poses (their record, their cameras, the
station check and the pose file's tree copy on resume)."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from allo_usd.core.errors import PlanError
from allo_usd.core.geometry import matrix_to_quat
from allo_usd.core.paths import BASE_STAGE
from allo_usd.plan.model import (N_POSES, Anomalies, AnomalyChoice, Counts, Dates, Plan, Poses, Quality,
                                 grid_sizes)
from allo_usd.plan.posefile import (CSV_COLUMNS, MAX_POSE_DISTANCE_M, MAX_POSES, UserPose, parse_pose_file,
                                    read_pose_file, write_pose_file)

HEADER = ",".join(CSV_COLUMNS)
ROW = "a,train,1,2,3,1,0,0,0"


def _csv(*rows: str, header: str = HEADER, nl: str = "\n") -> bytes:
    return nl.join([header, *rows]).encode() + nl.encode()


def _obj(name="a", split="train", position=(1, 2, 3), q=(1, 0, 0, 0), **extra) -> dict:
    return {"name": name, "split": split, "position": list(position), "orientation_wxyz": list(q), **extra}


# ---------------------------------------------------------------------------------------------
# Parsing


def test_csv_any_column_order_bom_crlf_comments():
    data = "\ufeff# my poses\r\nqz,qy,qx,qw,z,y,x,split,name\r\n\r\n0,0,0,1,3,2,1,TEST,p_1\r\n" \
           "0,0.7071067811865476,0,0.7071067811865476,0,0,-40,train,p-2\r\n"
    poses = parse_pose_file(data.encode(), "mine.csv", ".csv")
    assert [(p.name, p.split, p.line) for p in poses] == [("p_1", "test", 4), ("p-2", "train", 5)]
    assert poses[0].position == (1.0, 2.0, 3.0)
    assert poses[0].orientation == (1.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(poses[1].rotation() @ [0, 0, -1], [-1, 0, 0], atol=1e-15)   # looks along -X


def test_json_line_numbers_of_each_object():
    text = '[\n  {"name": "a", "split": "train",\n   "position": [1, 2, 3], "orientation_wxyz": [1, 0, 0, 0]},\n\n' \
           '  {"name": "b", "split": "test", "position": [0, 0, -50], "orientation_wxyz": [0, 1, 0, 0]}\n]\n'
    poses = parse_pose_file(("\ufeff" + text).replace("\n", "\r\n").encode(), "mine.json", ".json")
    assert [(p.name, p.split, p.line) for p in poses] == [("a", "train", 2), ("b", "test", 5)]
    np.testing.assert_allclose(poses[1].rotation(), np.diag([1.0, -1.0, -1.0]))


def test_near_unit_quaternion_is_normalised():
    (p,) = parse_pose_file(_csv("a,train,0,0,0,1.0005,0,0,0"), "f.csv", ".csv")
    assert p.orientation == (1.0, 0.0, 0.0, 0.0)
    (p,) = parse_pose_file(_csv("a,train,0,0,0,0.5,0.5,0.5,0.5004"), "f.csv", ".csv")
    assert math.isclose(sum(c * c for c in p.orientation), 1.0, rel_tol=1e-15)


CSV_ERRORS = [
    (HEADER.replace(",qz", "") + "\n" + ROW[:-2] + "\n", 1, "missing columns \\['qz'\\]"),
    (HEADER + ",note\n" + ROW + ",hi\n", 1, "1 unknown column \\(column 10\\)"),
    (HEADER + ",x\n" + ROW + ",1\n", 1, "columns named twice"),
    (HEADER + "\n" + ROW + "\nb,test,1,two,3,1,0,0,0\n", 3, "y is not a number"),
    (HEADER + "\n" + ROW + "\nb,test,1,nan,3,1,0,0,0\n", 3, "not a finite number"),
    (HEADER + "\nb,test,1,2,inf,1,0,0,0\n", 2, "not a finite number"),
    (HEADER + "\nb,test,1,2,3,0,0,0,0\n", 2, "norm 0, not 1"),
    (HEADER + "\nb,test,1,2,3,1,0.1,0,0\n", 2, "norm 1.00499"),
    (HEADER + "\nb,validation,1,2,3,1,0,0,0\n", 2, "the split of pose 'b' is neither train nor test"),
    (HEADER + "\n" + ROW + "\n" + ROW + "\n", 3, "'a' is used twice \\(first on line 2\\)"),
    (HEADER + "\n,train,1,2,3,1,0,0,0\n", 2, "has no name"),
    (HEADER + "\nmy pose,train,1,2,3,1,0,0,0\n", 2, "the pose name is not an identifier"),
    (HEADER + "\n../x,train,1,2,3,1,0,0,0\n", 2, "is not an identifier"),
    (HEADER + "\n" + ROW + "\nb,test,1,2\n", 3, "4 values for 9 columns"),
    (HEADER + "\nfar,test,10001,0,0,1,0,0,0\n", 2, "10,001 m from the station"),
    ("", 1, "no header and no poses"),
    (HEADER + "\n", 1, "holds no poses"),
]


@pytest.mark.parametrize("text,line,match", CSV_ERRORS)
def test_csv_errors_name_file_line_and_fix(text, line, match):
    with pytest.raises(PlanError, match=match) as e:
        parse_pose_file(text.encode(), "poses.csv", ".csv")
    assert str(e.value).startswith(f"pose file poses.csv:{line}: ") and "; fix: " in str(e.value)


JSON_ERRORS = [
    ("", 1, "is empty"),
    ('{"name": "a"}', 1, "not a JSON list"),
    ("[]", 1, "holds no poses"),
    ('[\n {"name": "a",\n  "split": "train" "position": []}]', 3, "not valid JSON"),
    ([_obj(), 5], 3, "entry 2 is not an object \\(a JSON number\\)"),
    ([_obj(), _obj("b", note=1)], 3, "1 unknown key"),
    ([_obj(), {"name": "b", "split": "test", "position": [1, 2, 3]}], 3, "missing keys \\['orientation_wxyz'\\]"),
    ([_obj(), _obj("b", position=(1, 2))], 3, "position is not a list of 3 numbers \\(it holds 2 values\\)"),
    ([_obj(), _obj("b", position=(1, "2", 3))], 3, "y is not a number \\(a JSON string\\)"),
    ([_obj(), _obj("b", position=(1, 2, True))], 3, "z is not a number \\(a JSON boolean\\)"),
    ([_obj(), _obj("b", q=(2, 0, 0, 0))], 3, "has norm 2"),
    ([_obj(), _obj("b", split="val")], 3, "the split of pose 'b'"),
    ([_obj(), _obj("a")], 3, "used twice"),
    ([_obj(), _obj(1)], 3, "has no name"),
    ([_obj(), _obj("b", position=(0, 0, -2e4))], 3, "20,000 m from the station"),
]


@pytest.mark.parametrize("content,line,match", JSON_ERRORS)
def test_json_errors_name_file_line_and_fix(content, line, match):
    text = content if isinstance(content, str) else "[\n" + ",\n".join(json.dumps(o) for o in content) + "\n]\n"
    with pytest.raises(PlanError, match=match) as e:
        parse_pose_file(text.encode(), "poses.json", ".json")
    assert str(e.value).startswith(f"pose file poses.json:{line}: ") and "; fix: " in str(e.value)


SECRET = "HUNTER2"   # stands for text the file holds and its user never meant to show


@pytest.mark.parametrize("text,suffix", [
    (f"PATH=/bin,{SECRET}=x\n", ".csv"),                                   # a file that is no pose file at all
    (f"{HEADER},{SECRET}\n{ROW},1\n", ".csv"),                               # an unknown column
    (f"{HEADER}\n{SECRET} x,train,1,2,3,1,0,0,0\n", ".csv"),                 # a name that is no identifier
    (f"{HEADER}\nb,{SECRET},1,2,3,1,0,0,0\n", ".csv"),                      # a split
    (f"{HEADER}\nb,train,{SECRET},2,3,1,0,0,0\n", ".csv"),                  # a number
    (f'[{{"{SECRET}": 1}}]', ".json"),                                         # an unknown key
    (f'["{SECRET}"]', ".json"),                                                # an entry that is no object
    (f'[{{"name": "a", "split": "train", "position": "{SECRET}", "orientation_wxyz": [1, 0, 0, 0]}}]', ".json"),
    (f'[{{"name": "a", "split": "train", "position": [1, "{SECRET}", 3], "orientation_wxyz": [1, 0, 0, 0]}}]',
     ".json"),
    (f'[{{"name": "{SECRET} x", "split": "train", "position": [1, 2, 3], "orientation_wxyz": [1, 0, 0, 0]}}]',
     ".json"),
    (f'[{{"name": "a", "split": "{SECRET}", "position": [1, 2, 3], "orientation_wxyz": [1, 0, 0, 0]}}]', ".json"),
])
def test_a_refusal_never_quotes_the_files_text(text, suffix):
    """A plan may name any file as its pose file: what the file holds never reaches the message, which
    names the line, the column or key and the rule instead."""
    with pytest.raises(PlanError) as e:
        parse_pose_file(text.encode(), f"poses{suffix}", suffix)
    msg = str(e.value)
    assert SECRET.lower() not in msg.lower() and "; fix: " in msg and "\n" not in msg, msg
    assert msg.startswith(f"pose file poses{suffix}:"), msg


def test_too_many_poses_and_not_utf8():
    rows = [f"p{i},train,{i % 90},0,0,1,0,0,0" for i in range(MAX_POSES + 1)]
    with pytest.raises(PlanError, match=f"poses.csv:{MAX_POSES + 2}: more than 10,000 poses"):
        parse_pose_file(_csv(*rows), "poses.csv", ".csv")
    with pytest.raises(PlanError, match="poses.csv:2: the file is not UTF-8"):
        parse_pose_file(_csv("a,train,1,2,3,1,0,0,0\xff").replace(b"\xc3\xbf", b"\xff"), "poses.csv", ".csv")


def test_read_pose_file_errors(tmp_path):
    with pytest.raises(PlanError, match="does not exist; fix"):
        read_pose_file(tmp_path / "none.csv")
    with pytest.raises(PlanError, match="neither .csv nor .json"):
        read_pose_file(tmp_path / "poses.txt")
    f = tmp_path / "p.csv"
    f.write_bytes(_csv(ROW))
    pf = read_pose_file(f)
    assert pf.name == "p.csv" and len(pf.sha256) == 64 and pf.source(pf.poses[0]) == "p.csv:2"


def test_distance_cap_is_the_readers():
    from allo_usd.usd.reader_bounds import MAX_CAMERA_DISTANCE_M

    assert MAX_POSE_DISTANCE_M == MAX_CAMERA_DISTANCE_M


_coord = st.floats(-MAX_POSE_DISTANCE_M / 2, MAX_POSE_DISTANCE_M / 2, allow_nan=False)
_quat = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(lambda q: sum(c * c for c in q) > 0.01)
_poses = st.lists(st.tuples(st.from_regex(r"[A-Za-z][A-Za-z0-9_-]{0,10}", fullmatch=True),
                            st.sampled_from(["train", "test"]), st.tuples(_coord, _coord, _coord), _quat),
                  min_size=1, max_size=8, unique_by=lambda t: t[0])


@settings(max_examples=60, deadline=None)
@given(poses=_poses, suffix=st.sampled_from([".csv", ".json"]))
@pytest.mark.slow
def test_round_trip(tmp_path_factory, poses, suffix):
    written = []
    for name, split, pos, q in poses:
        n = math.sqrt(sum(c * c for c in q))
        written.append(UserPose(name, split, pos, tuple(c / n for c in q), 0))
    path = write_pose_file(tmp_path_factory.mktemp("rt") / f"poses{suffix}", written)
    back = read_pose_file(path).poses
    assert [(p.name, p.split, p.position) for p in back] == [(p.name, p.split, p.position) for p in written]
    for a, b in zip(back, written):
        np.testing.assert_allclose(a.orientation, b.orientation, rtol=0, atol=1e-15)
    lines = path.read_text().splitlines()
    assert [p.line for p in back] == ([i + 2 for i in range(len(written))] if suffix == ".csv" else
                                      [i + 1 for i, text in enumerate(lines) if text == " {"])


# ---------------------------------------------------------------------------------------------
# The plan


def _base_poses():
    from allo_usd.usd.stage_geometry import StageGeometry

    return {p.index: p for p in StageGeometry(BASE_STAGE).poses()}


def _like(index: int, name: str, split: str) -> UserPose:
    """A file pose exactly at built-in pose `index` of the shipped base stage."""
    p = _base_poses()[index]
    return UserPose(name, split, tuple(map(float, p.position)), tuple(map(float, matrix_to_quat(p.rotation))), 0)


def file_plan(pose_file: Path, sigmas=(1.0, 0.2), **poses) -> Plan:
    return Plan(name="own-poses", dates=Dates(days=1),
                poses=Poses(file=str(pose_file), position_sigma_m=sigmas[0], angle_sigma_rad=sigmas[1],
                            **{"train": [], "test": [], **poses}),
                anomalies=Anomalies(assets=[AnomalyChoice(id="power_drill", variants=["yellow"])], depths=[0, 1]),
                counts=Counts(normal_train=1, normal_test=1, anomalous_test=2),
                quality=Quality(resolution=(64, 36), samples=4), base_stage=str(BASE_STAGE))


@pytest.fixture(scope="module")
def pose_csv(tmp_path_factory) -> Path:
    return write_pose_file(tmp_path_factory.mktemp("poses") / "station_poses.csv",
                           [_like(1, "port_truss", "train"), _like(41, "node_view", "test")])


def test_plan_numbers_file_poses_after_the_rig(pose_csv):
    plan = file_plan(pose_csv, train=[1, 2], test=[41])
    assert plan.poses.numbers("train") == [1, 2, N_POSES + 1] and plan.poses.numbers("test") == [41, N_POSES + 2]
    assert grid_sizes(plan)["normal_train"] == 3 and grid_sizes(plan)["anomalous_test"] == 2 * 2
    only_file = file_plan(pose_csv)   # "instead of": the lists emptied; the file's poses count
    assert only_file.poses.numbers("train") == [N_POSES + 1]
    with pytest.raises(ValueError, match="no poses"):
        Poses(train=[], test=[])
    with pytest.raises(ValueError, match="norm 2"):
        bad = pose_csv.parent / "bad.csv"
        bad.write_bytes(_csv("a,train,1,2,3,2,0,0,0"))
        Poses(file=str(bad))
    with pytest.raises(ValueError, match="position_sigma_m"):
        Poses(position_sigma_m=-1)
    with pytest.raises(ValueError, match="angle_sigma_rad"):
        Poses(angle_sigma_rad=3)


def test_plan_file_round_trips_through_toml(pose_csv, tmp_path):
    from allo_usd.plan.io import load_plan, save_plan

    plan = file_plan(pose_csv, sigmas=(0.5, 0.1))
    assert load_plan(save_plan(plan, tmp_path / "p.toml")) == plan


# ---------------------------------------------------------------------------------------------
# Authored trees


_STAGES: list = []   # keep the stages the prims below belong to open


def _world(layer: Path):
    from pxr import Usd

    _STAGES.append(Usd.Stage.Open(str(layer)))
    return _STAGES[-1].GetPrimAtPath("/World")


def _camera(layer: Path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(layer))
    cam = stage.GetPrimAtPath("/World/Camera")
    m = np.array(UsdGeom.Xformable(cam).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    return m[:3, 3], m[:3, :3]


@pytest.fixture(scope="module")
def exact_tree(pose_csv, tmp_path_factory):
    """Sigma 0: every camera at its file pose exactly; normal train, normal test and anomalous test."""
    from allo_usd.run.author import author

    out = tmp_path_factory.mktemp("exact")
    return out, author(file_plan(pose_csv, sigmas=(0.0, 0.0)), out, progress=False, workers=1)


@pytest.mark.slow
def test_file_poses_author_at_their_pose_with_their_record(exact_tree, pose_csv):
    from allo_usd.usd.inspect import describe, format_description

    out, done = exact_tree
    scenes = {p.relative_to(out / "scenes").parts[:2]: p for p in done.paths}
    assert set(scenes) == {("train", "normal"), ("test", "normal"), ("test", "anomaly")}
    file = read_pose_file(pose_csv)
    for (split, _), layer in scenes.items():
        pose = next(p for p in file.poses if p.split == split)
        world = _world(layer)
        assert world.GetAttribute("allo:pose").Get() == N_POSES + 1 + file.poses.index(pose)
        assert world.GetAttribute("allo:poseName").Get() == pose.name
        assert world.GetAttribute("allo:poseSource").Get() == f"station_poses.csv:{pose.line}"
        assert world.GetAttribute("allo:poseSourceSha256").Get() == file.sha256
        assert world.GetAttribute("allo:positionSigma").Get() == 0.0   # not the paper's: recorded
        pos, rot = _camera(layer)
        assert tuple(pos) == pose.position                            # sigma 0: exactly the file pose
        np.testing.assert_allclose(rot, pose.rotation(), rtol=0, atol=1e-12)
        d = describe(layer)
        assert d["pose_file"] == {"name": pose.name, "source": f"station_poses.csv:{pose.line}",
                                  "sha256": file.sha256}
        assert f"pose file: {pose.name} from station_poses.csv:{pose.line}" in format_description(d)
    assert (out / "inputs" / "station_poses.csv").read_bytes() == pose_csv.read_bytes()
    assert "inputs/" not in (out / "plan.toml").read_text()   # the plan as given, not the tree copy


@pytest.mark.slow
def test_perturbation_uses_the_plans_sigmas(pose_csv, tmp_path):
    from allo_usd.core.seeds import scene_seed
    from allo_usd.run.author import author

    plan = file_plan(pose_csv, sigmas=(0.5, 0.1))
    (layer,) = author(plan, tmp_path, limit=1, progress=False, workers=1).paths
    world, pose = _world(layer), read_pose_file(pose_csv).poses[0]
    assert (world.GetAttribute("allo:positionSigma").Get(), world.GetAttribute("allo:angleSigma").Get()) == (0.5, 0.1)
    rng = np.random.default_rng(scene_seed(plan.seeds[0], 0, N_POSES + 1)[0])
    dpos, dang = rng.normal(0, 0.5, 3), rng.normal(0, 0.1, 3)
    np.testing.assert_allclose(world.GetAttribute("allo:cameraOffsetPosition").Get(), dpos, rtol=0, atol=0)
    np.testing.assert_allclose(world.GetAttribute("allo:cameraOffsetRotation").Get(), dang, rtol=0, atol=0)
    pos, _ = _camera(layer)
    np.testing.assert_allclose(pos, np.array(pose.position) + dpos, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_default_sigmas_and_rig_poses_author_no_new_attributes(tmp_path):
    from allo_usd.run.author import author

    plan = Plan(name="rig", dates=Dates(days=1), poses=Poses(train=[1], test=[41]), counts=Counts(normal_train=1),
                anomalies=Anomalies(assets=[]), quality=Quality(resolution=(64, 36), samples=4),
                base_stage=str(BASE_STAGE))
    (layer,) = author(plan, tmp_path, limit=1, progress=False, workers=1).paths
    pose_layer = (tmp_path / "poses" / "s2030" / "d000_p01.usda").read_text()
    assert "allo:pose = 1" in pose_layer
    assert not any(a in pose_layer for a in ("poseName", "poseSource", "Sigma"))
    assert not (tmp_path / "inputs").exists()


@pytest.mark.slow
def test_pose_inside_the_station_is_refused_with_its_line(pose_csv, tmp_path):
    from allo_usd.run.author import author
    from allo_usd.usd.stage_geometry import StageGeometry

    points, _ = StageGeometry(BASE_STAGE).station_triangles()
    inside = UserPose("in_the_wall", "test", tuple(map(float, points[0])), (1.0, 0.0, 0.0, 0.0), 0)
    bad = write_pose_file(tmp_path / "bad.csv", [*read_pose_file(pose_csv).poses, inside])
    out = tmp_path / "out"
    with pytest.raises(PlanError, match="pose file bad.csv:4: pose 'in_the_wall' at .* inside the station.*fix: move"):
        author(file_plan(bad), out, progress=False, workers=1)
    assert not (out / "scenes").exists() and not (out / "poses").exists() and not (out / "inputs").exists()


@pytest.mark.slow
def test_edited_pose_file_on_resume_is_refused(pose_csv, tmp_path):
    from allo_usd.run.author import author

    mine = tmp_path / "poses.csv"
    shutil.copyfile(pose_csv, mine)
    out = tmp_path / "out"
    author(file_plan(mine), out, limit=1, progress=False, workers=1)
    original = mine.read_bytes()
    mine.write_bytes(original.replace(b"port_truss", b"port_trusz"))
    with pytest.raises(PlanError, match="poses.csv changed since .* was authored from it .*fix: restore"):
        author(file_plan(mine), out, limit=2, progress=False, workers=1)
    assert len(list((out / "scenes").rglob("*.usda"))) == 1
    mine.write_bytes(original)   # restored: the run resumes, but not with other sigmas (plan.toml compares them)
    with pytest.raises(PlanError, match="poses.position_sigma_m 1.0 in the tree, 0.5 in the plan given"):
        author(file_plan(mine, sigmas=(0.5, 0.2)), out, limit=2, progress=False, workers=1)
    assert len(author(file_plan(mine), out, limit=2, progress=False, workers=1).paths) == 2


def test_opencv_conversion_in_the_docs():
    """The module doc's rule: OpenCV camera-to-world (w, x, y, z) -> (-x, w, z, -y) is this convention,
    R = R_cv @ diag(1, -1, -1): the camera looks along OpenCV's +z and its +Y is OpenCV's -y."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
        r_cv = UserPose("cv", "train", (0, 0, 0), (w, x, y, z), 1).rotation()
        r = UserPose("usd", "train", (0, 0, 0), (-x, w, z, -y), 1).rotation()
        np.testing.assert_allclose(r, r_cv @ np.diag([1.0, -1.0, -1.0]), atol=1e-12)
        np.testing.assert_allclose(r @ [0, 0, -1], r_cv @ [0, 0, 1], atol=1e-12)


@pytest.mark.skipif(not os.path.exists("/proc/self/environ"), reason="no /proc here")
@pytest.mark.parametrize("target", ["/proc/self/environ", "/proc/self/mounts"])
def test_a_pose_file_linked_to_a_pseudo_file_is_refused_and_nothing_of_it_shown(tmp_path, target):
    """/proc/self/environ passed the gate as a regular file of size 0 and its first line (the process's
    environment) was quoted as the CSV header: refused by the gate now, the message names the rule."""
    link = tmp_path / "poses.csv"
    link.symlink_to(target)
    with open(target, "rb") as f:
        content = [e.decode(errors="replace") for e in f.read().replace(b"\0", b"\n").splitlines() if len(e) >= 8]
    with pytest.raises(PlanError) as e:
        read_pose_file(link)
    msg = str(e.value)
    assert "is a pseudo-file" in msg and "fix: point it at a file on disk" in msg and "\n" not in msg, msg
    assert not [c for c in content if c in msg], msg
