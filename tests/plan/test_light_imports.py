"""Plan validation loads nothing heavy: anomaly ids and DE421's range are constants, checked here
against the builders and the real ephemeris file."""

from __future__ import annotations

import pytest

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.process
def test_validating_a_plan_leaves_builders_and_skyfield_unloaded():
    code = ("import sys\n"
            "from allo_usd.plan.model import paper_plan, demo_plan\n"
            "paper_plan(); demo_plan()\n"
            "heavy = [m for m in ('allo_usd.assets.anomalies', 'skyfield', 'skyfield_data', 'allo_usd.sky.model')"
            " if m in sys.modules]\n"
            "assert not heavy, heavy\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, cwd=ROOT)


def test_catalogue_names_every_builder():
    from allo_usd.assets import anomalies
    from allo_usd.assets.catalogue import ANOMALY_IDS, ANOMALY_VARIANTS

    assert tuple(anomalies._BUILDERS) == ANOMALY_IDS
    assert anomalies.ANOMALY_VARIANTS is ANOMALY_VARIANTS


def test_de421_range_constants_match_the_file():
    """The UTC constants are the file's limits rounded inwards to the microsecond."""
    import math
    from datetime import datetime, timedelta, timezone

    from allo_usd.core.timefmt import format_utc
    from allo_usd.sky import ephemeris_range as R
    from allo_usd.sky.ephemeris import load_de421, quiet_expiry

    e = load_de421()
    assert (e.start_tdb_jd, e.end_tdb_jd) == (R.DE421_START_TDB_JD, R.DE421_END_TDB_JD)
    utc = []
    with quiet_expiry():
        for jd, inwards in ((e.start_tdb_jd, math.ceil), (e.end_tdb_jd, math.floor)):
            c = e.ts.tdb_jd(jd).utc
            minute = datetime(*map(int, c[:5]), tzinfo=timezone.utc)
            utc.append(format_utc(minute + timedelta(microseconds=inwards(c.second * 1e6))))
    assert tuple(utc) == (R.DE421_START_UTC, R.DE421_END_UTC)
