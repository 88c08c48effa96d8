"""Property-based tests of the plan model (hypothesis): any dict of plan fields, valid or hostile
(wrong types, huge numbers, unknown keys), is either a Plan that saves and re-reads to the same
Plan (and the same bytes when saved again) and counts its scenes right, or a PlanError; and any
file content is either a plan or a PlanError. Never another exception."""

from __future__ import annotations

import pytest

import tempfile
from datetime import date, timezone
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from allo_usd.assets.catalogue import ANOMALY_VARIANTS
from allo_usd.core.errors import PlanError
from allo_usd.plan.enumeration import count_scenes, enumerate_scenes
from allo_usd.plan.io import load_plan, make_plan, save_plan
from allo_usd.plan.model import STATION_UNITS, STATION_UP_AXES
from allo_usd.plan.settings import DENOISE_PREFILTERS, DENOISE_QUALITIES, PRESETS

EXAMPLES = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SMALL_ENOUGH_TO_ENUMERATE = 5000

GARBAGE = st.one_of(
    st.none(), st.booleans(), st.integers(), st.integers(min_value=10**18, max_value=10**60),
    st.integers(max_value=-1), st.floats(), st.floats(min_value=1e9, max_value=1e300),
    st.text(max_size=12), st.lists(st.integers(), max_size=4),
    st.dictionaries(st.text(max_size=6), st.integers(), max_size=2),
)


def field(valid):
    """Mostly valid values, sometimes anything (one in eight)."""
    return st.integers(0, 7).flatmap(lambda i: GARBAGE if i == 0 else valid)   # (one_of would flatten GARBAGE)


def table(required=None, **optional):
    return field(st.fixed_dictionaries(required or {}, optional=optional))


ANOMALY = st.sampled_from(sorted(ANOMALY_VARIANTS)).flatmap(
    lambda a: st.one_of(st.just(a), st.sampled_from(ANOMALY_VARIANTS[a]).map(lambda v: f"{a}:{v}"),
                        st.fixed_dictionaries({"id": st.just(a)},
                                              optional={"variants": st.lists(st.sampled_from(ANOMALY_VARIANTS[a]),
                                                                             min_size=1, max_size=2, unique=True)})))
DATE = st.dates(date(1890, 1, 1), date(2060, 12, 31))

PLAN_FIELDS = dict(
    dates=table(start=field(st.one_of(DATE, DATE.map(str), st.just("9999-12-31"))),
                days=field(st.integers(1, 6)), step_days=field(st.integers(1, 4000))),
    perilune_epoch=field(st.datetimes(timezones=st.just(timezone.utc)).map(lambda t: t.isoformat())),
    poses=table(train=field(st.lists(st.integers(1, 50), max_size=4, unique=True)),
                test=field(st.lists(st.integers(1, 50), max_size=3, unique=True))),
    anomalies=table(assets=field(st.lists(ANOMALY, max_size=3)),
                    depths=field(st.lists(st.integers(0, 4), min_size=1, max_size=5, unique=True)),
                    reserve_groups_per_slot=field(st.integers(0, 100))),
    counts=table(normal_train=field(st.integers(0, 40)), normal_test=field(st.integers(0, 20)),
                 anomalous_test=field(st.integers(0, 60))),
    effects=table(sensor_noise=field(st.booleans()), glare=field(st.booleans()),
                  inspection_light=field(st.booleans()), body_shine=field(st.booleans())),
    quality=table(preset=field(st.sampled_from(sorted(PRESETS))),
                  resolution=field(st.tuples(st.integers(1, 9000), st.integers(1, 9000)).map(list)),
                  samples=field(st.integers(1, 70000)), denoise=field(st.booleans()),
                  denoise_prefilter=field(st.sampled_from(DENOISE_PREFILTERS)),
                  denoise_quality=field(st.sampled_from(DENOISE_QUALITIES)),
                  max_bounces=field(st.integers(0, 2000)),
                  adaptive_threshold=field(st.floats(0.0, 1.0))),
    seeds=field(st.lists(st.integers(0, 2**40), min_size=1, max_size=3, unique=True)),
    station=table(source=field(st.sampled_from(["procedural", "model.glb", "a/b.stl", "x.usda"])),
                  units=field(st.sampled_from(STATION_UNITS)), up_axis=field(st.sampled_from(STATION_UP_AXES))),
    base_stage=field(st.sampled_from(["stages/base.usda", "other.usda"])),
)
SMALL_DATES = st.fixed_dictionaries({"days": st.integers(1, 4)}, optional={"start": DATE.map(str)})
PLAN_DICTS = st.builds(
    lambda plan, dates, unknown: {**plan, **dates, **unknown},
    st.fixed_dictionaries({"name": field(st.from_regex(r"[A-Za-z0-9_.-]{1,10}", fullmatch=True))},
                          optional=PLAN_FIELDS),
    st.one_of(st.just({}), st.fixed_dictionaries({"dates": SMALL_DATES})),          # small plans, to enumerate
    st.integers(0, 9).flatmap(lambda i: st.dictionaries(st.text(max_size=8), GARBAGE, min_size=1, max_size=2)
                              if i == 0 else st.just({})),
)


@EXAMPLES
@given(data=PLAN_DICTS)
@pytest.mark.slow
def test_any_plan_dict_is_a_plan_that_round_trips_or_a_plan_error(data):
    try:
        plan = make_plan(data)
    except PlanError:
        return
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in (".toml", ".yaml"):
            first = save_plan(plan, Path(tmp) / f"first{suffix}")
            again = load_plan(first)
            assert again == plan
            assert save_plan(again, Path(tmp) / f"second{suffix}").read_bytes() == first.read_bytes()
    n = count_scenes(plan)
    if n <= SMALL_ENOUGH_TO_ENUMERATE:
        assert len(enumerate_scenes(plan)) == n


@EXAMPLES
@given(content=st.one_of(st.binary(max_size=200), st.text(max_size=200)), suffix=st.sampled_from([".toml", ".yaml"]))
def test_any_file_is_a_plan_or_a_plan_error(content, suffix):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"plan{suffix}"
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content, encoding="utf-8")
        try:
            load_plan(path)
        except PlanError:
            pass
