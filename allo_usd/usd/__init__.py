"""Everything that touches pxr: schema, prim layout, the allo: attribute table, authoring, reading, inspect/diff, sandbox."""
