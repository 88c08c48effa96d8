"""The allo: attribute table (allo_usd.usd.attributes) agrees with the schema file, and no other
module spells an attribute name itself."""

from __future__ import annotations

import pytest

import ast
from pathlib import Path

import allo_usd
from allo_usd.core.paths import SCHEMAS
from allo_usd.usd import attributes as A

PACKAGE = Path(allo_usd.__file__).parent


def _schema_classes() -> dict[str, dict[str, str]]:
    """{API schema: {attribute: Sdf type name}} from generatedSchema.usda."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(SCHEMAS / "alloUsd" / "generatedSchema.usda"))
    assert layer is not None
    return {prim.name: {attr.name: str(attr.typeName) for attr in prim.attributes}
            for prim in layer.rootPrims}


def test_table_matches_schema_exactly():
    schema = _schema_classes()
    table = {api: {a.name: a.sdf_type for a in group} for api, group in A.BY_SCHEMA.items()}
    assert set(table) == set(schema)
    for api in schema:
        assert table[api] == schema[api], api


def test_table_entries_are_consistent():
    assert len(A.BY_NAME) == len(A.ALL)                     # no name twice
    for api, group in A.BY_SCHEMA.items():
        assert all(a.api_schema == api and a.name.startswith(A.NAMESPACE) and a.prim.startswith("/")
                   for a in group)
    assert all(a.name.startswith(A.SENSOR_PREFIX) for a in A.SENSOR)
    assert all(a.name.startswith(A.ANOMALY_PREFIX) for a in A.ANOMALY)


def test_sensor_attributes_cover_sensor_params():
    from dataclasses import fields

    from allo_usd.core.sensor import SensorParams

    assert list(A.SENSOR_ATTRIBUTES) == [f.name for f in fields(SensorParams)]


def _string_constants(path: Path):
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.lineno, node.value


@pytest.mark.slow
def test_no_attribute_name_spelled_outside_the_table():
    names = set(A.BY_NAME)
    found = [f"{path.relative_to(PACKAGE)}:{line}: {value!r}"
             for path in sorted(PACKAGE.rglob("*.py")) if path.name != "attributes.py" or path.parent.name != "usd"
             for line, value in _string_constants(path) if value in names]
    assert not found, "spell these through allo_usd.usd.attributes:\n" + "\n".join(found)


@pytest.mark.slow
def test_no_prim_path_spelled_outside_the_layout():
    """Prim paths of the stage live in allo_usd.usd.layout (string constants starting /World or /Render)."""
    found = [f"{path.relative_to(PACKAGE)}:{line}: {value!r}"
             for path in sorted(PACKAGE.rglob("*.py")) if path.name != "layout.py" or path.parent.name != "usd"
             for line, value in _string_constants(path)
             if value.startswith(("/World", "/Render"))]
    assert not found, "spell these through allo_usd.usd.layout:\n" + "\n".join(found)
