"""The package's version, in the lowest layer: the modules that record it (a render's JSON, a
layer's customLayerData, the identity's versions) import it from here, not from the package root,
whose lazy API names modules of every layer (importing the root from inside would be a cycle)."""

__version__ = "0.1.0"
