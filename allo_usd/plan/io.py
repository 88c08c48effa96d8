"""Plan files: TOML or YAML by extension, validated on load with errors that name the field and
the fix, written atomically; and the plan's JSON Schema (schemas/plan.schema.json).

A written plan holds only the fields its author set (pydantic's `model_fields_set`, through the
nested models), so it re-reads to the same Plan and every field left out keeps its meaning: the
quality preset fills it, or the default does. Hostile files fail fast, as PlanError: a file above
MAX_PLAN_BYTES is refused before it is parsed, text that is not UTF-8 is named as such, YAML
aliases (the "billion laughs" expansion) and nesting deeper than MAX_DEPTH are refused, a YAML key given twice in
one mapping is refused as TOML refuses it (YAML's loader would keep the last), and validation messages show at most
MAX_ERRORS problems, each value cut short; the plan's size in scenes is bounded when it is
validated (allo_usd.plan.model.MAX_PLAN_SCENES). A parser's refusal is one line naming the line and
column (YAML's own messages span several), never a line of the file: the plan's own keys and short
values may be named (its author wrote them), the text around them is not shown. A written TOML plan lists its anomalies as an array of
tables, one `[[anomalies.assets]]` block each, so a block of one's own (docs/guide/bring_your_own.md, Your own hazards)
can be appended to it; appending one to an inline `assets = [...]` is named as such."""

from __future__ import annotations

import json
import re
from pathlib import Path

from pydantic import ValidationError

from allo_usd.core.errors import PlanError
from allo_usd.plan.model import Plan, _short

MAX_PLAN_BYTES = 1 << 18   # 256 KiB (parsed in about a second at worst): the paper's plan is under 1 KB
MAX_ERRORS = 20            # problems listed per invalid plan
MAX_LINE = 400             # characters per listed problem
MAX_DEPTH = 32             # YAML nesting (a plan's deepest value is 5 deep: anomalies.assets[i].variants)


def format_validation_error(exc: ValidationError) -> str:
    """pydantic's errors as 'field: problem; fix: ...' lines: at most MAX_ERRORS of them, each cut
    to MAX_LINE characters, values shortened, so a hostile input is never printed whole."""
    lines = []
    errors = exc.errors(include_url=False, include_context=False)
    for err in errors[:MAX_ERRORS]:
        loc = _cut(".".join(str(x) for x in err["loc"]) or "plan", 120)
        msg = err["msg"].removeprefix("Value error, ")
        if "fix:" not in msg:
            if err["type"] == "extra_forbidden":
                msg += "; fix: remove it or check its spelling (see schemas/plan.schema.json)"
            elif err["type"] == "missing":
                msg += "; fix: add it"
            else:
                msg += f"; fix: give a valid value (got {_short(err.get('input'))})"
        line = f"{loc}: {msg}"
        lines.append(line if len(line) <= MAX_LINE else line[:MAX_LINE - 3] + "...")
    if len(errors) > MAX_ERRORS:
        lines.append(f"... and {len(errors) - MAX_ERRORS} more problems")
    return "\n".join(lines)


def make_plan(data: dict, source: str = "plan") -> Plan:
    try:
        return Plan.model_validate(data)
    except ValidationError as exc:
        raise PlanError(f"{source} is not a valid plan:\n{format_validation_error(exc)}") from None


def _format(path: Path) -> str:
    suffix = Path(path).suffix.lower()
    if suffix == ".toml":
        return "toml"
    if suffix in (".yaml", ".yml"):
        return "yaml"
    raise PlanError(f"{path}: unknown plan format {suffix!r}; fix: name the file .toml, .yaml or .yml")


def load_plan(path: Path) -> Plan:
    path = Path(path)
    fmt = _format(path)
    from allo_usd.core.files import read_user_text

    # the project's read gate: a FIFO, device or directory is refused by os.stat before any open, and a
    # file over the bound is refused before it is read (and read no further than the bound)
    text = read_user_text(path, MAX_PLAN_BYTES, "plan", {
        "missing": f"write one with `allo-usd plan --paper --out {path}`",
        "too_big": "check it is the plan file (the paper's plan is under 1 KB)",
        "grew": "check it is the plan file (the paper's plan is under 1 KB)",
        "not_regular": "pass a plan file (TOML or YAML), not a FIFO, device or directory",
        "not_utf8": f"give a {fmt.upper()} plan file, e.g. from `allo-usd plan --paper`",
        "": "check its permissions"}, error=PlanError)
    try:
        data = _parse(text, fmt)
    except _AliasFound as exc:
        raise PlanError(f"plan {path} uses a YAML alias ({exc}); a plan may not, since aliases can expand "
                        "without bound; fix: write the value out where it is used") from None
    except _DuplicateKey as exc:
        raise PlanError(f"{path} is not valid YAML: key {_cut(repr(exc.key), 80)} is given twice in one mapping "
                        f"(at line {exc.line}, first at line {exc.first}); fix: keep one of the two") from None
    except Exception as exc:  # tomllib.TOMLDecodeError, yaml.YAMLError, a date out of range, deep nesting
        # Nesting is named in our words, whichever check refused it first: ours (_TooDeep), the parser's
        # own limit (libyaml's scanner looks ahead past MAX_DEPTH) or Python's (tomllib recurses).
        line = exc.line if isinstance(exc, _TooDeep) else _deep_line(text)
        if line is not None or isinstance(exc, RecursionError):
            where = f", at line {line}" if line is not None else ""
            raise PlanError(f"{path} is not valid {fmt.upper()}: values nested too deeply (over {MAX_DEPTH} levels"
                            f"{where}; a plan's values nest at most 5 deep); fix: check it is a plan file, e.g. "
                            "from `allo-usd plan --paper`") from None
        inline = _inline_extended(exc) if fmt == "toml" else None
        if inline is not None:
            raise PlanError(f"{path} is not valid TOML: {inline}") from None
        raise PlanError(f"{path} is not valid {fmt.upper()}: {_cut(_parser_message(exc))}; fix the syntax") from None
    if not isinstance(data, dict):
        raise PlanError(f"{path} holds no table of plan fields; fix: start from `allo-usd plan --paper`")
    return make_plan(data, str(path))


class _AliasFound(Exception):
    pass


_IMMUTABLE = re.compile(r"Cannot mutate immutable namespace \(([^)]*)\) \(at line (\d+), column \d+\)")


def _inline_extended(exc: Exception) -> str | None:
    """tomllib's "Cannot mutate immutable namespace" (a `[[t.k]]` or `[t.k]` header after `k = [...]` or
    `k = {...}` was written inline under [t]) in words that say what happened and how to mend it; else None."""
    found = _IMMUTABLE.search(str(exc))
    if found is None:
        return None
    keys = [k.strip().strip("'\"") for k in found.group(1).split(",") if k.strip()]
    dotted, last, line = ".".join(keys), keys[-1] if keys else "", found.group(2)
    table = ".".join(keys[:-1])
    where = f" under [{table}]" if table else ""
    return (f"line {line} adds a table to {dotted}, which is written inline earlier ({last} = [...]{where}), and "
            f"TOML cannot extend an inline array or table; fix: write each entry of {dotted} as its own [[{dotted}]] "
            "block with its keys on the lines below (as `allo-usd plan` writes plans), or put the new entry inside "
            "the inline array")


def _parser_message(exc: Exception) -> str:
    """A parser's refusal as one line: PyYAML's marked errors as "PROBLEM at line L, column C (CONTEXT at
    line L, column C)" (its own text spans four lines and names "<unicode string>"), others with their
    whitespace runs joined."""
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem and mark is not None:
        text = f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
        context, cmark = getattr(exc, "context", None), getattr(exc, "context_mark", None)
        if context:
            text += f" ({context}" + (f" at line {cmark.line + 1}, column {cmark.column + 1}" if cmark else "") + ")"
        return " ".join(text.split())
    return " ".join(str(exc).split())


class _DuplicateKey(Exception):
    def __init__(self, key, line: int, first: int):
        super().__init__(key, line, first)
        self.key, self.line, self.first = key, line, first


_LOADERS: dict = {}


def _plan_loader(base):
    """`base` (CSafeLoader or SafeLoader) that refuses a key given twice in one mapping, at any depth, naming
    the key and both lines; made once per base class."""
    if base in _LOADERS:
        return _LOADERS[base]
    import yaml

    class PlanLoader(base):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key, line = self.construct_object(key_node, deep=True), key_node.start_mark.line + 1
                    try:
                        if key in seen:
                            raise _DuplicateKey(key, line, seen[key])
                        seen[key] = line
                    except TypeError:   # an unhashable key: the base class refuses it
                        continue
            return super().construct_mapping(node, deep)

    _LOADERS[base] = PlanLoader
    return PlanLoader


class _TooDeep(Exception):
    def __init__(self, line: int):
        super().__init__(line)
        self.line = line


def _deep_line(text: str) -> int | None:
    """The line where `[`/`{` nesting first goes over MAX_DEPTH outside quotes and comments (TOML, YAML
    flow collections), or None. Asked only of text a parser refused: it decides whether the refusal
    is named as nesting, so the message does not depend on the parser's wording."""
    depth, line, quote, escaped, comment = 0, 1, "", False, False
    for ch in text:
        if ch == "\n":
            line, comment = line + 1, False
        if comment:
            continue
        if quote:
            if escaped:
                escaped = False
            elif ch == "\\" and quote == '"':
                escaped = True
            elif ch == quote:
                quote = ""
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            comment = True
        elif ch in "[{":
            depth += 1
            if depth > MAX_DEPTH:
                return line
        elif ch in "]}":
            depth = max(depth - 1, 0)
    return None


def _parse(text: str, fmt: str):
    if fmt == "toml":
        import tomllib

        return tomllib.loads(text)
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)   # libyaml when present: about 5x faster
    depth = 0
    for event in yaml.parse(text, Loader=loader):   # checked before anything is built
        if isinstance(event, yaml.AliasEvent):
            raise _AliasFound(f"*{_cut(event.anchor, 40)} at line {event.start_mark.line + 1}")
        if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            depth += 1
            if depth > MAX_DEPTH:   # libyaml's node builder recurses in C: far deeper, it crashes the process
                raise _TooDeep(event.start_mark.line + 1)
        elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            depth -= 1
    return yaml.load(text, Loader=_plan_loader(loader))


def _cut(text: str, limit: int = MAX_LINE) -> str:
    return text if len(text) <= limit else text[:limit - 3] + "..."


def plan_data(plan: Plan) -> dict:
    """What a plan file records: the fields its author set, in every nested model (None is never written)."""
    return plan.model_dump(mode="json", exclude_unset=True, exclude_none=True)


def save_plan(plan: Plan, path: Path) -> Path:
    """Write `plan` as TOML or YAML (by extension), atomically."""
    from allo_usd.core.files import write_text_atomic

    path = Path(path)
    data = plan_data(plan)
    if _format(path) == "toml":
        text = toml_text(data)
    else:
        import yaml

        text = yaml.safe_dump(data, sort_keys=False)
    return write_text_atomic(path, text)


def toml_text(data: dict) -> str:
    """`data` as TOML (tomli_w), with anomalies.assets as an array of tables: one [[anomalies.assets]]
    block per asset (a colour table as its [anomalies.assets.colors] sub-table), which tomli_w would
    write inline (`assets = [{ id = "power_drill" }]`) when short. A user can then append a
    [[anomalies.assets]] block of their own at the end of the file; after an inline array that is
    a TOML error. Other tables are written by tomli_w as before, in the same order."""
    import tomli_w

    anomalies = data.get("anomalies")
    assets = anomalies.get("assets") if isinstance(anomalies, dict) else None
    if not assets:
        return tomli_w.dumps(data)
    chunks = []
    plain = {k: v for k, v in data.items() if not isinstance(v, dict)}
    if plain:
        chunks.append(tomli_w.dumps(plain))
    for key, value in data.items():
        if not isinstance(value, dict):
            continue
        if key != "anomalies":
            chunks.append(tomli_w.dumps({key: value}))
            continue
        rest = {k: v for k, v in value.items() if k != "assets"}
        if rest:
            chunks.append(tomli_w.dumps({key: rest}))
        for asset in assets:
            block = "[[anomalies.assets]]\n" + tomli_w.dumps({k: v for k, v in asset.items() if not isinstance(v, dict)})
            for k, v in asset.items():
                if isinstance(v, dict):
                    block += f"\n[anomalies.assets.{k}]\n" + tomli_w.dumps(v)
            chunks.append(block)
    return "\n".join(chunks)


def schema_text() -> str:
    """The plan's JSON Schema as committed in schemas/plan.schema.json (deterministic)."""
    return json.dumps(Plan.model_json_schema(), sort_keys=True, indent=2) + "\n"
