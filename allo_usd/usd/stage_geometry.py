"""What a base stage offers authoring before any scene layer exists, read with pxr: the camera
rig's poses and the lens they were chosen through (`read_rig`, `read_rig_lens`), world-space
triangles for ray casting (`read_triangles`), and the station's joints (`station_joints`,
`joint_op`; `set_joint_angles` poses them in a stage's session layer, the files untouched, and
`read_joint_angles` reports them). `StageGeometry` and `scene_inputs` hand these to
allo_usd.scene.resolve. A stage is opened through the reader's gate (allo_usd.usd.read.open_stage)
and its transforms and meshes are checked as the reader checks them (allo_usd.usd.reader_bounds).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from allo_usd.usd import attributes as A
from allo_usd.usd import layout
from allo_usd.core.errors import LayerError
from allo_usd.core import fixedmath as fm
from allo_usd.usd.read import open_stage
from allo_usd.usd.reader_bounds import mesh_topology, world_matrix


def read_rig(base_stage: str | Path) -> list:
    """The base camera poses recorded in the base stage (the stage, not code, is the record)."""
    from pxr import Usd, UsdGeom

    from allo_usd.scene.spec import CameraPose

    stage = open_stage(base_stage)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    poses = []
    for prim in stage.GetPrimAtPath(layout.RIG).GetChildren():
        if not prim.HasAPI("AlloCameraPoseAPI"):
            continue
        m = world_matrix(cache, prim)
        poses.append(CameraPose(int(prim.GetAttribute(A.POSE_INDEX.name).Get()),
                                str(prim.GetAttribute(A.POSE_SPLIT.name).Get()), m[:3, 3].copy(), m[:3, :3].copy()))
    if not poses:
        raise LayerError(f"{base_stage} has no camera poses under {layout.RIG}; regenerate the base stage")
    return sorted(poses, key=lambda p: p.index)


def read_rig_lens(base_stage: str | Path, width: int | None = None):
    """The lens the rig's views were chosen through (core.camera_model.CameraModel), as each pose's
    AlloCameraPoseAPI records it in UsdGeom.Camera's units (the poses are Xforms, not cameras). The
    principal-point offset is in pixels of a `width`-pixel image (needs `width` when one is recorded)."""
    from allo_usd.core.camera_model import CameraModel

    stage = open_stage(base_stage)
    found = set()
    for prim in stage.GetPrimAtPath(layout.RIG).GetChildren():
        if prim.HasAPI("AlloCameraPoseAPI"):
            found.add(tuple(tuple(v) if hasattr(v, "__len__") else v
                            for v in (prim.GetAttribute(a.name).Get() for a in A.POSE_LENS)))
    if len(found) != 1:
        raise LayerError(f"{base_stage}: the rig's poses record {len(found)} different lenses under {layout.RIG} "
                         "(one expected); regenerate the base stage")
    from decimal import Decimal

    def mm(v) -> float:  # tenths of a unit (a float32) -> mm, from its shortest decimal: 0.36 -> 36.0, not 36.0000014
        return float(Decimal(str(np.float32(v))) * 100)

    *lens, clip = next(iter(found))
    focal, h_ap, v_ap, h_off, v_off = (mm(v) for v in lens)
    offset = (0.0, 0.0)
    if (h_off, v_off) != (0.0, 0.0):
        if width is None:
            raise LayerError(f"{base_stage}: the rig's lens has a principal-point offset; give the image width")
        px_per_mm = width / h_ap
        offset = (-h_off * px_per_mm + 0.0, v_off * px_per_mm + 0.0)
    clip = tuple(float(Decimal(str(np.float32(c)))) for c in clip)
    return CameraModel(focal, h_ap, v_ap, clip, offset)


def read_triangles(layer_path: str | Path, root: str, variant: str | None = None,
                   joint_angles: dict[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World-space (points, triangles) of every mesh under `root`, for ray casting; `joint_angles`
    ({joint prim name: degrees}) sets the joint op of each AlloJointAPI prim under `root` first (in
    the stage's session layer: the files are not touched)."""
    from pxr import Usd, UsdGeom

    from allo_usd.assets.mesh import fan_triangulate

    stage = open_stage(layer_path)
    prim = stage.GetPrimAtPath(root) if root else stage.GetDefaultPrim()
    if not prim:
        raise LayerError(f"{layer_path} has no prim {root}")
    if joint_angles:
        set_joint_angles(stage, prim, joint_angles, layer_path)
    if variant is not None:
        vs = prim.GetVariantSets().GetVariantSet("variant")
        if variant not in vs.GetVariantNames():
            raise LayerError(f"{layer_path}: unknown variant {variant!r}; choose one of {vs.GetVariantNames()}")
        vs.SetVariantSelection(variant)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    pts, tris, off = [], [], 0
    for p in Usd.PrimRange(prim):
        if p.IsA(UsdGeom.Mesh):
            points, counts, indices = mesh_topology(p)
            local = points.astype(np.float64)
            m = world_matrix(cache, p)
            pts.append(fm.apply(m[:3, :3], local) + m[:3, 3])   # fixed-order sums: placement reads these
            t = fan_triangulate(counts, indices)
            tris.append(t + off)
            off += len(local)
    if not pts:
        raise LayerError(f"{layer_path}: no meshes under {root}")
    return np.concatenate(pts), np.concatenate(tris)


def joint_op(prim):
    """The joint-angle xformOp of an AlloJointAPI prim: its last op, a single-axis rotate."""
    from pxr import UsdGeom

    ops = UsdGeom.Xformable(prim).GetOrderedXformOps()
    if not ops or ops[-1].GetOpType() not in (UsdGeom.XformOp.TypeRotateX, UsdGeom.XformOp.TypeRotateY,
                                              UsdGeom.XformOp.TypeRotateZ):
        raise LayerError(f"joint {prim.GetPath()} has no single-axis rotate as its last xformOp (its joint angle); "
                         "fix the base stage: regenerate it with scripts/make_base_stage.py")
    return ops[-1]


def station_joints(stage, root=None) -> dict:
    """{joint prim name: prim} of every AlloJointAPI prim under `root` (default the station)."""
    from pxr import Usd

    top = root if root is not None else stage.GetPrimAtPath(layout.STATION)
    if not top:
        return {}
    return {p.GetName(): p for p in Usd.PrimRange(top) if p.HasAPI("AlloJointAPI")}


def set_joint_angles(stage, root, angles: dict[str, float], where) -> None:
    """Author each joint's angle in the stage's session layer (the files stay as they are)."""
    from pxr import Usd

    joints = station_joints(stage, root)
    unknown = sorted(set(angles) - set(joints))
    if unknown:
        raise LayerError(f"{where}: the station has no joints {unknown} (it has {sorted(joints)}); fix: regenerate "
                         "the base stage with scripts/make_base_stage.py, or turn station.track_sun off")
    with Usd.EditContext(stage, stage.GetSessionLayer()):
        for name, value in angles.items():
            joint_op(joints[name]).Set(float(value))


def read_joint_angles(layer_path: str | Path) -> dict[str, dict]:
    """{joint name: {path, op, angle, axis, lower, upper, tracks}} of the station's joints as a layer composes them."""
    stage = open_stage(layer_path)
    out = {}
    for name, prim in station_joints(stage).items():
        op = joint_op(prim)
        rec = {"path": str(prim.GetPath()), "op": op.GetOpName(), "angle": float(op.Get())}
        for key, attr in (("axis", A.JOINT_AXIS), ("lower", A.JOINT_LOWER_LIMIT), ("upper", A.JOINT_UPPER_LIMIT),
                          ("tracks", A.JOINT_TRACKS)):
            value = prim.GetAttribute(attr.name).Get()
            rec[key] = value if isinstance(value, str) or value is None else float(value)
        out[name] = rec
    return out


class StageGeometry:
    """A base stage's geometry for scene resolution (allo_usd.scene.resolve.StationGeometry): its
    camera rig, the station's triangles and each anomaly asset's triangles, read with pxr."""

    def __init__(self, base_stage: str | Path, assets: dict | None = None):
        self.base_stage = Path(base_stage)
        self.assets = dict(assets or {})   # {anomaly id: interface layer} of a plan's own hazards

    def poses(self) -> list:
        return read_rig(self.base_stage)

    def station_triangles(self, angles: dict[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The station's triangles, its joints (read from the base stage, so an edited stage is seen)
        at `angles` ({joint name: degrees}) or as the base stage has them."""
        return read_triangles(self.base_stage, layout.STATION, joint_angles=angles)

    def anomaly_triangles(self, asset: str, variant: str) -> tuple[np.ndarray, np.ndarray]:
        path = self.assets.get(asset, self.base_stage.parent / "anomalies" / f"{asset}.usda")
        return read_triangles(path, layout.asset_root(asset), variant)


def scene_inputs(base_stage: str | Path, sky, perilune_epoch: str, assets: dict | None = None,
                 track_sun: bool = False):
    """SceneInputs over a base stage (and a plan's own hazards, {id: interface layer}): what
    allo_usd.scene.resolve needs, read from USD. `track_sun`: the station's arrays follow each day's Sun."""
    from allo_usd.scene.resolve import SceneInputs

    return SceneInputs(StageGeometry(base_stage, assets), sky, perilune_epoch, track_sun=track_sun)
