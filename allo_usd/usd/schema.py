"""Explicit, idempotent registration of the allo-usd codeless schema.

Called by every entry point that authors or reads allo: properties, never at import time, so
that the plugin is registered before the schema registry is first consulted.
"""

from __future__ import annotations

from functools import lru_cache

from allo_usd.core.errors import AlloError
from allo_usd.core.paths import SCHEMAS
from allo_usd.usd.attributes import BY_SCHEMA

API_SCHEMAS = tuple(BY_SCHEMA)
# The codeless schema plugin: a resource plugin whose paths are relative to its own folder, so a
# byte copy of these files anywhere (an authored tree's schema/, allo_usd.usd.compose) works as is.
PLUGIN = SCHEMAS / "alloUsd"
PLUGIN_FILES = ("generatedSchema.usda", "plugInfo.json")


@lru_cache(maxsize=1)
def register() -> None:
    from pxr import Plug, Usd

    Plug.Registry().RegisterPlugins(str(PLUGIN))
    reg = Usd.SchemaRegistry()
    missing = [n for n in API_SCHEMAS if reg.FindAppliedAPIPrimDefinition(n) is None]
    if missing:
        raise AlloError(f"the allo-usd schema did not register {missing}: USD reads schema plugins once, "
                        "when the first stage is opened, so call allo_usd.usd.schema.register() before any other "
                        f"use of pxr.Usd in this process (and check {PLUGIN} is intact)")


def apply(prim, name: str) -> None:
    """Apply one of our single-apply API schemas to a prim (records it in apiSchemas)."""
    register()
    if name not in API_SCHEMAS:
        raise AlloError(f"unknown allo-usd API schema {name!r}; known: {API_SCHEMAS}")
    prim.AddAppliedSchema(name)
