"""The layout of an authored tree (the OUT of `allo-usd author`): every folder and file name in it,
and the path of each layer from what names it (a scene id, a day, a camera sample, a hazard id).

Authoring writes the tree, composition links its layers, the dispatcher and the safety rules
walk it and the command line names its parts in messages; all of them take the names from here,
so renaming a folder is one edit and no reader can disagree with the writer:

    OUT/plan.toml                                  the plan it was authored from (its record, and its root)
    OUT/stages/base.usda (+ its assets)            the tree's own base stage (station_source.json: a built one's model)
    OUT/sky/dDDD.usda                              one per day
    OUT/poses/sSEED/dDDD_pPP[_ASSET-VARIANT].usda  one per camera sample
    OUT/scenes/SPLIT/KIND/SCENE_ID.usda            one per scene
    OUT/hazards/ID/ID.usda (+ ID/, source.json)    a plan's own hazards, converted
    OUT/schema/                                    the Allo*API schemas' plugin (PXR_PLUGINPATH_NAME)
    OUT/inputs/POSE_FILE                           the tree's byte copy of the plan's pose file
    OUT/skipped.csv, reserves.csv, counts.csv      the author run's ledgers
    OUT/versions.json                              the library versions of each run (core.provenance)
    OUT/.allo-author.lock                          one author run at a time

Names and paths only: nothing here reads or writes a file, and nothing imports pxr, so the
command line and the dispatcher's scan import it at no cost.
"""

from __future__ import annotations

import os
from pathlib import Path

# versions.json is written by core.provenance, which the core layer cannot import from here; its name
# is part of this layout all the same (TREE_ENTRIES).
from allo_usd.core.provenance import TREE_VERSIONS

# Folders
SKY_DIR, POSE_DIR, SCENE_DIR, STAGE_DIR, SCHEMA_DIR = "sky", "poses", "scenes", "stages", "schema"
HAZARD_DIR = "hazards"             # a plan's own hazards, converted (allo_usd.usd.hazard)
POSE_INPUTS = "inputs"             # the tree's byte copy of the plan's pose file (run.author_tree.with_tree_poses)

# Files
TREE_PLAN = "plan.toml"            # the plan a tree was authored from (its record, and its root for usd.safety)
TREE_LOCK = ".allo-author.lock"    # one author run at a time per tree (core.files.RunLock)
BASE_STAGE_FILE = "base.usda"      # the tree's base stage, in STAGE_DIR
STATION_MARKER = "station_source.json"   # in a model-built STAGE_DIR: which file (and sha256) it was built from
HAZARD_MARKER = "source.json"      # in HAZARD_DIR/ID: what the hazard was converted from
SKIPPED_CSV = "skipped.csv"        # every skipped depth and why
RESERVES_CSV = "reserves.csv"      # each reserve group used: its (day, pose) and its decided depths
COUNTS_CSV = "counts.csv"          # planned vs authored, written when a run finishes
LAYER_SUFFIX = ".usda"             # every layer authoring writes

# Groups of the names above
LAYER_DIRS = (SCENE_DIR, SKY_DIR, POSE_DIR)   # the authored layers: a tree holding them must record its plan
# The folders a tree grants its own scene layers (usd.safety): what their composition may read.
GRANTED_DIRS = (SCENE_DIR, SKY_DIR, POSE_DIR, STAGE_DIR, HAZARD_DIR)
# The folders a tree of the demo's shape (`allo-usd demo`'s OUT/layers: scene layers at its top, no
# scenes/ and no plan.toml) grants beside its scene layers (usd.safety.tree_grants).
LAYER_FOLDER_DIRS = (SKY_DIR, POSE_DIR, STAGE_DIR, SCHEMA_DIR)
# The shared folders beside the scenes (sublayers, the base stage's assets, the schema plugin): the
# dispatcher does not search them for scene layers.
SUPPORT_DIRS = (SKY_DIR, POSE_DIR, STAGE_DIR, SCHEMA_DIR, HAZARD_DIR)
# What authoring writes at the top of a tree (plan.toml aside): `replace` removes exactly these.
TREE_ENTRIES = (SCENE_DIR, SKY_DIR, POSE_DIR, STAGE_DIR, HAZARD_DIR, SCHEMA_DIR, COUNTS_CSV, SKIPPED_CSV,
                RESERVES_CSV, POSE_INPUTS, TREE_VERSIONS)


def tree_base_stage(out_dir: Path) -> Path:
    """Where a tree's own copy of the base stage lives."""
    return Path(out_dir) / STAGE_DIR / BASE_STAGE_FILE


def tree_schema(out_dir: Path) -> Path:
    """The folder of a tree's copy of the schema plugin (what PXR_PLUGINPATH_NAME names)."""
    return Path(out_dir) / SCHEMA_DIR


def sky_layer_path(out_dir: Path, day: int) -> Path:
    return Path(out_dir, SKY_DIR, f"d{day:03d}{LAYER_SUFFIX}")   # one Path built (a run names ~200,000 paths)


def pose_layer_path(out_dir: Path, seed: int, sample_id: str) -> Path:
    return Path(out_dir, POSE_DIR, f"s{seed}", f"{sample_id.split('_', 1)[1]}{LAYER_SUFFIX}")


def scene_layer_path(out_dir: Path, split: str, kind: str, scene_id: str) -> Path:
    return Path(out_dir, SCENE_DIR, split, kind, f"{scene_id}{LAYER_SUFFIX}")


def existing_scene_ids(out_dir: Path) -> set[str]:
    """The scene ids whose layers a tree holds (scene_layer_path's files, read back from the folders)."""
    root = out_dir / SCENE_DIR
    found = set()
    for split in ("train", "test"):
        for kind in ("normal", "anomaly"):
            d = root / split / kind
            if d.is_dir():
                found.update(e.name[:-len(LAYER_SUFFIX)] for e in os.scandir(d) if e.name.endswith(LAYER_SUFFIX))
    return found


def hazard_root(out_dir: Path, asset: str) -> Path:
    return Path(out_dir) / HAZARD_DIR / asset


def hazard_asset_path(out_dir: Path, asset: str) -> Path:
    """The interface layer of a tree's converted hazard (what scene layers reference)."""
    return hazard_root(out_dir, asset) / f"{asset}{LAYER_SUFFIX}"
