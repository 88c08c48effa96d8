"""Plan files: TOML or YAML by extension, validated on load with errors that name the field and
the fix, written atomically; and the plan's JSON Schema (schemas/plan.schema.json)."""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import ValidationError

from allo_usd.core.errors import PlanError
from allo_usd.plan.model import Plan


def format_validation_error(exc: ValidationError) -> str:
    """pydantic's errors as 'field: problem; fix: ...' lines."""
    lines = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "plan"
        msg = err["msg"].removeprefix("Value error, ")
        if "fix:" not in msg:
            if err["type"] == "extra_forbidden":
                msg += "; fix: remove it or check its spelling (see schemas/plan.schema.json)"
            elif err["type"] == "missing":
                msg += "; fix: add it"
            else:
                msg += f"; fix: give a valid value (got {err.get('input')!r})"
        lines.append(f"{loc}: {msg}")
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
    if not path.is_file():
        raise PlanError(f"plan {path} does not exist; fix: write one with `allo-usd plan --paper --out {path}`")
    text = path.read_text()
    try:
        if fmt == "toml":
            import tomllib

            data = tomllib.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as exc:  # tomllib.TOMLDecodeError, yaml.YAMLError
        raise PlanError(f"{path} is not valid {fmt.upper()}: {exc}; fix the syntax") from None
    if not isinstance(data, dict):
        raise PlanError(f"{path} holds no table of plan fields; fix: start from `allo-usd plan --paper`")
    return make_plan(data, str(path))


def plan_data(plan: Plan) -> dict:
    return plan.model_dump(mode="json", exclude_none=True)


def save_plan(plan: Plan, path: Path) -> Path:
    """Write `plan` as TOML or YAML (by extension), atomically."""
    from allo_usd.core.files import write_text_atomic

    path = Path(path)
    data = plan_data(plan)
    if _format(path) == "toml":
        import tomli_w

        text = tomli_w.dumps(data)
    else:
        import yaml

        text = yaml.safe_dump(data, sort_keys=False)
    return write_text_atomic(path, text)


def schema_text() -> str:
    """The plan's JSON Schema as committed in schemas/plan.schema.json (deterministic)."""
    return json.dumps(Plan.model_json_schema(), sort_keys=True, indent=2) + "\n"
