"""A plan's scenes: the exact, deterministic list of (split, kind, day, pose, seed, anomaly, depth)
to author, the per-asset quotas, and the reserve groups that top up skipped depths."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from allo_usd.core.seeds import key_hash
from allo_usd.plan.model import Plan, planned_sizes


@dataclass(frozen=True, slots=True)
class SceneKey:
    """One scene of a plan. Anomalous scenes with the same (seed, day, pose, asset, variant) are the
    depths of one placement and share its camera sample."""

    scene_id: str
    split: str              # train | test
    kind: str               # normal | anomaly
    day: int                # index into the plan's epochs
    pose: int
    seed: int               # the plan seed of this pipeline run
    asset: str | None = None
    variant: str | None = None
    depth_index: int = 0
    reserve: int = 0        # 0: a planned scene; k >= 1: the k-th reserve group of its (seed, asset, variant)

    @property
    def sample_id(self) -> str:
        """The camera sample (pose layer) this scene uses."""
        base = f"s{self.seed}_d{self.day:03d}_p{self.pose:02d}"
        if self.asset is None:
            return base
        return f"{base}_{self.asset}-{self.variant}" + (f"_r{self.reserve}" if self.reserve else "")


def _rng(*keys) -> np.random.Generator:
    return np.random.default_rng(key_hash(*keys))


def _split_evenly(total: int, parts: int) -> list[int]:
    q, r = divmod(total, parts)
    return [q + (i < r) for i in range(parts)]


def enumerate_scenes(plan: Plan) -> list[SceneKey]:
    """Every scene of the plan, as a list: `list(iter_scenes(plan))` (see there)."""
    return list(iter_scenes(plan))


def count_scenes(plan: Plan) -> int:
    """len(enumerate_scenes(plan)), by arithmetic (allo_usd.plan.model.planned_sizes): nothing is enumerated."""
    return sum(planned_sizes(plan).values())


def iter_scenes(plan: Plan) -> Iterator[SceneKey]:
    """Every scene of the plan, lazily, in a fixed order: normal train, normal test, anomalous test.

    Subsets are drawn by generators seeded from the plan seeds and the scene group's name, so the
    same plan always enumerates the same scenes. Normal scenes: the (seed, day, pose) grid, or a
    seeded subset of `counts`. Anomalous scenes: placements of len(depths) images each, split
    evenly over the seeds; per seed a seeded sample of (day, test pose) pairs without repeats,
    anomaly (asset, variant) assigned round-robin in the sampled order; a count that is not a
    multiple of len(depths) drops the highest depths of the last placement. These are the planned
    scenes; depths that placement skips are topped up when authoring, from `reserve_group`s.

    Lazy: taking the first N scenes (`author --limit N`) builds no more than the subset indices of
    a normal split and one seed's placements; the plan's size is bounded when it is validated.
    """
    days, seeds = plan.dates.days, plan.seeds
    test_poses = plan.poses.numbers("test")   # built-in, then the pose file's (plan.model.Poses)
    for split, poses, count in (("train", plan.poses.numbers("train"), plan.counts.normal_train),
                                ("test", test_poses, plan.counts.normal_test)):
        n_grid = len(seeds) * days * len(poses)   # (seed, day, pose) in that nesting order
        if count is not None and count < n_grid:
            cells = np.sort(_rng("normal", split, *seeds).choice(n_grid, size=count, replace=False))
        else:
            cells = range(n_grid)
        for i in cells:
            sd, p = divmod(int(i), len(poses))
            s, d = divmod(sd, days)
            yield SceneKey(f"s{seeds[s]}_d{d:03d}_p{poses[p]:02d}", split, "normal", d, poses[p], seeds[s])

    depths = plan.anomalies.depths
    by_asset = [a.choices() for a in plan.anomalies.assets]
    pairs_per_seed = days * len(test_poses)
    n_anom = plan.counts.anomalous_test
    if not by_asset or not test_poses or n_anom == 0:
        return
    n_place = pairs_per_seed * len(seeds) if n_anom is None else math.ceil(n_anom / len(depths))
    left = n_place * len(depths) if n_anom is None else n_anom
    for seed, k in zip(seeds, _split_evenly(n_place, len(seeds))):
        picked = _rng("anomaly", seed, *seeds).permutation(pairs_per_seed)[:k]
        rows = []
        for j, idx in enumerate(picked):
            d, p = divmod(int(idx), len(test_poses))
            asset, variant = _round_robin(by_asset, j)
            rows.append((d, test_poses[p], asset, variant))
        for d, p, asset, variant in sorted(rows):
            for z in depths:
                if left <= 0:
                    return
                left -= 1
                yield SceneKey(f"s{seed}_d{d:03d}_p{p:02d}_{asset}-{variant}_z{z}", "test", "anomaly",
                               d, p, seed, asset, variant, z)


def _round_robin(by_asset: list[list[tuple[str, str]]], j: int) -> tuple[str, str]:
    """Placement j's anomaly: asset j mod n, and that asset's variants in turn."""
    lst = by_asset[j % len(by_asset)]
    return lst[(j // len(by_asset)) % len(lst)]


# ---------------------------------------------------------------------------------------------
# Top-up: reserve placement groups for depths the placement check skips


def anomaly_quotas(keys: list[SceneKey]) -> dict[tuple[int, str, str], int]:
    """The anomalous depth slots of `keys` per (seed, asset, variant), in order of first appearance:
    the count each must reach when authored (its quota)."""
    quotas: dict[tuple[int, str, str], int] = {}
    for k in keys:
        if k.kind == "anomaly" and not k.reserve:
            sav = (k.seed, k.asset, k.variant)
            quotas[sav] = quotas.get(sav, 0) + 1
    return quotas


def reserve_cap(plan: Plan, shortfall: int) -> int:
    """At most this many reserve groups may be drawn for a (seed, asset, variant) with `shortfall`
    skipped depth slots: `anomalies.reserve_groups_per_slot` per slot. With the paper plan's
    worst yields (wrench and bolt cluster: ~2 of 5 depths pass) that is ~6x what the shortfall
    needs, and it bounds the work for an asset that can never be placed."""
    return plan.anomalies.reserve_groups_per_slot * max(0, shortfall)


_RESERVE_PAIRS: dict[tuple, np.ndarray] = {}   # a permutation per (plan grid, seed, asset, variant)


def _reserve_pairs(plan: Plan, seed: int, asset: str, variant: str) -> np.ndarray:
    key = (plan.dates.days, tuple(plan.poses.numbers("test")), tuple(plan.seeds), seed, asset, variant)
    if key not in _RESERVE_PAIRS:
        n = plan.dates.days * len(key[1])
        _RESERVE_PAIRS[key] = _rng("reserve", seed, asset, variant, *plan.seeds).permutation(n)
    return _RESERVE_PAIRS[key]


def reserve_group(plan: Plan, seed: int, asset: str, variant: str, k: int) -> list[SceneKey]:
    """The k-th (k >= 1) reserve placement group of (seed, asset, variant): one scene per plan depth.

    Its (day, test pose) is entry k-1 (cycling) of a permutation of the seed's (day, test pose)
    pairs drawn from a stream of its own (seeded by "reserve", the seed, asset and variant and the
    plan seeds), so it never disturbs the planned scenes and does not depend on how many reserves
    other groups use. Its scene ids end in `_r{k}_z{depth}` and its camera sample is a pose layer
    of its own (`SceneKey.sample_id`; the camera seed path ends in `r{k}`, allo_usd.scene.resolve), so
    a reserve group at a (day, pose) the plan already uses is a fresh draw."""
    if k < 1:
        raise ValueError(f"reserve groups are numbered from 1, not {k}")
    pairs = _reserve_pairs(plan, seed, asset, variant)
    test_poses = plan.poses.numbers("test")
    d, p = divmod(int(pairs[(k - 1) % len(pairs)]), len(test_poses))
    pose = test_poses[p]
    return [SceneKey(f"s{seed}_d{d:03d}_p{pose:02d}_{asset}-{variant}_r{k}_z{z}", "test", "anomaly", d, pose, seed,
                     asset, variant, z, k) for z in plan.anomalies.depths]
