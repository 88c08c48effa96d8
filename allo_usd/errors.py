"""Typed errors: each message names the problem and the fix, so nothing prints-and-returns-None."""


class AlloError(Exception):
    """Base of every error this package raises on purpose."""


class EphemerisRangeError(AlloError, ValueError):
    """An epoch lies outside the range the shipped ephemeris (DE421) covers."""


class DegenerateMeshError(AlloError, ValueError):
    """A mesh has no area, NaN points or indices out of range."""


class LayerError(AlloError, ValueError):
    """A scene layer is malformed, incomplete or refers to something missing."""


class AssetError(AlloError, FileNotFoundError):
    """An asset file is missing or cannot be converted."""


class PlacementError(AlloError, RuntimeError):
    """An anomaly or camera could not be placed within the attempt budget."""
