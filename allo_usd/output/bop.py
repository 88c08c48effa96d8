"""BOP-shaped pose files of the dataset (`bop/CATEGORY/`), as the BOP toolkit (bop_toolkit_lib.inout)
and BlenderProc's BopWriter write them, so 6D-pose code reads the anomaly's pose as it reads BOP's:

    bop/CATEGORY/camera.json                    BOP's sensor file (fx, fy, cx, cy, width, height, depth_scale)
    bop/CATEGORY/models.json                    obj_id -> model_id (ASSET/VARIANT), asset, variant, path
    bop/CATEGORY/SPLIT/CHUNK/scene_camera.json  per image: cam_K, depth_scale, cam_R_w2c, cam_t_w2c
    bop/CATEGORY/SPLIT/CHUNK/scene_gt.json      per image: [{obj_id, cam_R_m2c, cam_t_m2c, model_scale}]
    bop/CATEGORY/SPLIT/CHUNK/scene_gt_info.json per image: [{bbox_obj, bbox_visib, px_count_all, ...}]
    bop/CATEGORY/SPLIT/CHUNK/rgb/IMID.png       the dataset image (a hard link)
    bop/CATEGORY/SPLIT/CHUNK/depth/IMID.png     uint16 depth, depth * depth_scale = mm (depth pass only)
    bop/CATEGORY/SPLIT/CHUNK/mask/IMID_GTID.png        full silhouette in the image, 0/255 (the amodal pass, else the render JSON's amodal_segmentation)
    bop/CATEGORY/SPLIT/CHUNK/mask_visib/IMID_GTID.png  visible part, 0/255 (from the class mask)

Why this shape: BOP's DATASET/SPLIT/SCENE/ layout, the category as the dataset. A BOP "scene" is
a chunk of 1000 images, as BlenderProc's `frames_per_chunk`: IMID is the image's manifest index
(unique in the category, kept across re-runs) and CHUNK = IMID // 1000, so a re-run that adds
scenes rewrites only the chunks that gain them.

BOP's units and conventions: row-major 3x3 rotations, translations in mm, the OpenCV camera frame
(x right, y down, z forward), u = fx x / z + cx (the render JSON's pixel convention,
allo_usd.output.annotations: pixel centres at integers). `cam_t_m2c` maps the model, in mm and
scaled by `model_scale` (the anomaly prim's scale, kept out of R so that R is a proper rotation):
x_cam_mm = R @ (diag(model_scale) @ x_model_m * 1000) + t. Boxes are bop_toolkit's
`misc.calc_2d_bbox`: [x_min, y_min, x_max - x_min, y_max - y_min] of the pixel indices (no + 1,
unlike COCO), [-1, -1, -1, -1] when nothing is visible. scene_gt_info follows the toolkit's
scripts/calc_gt_info.py (gt_info): px_count_all, bbox_obj and visib_fract = px_count_visib /
px_count_all count the full silhouette on its 3W x 3H canvas, the part outside the image included
(bbox_obj unclipped: it may start below 0 or end past the image); px_count_visib and bbox_visib
inside the image. `px_count_valid` (silhouette pixels in the image with a non-zero depth) wherever the
depth pass was rendered (the silhouette in the image: the amodal pass's, else the recorded RLE's). An anomalous image whose render records no pose
(rendered before poses were recorded) has empty lists, and one recorded before the canvas was
counted keeps its in-image values, labelled `silhouette` "image"; `allo-usd dataset` says how many
of each.

Depth: DEPTH_SCALE = 10 (mm per unit: 1 cm steps, up to 655.35 m). A 1920x1080 arm camera sees
the station from metres to a few hundred metres; 1 mm steps (BOP's 1.0) would end at 65.5 m. The
float EXR in depth/ keeps the exact metres. Pixels without a valid depth (background, the Moon,
the Earth and the Sun, thousands of km away, anything past 65535 * DEPTH_SCALE mm) are 0, BOP's
"no depth measurement".
"""

from __future__ import annotations

import json
import math

import numpy as np

DEPTH_SCALE = 10.0          # mm per unit of the uint16 depth PNG
CHUNK = 1000                # images per BOP scene folder (BlenderProc's frames_per_chunk)
NO_BOX = [-1, -1, -1, -1]   # bop_toolkit's box of an invisible object


def chunk_of(index: int) -> str:
    return f"{int(index) // CHUNK:06d}"


def depth_png(depth_m: np.ndarray, depth_scale: float = DEPTH_SCALE) -> np.ndarray:
    """uint16 BOP depth (value * depth_scale = mm) of a float depth in metres; 0 where the depth is
    not finite, not positive, or past the range (BOP's invalid)."""
    d = np.asarray(depth_m, dtype=np.float64)
    units = np.rint(np.where(np.isfinite(d), d, 0.0) * (1000.0 / depth_scale))
    return np.where((units > 0) & (units <= 65535), units, 0).astype(np.uint16)


def bop_box(xyxy) -> list[int]:
    """bop_toolkit's [x, y, w, h] (w = x_max - x_min) of an inclusive pixel box, NO_BOX for None."""
    if xyxy is None:
        return list(NO_BOX)
    x0, y0, x1, y1 = (int(v) for v in xyxy)
    return [x0, y0, x1 - x0, y1 - y0]


def _numbers(value, n: int) -> list[float] | None:
    """`value` as a list of n finite floats, else None (the render JSON is not trusted)."""
    if not isinstance(value, list) or len(value) != n:
        return None
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in value):
        return None
    return [float(v) for v in value]


def _matrix(value, n: int) -> np.ndarray | None:
    if not isinstance(value, list) or len(value) != n:
        return None
    rows = [_numbers(r, n) for r in value]
    return None if any(r is None for r in rows) else np.array(rows)


def camera_entry(camera: dict, depth_scale: float = DEPTH_SCALE) -> dict | None:
    """scene_camera.json's entry of an image from its render JSON's `annotations.camera`: cam_K
    (row-major 9), depth_scale, cam_R_w2c (row-major 9), cam_t_w2c (mm); None if it is not there."""
    k = _matrix(camera.get("K_px"), 3) if isinstance(camera, dict) else None
    w2c = _matrix(camera.get("world_to_cam_opencv"), 4) if isinstance(camera, dict) else None
    if k is None or w2c is None:
        return None
    return {"cam_K": k.ravel().tolist(), "depth_scale": depth_scale, "cam_R_w2c": w2c[:3, :3].ravel().tolist(),
            "cam_t_w2c": (w2c[:3, 3] * 1000.0).tolist()}


def sensor(entry: dict, width: int, height: int) -> dict:
    """BOP's DATASET/camera.json from one image's scene_camera entry."""
    k = entry["cam_K"]
    return {"cx": k[2], "cy": k[5], "depth_scale": entry["depth_scale"], "fx": k[0], "fy": k[4],
            "height": int(height), "width": int(width)}


def pose(anomaly: dict) -> dict | None:
    """{cam_R_m2c, cam_t_m2c, model_scale} from the render JSON's `annotations.anomaly.pose`
    (tests/output/test_coco_bop.py reprojects it), or None if it records none."""
    p = anomaly.get("pose") if isinstance(anomaly, dict) else None
    if not isinstance(p, dict):
        return None
    r, t = _numbers(p.get("cam_R_m2c"), 9), _numbers(p.get("cam_t_m2c"), 3)
    scale = _numbers(p.get("model_scale"), 3) if p.get("model_scale") is not None else [1.0, 1.0, 1.0]
    if r is None or t is None or scale is None:
        return None
    return {"cam_R_m2c": r, "cam_t_m2c": t, "model_scale": scale}


def model(anomaly: dict, scene_anomaly: dict) -> dict:
    """{model_id, asset, variant, path} of the anomaly: the render JSON's `model` when recorded,
    else the scene's asset and variant (path unknown: None)."""
    m = anomaly.get("model") if isinstance(anomaly, dict) else None
    m = m if isinstance(m, dict) else {}
    asset = str(m.get("asset") or (scene_anomaly or {}).get("asset") or "")
    variant = m.get("variant", (scene_anomaly or {}).get("assetVariant", ""))
    variant = "" if variant is None else str(variant)
    model_id = m.get("model_id") if isinstance(m.get("model_id"), str) else f"{asset}/{variant}"
    path = m.get("path") if isinstance(m.get("path"), str) and m.get("path") else None
    return {"model_id": model_id, "asset": asset, "variant": variant, "path": path}


def _canvas(anomaly: dict, shape, at_least: int) -> tuple[int, list[int] | None] | None:
    """(px_count_all, inclusive box) of the render JSON's full silhouette on the toolkit's canvas
    (`amodal_pixels_canvas`, `bbox_amodal_canvas_xyxy_px`), None when it records none (a render made
    before the canvas was counted) or values that cannot be (not whole numbers, fewer pixels than
    `at_least` or than the canvas holds, a box off the canvas or missing for a non-empty silhouette)."""
    height, width = shape
    count, box = anomaly.get("amodal_pixels_canvas"), anomaly.get("bbox_amodal_canvas_xyxy_px")
    if isinstance(count, bool) or not isinstance(count, int) or not at_least <= count <= 9 * width * height:
        return None
    if box is None:
        return (0, None) if count == 0 else None
    if not (isinstance(box, list) and len(box) == 4 and all(isinstance(v, int) and not isinstance(v, bool) for v in box)):
        return None
    x0, y0, x1, y1 = box
    if not (-width <= x0 <= x1 < 2 * width and -height <= y0 <= y1 < 2 * height) or count == 0:
        return None
    return count, box


def gt_info(visible: np.ndarray, amodal: np.ndarray | None, anomaly: dict, depth_units: np.ndarray | None,
            amodal_source: str = "amodal_pass") -> dict:
    """scene_gt_info.json's entry, as the BOP toolkit's scripts/calc_gt_info.py computes it (the
    toolkit renders the object on a canvas of 3W x 3H, principal point shifted by (W, H)):

    - px_count_visib, bbox_visib: the visible part (the class mask's or the object's own pixels),
      inside the image; bbox as misc.calc_2d_bbox;
    - px_count_all: the full silhouette's pixels on that canvas (pixel centres (u, v) at integers,
      u in [-W, 2W), v in [-H, 2H)), the part outside the image included: the render JSON's
      `amodal_pixels_canvas` (allo_usd.output.annotations: the `amodal` pass's pixels in the image,
      a ray cast outside it);
    - bbox_obj: misc.calc_2d_bbox (clip=False) of those canvas pixels in image coordinates (it may
      start below 0 and end past W or H): the render JSON's `bbox_amodal_canvas_xyxy_px`;
    - bbox_obj and bbox_visib are [-1, -1, -1, -1] when px_count_visib is 0 (the toolkit's rule,
      whatever the full silhouette);
    - visib_fract = px_count_visib / px_count_all (0.0 when px_count_all is 0);
    - px_count_valid: the silhouette's pixels in the image with a non-zero depth, where the full
      silhouette's pixels in the image (`amodal`: the pass's, or the render JSON's
      `amodal_segmentation`, `amodal_source` naming which) and the depth are both there.

    `silhouette` says which frame px_count_all, bbox_obj and visib_fract were counted on: "canvas"
    (the toolkit's), or "image" for a render whose JSON predates the canvas count (its in-image
    amodal mask or recorded count and box: a truncated object's visib_fract is then too high; re-render
    it). `visib_source`: where the full silhouette comes from ("amodal_pass" or "raycast")."""
    from allo_usd.output.annotations import mask_bbox

    visible = np.asarray(visible, dtype=bool)
    px_visib = int(np.count_nonzero(visible))
    info = {"bbox_visib": bop_box(mask_bbox(visible.astype(np.uint8), 1)) if px_visib else list(NO_BOX),
            "px_count_visib": px_visib}
    anomaly = anomaly if isinstance(anomaly, dict) else {}
    amodal = None if amodal is None else np.asarray(amodal, dtype=bool)
    in_image = 0 if amodal is None else int(np.count_nonzero(amodal))
    source = amodal_source if amodal is not None else str(anomaly.get("visib_source") or "raycast")
    canvas = _canvas(anomaly, visible.shape, max(px_visib, in_image))
    if canvas is not None:
        (px_all, box), frame = canvas, "canvas"
    elif amodal is not None:
        px_all, box, frame = in_image, mask_bbox(amodal.astype(np.uint8), 1), "image"
    else:
        px_all, box, frame = anomaly.get("amodal_pixels"), anomaly.get("bbox_amodal_xyxy_px"), "image"
        if isinstance(px_all, bool) or not isinstance(px_all, int) or px_all < 0:
            return info   # an older render: no full silhouette recorded
        box = box if _numbers(box, 4) is not None else None
    info |= {"bbox_obj": bop_box(box) if px_visib else list(NO_BOX), "px_count_all": px_all,
             "visib_source": source, "silhouette": frame}
    if amodal is not None and depth_units is not None:
        info["px_count_valid"] = int(np.count_nonzero(depth_units[amodal]))
    info["visib_fract"] = px_visib / px_all if px_all > 0 else 0.0
    return info


def dumps(content: dict) -> str:
    """bop_toolkit_lib.inout.save_json's text: one line per image id, ids in numeric order."""
    items = sorted(content.items(), key=lambda kv: int(kv[0]))
    lines = [f'  "{k}": {json.dumps(v, sort_keys=True)}' for k, v in items]
    return "{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}"
