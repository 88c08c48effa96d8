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


def extends_copy(copy_dir) -> bool:
    """Whether the package's schema extends the copy of it in `copy_dir` (an authored tree's schema/):
    the same plugInfo.json, and every class and attribute the copy's generatedSchema.usda declares also
    declared here with the same type. Such a copy is an earlier version of this schema (a tree authored
    before attributes were added); the layers authored with it use nothing this one lacks. The copy is
    read through the read gate (a FIFO or a huge file is never parsed) and anything unreadable is not
    extended."""
    import filecmp
    from pathlib import Path

    from allo_usd.core.files import InputRefused, read_user_text

    copy_dir = Path(copy_dir)
    try:
        if not filecmp.cmp(PLUGIN / "plugInfo.json", copy_dir / "plugInfo.json", shallow=False):
            return False
        text = read_user_text(copy_dir / "generatedSchema.usda", 1 << 20, "the tree's schema copy")
    except (OSError, InputRefused):
        return False
    from pxr import Sdf, Tf

    old = Sdf.Layer.CreateAnonymous(".usda")
    try:
        if not old.ImportFromString(text):
            return False
    except Tf.ErrorException:
        return False
    new = Sdf.Layer.FindOrOpen(str(PLUGIN / "generatedSchema.usda"))
    for prim in old.rootPrims:
        ours = new.GetPrimAtPath(prim.path)
        if ours is None:
            return False
        for attr in prim.attributes:
            mine = ours.attributes.get(attr.name)
            if mine is None or mine.typeName != attr.typeName:
                return False
    return True
