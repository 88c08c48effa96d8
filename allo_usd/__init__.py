"""allo-usd: the ALLO lunar-orbit anomaly dataset, authored as USD layers and rendered with Cycles."""

__version__ = "0.1.0"
