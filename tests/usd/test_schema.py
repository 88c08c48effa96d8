from pxr import Usd

from allo_usd.usd import schema


def test_register_is_explicit_and_idempotent():
    schema.register()
    schema.register()
    reg = Usd.SchemaRegistry()
    for name in schema.API_SCHEMAS:
        assert reg.FindAppliedAPIPrimDefinition(name) is not None


def test_applied_schema_brings_its_properties():
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/W", "Xform")
    schema.apply(prim, "AlloSceneAPI")
    assert prim.HasAPI("AlloSceneAPI")
    assert prim.GetAttribute("allo:split").GetMetadata("allowedTokens") == ["train", "test"]
