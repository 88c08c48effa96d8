"""The author run's ledgers at the top of a tree: skipped.csv (every skipped depth and why; a
reserve depth carries its group number), reserves.csv (each reserve group used: its (day, pose) and
the depths authored and skipped, so a resumed run reuses them instead of recomputing) and
counts.csv (planned vs authored), and the summary the command line prints from the counts. Each is
written whole under a temporary name and renamed (core.files.write_text_atomic).
"""

from __future__ import annotations

import csv
import io
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

from allo_usd.core.files import write_text_atomic
from allo_usd.plan.enumeration import SceneKey
from allo_usd.plan.model import Plan
from allo_usd.usd.tree import RESERVES_CSV

if TYPE_CHECKING:
    from allo_usd.run.topup import TopUp

SKIPPED_FIELDS = ("scene_id", "seed", "day", "pose", "asset", "variant", "depth_index", "reserve", "reason")
RESERVE_FIELDS = ("seed", "asset", "variant", "reserve", "day", "pose", "authored", "skipped")
COUNT_FIELDS = ("split", "kind", "asset", "planned", "authored", "skipped", "reserve_groups", "from_reserve",
                "short")


def _write_csv(path: Path, fields: tuple, rows: list[dict]) -> Path:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row[k]) for k in fields})
    return write_text_atomic(path, buf.getvalue())


def read_skipped(path: Path) -> dict[str, dict]:
    if not path.is_file():
        return {}
    with open(path, newline="") as fh:
        return {row["scene_id"]: row for row in csv.DictReader(fh)}


def write_skipped(path: Path, rows: dict[str, dict]) -> Path:
    return _write_csv(path, SKIPPED_FIELDS, [rows[sid] for sid in sorted(rows)])


def _depth_list(text: str) -> tuple[int, ...]:
    return tuple(int(z) for z in str(text or "").split())


def read_reserves(path: Path) -> dict[tuple, dict]:
    """reserves.csv by (seed, asset, variant, k): the group's (day, pose) and its decided depths."""
    if not path.is_file():
        return {}
    out = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            out[(int(row["seed"]), row["asset"], row["variant"], int(row["reserve"]))] = {
                "day": int(row["day"]), "pose": int(row["pose"]),
                "authored": _depth_list(row["authored"]), "skipped": _depth_list(row["skipped"])}
    return out


def write_reserves(path: Path, entries: dict[tuple, dict]) -> Path:
    rows = [{"seed": s, "asset": a, "variant": v, "reserve": k, "day": e["day"], "pose": e["pose"],
             "authored": " ".join(map(str, e["authored"])), "skipped": " ".join(map(str, e["skipped"]))}
            for (s, a, v, k), e in entries.items()]
    return _write_csv(path, RESERVE_FIELDS, rows)


def read_counts(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def write_counts(path: Path, rows: list[dict]) -> Path:
    return _write_csv(path, COUNT_FIELDS, rows)


def count_rows(plan: Plan, keys: list[SceneKey], skipped: dict, topup: TopUp | None) -> list[dict]:
    """counts.csv: planned vs authored scenes per (split, kind), and per anomaly asset."""
    walks = topup.walks if topup is not None else {}
    rows = []
    for split, kind in (("train", "normal"), ("test", "normal"), ("test", "anomaly")):
        mine = [k for k in keys if (k.split, k.kind) == (split, kind)]
        lost = sum(k.scene_id in skipped for k in mine)
        groups = sum(len(w.entries) for w in walks.values()) if kind == "anomaly" else 0
        extra = sum(len(w.authored) for w in walks.values()) if kind == "anomaly" else 0
        rows.append({"split": split, "kind": kind, "asset": "", "planned": len(mine),
                     "authored": len(mine) - lost + extra, "skipped": lost, "reserve_groups": groups,
                     "from_reserve": extra, "short": len(mine) - (len(mine) - lost + extra)})
    per_asset: dict[str, Counter] = {}
    for k in keys:
        if k.kind == "anomaly":
            c = per_asset.setdefault(k.asset, Counter())
            c["planned"] += 1
            c["skipped"] += k.scene_id in skipped
    for (_, asset, _), w in walks.items():
        per_asset[asset]["reserve_groups"] += len(w.entries)
        per_asset[asset]["from_reserve"] += len(w.authored)
    for asset, c in per_asset.items():
        authored = c["planned"] - c["skipped"] + c["from_reserve"]
        rows.append({"split": "test", "kind": "anomaly", "asset": asset, "planned": c["planned"],
                     "authored": authored, "skipped": c["skipped"], "reserve_groups": c["reserve_groups"],
                     "from_reserve": c["from_reserve"], "short": c["planned"] - authored})
    return rows


def summary_lines(counts: list[dict], topup: bool = True) -> list[str]:
    """Planned vs authored, one line per (split, kind), and a line per asset left short (SHORT when
    the top-up ran out of reserve groups; a plain note when the plan turned the top-up off)."""
    lines = []
    for r in counts:
        if r["asset"]:
            continue
        line = f"{r['split']}/{r['kind']}: {int(r['authored']):,} of {int(r['planned']):,} planned authored"
        if r["kind"] == "anomaly":
            line += (f" ({int(r['skipped']):,} planned depths skipped, {int(r['from_reserve']):,} topped up from "
                     f"{int(r['reserve_groups']):,} reserve groups)")
        lines.append(line)
    short = [r for r in counts if r["asset"] and int(r["short"]) > 0]
    for r in short:
        if not topup:
            lines.append(f"{r['asset']}: {int(r['authored']):,} of {int(r['planned']):,} ({int(r['short']):,} skipped "
                         "depths not replaced: the plan turns the top-up off, anomalies.reserve_groups_per_slot = 0)")
            continue
        lines.append(f"SHORT: {r['asset']}: {int(r['authored']):,} of {int(r['planned']):,} "
                     f"({int(r['short']):,} missing: it used every reserve group the top-up bound allows, "
                     f"{int(r['reserve_groups']):,}, see {RESERVES_CSV}; fix: raise anomalies.reserve_groups_per_slot, "
                     f"or leave this asset out of the plan)")
    return lines
