"""What a scene layer says it is: its allo: identity attributes and provenance, its anomaly objects
(asset, variant and model frame of each, as composed), and the check that every variant selection
names a variant. pxr only.

Labels come from the composed stage (docs/usd/what_renders.md, "Labels"):
- An anomaly object is the nearest ancestor-or-self of an anomaly-class mesh where the class label is
  applied (read_geometry._class_id): /World/Anomaly for the scene's planned anomaly, /World/Wrench
  for a user's `def Xform "Wrench" (references = @.../wrench.usda@)`, a mesh labelled on itself.
- Its asset is the stem of the file its direct references and payloads name (the project's anomaly
  assets are stages/anomalies/ASSET.usda, a plan's hazards hazards/ID/ID.usda: the stem is the asset
  name; a user's own file: its stem too, characters outside [A-Za-z0-9_-] as "_"); an object that
  references no file (inline geometry) is named by its prim. Two different files: refused.
- Its variant is the composed selection of its `variant` variant set (None without one).
- /World/Anomaly's allo:anomaly:asset / assetVariant must agree with that, where they are authored at
  least as strongly as the reference or selection they describe; a selection or reference authored
  in a stronger layer than the label supersedes it (a user's layer that picks `red` over the scene
  layer's `yellow`: the records say red); a label stronger than the composition it contradicts is
  refused in one line.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from allo_usd.core.errors import LayerError
from allo_usd.core.labels import ANOMALY
from allo_usd.core.scene_labels import SPLITS, TOKEN, VARIANTS, label_problem
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


def read_meta(stage, meshes=()) -> dict:
    """The scene's identity and labels. `meshes`: the MeshDescs read (their anomaly objects are
    listed in meta["anomalies"], each with its composed asset, variant and model frame)."""
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
        meta["anomaly"] |= {k: v for k, v in composed_labels(anomaly, check=True).items() if v is not None}
        meta["anomaly_model"] = anomaly_model(stage, anomaly)
    objects = sorted({m.object or m.path for m in meshes if m.class_id == ANOMALY})
    if objects:
        meta["anomalies"] = [anomaly_object(stage, stage.GetPrimAtPath(p)) for p in objects]
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


def _referenced_files(prim) -> list[str]:
    """The files the prim's own (not ancestral) references and payloads name at the strongest site that
    introduces any (absolute, strongest first, each once). Arcs the referenced file introduces in
    turn (its variants' payloads) build the asset; they do not say which asset it is. Internal
    references name no file."""
    from pxr import Pcp, Usd

    files, site = [], None
    for arc in Usd.PrimCompositionQuery(prim).GetCompositionArcs():
        if arc.GetArcType() not in (Pcp.ArcTypeReference, Pcp.ArcTypePayload) or arc.IsAncestral():
            continue
        intro = arc.GetIntroducingNode()
        here = (str(intro.path), intro.layerStack.identifier.rootLayer.identifier)
        site = site or here
        target = arc.GetTargetNode().layerStack.identifier.rootLayer
        if here != site or target.identifier == here[1]:
            continue
        path = target.realPath or target.identifier
        if path not in files:
            files.append(path)
    return files


def _strongest(prim, has) -> int | None:
    """The index in the prim's stack (0 strongest) of the first spec for which has(spec), else None."""
    return next((i for i, spec in enumerate(prim.GetPrimStack()) if has(spec)), None)


def composed_asset(prim) -> str:
    """The asset an anomaly object is (module docstring): its referenced file's stem, or its prim name."""
    files = _referenced_files(prim)
    if len(files) > 1:
        names = " and ".join(Path(f).name for f in files)
        raise LayerError(f"{prim.GetPath()} is one anomaly object but references {names}; reference one asset "
                         "per prim (put the other on a prim of its own)")
    name = Path(files[0]).stem if files else prim.GetName()
    return name if TOKEN.match(name) else "".join(c if TOKEN.match(c) else "_" for c in name)


def composed_variant(prim) -> str | None:
    """The composed selection of the prim's `variant` variant set (None without one or without a selection)."""
    if not prim.GetVariantSets().HasVariantSet("variant"):
        return None
    return prim.GetVariantSets().GetVariantSet("variant").GetVariantSelection() or None


def composed_labels(prim, check: bool = False) -> dict:
    """{"asset", "assetVariant"} of an anomaly prim as composed. `check`: a LayerError where its
    allo:anomaly:asset / assetVariant says otherwise and is authored at least as strongly as the
    reference or the variant selection it contradicts (module docstring)."""
    asset, variant = composed_asset(prim), composed_variant(prim)
    if check:
        arcs = _strongest(prim, lambda s: s.referenceList.GetAddedOrExplicitItems()
                          or s.payloadList.GetAddedOrExplicitItems())
        chosen = _strongest(prim, lambda s: "variant" in s.variantSelections)
        for attr, value, what, strength in ((A.ANOMALY_ASSET.name, asset, "references", arcs),
                                            (A.ANOMALY_ASSET_VARIANT.name, variant, "selects variant", chosen)):
            said = _attr_value(prim, attr)
            if said is None or said == value:
                continue
            label = _strongest(prim, lambda s: attr in s.properties and s.properties[attr].HasDefaultValue())
            if label is not None and strength is not None and strength < label:
                continue   # the reference or selection is stronger: it supersedes the label
            shown = (f"{Path(_referenced_files(prim)[0]).name}" if what == "references" and _referenced_files(prim)
                     else repr(value))
            raise LayerError(f"the layer says {attr.split(':')[-1]} {said!r} but {prim.GetPath()} {what} {shown}; "
                             f"fix {attr} or the {'reference' if what == 'references' else 'variant selection'}")
    return {"asset": asset, "assetVariant": variant}


def _attr_value(prim, name):
    attr = prim.GetAttribute(name)
    return attr.Get() if attr and attr.HasAuthoredValue() else None


def anomaly_object(stage, prim) -> dict:
    """One anomaly object's labels and model frame: path, asset, variant (composed), and anomaly_model's
    reference and local_to_world."""
    labels = composed_labels(prim)
    return {"path": str(prim.GetPath()), "asset": labels["asset"], "variant": labels["assetVariant"],
            **anomaly_model(stage, prim)}


def anomaly_prims(stage) -> list:
    """The stage's anomaly objects (the prims read_scene's anomaly-class meshes are part of), without
    reading the meshes: the same walk (active, defined, visible, outside /World/Rig and /Render) and
    label rule (read_geometry.class_and_object), /World/Anomaly first, then the others in path order."""
    from pxr import Usd, UsdGeom

    from allo_usd.usd.read_geometry import class_and_object

    found = set()
    it = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.PrimIsActive & Usd.PrimIsDefined & ~Usd.PrimIsAbstract))
    for prim in it:
        path = prim.GetPath()
        if (prim.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(prim).ComputeVisibility() == UsdGeom.Tokens.invisible
                or path.HasPrefix(layout.RIG) or path.HasPrefix(layout.RENDER)):
            it.PruneChildren()
        elif prim.IsA(UsdGeom.Mesh):
            cls, obj = class_and_object(prim)
            if cls == ANOMALY:
                found.add(obj)
    return [stage.GetPrimAtPath(p) for p in sorted(found, key=lambda p: (p != layout.ANOMALY, p))]
