"""What a scene layer says it is: its allo: identity attributes and provenance, the anomaly's asset,
variant and model frame, and the check that every variant selection names a variant. pxr only."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from allo_usd.core.errors import LayerError
from allo_usd.core.scene_labels import SPLITS, VARIANTS, label_problem
from allo_usd.usd import attributes as A
from allo_usd.usd import layout


def check_variants(prim) -> None:
    """Every variant selection names a variant the prim's asset has (else USD silently composes none)."""
    if not prim.HasVariantSets():
        return
    sets = prim.GetVariantSets()
    for name in sets.GetNames():
        vset = sets.GetVariantSet(name)
        selection, choices = vset.GetVariantSelection(), vset.GetVariantNames()
        if selection not in choices and (selection or prim.GetPath().name == "Anomaly"):
            raise LayerError(f"{prim.GetPath()}: variant {name}={selection!r} is not one of {choices}; choose one of "
                             "those (unknown anomaly variant?)")


def read_meta(stage) -> dict:
    world = stage.GetDefaultPrim()
    meta = {}
    for attr in world.GetAttributes():
        name = attr.GetName()
        if name.startswith(A.NAMESPACE):
            value = attr.Get()
            meta[name[len(A.NAMESPACE):]] = tuple(value) if hasattr(value, "__len__") and not isinstance(value, str) else value
    provenance = dict(stage.GetRootLayer().customLayerData.get("allo", {}))
    meta["provenance"] = provenance
    anomaly = stage.GetPrimAtPath(layout.ANOMALY)
    if anomaly and anomaly.IsActive():
        meta["anomaly"] = {a.GetName().split(":")[-1]: a.Get() for a in anomaly.GetAttributes()
                           if a.GetName().startswith(A.ANOMALY_PREFIX)}
        meta["anomaly_model"] = anomaly_model(stage, anomaly)
    problem = label_problem(meta, required=False)   # dataset's check (core.scene_labels): never record what it refuses
    if problem:
        raise LayerError(f"{stage.GetRootLayer().identifier}: {problem} ({layout.WORLD}'s {A.SPLIT.name}, "
                         f"{A.VARIANT.name} and {layout.ANOMALY}'s {A.ANOMALY_PREFIX}* attributes); fix the layer: "
                         f"{A.SPLIT.name} is {' or '.join(SPLITS)}, {A.VARIANT.name} {' or '.join(VARIANTS)}")
    return meta


def anomaly_model(stage, prim) -> dict:
    """The anomaly's model frame for its pose (output.annotations): the prim's local-to-world (column
    vectors; its meshes' points map into this frame) and the file its strongest reference or payload
    names, relative to the root layer's directory (None when it is authored inline)."""
    from pxr import Usd, UsdGeom

    m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()), dtype=np.float64).T
    ref = next((spec.layer.ComputeAbsolutePath(r.assetPath) for spec in prim.GetPrimStack()
                for r in (*spec.referenceList.GetAddedOrExplicitItems(), *spec.payloadList.GetAddedOrExplicitItems())
                if r.assetPath), None)
    here = Path(stage.GetRootLayer().realPath or ".").parent
    return {"reference": None if not ref else os.path.relpath(ref, here), "local_to_world": m.tolist()}
