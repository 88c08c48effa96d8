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


class ImportOptionError(AlloError, ValueError):
    """An argument to the mesh importer (units, up axis, rotation, texture size) is invalid."""


class PlacementError(AlloError, RuntimeError):
    """An anomaly or camera could not be placed within the attempt budget."""


class EpochError(AlloError, ValueError):
    """An epoch is not a timezone-aware datetime (naive, NaN, wrong type) or cannot be parsed."""


class SkyInputError(AlloError, ValueError):
    """A number fed to the sky/orbit/eclipse geometry is non-finite or out of its valid domain."""


class UnknownAnomalyError(AlloError, ValueError):
    """An anomaly asset id or variant that the procedural library does not define."""


class DiskFullError(AlloError, OSError):
    """The output device is full (ENOSPC): a batch stops cleanly; finished outputs are kept."""


class RenderFailedError(AlloError, RuntimeError):
    """Blender produced no usable image for reasons outside the layer (an I/O error, a cut-short
    file): the dispatcher retries it like a crash instead of recording the layer as bad."""


class PlanError(AlloError, ValueError):
    """A dataset plan is invalid, unreadable or cannot be authored; the message names the field and the fix."""
