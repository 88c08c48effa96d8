"""allo_usd.usd.compose's tree check: TreeLinks (one run's memo of relative paths and of which files
lie inside the tree) answers as the plain forms it stands in for, core.files.relpath (symlinks and
".." included) and os.path.commonpath, and refuses a base stage outside the tree with or without a run."""

from __future__ import annotations

import os

import pytest

from allo_usd.core.errors import LayerError
from allo_usd.core.files import relpath
from allo_usd.core.paths import BASE_STAGE
from allo_usd.usd.compose import TreeLinks, _inside, _uncached, copy_base_stage, write_composed_scene, write_pose_layer

from tests.support.helpers import make_spec


def test_tree_links_are_relpath_through_symlinks_and_dot_dots(tmp_path, monkeypatch):
    real = tmp_path / "real"
    for d in ("scenes/test/anomaly", "poses/s2030", "sky", "stages/anomalies", "elsewhere"):
        (real / d).mkdir(parents=True)
    for f in ("poses/s2030/d000_p01.usda", "sky/d000.usda", "stages/base.usda", "elsewhere/target.usda"):
        (real / f).write_text("#usda 1.0\n")
    os.symlink(real, tmp_path / "tree")                                          # the whole tree linked
    os.symlink(real / "elsewhere" / "target.usda", real / "sky" / "d001.usda")  # a layer that is a link
    os.symlink(real / "elsewhere", real / "stages" / "anomalies" / "linked")    # a linked directory
    monkeypatch.chdir(tmp_path)
    links = TreeLinks()
    starts = [tmp_path / "tree" / "scenes" / "test" / "anomaly", real / "scenes" / "test" / "anomaly",
              "tree/scenes/test/anomaly", "tree/stages/anomalies/linked/.."]
    targets = [real / "poses/s2030/d000_p01.usda", tmp_path / "tree/sky/d000.usda", "tree/sky/d001.usda",
               "tree/stages/base.usda", "tree/stages/anomalies/linked/../base.usda", "tree/scenes/missing.usda",
               tmp_path / "tree/stages/anomalies/linked/target.usda"]
    for _ in range(2):   # a second time from the cache
        for start in starts:
            for target in targets:
                assert links.relpath(target, start) == relpath(target, start), (target, start)


def test_inside_by_folder_is_commonpaths_rule():
    """write_composed_scene's tree check, decided per folder (and kept per run), answers as
    os.path.commonpath([top, target]) == top for the tree itself, paths below it, siblings that
    share a prefix and the file system's root."""
    tops = ["/", "/a", "/a/b", "/a/bc", "/x/y/z"]
    paths = ["/", "/a", "/a/b", "/a/b/c", "/a/bc", "/a/bc/d", "/a/b/c/d/e.usda", "/ab", "/a/b.usda", "/x/y",
             "/x/y/z", "/x/y/z/w", "/x/y/zz/w"]
    links = TreeLinks()
    for top in tops:
        for p in paths:
            want = os.path.commonpath([top, p]) == top
            assert _inside(top, p, _uncached) == want and _inside(top, p, links.once) == want, (top, p)


def test_a_scene_layer_naming_a_file_outside_its_tree_is_refused_with_or_without_a_run(tmp_path):
    """The tree check still refuses a base stage outside the tree (a run's TreeLinks keeps answers,
    not refusals), writes nothing, and accepts the same layer once the stage is the tree's own copy."""
    spec = make_spec()
    tree = tmp_path / "tree"
    pose = write_pose_layer(tree / "poses" / "p.usda", pose=1, camera=spec.camera, seed=1, seed_path="t",
                            sample_id="s1_d000_p01")
    sky = tree / "sky" / "d000.usda"
    sky.parent.mkdir(parents=True)
    sky.write_text("#usda 1.0\n")
    links = TreeLinks()
    for run in (None, links, links):
        with pytest.raises(LayerError, match="outside its tree"):
            write_composed_scene(spec, tree / "scenes" / "a.usda", pose_layer=pose, sky_layer=sky,
                                 base_stage=BASE_STAGE, root=tree, links=run)
    assert not (tree / "scenes" / "a.usda").exists()
    own = copy_base_stage(BASE_STAGE, tree)
    layer = write_composed_scene(spec, tree / "scenes" / "a.usda", pose_layer=pose, sky_layer=sky, base_stage=own,
                                 root=tree, links=links)
    assert "@../stages/base.usda@" in layer.read_text()
