"""An authored tree carries the codeless schema plugin (OUT/schema: plugInfo.json, generatedSchema.usda),
so plain usd-core, pointed at it with PXR_PLUGINPATH_NAME, applies the Allo*API schemas. Without
the variable usd-core opens the same layers without an error and silently drops them: that is
the problem the plugin solves, shown here too."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from allo_usd.core.errors import LayerError
from allo_usd.usd.compose import copy_schema
from allo_usd.usd.tree import tree_schema
from allo_usd.usd.schema import API_SCHEMAS, PLUGIN, PLUGIN_FILES

from tests.support.plans import tiny_plan

# Runs in a fresh interpreter that imports only pxr: what any usd-core user has.
PROBE = r"""
import json, sys
from pxr import Usd
reg = Usd.SchemaRegistry()
report = {"registered": {}, "prims": [], "values": []}
asked = json.loads(sys.argv[1])   # [layer, prim, attribute] whose value to report
for path in sys.argv[2:]:
    stage = Usd.Stage.Open(path)
    for layer, prim, name in asked:
        if layer == path:
            attr = stage.GetPrimAtPath(prim).GetAttribute(name)
            report["values"].append([name, attr.IsValid(), repr(attr.Get())])
    for prim in stage.Traverse():
        listop = prim.GetMetadata("apiSchemas")
        named = [n for n in (listop.ApplyOperations([]) if listop else []) if n.startswith("Allo")]
        if not named:
            continue
        rec = {"layer": path, "prim": str(prim.GetPath()), "named": named,
               "applied": [n for n in prim.GetAppliedSchemas() if n.startswith("Allo")],
               "has_api": {n: prim.HasAPI(n) for n in named}, "fallbacks": []}
        for n in named:
            definition = reg.FindAppliedAPIPrimDefinition(n)
            report["registered"][n] = definition is not None
            for a in (definition.GetPropertyNames() if definition else []):
                attr = prim.GetAttribute(a)
                if not attr.HasAuthoredValue():
                    rec["fallbacks"].append([a, repr(attr.Get()), repr(definition.GetAttributeFallbackValue(a))])
        report["prims"].append(rec)
report["allo_usd_imported"] = any(m.split(".")[0] == "allo_usd" for m in sys.modules)
print(json.dumps(report))
"""


@pytest.fixture(scope="module")
def moved_tree(tmp_path_factory):
    """A tiny authored tree, then moved elsewhere (the plugin must not depend on where it was made)."""
    from allo_usd.run.author import author_plan

    made = tmp_path_factory.mktemp("made") / "tree"
    paths = author_plan(tiny_plan(), made, progress=False)
    moved = tmp_path_factory.mktemp("moved") / "somewhere" / "else"
    shutil.move(made, moved)
    return moved, [moved / p.relative_to(made) for p in paths]


def _probe(layers: list[Path], plugin_path: Path | None, asked: list | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PXR_") and k != "PYTHONPATH"}
    if plugin_path is not None:
        env["PXR_PLUGINPATH_NAME"] = str(plugin_path)
    r = subprocess.run([sys.executable, "-I", "-c", PROBE, json.dumps(asked or []), *map(str, layers)], env=env, cwd=layers[0].parent,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert not report["allo_usd_imported"] and report["prims"]
    return report


def _scenes(tree: Path, paths: list[Path]) -> list[Path]:
    """A normal and an anomalous scene layer: between them they name every Allo*API schema."""
    return [next(p for p in paths if "_z" not in p.name), next(p for p in paths if "_z" in p.name)]


def test_the_tree_carries_a_relocatable_copy_of_the_plugin(moved_tree):
    tree, _ = moved_tree
    assert sorted(p.name for p in tree_schema(tree).iterdir()) == sorted(PLUGIN_FILES)
    for f in PLUGIN_FILES:
        assert (tree_schema(tree) / f).read_bytes() == (PLUGIN / f).read_bytes(), f
    for plugin in json.loads((tree_schema(tree) / "plugInfo.json").read_text())["Plugins"]:
        for key in ("LibraryPath", "ResourcePath", "Root"):
            assert not os.path.isabs(plugin.get(key, "")), (key, plugin[key])   # relative: moves with the tree


@pytest.mark.process
def test_plain_usd_core_applies_the_allo_schemas_with_the_trees_plugin(moved_tree):
    tree, paths = moved_tree
    report = _probe(_scenes(tree, paths), tree_schema(tree))
    assert report["registered"] == {n: True for n in API_SCHEMAS}
    for rec in report["prims"]:
        assert rec["applied"] == rec["named"], rec
        assert all(rec["has_api"].values()), rec
    fallbacks = [f for rec in report["prims"] for f in rec["fallbacks"]]
    assert fallbacks   # (the scene leaves some sensor parameters to the schema's fallbacks)
    for name, value, fallback in fallbacks:
        assert value == fallback and value != "None", (name, value, fallback)


def _fallback_attributes(tree: Path, paths: list[Path]) -> list[list[str]]:
    """[layer, prim, attribute] of every allo: attribute the scenes leave to a schema fallback."""
    report = _probe(_scenes(tree, paths), tree_schema(tree))
    return [[rec["layer"], rec["prim"], f[0]] for rec in report["prims"] for f in rec["fallbacks"]]


@pytest.mark.process
def test_without_the_plugin_usd_core_silently_drops_the_allo_schemas(moved_tree):
    """The problem: no error, but no Allo*API applied and no fallback values."""
    tree, paths = moved_tree
    asked = _fallback_attributes(tree, paths)
    report = _probe(_scenes(tree, paths), None, asked)
    assert set(report["registered"]) == set(API_SCHEMAS) and not any(report["registered"].values())
    for rec in report["prims"]:
        assert rec["applied"] == [] and not any(rec["has_api"].values()), rec
    assert len(report["values"]) == len(asked) > 0
    assert all(not valid and value == "None" for _, valid, value in report["values"]), report["values"]


def test_a_tree_whose_plugin_differs_is_refused(tmp_path):
    copy_schema(tmp_path)
    copy_schema(tmp_path)   # an identical copy is kept
    (tree_schema(tmp_path) / "plugInfo.json").write_text("{}")
    with pytest.raises(LayerError, match=r"schema is not a copy of .*alloUsd .*plugInfo.json.*Fix:"):
        copy_schema(tmp_path)


def _without_target_attributes(text: str) -> str:
    """The schema as it was before the target mode's two attributes (a tree authored then holds this copy)."""
    kept = [line for line in text.splitlines(keepends=True)
            if "allo:render:targetPsnr" not in line and "allo:render:timeLimit" not in line]
    assert len(kept) == len(text.splitlines()) - 2
    return "".join(kept)


def test_a_tree_with_an_earlier_schema_is_upgraded_and_one_edited_otherwise_is_refused(tmp_path):
    """A tree authored before attributes were added keeps working: its copy, which the package's schema
    extends, is replaced by the package's (its layers use nothing the new one lacks); a copy with an
    attribute of its own, a retyped one, or a FIFO in its place is still refused."""
    from allo_usd.usd.schema import PLUGIN

    schema = tree_schema(tmp_path) / "generatedSchema.usda"
    current = (PLUGIN / "generatedSchema.usda").read_text()
    copy_schema(tmp_path)
    schema.write_text(_without_target_attributes(current))
    copy_schema(tmp_path)
    assert schema.read_text() == current
    for edited in (current.replace("    int allo:render:seed = 0", "    int allo:render:seed = 0\n    int allo:mine = 1"),
                   current.replace("int allo:render:samples = 64", "float allo:render:samples = 64")):
        schema.write_text(edited)
        with pytest.raises(LayerError, match=r"schema is not a copy of .*generatedSchema.usda.*Fix:"):
            copy_schema(tmp_path)
    schema.unlink()
    os.mkfifo(schema)
    with pytest.raises(LayerError, match=r"schema is not a copy of .*Fix:"):
        copy_schema(tmp_path)
