"""The package's import graph follows the data flow: no circles, no lower layer importing a higher
one, pxr only in `usd/`, bpy only in `blender/` and the render worker's entry (ast, nothing imported)."""

from __future__ import annotations

import ast
from pathlib import Path

import allo_usd

PACKAGE = Path(allo_usd.__file__).parent

# Layers in the order data passes through them; a module may import its own layer and lower ones.
LAYERS = ("core", "assets", "sky", "plan", "scene", "usd", "blender", "output", "run", "")
PXR_ALLOWED = ("usd",)
BPY_ALLOWED = ("blender", "run.worker")
BPY_NAMES = ("bpy", "mathutils")


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return ".".join(parts)


def imports_of(path: Path, source: str | None = None) -> list[tuple[str, int]]:
    """Every module `path` imports (at top level or inside functions), absolute, with its line
    (`source`: this text read as if it were the file at `path`)."""
    tree = ast.parse(path.read_text() if source is None else source)
    mod = module_name(path)
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ("allo_usd." + mod).split(".")
                base = base if is_pkg else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            out.append((target, node.lineno))
            # `from allo_usd.x import y` may import the submodule allo_usd.x.y
            for a in node.names:
                out.append((f"{target}.{a.name}", node.lineno))
    return out


def project_modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def layer_of(mod: str) -> str:
    top = mod.split(".")[0] if mod else ""
    return top if top in LAYERS else ""


def internal_edges() -> dict[str, set[str]]:
    mods = project_modules()
    edges: dict[str, set[str]] = {m: set() for m in mods}
    for m, path in mods.items():
        for target, _ in imports_of(path):
            if target.startswith("allo_usd."):
                t = target[len("allo_usd."):]
                if t in mods and t != m:
                    edges[m].add(t)
    return edges


def test_every_module_is_seen():
    mods = project_modules()
    assert {"core.errors", "usd.read", "blender.build", "run.dispatch", "plan.model"} <= set(mods)


def test_no_import_cycles():
    edges = internal_edges()
    state: dict[str, int] = {}
    cycles = []

    def visit(m, stack):
        state[m] = 1
        stack.append(m)
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t, stack)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_no_lower_layer_imports_a_higher_one():
    rank = {name: i for i, name in enumerate(LAYERS)}
    bad = []
    for m, targets in internal_edges().items():
        for t in targets:
            if rank[layer_of(t)] > rank[layer_of(m)]:
                bad.append(f"{m} ({layer_of(m) or 'top'}) imports {t} ({layer_of(t) or 'top'})")
    assert not bad, "backward edges:\n" + "\n".join(sorted(bad))


def root_imports(path: Path, source: str | None = None) -> list[int]:
    """The lines of `path` that import the package root itself (`import allo_usd`, `from allo_usd
    import x`, `from .. import x` reaching it), not one of its submodules."""
    return [line for target, line in imports_of(path, source) if target == "allo_usd"]


def test_no_layer_imports_the_package_root():
    """The root's lazy API names modules of every layer (allo_usd.run.author, allo_usd.run.dispatch,
    ...), so a module of a layer that imports the root (`from allo_usd import __version__`) closes a
    circle through allo_usd/__init__.py; the version lives in allo_usd.core.version. Only the top
    level (the root and the command line beside it, which the root never names) may use the root."""
    bad = [f"{m}:{line} imports the package root allo_usd" for m, path in project_modules().items()
           if layer_of(m) for line in root_imports(path)]
    assert not bad, "\n".join(bad)


def test_the_root_check_sees_a_planted_root_import():
    """The walk is not vacuous: each form of importing the root from a layer's module is found, and
    importing a submodule is not taken for it."""
    at = PACKAGE / "run" / "job.py"
    for code in ("from allo_usd import __version__\n", "import allo_usd\n", "from .. import x\n"):
        assert root_imports(at, code) == [1], code
    submodules = "from allo_usd.core.version import __version__\nfrom . import job\nimport allo_usd.core\n"
    assert root_imports(at, submodules) == []


def _allowed(mod: str, prefixes: tuple[str, ...]) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def test_pxr_only_in_the_usd_layer():
    bad = [f"{m}:{line} imports {t}" for m, path in project_modules().items() for t, line in imports_of(path)
           if (t == "pxr" or t.startswith("pxr.")) and not _allowed(m, PXR_ALLOWED)]
    assert not bad, "\n".join(bad)


def test_bpy_only_in_blender_and_the_worker_entry():
    bad = [f"{m}:{line} imports {t}" for m, path in project_modules().items() for t, line in imports_of(path)
           if t.split(".")[0] in BPY_NAMES and not _allowed(m, BPY_ALLOWED)]
    assert not bad, "\n".join(bad)


def test_the_checker_sees_a_planted_backward_edge(tmp_path):
    """The walk is not vacuous: a relative import from core into run is resolved and ranked."""
    fake = PACKAGE / "core" / "errors.py"
    tree_imports = imports_of(fake)
    assert all(not t.startswith("allo_usd.run") for t, _ in tree_imports)
    planted = tmp_path / "x.py"
    planted.write_text("from ..run import dispatch\n")
    # resolve as if it sat at allo_usd/core/x.py
    src = ast.parse(planted.read_text()).body[0]
    assert src.level == 2 and layer_of("run.dispatch") == "run"
    assert LAYERS.index(layer_of("run.dispatch")) > LAYERS.index(layer_of("core.x"))
