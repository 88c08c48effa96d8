"""python -m allo_usd.plan: regenerate schemas/plan.schema.json (a test checks it is current)."""

from allo_usd.core.paths import SCHEMAS
from allo_usd.plan.io import schema_text

(SCHEMAS / "plan.schema.json").write_text(schema_text())
print(SCHEMAS / "plan.schema.json")
