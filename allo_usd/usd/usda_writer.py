"""The .usda text of a layer from its opinions (`Prim` lists), and the atomic write of that text.

`write_layer` writes the text Sdf's ExportToString gives for the layer: written directly
(`fast_layer_text`) when every value is of a kind whose text is known to be Sdf's, else authored
with the Sdf API (`sdf_layer_text`; far cheaper than through Usd.Stage: docs/benchmarks/bench_author.md).
The two give the same bytes (tests/usd/test_usda_writer.py); the direct writer costs about a
third. What the opinions are is decided elsewhere: a scene's in allo_usd.usd.scene_layer, the
shared sky and camera-sample layers' in allo_usd.usd.compose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from allo_usd.core.version import __version__
from allo_usd.usd import schema
from allo_usd.usd import layout
from allo_usd.core.files import write_text_atomic


@dataclass
class Prim:
    """The opinions one layer holds on one prim: {attr: (Sdf type name, value)} plus metadata."""

    path: str
    attrs: dict = field(default_factory=dict)
    api: tuple[str, ...] = ()
    define: str = ""              # type name to `def` (e.g. "Xform"); empty = `over`
    reference: str = ""
    variants: dict = field(default_factory=dict)
    active: bool | None = None
    rels: dict = field(default_factory=dict)  # {relationship: [target paths]} (explicit targets)


_VALUE_TYPES: dict[str, tuple] = {}


def _value_type(type_name: str) -> tuple:
    """(Sdf value type, variability) of a Prim attribute's type name ("double3", "uniform token[]"),
    looked up once per name: a layer authors a few dozen attributes, a plan ~90,000 layers."""
    found = _VALUE_TYPES.get(type_name)
    if found is None:
        from pxr import Sdf

        uniform = type_name.startswith("uniform ")
        found = _VALUE_TYPES[type_name] = (Sdf.ValueTypeNames.Find(type_name.removeprefix("uniform ")),
                                           Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
    return found


def layer_text(prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> str:
    """The .usda text of a layer holding `prims`: written directly (`fast_layer_text`) when every
    value is of a kind whose text is known to be Sdf's, else through the Sdf API (`sdf_layer_text`).
    The two give the same bytes (tests/usd/test_usda_writer.py); the direct writer costs about a third."""
    text = fast_layer_text(prims, sublayers, custom, doc)
    return sdf_layer_text(prims, sublayers, custom, doc) if text is None else text


def sdf_layer_text(prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> str:
    """The .usda text of a layer holding `prims` (Sdf API inside one change block): the reference
    the direct writer is held to, and the way any value it does not know is written."""
    from pxr import Sdf

    layer = Sdf.Layer.CreateAnonymous(".usda")
    with Sdf.ChangeBlock():
        layer.subLayerPaths[:] = list(sublayers)
        layer.defaultPrim = layout.WORLD_NAME
        layer.customLayerData = {"allo": {"packageVersion": __version__, **custom}}
        layer.documentation = doc
        layer.pseudoRoot.SetInfo("upAxis", "Z")
        layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
        for prim in prims:
            spec = Sdf.CreatePrimInLayer(layer, prim.path)
            if prim.define:
                spec.specifier = Sdf.SpecifierDef
                spec.typeName = prim.define
            if prim.api:
                spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=list(prim.api)))
            if prim.reference:
                spec.referenceList.Prepend(Sdf.Reference(prim.reference))
            for vset, choice in prim.variants.items():
                spec.variantSelections[vset] = choice
            if prim.active is not None:
                spec.active = prim.active
            for name, (type_name, value) in prim.attrs.items():
                vtype, variability = _value_type(type_name)
                Sdf.AttributeSpec(spec, name, vtype, variability).default = value
            for name, targets in prim.rels.items():
                rel = Sdf.RelationshipSpec(spec, name, custom=False)
                rel.targetPathList.explicitItems = [Sdf.Path(t) for t in targets]
    return layer.ExportToString()


# --- the direct .usda writer ------------------------------------------------------------------
# It knows exactly what layer_text authors and nothing more; anything else (a value of another
# Python type, a string needing quotes or escapes, a name or path outside the plain identifier
# syntax, a number that is not finite) makes it return None, and the layer goes through Sdf.

class _Unknown(Exception):
    """A value the direct writer does not know how to write as Sdf would."""


_INDENT = "    "
_INT32 = (-2 ** 31, 2 ** 31 - 1)
_INT64 = (-2 ** 63, 2 ** 63 - 1)


def _plain(s: str) -> bool:
    """Printable ASCII without quotes or backslashes: Sdf writes it between double quotes as is."""
    return type(s) is str and s.isascii() and s.isprintable() and '"' not in s and "'" not in s and "\\" not in s


def _quote(s) -> str:
    if not _plain(s):
        raise _Unknown(s)
    return f'"{s}"'


def _ident(s) -> bool:
    """A plain identifier (prim, property or namespace part name)."""
    return type(s) is str and s.isascii() and s.replace("_", "a").isalnum() and not s[0].isdigit()


_NAMES: set[str] = set()        # property names already checked (a plan authors a few dozen, ~90,000 layers)
_PRIM_NAMES: set[str] = set()   # prim names already checked (identifiers)


def _name(s) -> str:
    if s in _NAMES and type(s) is str:
        return s
    if not (type(s) is str and s and all(_ident(part) for part in s.split(":"))):
        raise _Unknown(s)
    _NAMES.add(s)
    return s


def _path(p) -> str:
    """An absolute prim path of plain identifiers, as Sdf writes a target: </A/B>."""
    if not (type(p) is str and p.startswith("/") and all(_ident(part) for part in p[1:].split("/"))):
        raise _Unknown(p)
    return f"<{p}>"


def _asset(p) -> str:
    if not (_plain(p) and p and "@" not in p):
        raise _Unknown(p)
    return f"@{p}@"


def _shortest(digits: str, exp: int) -> str:
    """Shortest round-trip digits (no leading or trailing zeros) and the decimal exponent of the first,
    laid out as Tf's double-conversion does (TfStringify: fixed notation for exponents -6..14, else
    d.ddde<exp> with no '+')."""
    if -6 <= exp < 15:
        if exp < 0:
            return "0." + "0" * (-exp - 1) + digits
        if len(digits) <= exp + 1:
            return digits + "0" * (exp + 1 - len(digits))
        return f"{digits[:exp + 1]}.{digits[exp + 1:]}"
    return (f"{digits[0]}.{digits[1:]}" if len(digits) > 1 else digits) + f"e{exp}"


def _digits(mantissa: str, exp: int) -> tuple[str, int]:
    """(digits, exponent of the first) of a decimal mantissa 'I.F' (or 'I') times 10**exp."""
    whole, _, frac = mantissa.partition(".")
    digits = (whole + frac).lstrip("0")
    exp += len(whole) - 1 - (len(whole + frac) - len(digits))
    return digits.rstrip("0"), exp


def _double(x) -> str:
    """A double as Sdf writes it: Python's repr holds the same shortest round-trip digits. From 1e-4 to
    1e15 (most of a layer's values) repr already lays them out as Tf does, in fixed notation, but for
    a whole number's ".0" (the digits and _shortest's layout agree there: exponents -4 to 14)."""
    if type(x) is not float or x != x or x in (_INF, -_INF):
        raise _Unknown(x)
    if 1e-4 <= abs(x) < 1e15:
        r = repr(x)
        return r[:-2] if r.endswith(".0") else r
    if x == 0.0:
        return "-0" if str(x)[0] == "-" else "0"
    r = repr(abs(x))
    mantissa, _, e = r.partition("e")
    digits, exp = _digits(mantissa, int(e) if e else 0)
    return ("-" if x < 0 else "") + _shortest(digits, exp)


def _float(x) -> str:
    """A double stored as a float attribute (rounded to float32, as Sdf's cast), written with the float's
    own shortest round-trip digits (numpy's unique Dragon4 for float32, as double-conversion's). Kept
    per value (a run writes the same exposures and render settings into thousands of layers); zero is
    not kept, since 0.0 and -0.0 are one key."""
    if type(x) is not float or not abs(x) < _FLOAT32_SAFE:   # nan, inf or past float32's range
        raise _Unknown(x)
    text = _FLOATS.get(x) if x else None
    if text is None:
        text = _float_text(x)
        if x:
            if len(_FLOATS) >= 4096:
                _FLOATS.clear()
            _FLOATS[x] = text
    return text


_FLOATS: dict[float, str] = {}


def _float_text(x: float) -> str:
    import numpy as np

    f = np.float32(x)
    if f == 0.0:
        return "-0" if np.signbit(f) else "0"
    mantissa, _, e = np.format_float_scientific(abs(f), unique=True, trim="-").partition("e")
    digits, exp = _digits(mantissa, int(e))
    return ("-" if f < 0 else "") + _shortest(digits, exp)


_INF = float("inf")
_FLOAT32_SAFE = 3.4e38   # under float32's largest finite value: the cast stays finite


def _int(v, bounds=_INT32) -> str:
    if type(v) is not int or not bounds[0] <= v <= bounds[1]:
        raise _Unknown(v)
    return str(v)


def _gf(value, cls_name: str, n: int) -> list:
    if type(value).__name__ != cls_name or type(value).__module__ != "pxr.Gf":
        raise _Unknown(value)
    return [value[i] for i in range(n)]


def _tuple(items) -> str:
    return "(" + ", ".join(items) + ")"


def _quat(q) -> str:
    if type(q).__name__ != "Quatd" or type(q).__module__ != "pxr.Gf":
        raise _Unknown(q)
    im = q.GetImaginary()
    return _tuple([_double(q.GetReal()), *(_double(im[i]) for i in range(3))])


def _token_array(v) -> str:
    if type(v) is not list or not v:
        raise _Unknown(v)
    return "[" + ", ".join(_quote(t) for t in v) + "]"


_WRITERS = {
    "bool": lambda v: ("1" if v else "0") if type(v) is bool else _raise(v),
    "int": _int,
    "int64": lambda v: _int(v, _INT64),
    "double": _double,
    "float": _float,
    "string": _quote,
    "token": _quote,
    "double3": lambda v: _tuple([_double(c) for c in _gf(v, "Vec3d", 3)]),
    "quatd": _quat,
    "int2": lambda v: _tuple([_int(c) for c in _gf(v, "Vec2i", 2)]),
    "float2": lambda v: _tuple([_float(c) for c in _gf(v, "Vec2f", 2)]),
    "token[]": _token_array,
}


def _raise(v):
    raise _Unknown(v)


def _attr_line(name: str, type_name: str, value) -> str:
    base = type_name.removeprefix("uniform ")
    writer = _WRITERS.get(base)
    if writer is None:
        raise _Unknown(type_name)
    return f"{type_name} {_name(name)} = {writer(value)}"


def _rel_lines(name: str, targets, indent: str) -> list[str]:
    if not isinstance(targets, (list, tuple)) or not targets:
        raise _Unknown(targets)
    if len(targets) == 1:
        return [f"{indent}rel {_name(name)} = {_path(targets[0])}"]
    return [f"{indent}rel {_name(name)} = [", *(f"{indent}{_INDENT}{_path(t)}," for t in targets), f"{indent}]"]


_ORDER: dict[tuple[str, ...], tuple[str, ...]] = {}


def _property_order(names: tuple[str, ...]) -> tuple[str, ...]:
    """The order Sdf writes a prim's properties in (TfDictionaryLessThan: case-folded, digit runs by
    value), taken from Sdf itself once per set of names: a plan authors a handful of sets."""
    found = _ORDER.get(names)
    if found is None:
        from pxr import Sdf

        layer = Sdf.Layer.CreateAnonymous(".usda")
        spec = Sdf.CreatePrimInLayer(layer, "/P")
        for name in names:
            Sdf.AttributeSpec(spec, name, Sdf.ValueTypeNames.Int).default = 0
        lines = layer.ExportToString().split("\n")
        found = tuple(line.strip().removeprefix("int ").removesuffix(" = 0") for line in lines
                      if line.startswith(_INDENT + "int "))
        if sorted(found) != sorted(names):
            raise _Unknown(names)
        _ORDER[names] = found
    return found


class _Node:
    """One prim spec of the layer being written: its Prim (None: an ancestor only) and children."""

    __slots__ = ("prim", "children")

    def __init__(self):
        self.prim: Prim | None = None
        self.children: dict[str, _Node] = {}


def _prim_lines(name: str, node: _Node, depth: int, out: list[str]) -> None:
    ind = _INDENT * depth
    prim = node.prim
    head = f'{ind}{"def" if prim is not None and prim.define else "over"} '
    if prim is not None and prim.define:
        head += f"{_name(prim.define)} "
    head += f'"{name}"'
    meta: list[str] = []
    props: dict[str, list[str]] = {}
    if prim is not None:
        inner = ind + _INDENT
        if prim.active is not None:
            if type(prim.active) is not bool:
                raise _Unknown(prim.active)
            meta.append(f"{inner}active = {'true' if prim.active else 'false'}")
        if prim.api:
            meta.append(f"{inner}prepend apiSchemas = [{', '.join(_quote(a) for a in prim.api)}]")
        if prim.reference:
            meta.append(f"{inner}prepend references = {_asset(prim.reference)}")
        if prim.variants:
            meta.append(f"{inner}variants = {{")
            for vset in sorted(prim.variants):
                choice = prim.variants[vset]
                if not _ident(choice):       # Sdf checks a variant name's syntax (and may refuse it)
                    raise _Unknown(choice)
                meta.append(f"{inner}{_INDENT}string {_name(vset)} = {_quote(choice)}")
            meta.append(f"{inner}}}")
        for attr, (type_name, value) in prim.attrs.items():
            props[attr] = [inner + _attr_line(attr, type_name, value)]
        for rel, targets in prim.rels.items():
            if rel in props:
                raise _Unknown(rel)
            props[rel] = _rel_lines(rel, targets, inner)
    if meta:
        out.append(head + " (")
        out += meta
        out.append(f"{ind})")
    else:
        out.append(head)
    out.append(ind + "{")
    for prop in _property_order(tuple(props)) if props else ():
        out += props[prop]
    for i, (child, sub) in enumerate(node.children.items()):
        if props or i:
            out.append("")
        _prim_lines(child, sub, depth + 1, out)
    out.append(ind + "}")


def _custom_lines(custom: dict) -> list[str]:
    """customLayerData's allo dictionary (std::map order: by bytes), ints as int or int64 as Vt keeps them."""
    out = []
    for key in sorted(custom):
        value = custom[key]
        if not _ident(key):
            raise _Unknown(key)
        if type(value) is str:
            out.append(f"string {key} = {_quote(value)}")
        elif type(value) is int and _INT32[0] <= value <= _INT32[1]:
            out.append(f"int {key} = {value}")
        elif type(value) is int and _INT64[0] <= value <= _INT64[1]:
            out.append(f"int64 {key} = {value}")
        else:
            raise _Unknown(value)
    return [_INDENT * 3 + line for line in out]


def fast_layer_text(prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> str | None:
    """`sdf_layer_text`'s bytes written directly, or None when something in the layer is outside what
    this writer knows (the caller then uses Sdf)."""
    try:
        if not doc:                          # Sdf writes no doc line for an empty one
            return None
        root = _Node()
        seen = set()
        for prim in prims:
            if prim.path in seen or not prim.path.startswith("/"):
                return None
            seen.add(prim.path)
            node = root
            for part in prim.path[1:].split("/"):
                if part not in _PRIM_NAMES:
                    if not _ident(part):
                        return None
                    _PRIM_NAMES.add(part)
                node = node.children.get(part) or node.children.setdefault(part, _Node())
            node.prim = prim
        out = ["#usda 1.0", "(", f"{_INDENT}customLayerData = {{", f"{_INDENT * 2}dictionary allo = {{",
               *_custom_lines({"packageVersion": __version__, **custom}), f"{_INDENT * 2}}}", f"{_INDENT}}}",
               f'{_INDENT}defaultPrim = {_quote(layout.WORLD_NAME)}', f"{_INDENT}doc = {_quote(doc)}",
               f"{_INDENT}metersPerUnit = 1"]
        if sublayers:
            out.append(f"{_INDENT}subLayers = [")
            out.append(",\n".join(f"{_INDENT * 2}{_asset(s)}" for s in sublayers))
            out.append(f"{_INDENT}]")
        out += [f'{_INDENT}upAxis = "Z"', ")", ""]
        for name, node in root.children.items():
            _prim_lines(name, node, 0, out)
            out.append("")
        return "\n".join(out) + "\n"
    except _Unknown:
        return None


def write_layer(path: Path, prims: list[Prim], sublayers: list[str], custom: dict, doc: str) -> Path:
    schema.register()
    return write_text_atomic(path, layer_text(prims, sublayers, custom, doc))
