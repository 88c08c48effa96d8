"""An anomaly asset's triangles in its own frame: what the dataset's BOP models (allo_usd.output.bop_models)
are made of.

The model frame is the frame the BOP poses use (docs/formats/coco_bop.md): the anomaly prim's own, which
is the referenced asset file's default prim. So the asset file is opened alone, its `variant` selected
(in the stage's session layer: nothing is written), and every rendered mesh under the default prim is
mapped into the default prim's frame (its relative transform, not the default prim's own ops, which the
scene's anomaly prim replaces). Points stay in the file's units, as the scene reads them (metres for
every asset this project authors). Faces are fan-triangulated (allo_usd.assets.mesh.fan_triangulate),
and turned to counter-clockwise for a left-handed mesh.

The file is read as any user layer: every file its composition reads is checked before USD opens it
(allo_usd.usd.dependencies.walk: allowed roots, regular files, bounded sizes), the composed stage again
(allo_usd.usd.safety.check_stage), and every mesh is held to allo_usd.usd.reader_bounds.mesh_topology.
Anything refused is a LayerError naming the file and the fix.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from allo_usd.core import fixedmath as fm
from allo_usd.core.errors import LayerError

VARIANT_SET = "variant"   # the anomaly assets' variant set (allo_usd.usd.asset.write_interface)


@dataclass(frozen=True)
class ModelMesh:
    points: np.ndarray      # (N, 3) float64, the model frame, the file's units (metres)
    triangles: np.ndarray   # (M, 3) int64 indices into points, counter-clockwise seen from outside


def read_model(path: str | Path, variant: str | None) -> ModelMesh:
    """The triangles of the asset file `path` with `variant` selected (None or "": the file's own
    selection), in its default prim's frame; LayerError when it is refused or holds no mesh."""
    from pxr import Tf, Usd, UsdGeom

    from allo_usd.usd import schema
    from allo_usd.assets.mesh import fan_triangulate
    from allo_usd.usd.dependencies import tf_message, walk
    from allo_usd.usd.reader_bounds import mesh_topology, object_meshes
    from allo_usd.usd.safety import check_stage

    path = Path(path)
    schema.register()
    if not path.is_file():
        raise LayerError(f"model {path} does not exist; fix: keep the authored tree the renders were made from "
                         "beside the dataset, or re-render")
    opened = walk(path)   # every file it reads, checked before USD opens any
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise LayerError(f"model {path} is not a readable USD file ({tf_message(exc)[:200]}); fix: re-author "
                         "the tree") from None
    del opened
    root = stage.GetDefaultPrim() if stage is not None else None
    if root is None or not root.IsValid():
        raise LayerError(f"model {path} has no default prim; fix: re-author the tree")
    if variant:
        vset = root.GetVariantSets().GetVariantSet(VARIANT_SET)
        if variant not in vset.GetVariantNames():
            raise LayerError(f"model {path} has no variant {variant!r}; fix: re-author the tree")
        with Usd.EditContext(stage, stage.GetSessionLayer()):
            vset.SetVariantSelection(variant)
    if stage.GetCompositionErrors():
        raise LayerError(f"model {path} does not compose; fix: restore the files it names or re-author the tree")
    check_stage(stage, path)
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    points, triangles, count = [], [], 0
    for prim in object_meshes(root, lambda limit: LayerError(f"model {path} holds more than {limit:,} prims; fix: "
                                                             "give a single object model")):
        pts, counts, indices = mesh_topology(prim)
        m = np.array(cache.ComputeRelativeTransform(prim, root)[0], dtype=np.float64).T   # column vectors
        tris = fan_triangulate(counts, indices)
        if UsdGeom.Mesh(prim).GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
            tris = tris[:, [0, 2, 1]]
        points.append(fm.apply(m[:3, :3], pts.astype(np.float64)) + m[:3, 3])
        triangles.append(tris + count)
        count += len(pts)
    if not points:
        raise LayerError(f"model {path} (variant {variant!r}) has no rendered mesh; fix: re-author the tree")
    return ModelMesh(np.concatenate(points), np.concatenate(triangles).astype(np.int64))
