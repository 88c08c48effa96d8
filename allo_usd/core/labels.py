"""Mask classes: the ids the 3-class mask stores and the semantic labels that map to them."""

from __future__ import annotations


BACKGROUND, STATION, ANOMALY = 0, 1, 2  # mask classes; celestial bodies share STATION's label


CLASS_IDS = {"station": STATION, "celestial_body": STATION, "anomaly": ANOMALY}
