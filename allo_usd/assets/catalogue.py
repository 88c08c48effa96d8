"""The anomaly catalogue: ids and variant names only, so a plan can be checked without building
(or importing the builders of) any asset; allo_usd.assets.anomalies builds them."""

from __future__ import annotations

#: Every anomaly id mapped to its variants; the first variant is the default.
ANOMALY_VARIANTS: dict[str, tuple[str, ...]] = {
    "mli_blanket": ("gold", "silver", "white"),
    "mli_torn_sheet": ("silver", "gold"),
    "mli_strip": ("silver", "gold", "white"),
    "power_cable": ("black", "orange"),
    "data_cable": ("white", "blue"),
    "cable_harness": ("default", "grey"),
    "power_drill": ("yellow", "red"),
    "eva_glove": ("default", "worn", "curled"),
    "wrench": ("chrome", "black_oxide"),
    "hammer": ("claw", "mallet"),
    "bolt_cluster": ("steel", "titanium"),
    "tether_hook": ("default", "yellow"),
    "handrail": ("bent", "straight"),
    "crew_bag": ("white", "blue"),
    "experiment_box": ("default", "black"),
    "camera_unit": ("camera", "light"),
}
ANOMALY_IDS: tuple[str, ...] = tuple(ANOMALY_VARIANTS)
