"""The source audits' shared walker (tests/system/test_read_gate_audit.py, test_written_values.py): each
counts the package's sites of a kind of call or operator, named MODULE:SCOPE:CONSTRUCT so that an allow-list
can name each one with its reason."""

from __future__ import annotations

import ast
from collections import Counter


class ScopedSites(ast.NodeVisitor):
    """An ast visitor that knows where it is: `add(construct)` counts a site in `sites` as
    MODULE:SCOPE:CONSTRUCT, SCOPE the dotted names of the enclosing functions and classes (`<module>` at
    the top level). Subclasses add the visit_* methods that find their constructs."""

    def __init__(self, module: str, sites: Counter):
        self.module, self.sites, self.scope = module, sites, []

    def add(self, construct: str) -> None:
        self.sites[f"{self.module}:{'.'.join(self.scope) or '<module>'}:{construct}"] += 1

    def visit_FunctionDef(self, node):
        self.scope.append(node.name)
        self.generic_visit(node)
        self.scope.pop()

    visit_AsyncFunctionDef = visit_ClassDef = visit_FunctionDef
