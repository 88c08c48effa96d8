"""Plans mean one thing, and hostile plan files fail fast with a PlanError that names the field or
file and the fix: presets and explicit fields, date overflows, binary files, YAML
alias bombs, oversized files, and plans that expand to more scenes than anything could author."""

from __future__ import annotations

import itertools
import re
import tracemalloc

import pytest

from allo_usd.core.errors import PlanError
from allo_usd.plan.io import MAX_DEPTH, MAX_PLAN_BYTES, load_plan, make_plan, save_plan
from allo_usd.plan.model import MAX_PLAN_SCENES, demo_plan, paper_plan
from allo_usd.plan.settings import PRESETS


# ---------------------------------------------------------------------------------------------
# Presets and explicit fields: one meaning

@pytest.mark.parametrize("make", [paper_plan, demo_plan])
def test_editing_the_preset_in_a_written_plan_changes_the_quality(tmp_path, make):
    path = save_plan(make(), tmp_path / "plan.toml")
    text = path.read_text()
    assert "samples" not in text and "max_bounces" not in text   # the preset's fields are not written out
    old = make().quality.preset
    path.write_text(text.replace(f'preset = "{old}"', 'preset = "draft"'))
    edited = load_plan(path).quality
    assert edited.preset == "draft"
    assert {k: getattr(edited, k) for k in PRESETS["draft"]} == PRESETS["draft"]


def test_what_the_user_set_is_written_and_wins_over_the_preset(tmp_path):
    plan = make_plan({"name": "x", "quality": {"preset": "final", "samples": 100}})
    assert plan.quality.samples == 100 and plan.quality.max_bounces == PRESETS["final"]["max_bounces"]
    for suffix in (".toml", ".yaml"):
        path = save_plan(plan, tmp_path / f"p{suffix}")
        again = load_plan(path)
        assert again == plan and again.quality.samples == 100
        assert save_plan(again, tmp_path / f"q{suffix}").read_bytes() == path.read_bytes()
    assert "max_bounces" not in (tmp_path / "p.toml").read_text()


def test_an_unknown_preset_is_refused_with_the_choices():
    with pytest.raises(PlanError, match=r"quality\.preset.*draft.*preview.*final.*paper"):
        make_plan({"name": "x", "quality": {"preset": "fast"}})
    with pytest.raises(PlanError, match=r"quality\.preset"):
        make_plan({"name": "x", "quality": {"preset": "my-label"}})


def test_the_demo_preset_is_a_preset_and_the_demo_plan_keeps_its_quality():
    q = demo_plan().quality
    assert q.preset == "demo" and "demo" in PRESETS
    assert (q.samples, q.adaptive_threshold, q.denoise, q.max_bounces, q.denoise_prefilter, q.denoise_quality) == \
        (32, 0.0, True, 8, "FAST", "BALANCED")   # what the demo plan authored before presets had one meaning


# ---------------------------------------------------------------------------------------------
# Dates that leave DE421 (or the calendar)

@pytest.mark.parametrize("dates", [
    'start = 9999-12-31',
    'start = 2030-01-01\ndays = 1e9',           # a float TOML number pydantic reads as an int
    'days = 1000000000',
    'step_days = 100000000000\ndays = 2',
    'start = 0001-01-01',
    'days = 20000\nstep_days = 20000',
])
def test_dates_that_overflow_name_the_field_and_the_range(tmp_path, dates):
    path = tmp_path / "plan.toml"
    path.write_text(f'name = "x"\n[dates]\n{dates}\n')
    with pytest.raises(PlanError) as err:
        load_plan(path)
    msg = str(err.value)
    assert "dates" in msg and "1899-07-29" in msg and "2053-10-08" in msg and "fix:" in msg, msg


def test_a_perilune_epoch_at_the_end_of_the_calendar_is_a_plan_error():
    with pytest.raises(PlanError, match="perilune_epoch"):
        make_plan({"name": "x", "perilune_epoch": "9999-12-31T23:59:59-05:00"})


# ---------------------------------------------------------------------------------------------
# Files that are not plans

def test_a_binary_plan_file_is_a_plan_error_naming_the_file(tmp_path):
    for name in ("plan.toml", "plan.yaml"):
        path = tmp_path / name
        path.write_bytes(bytes(range(256)) * 4)
        with pytest.raises(PlanError, match=rf"{name}.*not UTF-8 text"):
            load_plan(path)


def test_a_file_above_the_size_bound_is_refused_before_parsing(tmp_path):
    path = tmp_path / "plan.yaml"
    path.write_text("name: x\n" + "#" * MAX_PLAN_BYTES)
    with pytest.raises(PlanError, match=r"plan\.yaml.*bytes"):
        load_plan(path)


BOMB = """\
a: &a ["x", "x", "x", "x", "x", "x", "x", "x", "x", "x"]
b: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]
c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]
d: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]
e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]
f: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e, *e]
g: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f, *f]
h: &h [*g, *g, *g, *g, *g, *g, *g, *g, *g, *g]
name: *h
"""


def test_a_yaml_alias_bomb_is_refused(tmp_path):
    path = tmp_path / "plan.yaml"
    path.write_text(BOMB)
    with pytest.raises(PlanError, match=r"plan\.yaml.*alias") as err:
        load_plan(path)
    assert len(str(err.value)) < 1000


@pytest.mark.parametrize("suffix, text", [
    (".yaml", "name: " + "[" * 50_000 + "]" * 50_000),    # libyaml's node builder would crash the process
    (".yaml", "name: x\nposes: " + "{a: " * 20_000 + "1" + "}" * 20_000),
    (".yaml", "name: x\nposes:\n" + "".join(" " * i + "a:\n" for i in range(1, 60)) + " " * 60 + "1\n"),  # block
    (".toml", "name = " + "[" * 50_000 + "]" * 50_000),
])
def test_deep_nesting_is_a_plan_error(tmp_path, suffix, text):
    path = tmp_path / f"plan{suffix}"
    path.write_text(text)
    # the project's own words (allo_usd.plan.io), whichever check refused it: ours, PyYAML's or Python's
    with pytest.raises(PlanError, match=rf"plan{re.escape(suffix)} is not valid (YAML|TOML): values nested too "
                                        rf"deeply \(over {MAX_DEPTH} levels.*; fix: "):
        load_plan(path)


@pytest.mark.parametrize("yaml_text, toml_text, key, line, first", [
    ("name: x\nquality:\n  samples: 3\n  samples: 2\n", 'name = "x"\n[quality]\nsamples = 3\nsamples = 2\n',
     "samples", 4, 3),
    ("name: x\nseeds: [1]\nname: y\n", 'name = "x"\nseeds = [1]\nname = "y"\n', "name", 3, 1),
    ("name: x\nquality: {samples: 3, samples: 2}\n", 'name = "x"\nquality = {samples = 3, samples = 2}\n',
     "samples", 2, 2),
    ("name: x\nanomalies:\n  assets:\n    - id: power_drill\n      id: wrench\n",
     'name = "x"\n[[anomalies.assets]]\nid = "power_drill"\nid = "wrench"\n', "id", 5, 4),
])
def test_a_key_given_twice_is_refused_in_yaml_as_in_toml(tmp_path, yaml_text, toml_text, key, line, first):
    """YAML's loader kept the last of two equal keys (the plan said samples 2, no error); TOML refuses them.
    Both refuse now, in one line; the YAML line names the key and both lines, at any depth."""
    for suffix, text in ((".toml", toml_text), (".yaml", yaml_text)):
        path = tmp_path / f"plan{suffix}"
        path.write_text(text)
        with pytest.raises(PlanError) as err:
            load_plan(path)
        assert "\n" not in str(err.value) and "fix" in str(err.value), err.value
    assert str(err.value) == (f"{path} is not valid YAML: key {key!r} is given twice in one mapping (at line {line}, "
                              f"first at line {first}); fix: keep one of the two")


def test_a_plan_written_in_yaml_still_loads_with_its_repeated_keys_in_separate_mappings(tmp_path):
    plan = make_plan({"name": "x", "quality": {"preset": "final", "samples": 100},
                      "anomalies": {"assets": [{"id": "power_drill"}, {"id": "wrench"}]}})
    path = save_plan(plan, tmp_path / "plan.yaml")
    assert path.read_text().count("id: ") == 2 and load_plan(path) == plan


@pytest.mark.parametrize("text", [
    "name: x\nseeds: HUNTER2 HUNTER2: 1\n",          # mapping values are not allowed here
    "name: x\nseeds: [HUNTER2, 1\nquality: 2\n",     # an unclosed flow sequence
    "name: x\n\tHUNTER2: 1\n",                       # a tab
    'name: "HUNTER2 \\q"\n',                         # an unknown escape
])
def test_a_yaml_syntax_error_names_line_and_column_never_the_line(tmp_path, text):
    """The rule for plan messages: line and column, never the line's text (PyYAML's own message quotes it
    under a caret)."""
    path = tmp_path / "plan.yaml"
    path.write_text(text)
    with pytest.raises(PlanError, match=r"is not valid YAML: .*line \d+, column \d+") as err:
        load_plan(path)
    assert "HUNTER2" not in str(err.value) and "\n" not in str(err.value), err.value


def test_validation_messages_never_print_the_whole_input():
    huge = list(range(100, 200_100))
    with pytest.raises(PlanError) as err:
        make_plan({"name": ["x"] * 100_000, "poses": {"train": huge}, "seeds": [-1] * 100_000,
                   **{f"field{i}": i for i in range(1000)}})
    msg = str(err.value)
    assert len(msg) < 10_000, len(msg)
    assert "name" in msg and "poses.train" in msg and "seeds" in msg and "more" in msg


# ---------------------------------------------------------------------------------------------
# Plans that expand to too many scenes; lazy enumeration

def test_a_plan_of_a_billion_scenes_is_refused_arithmetically():
    with pytest.raises(PlanError, match=rf"{MAX_PLAN_SCENES:,}.*fix:"):
        make_plan({"name": "x", "dates": {"start": "1900-01-01", "days": 20_000}, "seeds": list(range(1000))})


@pytest.mark.slow
def test_scenes_are_enumerated_lazily_and_counted_without_enumerating():
    from allo_usd.plan.enumeration import count_scenes, enumerate_scenes, iter_scenes

    big = make_plan({"name": "big", "dates": {"start": "1900-01-01", "days": 20_000}, "seeds": [1, 2, 3, 4]})
    n = count_scenes(big)
    assert 5_000_000 < n <= MAX_PLAN_SCENES
    tracemalloc.start()
    try:
        first = list(itertools.islice(iter_scenes(big), 100))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(first) == 100 and peak < 20_000_000, peak   # a list of every scene would take gigabytes
    for plan in (paper_plan(), demo_plan()):
        keys = enumerate_scenes(plan)
        assert count_scenes(plan) == len(keys) and list(iter_scenes(plan)) == keys


@pytest.mark.slow
def test_author_limit_does_not_enumerate_the_whole_plan(tmp_path, monkeypatch):
    """`author --limit N` takes the first N scenes from the lazy enumeration."""
    import allo_usd.plan.enumeration as enumeration
    import allo_usd.run.author as authoring
    from allo_usd.core.paths import BASE_STAGE

    taken = []

    def counting(plan):
        for key in enumeration.iter_scenes(plan):
            taken.append(key)
            yield key

    monkeypatch.setattr(authoring, "iter_scenes", counting)
    plan = make_plan({"name": "lim", "dates": {"days": 3}, "poses": {"train": [1, 2], "test": [41]},
                      "anomalies": {"assets": ["power_drill"]}, "quality": {"resolution": [64, 36]},
                      "base_stage": str(BASE_STAGE)})
    done = authoring.author(plan, tmp_path, limit=2, progress=False, workers=1)
    assert len(done.paths) == 2 and len(taken) <= 3


# ---------------------------------------------------------------------------------------------
# The target mode: a quality to aim at

def test_a_plans_target_is_written_read_and_reaches_the_render_spec(tmp_path):
    from allo_usd.plan.settings import RenderSpec, quality_of

    plan = make_plan({"name": "x", "quality": {"preset": "final", "target_psnr": 40, "time_limit": 120}})
    assert (plan.quality.target_psnr, plan.quality.time_limit, plan.quality.samples) == (40.0, 120.0, 192)
    path = save_plan(plan, tmp_path / "p.toml")
    assert "target_psnr = 40" in path.read_text() and load_plan(path) == plan
    spec = RenderSpec(**quality_of(plan.quality))
    assert (spec.target_psnr, spec.time_limit) == (40.0, 120.0)
    for name in PRESETS:   # the named presets keep their fixed samples
        fixed = make_plan({"name": "x", "quality": {"preset": name}}).quality
        assert (fixed.target_psnr, fixed.time_limit) == (0.0, 0.0)
    assert "target_psnr" not in save_plan(make_plan({"name": "x"}), tmp_path / "q.toml").read_text()


@pytest.mark.parametrize("quality,needle", [
    ({"target_psnr": "nan"}, "quality: target_psnr nan is not a PSNR in dB"),
    ({"target_psnr": -1}, "quality: target_psnr -1 is not a PSNR in dB"),
    ({"target_psnr": 1e9}, "quality: target_psnr 1e+09 is not a PSNR in dB"),
    ({"target_psnr": "inf"}, "quality: target_psnr inf is not"),
    ({"target_psnr": 40, "time_limit": -5}, "quality: time_limit -5 is not a number of seconds"),
    ({"target_psnr": 40, "time_limit": 1e300}, "quality: time_limit 1e+300 is not"),
    ({"time_limit": 60}, "quality: time_limit 60 is given without target_psnr"),
])
def test_a_bad_target_is_a_plan_error_naming_the_field_and_the_fix(tmp_path, quality, needle):
    for suffix, text in ((".toml", "[quality]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in quality.items())),
                         (".yaml", "quality:\n" + "".join(f"  {k}: {_yaml(v)}\n" for k, v in quality.items()))):
        path = tmp_path / f"p{suffix}"
        path.write_text('name = "x"\n' + text if suffix == ".toml" else "name: x\n" + text)
        with pytest.raises(PlanError) as info:
            load_plan(path)
        message = str(info.value)
        assert needle in message and "fix:" in message, message


def _toml(v):
    return {"nan": "nan", "inf": "inf"}.get(v, repr(v)) if isinstance(v, str) else repr(v)


def _yaml(v):
    return {"nan": ".nan", "inf": ".inf"}.get(v, v) if isinstance(v, str) else repr(v)


def test_a_target_with_lens_glare_is_a_plan_error(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text('name = "x"\n[quality]\ntarget_psnr = 40\n[effects]\nglare = true\n')
    with pytest.raises(PlanError, match="quality.target_psnr with effects.glare: .*fix: turn lens glare off"):
        load_plan(path)
