"""COCO's compressed run-length encoding of a pixel set (pycocotools), as the render JSON's per-object
`segmentation` (output.annotations) and COCO's annotations (output.coco) both write it."""

from __future__ import annotations

import numpy as np


def rle(mask: np.ndarray) -> dict:
    """COCO compressed RLE of a boolean mask, JSON-ready ({"size": [h, w], "counts": str})."""
    from pycocotools import mask as mask_utils

    encoded = mask_utils.encode(np.asfortranarray(np.asarray(mask, dtype=np.uint8)))
    return {"size": [int(v) for v in encoded["size"]], "counts": encoded["counts"].decode("ascii")}
