"""COCO instance annotations of the dataset (`annotations/instances_{train,test}.json`): one image
entry per dataset image, one annotation per visible anomaly, as detection and segmentation code
(pycocotools, detectron2, mmdetection, torchvision's CocoDetection) reads them.

Conventions (docs/formats/coco_bop.md repeats them):
- `segmentation`: the visible anomaly (class mask == labels.ANOMALY) as COCO's compressed RLE,
  `pycocotools.mask.encode` of the mask in Fortran order, `counts` decoded to str for JSON, so
  `COCO.annToMask` gives the mask back exactly.
- `bbox`: [x, y, w, h] in COCO's pixel convention: (x, y) is the top-left corner of the top-left
  anomaly pixel (x = x_min, y = y_min, as column and row indices), w = x_max - x_min + 1 and
  h = y_max - y_min + 1 in pixels (what `pycocotools.mask.toBbox` gives for the RLE).
- `area`: the anomaly's pixel count (`pycocotools.mask.area`); `iscrowd` 0.
- One category per anomaly asset (user hazards included), the variant in the annotation's
  `variant`. The station is not a category: it is in every image, covers most of it and is the
  background an anomaly detector learns, not an object to find; a normal image must have no
  annotation. Its pixels are class 1 of the 3-class masks in allo_masks/ for segmentation.
- Normal images are listed with no annotation (COCO's way of saying "nothing here").
"""

from __future__ import annotations

import numpy as np

from allo_usd.output.annotations import mask_bbox
from allo_usd.output.rle import rle

SUPERCATEGORY = "anomaly"


def coco_bbox(xyxy) -> list[int] | None:
    """COCO [x, y, w, h] of an inclusive pixel box [x_min, y_min, x_max, y_max] (None stays None)."""
    if xyxy is None:
        return None
    x0, y0, x1, y1 = (int(v) for v in xyxy)
    return [x0, y0, x1 - x0 + 1, y1 - y0 + 1]


def instance(mask: np.ndarray) -> dict | None:
    """segmentation, area, bbox and iscrowd of the pixels set in a boolean mask (None if none is)."""
    from pycocotools import mask as mask_utils

    mask = np.asarray(mask, dtype=bool)
    box = mask_bbox(mask.astype(np.uint8), 1)
    if box is None:
        return None
    seg = rle(mask)
    area = int(mask_utils.area({"size": seg["size"], "counts": seg["counts"].encode("ascii")}))
    return {"segmentation": seg, "area": area, "bbox": coco_bbox(box), "iscrowd": 0}


def category_ids(assets, known: dict[str, int] | None = None) -> dict[str, int]:
    """{asset: category id}: ids already given keep them (a dataset's categories do not renumber
    when a re-run adds an asset); new assets get the next ids, in sorted order."""
    ids = {a: int(i) for a, i in (known or {}).items() if a in set(assets)}
    nxt = max(ids.values(), default=0) + 1
    for asset in sorted(set(assets) - set(ids)):
        ids[asset] = nxt
        nxt += 1
    return ids


def document(split: str, images: list[dict], annotations: list[dict], categories: dict[str, int]) -> dict:
    """The COCO file of one split: info, images, annotations, categories (no dates: a re-run that
    changes nothing writes the same bytes)."""
    return {"info": {"description": f"allo-usd dataset, {split} split: anomalies around a lunar-orbit station",
                     "version": "1.0", "url": "https://cocodataset.org/#format-data"},
            "licenses": [],
            "images": images,
            "annotations": annotations,
            "categories": [{"id": i, "name": a, "supercategory": SUPERCATEGORY}
                           for a, i in sorted(categories.items(), key=lambda kv: kv[1])]}
