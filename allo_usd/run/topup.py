"""The top-up: each (plan seed, asset, variant) reaches its planned number of anomalous images.

Each (plan seed, asset, variant) must reach its planned number of anomalous images (its quota), so
every hazard class keeps its share when the placement check skips depths. Once the planned
placements are authored, each shortfall is filled from reserve groups of the same asset and variant
(`allo_usd.plan.enumeration.reserve_group`), taken strictly in order k = 1, 2, ...: a reserve
group's depths are used in depth order while images are still missing, a depth that fails is
listed in skipped.csv (with its reserve number), and depths not needed are neither authored nor
listed. Reserve placements are computed on the pool in batches, ahead of need (some are computed
and thrown away), but decided in order in the parent, so the tree is a function of the plan
alone: not of the worker count, the chunking, or interruptions. A (seed, asset, variant) draws
at most `plan.reserve_cap` groups; what is still missing then is reported (counts.csv, the CLI
summary). reserves.csv records each used reserve group's decided depths, so a resumed run reuses
them instead of recomputing.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from allo_usd.plan.enumeration import SceneKey, anomaly_quotas, reserve_cap, reserve_group
from allo_usd.run import samples   # samples.write_sample looked up at each call (see allo_usd.run.samples)
from allo_usd.run.samples import AuthorContext, ensure_sky_layer
from allo_usd.usd.tree import scene_layer_path


@dataclass
class _Walk:
    """The reserve groups of one (seed, asset, variant), decided strictly in order."""

    sav: tuple
    need: int                 # images still missing
    cap: int                  # reserve groups it may use
    next_k: int = 1           # the next group to decide
    ahead: int = 0            # the highest group asked of the pool (or found in reserves.csv)
    inflight: set = field(default_factory=set)      # groups asked of the pool, not back yet
    results: dict = field(default_factory=dict)     # k -> Resolved, computed and not yet decided
    entries: dict = field(default_factory=dict)     # k -> {"day", "pose", "authored", "skipped"}: decided
    authored: list = field(default_factory=list)    # SceneKeys authored from reserves

    @property
    def open(self) -> bool:
        return self.need > 0 and self.next_k <= self.cap


class TopUp:
    """Every (seed, asset, variant)'s walk. `advance` decides every group it can (computed, or
    recorded in reserves.csv and present on disk) and writes its layers; `next_task` names the
    groups the pool should resolve next. Decisions depend only on each walk's groups in order, so
    how far ahead the pool computes, or which task finishes first, changes nothing written."""

    def __init__(self, ctx: AuthorContext, keys: list[SceneKey], skipped: dict, ledger: dict, bar):
        self.ctx, self.plan, self.skipped, self.ledger, self.bar = ctx, ctx.plan, skipped, ledger, bar
        self.depths = list(self.plan.anomalies.depths)
        self.quotas = anomaly_quotas(keys)
        anomalous = [k for k in keys if k.kind == "anomaly"]
        lost = Counter((k.seed, k.asset, k.variant) for k in anomalous if k.scene_id in skipped)
        self.walks = {sav: _Walk(sav, lost[sav], reserve_cap(self.plan, lost[sav])) for sav in self.quotas}
        # The expected images per reserve group, from the planned groups' yield of the same asset:
        # how many groups to compute ahead (a guess; it changes only how much work is thrown away).
        planned, passed = Counter(), Counter()
        for k in anomalous:
            planned[k.asset] += 1
            passed[k.asset] += k.scene_id not in skipped
        self.per_group = {a: max(1.0, len(self.depths) * passed[a] / planned[a]) for a in planned}
        self._turn = 0
        self.resolved = 0     # reserve groups resolved by the pool in this run (used or not)

    def _keys(self, walk: _Walk, k: int) -> list[SceneKey]:
        return reserve_group(self.plan, *walk.sav, k)

    def _from_ledger(self, walk: _Walk, keys: list[SceneKey]):
        """The decided depths of group k from reserves.csv, if they settle it with everything they
        authored on disk and everything they skipped in skipped.csv; else None (compute it)."""
        entry = self.ledger.get((*walk.sav, keys[0].reserve))
        if entry is None or (entry["day"], entry["pose"]) != (keys[0].day, keys[0].pose):
            return None
        outcome = {**{z: True for z in entry["authored"]}, **{z: False for z in entry["skipped"]}}
        need, used = walk.need, []
        for key in keys:
            if need == 0:
                break
            if key.depth_index not in outcome:
                return None
            ok = outcome[key.depth_index]
            if ok and not scene_layer_path(self.ctx.out_dir, key.split, key.kind, key.scene_id).exists():
                return None
            if not ok and key.scene_id not in self.skipped:
                return None
            used.append((key, ok))
            need -= ok
        return used

    def _decide(self, walk: _Walk, keys: list[SceneKey], used: list[tuple[SceneKey, bool]]) -> None:
        authored = [key for key, ok in used if ok]
        walk.need -= len(authored)
        walk.authored += authored
        walk.entries[keys[0].reserve] = {"day": keys[0].day, "pose": keys[0].pose,
                                        "authored": tuple(k.depth_index for k in authored),
                                        "skipped": tuple(k.depth_index for k, ok in used if not ok)}
        self.bar.update(len(authored))

    def advance(self) -> None:
        for walk in self.walks.values():
            while walk.open:
                keys = self._keys(walk, walk.next_k)
                resolved = walk.results.pop(walk.next_k, None)
                if resolved is not None:
                    used, need = [], walk.need
                    for key in keys:
                        if need == 0:
                            break
                        ok = not isinstance(resolved.results[key.depth_index], str)
                        used.append((key, ok))
                        need -= ok
                    ensure_sky_layer(self.ctx, keys[0].day)   # a reserve may fall on a day the plan's
                    rows = samples.write_sample(self.ctx, [key for key, _ in used], resolved)  # scenes do not use
                    self.skipped.update({r["scene_id"]: r for r in rows})
                else:
                    used = self._from_ledger(walk, keys)
                    if used is None:
                        break
                self._decide(walk, keys, used)
                walk.next_k += 1
            if not walk.open:
                walk.results.clear()

    def next_task(self, chunk: int) -> list[tuple] | None:
        """Up to `chunk` groups for the pool to resolve, or None: the walks take turns, and each asks
        for the group it waits on and for more only while the groups it has in hand are not expected,
        at its asset's planned yield, to cover what it still misses (so few are thrown away)."""
        walks = [w for w in self.walks.values() if w.open]
        for i in range(len(walks)):
            walk = walks[(self._turn + i) % len(walks)]
            ks = self._more(walk, chunk)
            if ks:
                self._turn = (self._turn + i + 1) % len(walks)
                walk.inflight.update(ks)
                return [(walk.sav, k, self._keys(walk, k)) for k in ks]
        return None

    def _more(self, walk: _Walk, chunk: int) -> list[int]:
        ks = []
        walk.ahead = max(walk.ahead, walk.next_k - 1)
        if walk.next_k not in walk.results and walk.next_k not in walk.inflight:
            ks.append(walk.next_k)                   # the group it waits on (not settled by reserves.csv)
            walk.ahead = max(walk.ahead, walk.next_k)
        per_group = self.per_group[walk.sav[1]]
        while len(ks) < chunk and walk.ahead < walk.cap and \
                (len(walk.inflight) + len(walk.results) + len(ks)) * per_group < walk.need:
            walk.ahead += 1
            if (*walk.sav, walk.ahead) not in self.ledger:   # recorded groups are most likely settled
                ks.append(walk.ahead)
        return ks

    def receive(self, results: list[tuple]) -> None:
        self.resolved += len(results)
        for sav, k, resolved in results:
            walk = self.walks[sav]
            walk.inflight.discard(k)
            if walk.open and k >= walk.next_k:
                walk.results[k] = resolved

    @property
    def need(self) -> int:
        return sum(w.need for w in self.walks.values())

    def entries(self) -> dict[tuple, dict]:
        return {(*sav, k): e for sav, w in self.walks.items() for k, e in sorted(w.entries.items())}

    def authored(self) -> list[SceneKey]:
        return [key for w in self.walks.values() for key in w.authored]
