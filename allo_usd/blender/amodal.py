"""The `amodal` pass: the planned anomaly's (/World/Anomaly's) full silhouette, as if nothing stood in front of it.

A second render of the scene Blender already holds, right after the main one (blender.render.render_current,
within `anomaly_alone`): every object but the anomaly's meshes (station, bodies, sun lamps, the spot) is
made invisible to camera rays (`visible_camera = False`; they still exist, so nothing is rebuilt), and
the render is mask-only:
1 sample, no bounces, no adaptive sampling, no denoiser, no depth or normal pass, no compositor.
The object index pass then holds the anomaly wherever a camera ray meets it, whatever hides it in
the main render. Both renders take the first sample at the same place (same seed), so the visible
anomaly pixels of the class mask are a subset of these (tests/output/test_annotations_pose.py).

Everything changed is put back afterwards (in a `finally`), value for value as read from Blender, so
a warm session (blender.session) goes on patching the scene it believes it shows, and the next render
is the one a fresh build would make. Cost against the RGB render: docs/benchmarks/bench_amodal.md.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from allo_usd.core.labels import ANOMALY
from allo_usd.usd import layout
from allo_usd.usd.description import SceneDescription

# (property, value) of the mask-only settings: Cycles' and the view layer's.
_CYCLES = (("samples", 1), ("use_adaptive_sampling", False), ("use_denoising", False), ("max_bounces", 0))
_LAYER = (("use_pass_z", False), ("use_pass_normal", False))


def _planned(desc: SceneDescription) -> set[str]:
    """The Blender object names (mesh paths) of the planned anomaly: the meshes of the anomaly object
    /World/Anomaly (MeshDesc.object). Another anomaly object (a user's second hazard) is not in the
    pass: its full silhouette is ray-cast over its own meshes (output.annotations.anomaly_record)."""
    return {m.path for m in desc.meshes if m.class_id == ANOMALY and m.object_path == layout.ANOMALY}


@contextmanager
def anomaly_alone(desc: SceneDescription):
    """Within: the Blender scene shows the planned anomaly (/World/Anomaly) alone to camera rays, mask-only
    (module docstring); after: every value changed is back as it was read."""
    import bpy

    keep = _planned(desc)

    scene = bpy.context.scene
    layer = scene.view_layers[0]
    saved: list[tuple[object, str, object]] = []

    def set_(owner, prop: str, value) -> None:
        saved.append((owner, prop, getattr(owner, prop)))
        setattr(owner, prop, value)

    try:
        for obj in scene.collection.objects:
            if obj.type != "CAMERA" and obj.name not in keep and obj.visible_camera:
                set_(obj, "visible_camera", False)
        for prop, value in _CYCLES:
            set_(scene.cycles, prop, value)
        for prop, value in _LAYER:
            set_(layer, prop, value)
        set_(scene.render, "use_compositing", False)
        yield
    finally:
        for owner, prop, value in reversed(saved):
            setattr(owner, prop, value)


def amodal_mask(desc: SceneDescription, ids: np.ndarray) -> np.ndarray:
    """(H, W) uint8: ANOMALY (2) where the object ids of the render `anomaly_alone` made show the planned
    anomaly (/World/Anomaly), else 0 (STEM_mask.png's convention)."""
    from allo_usd.blender.build import object_ids

    anomaly_ids = [i for i, (path, cls) in enumerate(object_ids(desc), start=1)
                   if cls == ANOMALY and path == layout.ANOMALY]
    return np.where(np.isin(ids, anomaly_ids), np.uint8(ANOMALY), np.uint8(0))
