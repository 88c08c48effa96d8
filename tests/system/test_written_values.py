"""Every value that reaches a file is computed with allo_usd.core.fixedmath, or its site is listed below
with the reason it may differ per machine. An AST scan of allo_usd/ (nothing imported) finds each use,
outside core/fixedmath.py, of a construct whose last bit depends on the CPU or its libraries:

- `**` and `pow(x, y)` (CPython calls glibc's `pow`, which has FMA and non-FMA variants picked per CPU),
  except between constants whose exact value is a double (`2 ** 20`, `2.0 ** -27`: any `pow` within an
  ulp returns that double), and `math.pow`;
- math's transcendental functions (`math.exp`, `log`, `sin`, `atan2`, `hypot`, ... : glibc, per CPU);
- numpy's transcendental ufuncs and `np.power` / `np.float_power` (SVML on AVX-512, glibc elsewhere);
- `@`, `np.dot`, `.dot()`, `np.matmul`, `np.inner`, `np.vdot`, `np.einsum`, `np.tensordot` and every
  `np.linalg` function (OpenBLAS / LAPACK kernels chosen per CPU).

Not flagged because their results are correctly rounded by IEEE-754 (so the same on every machine):
`+ - * /`, `math.sqrt` / `np.sqrt`, `abs`, `floor` / `rint`, `ldexp` / `frexp`, comparisons, `np.cross`
and `np.outer` (single products), and radians / degrees (one product, as fixedmath does it).

A site is `module:function:construct` (the enclosing function dotted with its class; the construct as
resolved through the module's imports, e.g. `numpy.linalg.norm` for `np.linalg.norm`), counted: a
second `**` in an allowed function is a new site too. The fix for a written value is the fixedmath
function named in the failure message; code whose output is per machine by design (Blender's image
side, pixels, timings) is allowed module-wide below, everything else site by site, each with its reason."""

from __future__ import annotations

import ast
from collections import Counter
from fractions import Fraction
from pathlib import Path

import allo_usd

from tests.support.source_audit import ScopedSites

PACKAGE = Path(allo_usd.__file__).parent
FIXEDMATH = "core/fixedmath.py"

_MATH = {"exp", "expm1", "exp2", "log", "log1p", "log2", "log10", "pow", "sin", "cos", "tan", "asin", "acos",
         "atan", "atan2", "sinh", "cosh", "tanh", "asinh", "acosh", "atanh", "erf", "erfc", "gamma", "lgamma",
         "cbrt", "hypot", "dist"}
_NUMPY = {"exp", "exp2", "expm1", "log", "log2", "log10", "log1p", "logaddexp", "logaddexp2", "sin", "cos",
          "tan", "arcsin", "arccos", "arctan", "arctan2", "sinh", "cosh", "tanh", "arcsinh", "arccosh",
          "arctanh", "power", "float_power", "cbrt", "hypot", "sinc", "angle", "dot", "vdot", "matmul", "inner",
          "einsum", "tensordot", "cov", "corrcoef", "polyfit"}
# what to use instead, by construct (the last name of a resolved callee)
FIX = {"**": "fixedmath.power, fixedmath.exp2, or x * x for a square",
       "pow": "fixedmath.power", "exp": "fixedmath.exp", "exp2": "fixedmath.exp2", "log": "fixedmath.log",
       "log2": "fixedmath.log2", "sin": "fixedmath.sin", "cos": "fixedmath.cos", "tan": "fixedmath.tan",
       "asin": "fixedmath.arcsin", "arcsin": "fixedmath.arcsin", "acos": "fixedmath.arccos",
       "arccos": "fixedmath.arccos", "atan": "fixedmath.arctan", "arctan": "fixedmath.arctan",
       "atan2": "fixedmath.arctan2", "arctan2": "fixedmath.arctan2", "hypot": "fixedmath.hypot",
       "dist": "fixedmath.norm of the difference", "power": "fixedmath.power", "float_power": "fixedmath.power",
       "@": "fixedmath.matmul", "dot": "fixedmath.dot or fixedmath.matmul", "matmul": "fixedmath.matmul",
       "inner": "fixedmath.dot", "vdot": "fixedmath.dot", "einsum": "fixedmath.dot / fixedmath.matmul",
       "tensordot": "fixedmath.matmul", "norm": "fixedmath.norm", "det": "fixedmath.det3",
       "angle": "fixedmath.arctan2"}

IMAGE_SIDE = "image side: its output is per machine by design (docs/reliability/rerendering.md), never a layer"
# module-path prefixes allowed whole, with the reason
ALLOWED_MODULES: dict[str, str] = {
    "blender/": IMAGE_SIDE + ": Blender's scene (lamp power, mesh rings), rendered by Cycles, which is per "
                "machine itself",
    "usd/read_lights.py": IMAGE_SIDE + ": the lights as Blender builds them (power, size, orientation); no light "
                          "value is written to the render JSON or the dataset",
}
EMBREE = ("feeds the ray-cast silhouette (embree, which picks its SSE2 or AVX2 kernels by CPU: the "
          "silhouette is per machine, docs/reliability/determinism.md)")
BOUND = ("a bound check (refuse the layer or not) on singular values: only a transform within the last bit of "
         "the bound could be decided differently, and no value is written")
# module:function:construct -> (count, why this value may differ per machine)
ALLOWED: dict[str, tuple[int, str]] = {
    "output/annotations.py:_Silhouette._dirs:@": (1, "the ray directions of the silhouette: " + EMBREE),
    "output/annotations.py:_Silhouette.__init__:numpy.linalg.inv": (1, "the camera's origin and axes for the rays: "
                                                                 + EMBREE),
    "output/annotations.py:_world_points:@": (1, "the triangles the silhouette is ray-cast against: " + EMBREE),
    "output/annotations.py:split_rotation_scale:numpy.linalg.svd": (
        1, "the polar rotation of a sheared model-to-camera transform only (no transform this project authors is "
           "sheared: its split is the fixed-order column norms); LAPACK's last bits for a user's sheared layer"),
    "usd/read_geometry.py:_check_instance_matrix:numpy.linalg.svd": (1, BOUND),
    "usd/reader_bounds.py:_scales:numpy.linalg.svd": (1, BOUND),
}


def _names(nodes: list[ast.AST]) -> dict[str, str]:
    """Local name -> dotted name it was imported as (import numpy as np: np -> numpy)."""
    names: dict[str, str] = {}
    for node in nodes:
        if isinstance(node, ast.Import):
            for a in node.names:
                names[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                names[a.asname or a.name] = f"{node.module}.{a.name}"
    return names


def _dotted(node: ast.AST, names: dict[str, str]) -> str | None:
    """`np.linalg.norm` -> `numpy.linalg.norm` through the module's imports; None unless a name chain."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    parts.append(names.get(node.id, node.id))
    return ".".join(reversed(parts))


def _forbidden(dotted: str) -> bool:
    module, _, name = dotted.rpartition(".")
    if module == "math":
        return name in _MATH
    if module == "numpy":
        return name in _NUMPY
    if module in ("numpy.linalg", "numpy.emath", "numpy.lib.scimath"):
        return not name.endswith("Error")
    return dotted in ("operator.pow", "operator.matmul", "operator.ipow", "operator.imatmul")


def _constants(tree: ast.Module, nodes: list[ast.AST]) -> dict[str, Fraction]:
    """Module-level names bound once to a numeric constant expression (BITS = 20), by value."""
    values: dict[str, Fraction] = {}
    seen = Counter(t.id for node in nodes if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign))
                   for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
                   if isinstance(t, ast.Name))
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name) \
                and seen[node.targets[0].id] == 1:
            v = _value(node.value, values)
            if v is not None:
                values[node.targets[0].id] = v
    return values


def _value(node: ast.AST, consts: dict[str, Fraction]) -> Fraction | None:
    """The exact value of a constant expression (numbers, module constants, + - * / and integral **)."""
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        return Fraction(node.value)
    if isinstance(node, ast.Name):
        return consts.get(node.id)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        v = _value(node.operand, consts)
        return None if v is None else (-v if isinstance(node.op, ast.USub) else v)
    if isinstance(node, ast.BinOp):
        a, b = _value(node.left, consts), _value(node.right, consts)
        if a is None or b is None:
            return None
        if isinstance(node.op, ast.Add):
            return a + b
        if isinstance(node.op, ast.Sub):
            return a - b
        if isinstance(node.op, ast.Mult):
            return a * b
        if isinstance(node.op, ast.Div) and b:
            return a / b
        if isinstance(node.op, ast.Pow) and b.denominator == 1 and abs(b) <= 1100 and (a or b >= 0):
            return a ** int(b)
    return None


def _exact_power(node: ast.BinOp, consts: dict[str, Fraction]) -> bool:
    """`a ** b` of constants whose exact value is an int (int ** non-negative int: Python's exact integer
    power) or a double (2.0 ** -27): the same on every machine."""
    a, b = _value(node.left, consts), _value(node.right, consts)
    if a is None or b is None or b.denominator != 1 or abs(b) > 1100 or (not a and b < 0):
        return False
    exact = a ** int(b)
    if exact.denominator == 1 and b >= 0 and all(isinstance(n, ast.Constant) and type(n.value) is int
                                                 for n in _leaves(node)):
        return True
    try:
        return Fraction(float(exact)) == exact
    except OverflowError:
        return False


def _leaves(node: ast.AST):
    return [n for n in ast.walk(node) if isinstance(n, ast.Constant)]


def written_value_sites() -> Counter:
    """Counter of module:function:construct over every machine-dependent construct in the package."""
    sites: Counter = Counter()
    for path in sorted(PACKAGE.rglob("*.py")):
        module = path.relative_to(PACKAGE).as_posix()
        if module == FIXEDMATH:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        nodes = list(ast.walk(tree))
        names, consts = _names(nodes), _constants(tree, nodes)

        class Visitor(ScopedSites):
            def visit_BinOp(self, node):
                if isinstance(node.op, ast.Pow) and not _exact_power(node, consts):
                    self.add("**")
                elif isinstance(node.op, ast.MatMult):
                    self.add("@")
                self.generic_visit(node)

            def visit_AugAssign(self, node):
                if isinstance(node.op, ast.Pow):
                    self.add("**")
                elif isinstance(node.op, ast.MatMult):
                    self.add("@")
                self.generic_visit(node)

            def visit_Call(self, node):
                fn = node.func
                if isinstance(fn, ast.Name) and fn.id == "pow" and "pow" not in names and len(node.args) == 2:
                    self.add("pow")
                elif isinstance(fn, ast.Attribute) and fn.attr == "dot":
                    receiver = _dotted(fn.value, names) or ""
                    if not receiver.endswith("fixedmath") and receiver != "numpy":
                        self.add(".dot")
                self.generic_visit(node)

            def visit_Attribute(self, node):
                dotted = _dotted(node, names)
                if dotted is not None:
                    if _forbidden(dotted):
                        self.add(dotted)
                    return   # the chain's prefixes (numpy.linalg) are not constructs
                self.generic_visit(node)

            def visit_Name(self, node):
                dotted = names.get(node.id)
                if dotted is not None and _forbidden(dotted):
                    self.add(dotted)

        Visitor(module, sites).visit(tree)
    return sites


def _allowed_module(site: str) -> bool:
    return any(site.startswith(prefix) for prefix in ALLOWED_MODULES)


def _fix(site: str) -> str:
    construct = site.rsplit(":", 1)[1]
    return FIX.get(construct.rsplit(".", 1)[-1], "fixedmath's function for it (inv4, matmul, norm, ...)")


def test_every_written_value_goes_through_fixedmath_or_is_allowed_with_its_reason():
    found = Counter({k: n for k, n in written_value_sites().items() if not _allowed_module(k)})
    allowed = Counter({k: n for k, (n, _) in ALLOWED.items()})
    new = found - allowed
    gone = allowed - found
    assert not new, (
        "machine-dependent maths outside allo_usd.core.fixedmath (on a value that reaches a file, use the "
        "fixedmath function named; on a per-machine value, add the site to ALLOWED with its reason):\n  "
        + "\n  ".join(f"{k} (x{n}): use allo_usd.core.{_fix(k)}" for k, n in sorted(new.items())))
    assert not gone, ("ALLOWED lists sites that are no longer there (remove them):\n  "
                      + "\n  ".join(f"{k} (x{n})" for k, n in sorted(gone.items())))


def test_every_allowed_site_says_why():
    assert all(n >= 1 and len(why) > 20 for n, why in ALLOWED.values())
    assert all(len(why) > 20 for why in ALLOWED_MODULES.values())
    assert all(PACKAGE.joinpath(prefix).exists() for prefix in ALLOWED_MODULES)


def test_the_scan_sees_machine_dependent_maths_and_names_the_fix(tmp_path, monkeypatch):
    """The scan's own check: a module with glibc's pow, math's and numpy's transcendentals, BLAS products
    and LAPACK is found, construct by construct; exact constant powers, sqrt, fixedmath and numpy's error
    classes are not; core/fixedmath.py itself is not scanned; the failure names the fixedmath function."""
    mod = __import__(__name__, fromlist=["PACKAGE"])
    pkg = tmp_path / "allo_usd"
    (pkg / "core").mkdir(parents=True)
    (pkg / "core" / "fixedmath.py").write_text("def exp2(x):\n    return 2.0 ** x\n")
    (pkg / "core" / "leak.py").write_text(
        "import math\nfrom math import exp\nimport numpy as np\nfrom numpy.linalg import norm\n"
        "from allo_usd.core import fixedmath as fm\n\nBITS = 20\n\n\n"
        "def leak(x, a, b):\n"
        "    y = x ** 2 + 2 ** BITS + 2.0 ** -27 + 2 ** 63 - 1 + 10 ** -3 + pow(x, 3) + math.pow(x, 0.5)\n"
        "    y += exp(x) + math.sqrt(x) + np.sqrt(x) + np.power(x, 2.4) + np.arccos(x) + fm.exp2(x)\n"
        "    c = a @ b + a.dot(b) + np.einsum('ij,ij->i', a, b) + np.linalg.inv(a) + norm(a) + fm.dot(a, b)\n"
        "    try:\n        np.linalg.det(a)\n    except np.linalg.LinAlgError:\n        pass\n"
        "    return y, c\n\n\nclass K:\n    def f(self, x):\n        x **= 2.0\n        return x\n")
    monkeypatch.setattr(mod, "PACKAGE", pkg)
    found = mod.written_value_sites()
    assert found == Counter({"core/leak.py:leak:**": 2, "core/leak.py:leak:pow": 1, "core/leak.py:leak:math.pow": 1,
                             "core/leak.py:leak:math.exp": 1, "core/leak.py:leak:numpy.power": 1,
                             "core/leak.py:leak:numpy.arccos": 1, "core/leak.py:leak:@": 1,
                             "core/leak.py:leak:.dot": 1, "core/leak.py:leak:numpy.einsum": 1,
                             "core/leak.py:leak:numpy.linalg.inv": 1, "core/leak.py:leak:numpy.linalg.norm": 1,
                             "core/leak.py:leak:numpy.linalg.det": 1, "core/leak.py:K.f:**": 1})
    monkeypatch.setattr(mod, "ALLOWED", {})
    monkeypatch.setattr(mod, "ALLOWED_MODULES", {})
    try:
        mod.test_every_written_value_goes_through_fixedmath_or_is_allowed_with_its_reason()
    except AssertionError as e:
        message = str(e)
    else:
        raise AssertionError("the scan passed a module full of machine-dependent maths")
    assert "core/leak.py:leak:numpy.linalg.norm (x1): use allo_usd.core.fixedmath.norm" in message
    assert "core/leak.py:leak:@ (x1): use allo_usd.core.fixedmath.matmul" in message
    monkeypatch.setattr(mod, "ALLOWED_MODULES", {"core/": "a whole folder allowed, for this check only"})
    mod.test_every_written_value_goes_through_fixedmath_or_is_allowed_with_its_reason()
