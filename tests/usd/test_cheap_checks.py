"""The cheap paths of the checks give the answers of the full checks they stand in for.

- the JSON read gate parses first and refuses depth from the parsed value (no bracket scan per record);
- the dispatcher's allowed_roots cache answers for one decision only: a fresh check (a render
  worker's) still refuses a tree folder turned into a symbolic link;
- a scene layer's header in the shape `author` writes is recognised without a USD parse, and any
  other shape takes the parse, so both agree;
- `dataset` keeps the stat at which each record passed check_render and the rows each contact sheet
  was drawn from: a re-run re-checks a record whose files changed and redraws only the sheets whose
  rows changed; an anomaly's BOP mask_visib is its ground-truth mask (one file, hard-linked).

Renders here are synthetic (tests/support/renders.py fake_render): no Cycles run."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from allo_usd.core.errors import LayerError
from allo_usd.core.files import MAX_JSON_DEPTH, InputRefused, read_head, read_user_json
from allo_usd.output.dataset import assemble, read_manifest
from allo_usd.usd import sniff
from allo_usd.usd.safety import allowed_roots, roots_cached

from tests.support.renders import fake_render


def _nest(depth: int) -> str:
    return "[" * depth + "]" * depth


# ---------------------------------------------------------------- the JSON read gate

def test_depth_between_the_bound_and_the_recursion_limit_is_refused_with_its_line(tmp_path):
    f = tmp_path / "r.json"
    f.write_text('{"a": 1,\n "b": ' + _nest(MAX_JSON_DEPTH + 30) + "}")   # json.loads parses this fine
    with pytest.raises(InputRefused) as err:
        read_user_json(f, 1 << 20, "render record")
    assert err.value.kind == "too_deep" and "(at line 2)" in str(err.value)
    f.write_text('{"b": ' + _nest(MAX_JSON_DEPTH - 1) + "}")                   # exactly the bound
    assert read_user_json(f, 1 << 20, "render record")["b"]
    f.write_text('{"b": ' + _nest(MAX_JSON_DEPTH) + ", }")                     # deep and broken: depth is named
    with pytest.raises(InputRefused) as err:
        read_user_json(f, 1 << 20, "render record")
    assert err.value.kind == "too_deep"
    f.write_text('{"b": [1, 2,]}')
    with pytest.raises(InputRefused) as err:
        read_user_json(f, 1 << 20, "render record")
    assert err.value.kind == "not_json"


# ---------------------------------------------------------------- allowed_roots, cached for one decision

def _tree(root: Path) -> Path:
    for d in ("scenes", "sky", "poses", "stages", "hazards"):
        (root / d).mkdir(parents=True)
    (root / "plan.toml").write_text('name = "t"\n')
    layer = root / "scenes" / "a.usda"
    layer.write_text("#usda 1.0\n")
    return layer


def _roots_entries(cache: dict) -> list:
    """The allowed_roots answers of a decision's cache (it also holds real_path's folders, check_root's
    answers and current_identity's input checksums, each under its own tag)."""
    return [k for k in cache if k[0] not in ("realpath", "check_root", "input")]


def test_the_roots_cache_serves_one_decision_and_a_fresh_check_refuses_a_linked_folder(tmp_path):
    layer = _tree(tmp_path / "tree")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    cache: dict = {}
    with roots_cached(cache):
        before = allowed_roots(layer)
        assert sniff.refusal(layer) is None
    assert len(_roots_entries(cache)) == 1 and Path(os.path.realpath(tmp_path / "tree" / "sky")) in before
    (tmp_path / "tree" / "sky").rmdir()
    (tmp_path / "tree" / "sky").symlink_to(elsewhere)
    with roots_cached(cache):   # the same decision: its answer stands
        assert allowed_roots(layer) == before
    with pytest.raises(LayerError, match="symbolic link"):   # a worker's check is fresh
        allowed_roots(layer)
    assert "symbolic link" in sniff.refusal(layer)
    with roots_cached():   # a new decision computes again
        assert "symbolic link" in sniff.refusal(layer)


def test_a_layer_that_is_a_link_is_never_answered_from_the_cache(tmp_path):
    layer = _tree(tmp_path / "tree")
    loose = tmp_path / "loose"
    loose.mkdir()
    (loose / "b.usda").write_text("#usda 1.0\n")
    (tmp_path / "tree" / "scenes" / "b.usda").symlink_to(loose / "b.usda")
    cache: dict = {}
    with roots_cached(cache):
        tree_roots = allowed_roots(layer)
        linked_roots = allowed_roots(tmp_path / "tree" / "scenes" / "b.usda")
    # the same folder as named, but its tree is its target's (none): computed, not looked up
    assert len(_roots_entries(cache)) == 1 and linked_roots != tree_roots
    assert not {tmp_path / "tree" / d for d in ("sky", "poses")} & {Path(r) for r in linked_roots}


# ---------------------------------------------------------------- recognising a scene layer

AUTHORED = ('#usda 1.0\n(\n    customLayerData = {\n        dictionary allo = {\n'
            '            string packageVersion = "0.1.0"\n            string sceneId = "s1"\n'
            '            int64 seed = 5233059138011408575\n        }\n    }\n    defaultPrim = "World"\n)\n\n'
            'over "World"\n{\n}\n')
HEADS = {
    "authored": AUTHORED,
    "second_custom_data": AUTHORED.replace('    defaultPrim = "World"\n',
                                           '    customLayerData = {\n        dictionary other = {\n        }\n    }\n'),
    "other_dictionary": AUTHORED.replace("dictionary allo", "dictionary mine"),
    "scene_id_elsewhere": AUTHORED.replace('string sceneId = "s1"', 'string sceneName = "s1"')
                                  .replace("{\n}\n", '{\n    string sceneId = "s1"\n}\n'),
    "string_with_braces": AUTHORED.replace('"0.1.0"', '"} } ) ("'),
    "comment_first": AUTHORED.replace("#usda 1.0\n", "#usda 1.0\n# made by hand\n"),
}


def test_the_header_shortcut_agrees_with_the_parse(tmp_path, monkeypatch):
    found = {}
    for name, text in HEADS.items():
        path = tmp_path / f"{name}.usda"
        path.write_text(text)
        head = read_head(path, sniff.HEAD_BYTES)
        quick = sniff.is_scene_layer(path)
        monkeypatch.setattr(sniff, "_AUTHORED_HEAD", __import__("re").compile(rb"(?!)"))   # the parse alone
        parsed = sniff.is_scene_layer(path)
        monkeypatch.undo()
        assert quick == parsed, name
        found[name] = (quick, bool(sniff._AUTHORED_HEAD.match(head)))
    assert found["authored"] == (True, True) and found["string_with_braces"] == (True, True)
    assert found["other_dictionary"] == (False, False) and found["scene_id_elsewhere"] == (False, False)
    # the prefix matches, but a second customLayerData replaces the first: the guard sends it to the parse
    assert found["second_custom_data"] == (False, True) and found["comment_first"] == (True, False)


# ---------------------------------------------------------------- dataset re-runs

def _assemble(renders: Path, out: Path) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assemble([renders], out)
    return [str(w.message) for w in caught]


def _mask(path: Path, anomaly: int, size=(64, 36), station: int = 600) -> None:
    """A 3-class mask PNG stored uncompressed: its size depends on the dimensions only."""
    w, h = size
    m = np.zeros(w * h, np.uint8)
    m[:station] = 1
    m[station:station + anomaly] = 2
    Image.fromarray(m.reshape(h, w)).save(path, compress_level=0)


def _state(out: Path) -> dict:
    return json.loads((out / "annotations" / "records.json").read_text())["state"]


def test_a_rerun_trusts_a_checked_record_by_stat_and_rechecks_a_changed_one(tmp_path):
    renders, out = tmp_path / "renders", tmp_path / "ds"
    fake_render(renders, "n1")
    fake_render(renders, "a1", split="test", variant="anomaly", anomaly=40)
    _mask(renders / "a1_mask.png", 40)
    assert not [m for m in _assemble(renders, out) if "refused" in m]
    checks = _state(out)["checks"]
    assert sorted(checks) == ["../renders/a1.json", "../renders/n1.json"]   # relative: no machine's path
    assert checks["../renders/a1.json"]["kind"] == "anomaly" and checks["../renders/a1.json"]["size"] == [64, 36]

    mask = renders / "a1_mask.png"
    st = mask.stat()
    _mask(mask, 41)   # in place (same inode), same size: the mask now contradicts the JSON's 40 pixels
    os.utime(mask, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert mask.stat().st_size == st.st_size and mask.stat().st_ino == st.st_ino
    assert not [m for m in _assemble(renders, out) if "refused" in m]   # the quick check trusts its stat

    os.utime(mask, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))     # touched: checked again, refused
    messages = _assemble(renders, out)
    assert any("refused" in m and "a1.json" in m and "anomaly pixels" in m for m in messages), messages
    assert "../renders/a1.json" not in _state(out)["checks"]


def test_contact_sheets_are_redrawn_only_for_a_split_whose_rows_changed(tmp_path):
    renders, out = tmp_path / "renders", tmp_path / "ds"
    for i in range(3):
        fake_render(renders, f"n{i}")
    fake_render(renders, "t0", split="test")
    fake_render(renders, "a0", split="test", variant="anomaly", anomaly=40)
    _assemble(renders, out)
    sheets = out / "contact_sheets"

    def stamps():
        return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in sheets.iterdir()}

    first = stamps()
    assert sorted(first) == ["allo_test.png", "allo_train.png"]
    records = (out / "annotations" / "records.json").read_bytes()
    _assemble(renders, out)
    assert stamps() == first                                         # nothing changed: nothing redrawn
    assert (out / "annotations" / "records.json").read_bytes() == records
    fake_render(renders, "t1", split="test")
    _assemble(renders, out)
    again = stamps()
    assert again["allo_train.png"] == first["allo_train.png"] and again["allo_test.png"] != first["allo_test.png"]
    (sheets / "allo_train.png").unlink()                             # a sheet gone is drawn again
    _assemble(renders, out)
    assert (sheets / "allo_train.png").is_file()


def test_an_anomalys_mask_visib_is_its_ground_truth_mask(tmp_path):
    renders, out = tmp_path / "renders", tmp_path / "ds"
    fake_render(renders, "a1", split="test", variant="anomaly", anomaly=40)
    fake_render(renders, "n1")
    _assemble(renders, out)
    row = next(r for r in read_manifest(out / "manifest.csv") if r["name"] == "a1")
    visib = out / "bop" / "allo" / "test" / "000000" / "mask_visib" / f"{int(row['index']):06d}_000000.png"
    truth = out / row["mask"]
    assert os.path.samefile(visib, truth)
    pixels = np.asarray(Image.open(truth))
    assert set(np.unique(pixels)) == {0, 255} and int((pixels == 255).sum()) == 40


def test_a_decision_resolves_folders_and_answers_check_root_once(tmp_path):
    """Inside one decision (roots_cached) real_path resolves a layer through its folder's cached real
    path and check_root answers a layer once; outside, and in a new decision, they look afresh. A
    layer that is itself a link is resolved in full, even inside."""
    from allo_usd.usd.dependencies import check_root
    from allo_usd.usd.safety import real_path

    layer = _tree(tmp_path / "tree")
    (tmp_path / "real").mkdir()
    (tmp_path / "real" / "b.usda").write_text("#usda 1.0\n")
    (tmp_path / "tree" / "scenes" / "b.usda").symlink_to(tmp_path / "real" / "b.usda")
    cache: dict = {}
    with roots_cached(cache):
        assert real_path(layer) == os.path.realpath(layer)
        assert real_path(tmp_path / "tree" / "scenes" / "b.usda") == str(tmp_path / "real" / "b.usda")
        assert check_root(layer) == os.path.realpath(layer)
        layer.unlink()   # gone after this decision looked: its answer stands for the decision
        assert check_root(layer) == os.path.realpath(layer) and sniff.refusal(layer) is None
    assert ("realpath", str(layer.parent)) in cache
    assert "cannot be read" in sniff.refusal(layer)   # a fresh look (a worker's)
    with roots_cached():
        assert "cannot be read" in sniff.refusal(layer)


def test_in_threads_keeps_order_shares_the_decision_cache_and_raises():
    """core.threads.in_threads: the answers in the items' order, each call sees the caller's
    roots_cached dict (one decision: one cache), and an exception reaches the caller."""
    from allo_usd.core.threads import in_threads
    from allo_usd.usd.safety import decision_cache

    cache: dict = {}

    def note(x):
        decision_cache()[("seen", x)] = x * x
        return x * 2

    with roots_cached(cache):
        assert in_threads(note, list(range(1000))) == [2 * x for x in range(1000)]
    assert cache == {("seen", x): x * x for x in range(1000)}

    def boom(x):
        if x == 700:
            raise ValueError("seven hundred")
        return x

    with pytest.raises(ValueError, match="seven hundred"):
        in_threads(boom, list(range(1000)))


def test_a_resume_decision_reads_each_layer_once(tmp_path, tiny_base):
    """The dispatcher's scan reads a scene layer once, to sniff it and checksum it; the resume
    check's checksum of the layer comes from that read (file_sha256's cache holds it under the
    layer's stat), and an edited layer is a new stat, so it is read again."""
    from allo_usd.output import checksums as m
    from allo_usd.run.dispatch import find_layers
    from allo_usd.usd.scene_layer import write_scene_layer

    from tests.support.helpers import make_spec

    for i in range(3):
        write_scene_layer(make_spec(seed=80 + i, scene_id=f"r{i}"), tmp_path / "layers" / f"r{i}.usda", tiny_base)
    m._SHA256.clear()
    layers = find_layers(tmp_path / "layers")
    assert [p.name for p in layers] == ["r0.usda", "r1.usda", "r2.usda"]
    keys = {Path(k[0]).name: k for k in m._SHA256}
    assert set(keys) == {"r0.usda", "r1.usda", "r2.usda"}
    for p in layers:
        st = p.stat()
        assert keys[p.name][1:4] == (st.st_mtime_ns, st.st_size, st.st_ino)
        assert m.file_sha256(p) == m.sha256_file(p)
    before = m._SHA256[keys["r1.usda"]]
    layers[1].write_text(layers[1].read_text() + "\n")
    assert m.file_sha256(layers[1]) == m.sha256_file(layers[1]) != before
