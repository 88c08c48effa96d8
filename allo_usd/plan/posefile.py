"""A plan's own camera poses: a pose file (CSV or JSON, chosen by the extension) read into UserPoses.

Conventions (the same as the built-in rig's, allo_usd.scene.rig):
- `position` (x, y, z): metres in the stage frame, which is the station frame, Z up;
- `orientation` (w, x, y, z): a unit quaternion rotating camera axes into the stage frame
  (camera-to-stage). The camera looks down its own -Z with +Y up, as UsdGeom.Camera does;
- `split`: "train" or "test"; `name`: a short identifier (letters, digits, _ and -, starting with a
  letter, at most 64 characters), unique within the file.

CSV: a header row naming the columns name, split, x, y, z, qw, qx, qy, qz, in any order; a column
that is not one of these is refused (a misspelt `qw ` would otherwise be silently dropped).
Blank lines and lines starting with '#' are skipped. JSON: a list of objects
{"name", "split", "position": [x, y, z], "orientation_wxyz": [w, x, y, z]} (no other keys). A UTF-8
byte-order mark and CRLF line ends are accepted. Every problem is a PlanError naming FILE:LINE (for
JSON, the line where the pose's object starts), the column or key, the rule and the fix.

A message never quotes the file's text: a plan may name any file as its pose file (a shared plan, a
link to a file the user never meant to show), and its bytes must not reach a terminal or a CI log.
Columns and keys are named by position or by their known names; a refused value is described, never
shown. Only values that passed their own check are shown: a pose name that is an identifier, and
numbers as parsed (a position's distance, a quaternion's norm).

A quaternion whose norm is within QUAT_TOLERANCE of 1 is normalised; one further off (or zero) is
refused, since it most likely holds a typo or a different convention.

From OpenCV (x right, y down, z forward), a camera-to-world rotation R_cv becomes this
convention's R = R_cv @ diag(1, -1, -1) (flip the camera's y and z axes); for a quaternion
q_cv = (w, x, y, z) that is q = q_cv * (0, 1, 0, 0), i.e. (w, x, y, z) -> (-x, w, z, -y). An OpenCV
world-to-camera pose (rvec, tvec) first becomes camera-to-world: R_cv = R(rvec).T and
position = -R(rvec).T @ tvec.

No pxr here (the plan layer): allo_usd.run.samples (AuthorContext) turns these into the scene layer's CameraPoses.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from allo_usd.core.errors import PlanError
from allo_usd.core.files import MAX_JSON_DEPTH, input_problem, json_too_deep, read_user_bytes

CSV_COLUMNS = ("name", "split", "x", "y", "z", "qw", "qx", "qy", "qz")
JSON_KEYS = ("name", "split", "position", "orientation_wxyz")
SPLITS = ("train", "test")
MAX_POSES = 10_000                # poses in one file (the built-in rig has 50)
MAX_POSE_FILE_BYTES = 4_000_000   # far above MAX_POSES lines
QUAT_TOLERANCE = 1e-3             # | |q| - 1 | above this is refused, below it q is normalised
MAX_POSE_DISTANCE_M = 1e4         # = allo_usd.usd.reader_bounds.MAX_CAMERA_DISTANCE_M (tests/plan/test_posefile.py checks)
NAME_PATTERN = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")
SUFFIXES = (".csv", ".json")


@dataclass(frozen=True)
class UserPose:
    """One pose of a pose file (see the module doc for the conventions)."""

    name: str
    split: str                                        # train | test
    position: tuple[float, float, float]              # metres, stage frame (Z up)
    orientation: tuple[float, float, float, float]    # (w, x, y, z), unit, camera-to-stage
    line: int                                         # 1-based line of the file

    def rotation(self) -> np.ndarray:
        """The (3, 3) camera-to-stage rotation matrix of `orientation`."""
        w, x, y, z = self.orientation
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@dataclass(frozen=True)
class PoseFile:
    """A pose file, read: its base name, sha256 and poses in file order."""

    name: str
    sha256: str
    poses: tuple[UserPose, ...]

    def source(self, pose: UserPose) -> str:
        """Where `pose` came from: 'BASENAME:LINE'."""
        return f"{self.name}:{pose.line}"


class _Reader:
    def __init__(self, label: str, text: bool):
        self.label, self.text = label, text   # text: numbers come as text (CSV)
        self.poses: list[UserPose] = []
        self.names: dict[str, int] = {}

    def fail(self, line: int, what: str, fix: str) -> PlanError:
        return PlanError(f"pose file {self.label}:{line}: {what}; fix: {fix}")

    def number(self, line: int, field: str, value) -> float:
        """A finite float from CSV text or a JSON number (not a JSON string or bool)."""
        if isinstance(value, bool) or not isinstance(value, (int, float, str) if self.text else (int, float)):
            raise self.fail(line, f"{field} is not a number (a JSON {_json_type(value)})",
                            f"write {field} as a decimal number")
        try:
            f = float(value.strip()) if isinstance(value, str) else float(value)
        except (ValueError, OverflowError):
            raise self.fail(line, f"{field} is not a number", f"write {field} as a decimal number, e.g. 1.5") from None
        if not math.isfinite(f):
            raise self.fail(line, f"{field} is not a finite number (NaN or infinite)", f"give a finite {field}")
        return f

    def add(self, line: int, name, split, xyz, wxyz) -> None:
        if len(self.poses) >= MAX_POSES:
            raise self.fail(line, f"more than {MAX_POSES:,} poses", "split the poses over several plans")
        if not isinstance(name, str) or not name.strip():
            raise self.fail(line, "the pose has no name", "give every pose a unique name, e.g. port_truss_1")
        name = name.strip()
        if not NAME_PATTERN.match(name):
            raise self.fail(line, "the pose name is not an identifier",
                            "use letters, digits, _ and -, starting with a letter, at most 64 characters")
        if name in self.names:
            raise self.fail(line, f"pose name {name!r} is used twice (first on line {self.names[name]})",
                            "give every pose a unique name")
        if not isinstance(split, str) or split.strip().lower() not in SPLITS:
            raise self.fail(line, f"the split of pose {name!r} is neither train nor test",
                            "write train or test")
        pos = tuple(self.number(line, f, v) for f, v in zip("xyz", xyz))
        dist = math.sqrt(sum(c * c for c in pos))
        if dist > MAX_POSE_DISTANCE_M:
            raise self.fail(line, f"pose {name!r} at {pos} m is {dist:,.0f} m from the station, beyond "
                                  f"{MAX_POSE_DISTANCE_M:,.0f} m", "give the position in metres in the stage frame")
        q = tuple(self.number(line, f, v) for f, v in zip(("qw", "qx", "qy", "qz"), wxyz))
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > QUAT_TOLERANCE:
            raise self.fail(line, f"orientation {q} of pose {name!r} has norm {norm:.6g}, not 1 (within "
                                  f"{QUAT_TOLERANCE:g})", "give a unit quaternion (w, x, y, z), camera-to-stage")
        self.names[name] = line
        self.poses.append(UserPose(name, split.strip().lower(), pos, tuple(c / norm for c in q), line))


def _read_csv(r: _Reader, text: str) -> None:
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise r.fail(1, "the file holds no header and no poses", f"write a header row {','.join(CSV_COLUMNS)} "
                                                                   "and one row per pose")
    rows = list(csv.reader(io.StringIO("\n".join(ln for _, ln in lines))))
    head_line, header = lines[0][0], [c.strip().lower() for c in rows[0]]
    extra = [i + 1 for i, c in enumerate(header) if c not in CSV_COLUMNS]   # by position: never the text
    missing = [c for c in CSV_COLUMNS if c not in header]
    dup = sorted({c for c in header if c in CSV_COLUMNS and header.count(c) > 1})
    if extra or missing or dup:
        what = "; ".join(s for s in (_unknown_columns(extra),
                                     f"missing columns {missing}" if missing else "",
                                     f"columns named twice {dup}" if dup else "") if s)
        raise r.fail(head_line, f"header: {what}",
                     f"the header must name exactly the columns {','.join(CSV_COLUMNS)} (any order)")
    col = {c: header.index(c) for c in CSV_COLUMNS}
    for (line, _), row in zip(lines[1:], rows[1:]):
        if len(row) != len(header):
            raise r.fail(line, f"{len(row)} values for {len(header)} columns",
                         f"give one value per column ({','.join(header)})")
        v = {c: row[i] for c, i in col.items()}
        r.add(line, v["name"], v["split"], (v["x"], v["y"], v["z"]), (v["qw"], v["qx"], v["qy"], v["qz"]))


def _unknown_columns(positions: list[int]) -> str:
    """Unknown header columns by position ("2 unknown columns (columns 3, 10)"), "" for none."""
    if not positions:
        return ""
    shown = ", ".join(map(str, positions[:10])) + (", ..." if len(positions) > 10 else "")
    n = len(positions)
    return f"{n} unknown column{'s' if n > 1 else ''} (column{'s' if n > 1 else ''} {shown})"


def _json_type(value) -> str:
    """A JSON value's type in words (what a message says instead of the value)."""
    for t, word in ((bool, "boolean"), (str, "string"), (int, "number"), (float, "number"), (list, "list"),
                    (dict, "object")):
        if isinstance(value, t):
            return word
    return "null" if value is None else type(value).__name__


def _line_of(text: str, index: int) -> int:
    return text.count("\n", 0, index) + 1


def _read_json(r: _Reader, text: str) -> None:
    dec = json.JSONDecoder()
    i = len(text) - len(text.lstrip())
    if i == len(text):
        raise r.fail(1, "the file is empty", 'write a JSON list of {"name", "split", "position", "orientation_wxyz"}')
    if text[i] != "[":
        raise r.fail(_line_of(text, i), "the file is not a JSON list",
                     'write a list: [{"name": ..., "split": ..., "position": [...], "orientation_wxyz": [...]}, ...]')
    deep = json_too_deep(text, MAX_JSON_DEPTH)   # json.loads recurses: a RecursionError on a few thousand levels
    if deep is not None:
        raise r.fail(deep, f"values nested over {MAX_JSON_DEPTH} levels deep", "a pose file is a list of objects "
                     'holding lists of numbers: [{"name": ..., "position": [x, y, z], ...}]')
    try:
        json.loads(text)
    except json.JSONDecodeError as exc:
        raise r.fail(exc.lineno, f"not valid JSON ({exc.msg})", "correct the JSON syntax there") from None
    i += 1
    ws = re.compile(r"\s*")
    first = True
    while True:
        i = ws.match(text, i).end()
        if text[i] == "]":
            break
        if not first:   # a ',' (json.loads above guarantees it)
            i = ws.match(text, i + 1).end()
        first = False
        line = _line_of(text, i)
        obj, i = dec.raw_decode(text, i)
        if not isinstance(obj, dict):
            raise r.fail(line, f"entry {len(r.poses) + 1} is not an object (a JSON {_json_type(obj)})",
                         'write {"name", "split", "position", "orientation_wxyz"}')
        extra = sum(k not in JSON_KEYS for k in obj)   # counted: a key's text is never shown
        missing = [k for k in JSON_KEYS if k not in obj]
        if extra or missing:
            what = "; ".join(s for s in (f"{extra} unknown key{'s' if extra > 1 else ''}" if extra else "",
                                         f"missing keys {missing}" if missing else "") if s)
            raise r.fail(line, what, f"give exactly the keys {', '.join(JSON_KEYS)}")
        for key, n in (("position", 3), ("orientation_wxyz", 4)):
            if not isinstance(obj[key], list) or len(obj[key]) != n:
                held = f"{len(obj[key])} values" if isinstance(obj[key], list) else f"a JSON {_json_type(obj[key])}"
                raise r.fail(line, f"{key} is not a list of {n} numbers (it holds {held})", f"give {n} numbers")
        r.add(line, obj["name"], obj["split"], obj["position"], obj["orientation_wxyz"])


def parse_pose_file(data: bytes, label: str, suffix: str) -> list[UserPose]:
    """The poses of a pose file's bytes; `label` names it in errors, `suffix` (.csv/.json) is its format."""
    r = _Reader(label, suffix.lower() == ".csv")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise r.fail(_line_of(data[:exc.start].decode("utf-8", "replace"), exc.start),
                     "the file is not UTF-8 text", "save it as UTF-8") from None
    if suffix.lower() == ".csv":
        _read_csv(r, text)
    elif suffix.lower() == ".json":
        _read_json(r, text)
    else:
        raise PlanError(f"pose file {label}: unknown format {suffix!r}; fix: name it .csv or .json")
    if not r.poses:
        raise r.fail(1, "the file holds no poses", "add at least one pose, or remove poses.file from the plan")
    return r.poses


_CACHE: dict[tuple, PoseFile] = {}


def read_pose_file(path: str | Path) -> PoseFile:
    """Read and check a pose file (see the module doc); raises PlanError naming FILE:LINE and the fix.
    Read through the project's read gate (core.files.read_user_bytes): a FIFO, a device such as
    /dev/zero, a directory or a file over MAX_POSE_FILE_BYTES is refused by os.stat before it is
    opened, and the read stops at the bound. Cached by (path, size, mtime), since a plan is
    validated more than once."""
    p = Path(path)
    if p.suffix.lower() not in SUFFIXES:
        raise PlanError(f"poses.file {str(path)!r} is neither .csv nor .json; fix: name the pose file .csv or .json")
    fix = {"missing": "give poses.file relative to the directory you run allo-usd in (or an absolute path)",
           "too_big": f"at most {MAX_POSES:,} poses, one per line",
           "not_regular": "point poses.file at a regular CSV or JSON file (not a FIFO, device or directory)",
           "": "check the path and its permissions"}
    key = None
    if input_problem(p, MAX_POSE_FILE_BYTES) is None:   # by os.stat alone: a FIFO is never opened
        try:
            st = p.stat()
            key = (str(p.resolve()), st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)
        except OSError:   # gone since: the read below says so
            pass
        if key in _CACHE:
            return _CACHE[key]
    data = read_user_bytes(p, MAX_POSE_FILE_BYTES, "pose file", fix, error=PlanError)
    poses = parse_pose_file(data, str(path), p.suffix)
    out = PoseFile(p.name, hashlib.sha256(data).hexdigest(), tuple(poses))
    if key is not None:
        _CACHE[key] = out
    return out


def write_pose_file(path: str | Path, poses: list[UserPose]) -> Path:
    """Write `poses` as a pose file (format by the extension), round-trip exact (repr of floats)."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        items = [{"name": q.name, "split": q.split, "position": list(q.position),
                  "orientation_wxyz": list(q.orientation)} for q in poses]
        p.write_text(json.dumps(items, indent=1) + "\n")
    else:
        rows = [",".join(CSV_COLUMNS)] + [",".join([q.name, q.split, *map(repr, q.position), *map(repr, q.orientation)])
                                          for q in poses]
        p.write_text("\n".join(rows) + "\n")
    return p
