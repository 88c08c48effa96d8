"""What a scene says about itself: its split, its variant (normal or anomalous) and its anomaly's
asset and variant. One check, shared by the two places that meet these values from outside:

- the layer reader (allo_usd.usd.read_labels.read_meta): a layer's `allo:split`, `allo:variant` and the
  anomaly prim's attributes, before a render records them in NAME.json's "scene";
- the dataset (allo_usd.output.dataset.check_render): the same fields read back from a render record.

So `render` never records a value `dataset` would refuse. The values name dataset folders
(train/, test/<asset>/), so they come from fixed sets or are plain tokens: "../../x" never is.
"""

from __future__ import annotations

import re

SPLITS = ("train", "test")                             # a scene's split, and the dataset's split folders
VARIANTS = {"normal": "good", "anomaly": "anomaly"}   # a scene's variant -> the dataset row's kind
TOKEN = re.compile(r"^[A-Za-z0-9_-]+$")               # an anomaly asset or variant


def label_problem(scene: dict, required: bool = True) -> str | None:
    """Why `scene`'s split, variant and anomaly cannot be filed in a dataset, or None. `required`:
    a missing split or variant is a problem too (a render record); the reader passes False, since
    a layer of one's own may say neither (it renders; dataset leaves such a render out)."""
    split, variant, anomaly = scene.get("split"), scene.get("variant"), scene.get("anomaly")
    if (required or split is not None) and split not in SPLITS:
        return f"split {split!r} is not one of {', '.join(SPLITS)}"
    if (required or variant is not None) and variant not in VARIANTS:
        return f"variant {variant!r} is not one of {', '.join(VARIANTS)}"
    if variant == "normal" and anomaly:
        return "a normal scene that records an anomaly"
    if anomaly is not None and (not isinstance(anomaly, dict) or not all(
            TOKEN.match(str(anomaly.get(k, ""))) for k in ("asset", "assetVariant"))):
        return f"anomaly {anomaly!r} does not name an asset and variant ([A-Za-z0-9_-])"
    return None
