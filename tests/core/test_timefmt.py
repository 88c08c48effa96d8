"""Recorded times round-trip to the microsecond: the perilune epoch a plan gives with
fractional seconds is the one the layers, `inspect --json` and the tree's plan record, and the sky
recomputed from the record is the sky that was authored. The DE421 range the errors print is the
range the checks accept, at the exact boundary instants."""

from __future__ import annotations

import json
from datetime import date, datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom
from typer.testing import CliRunner

from allo_usd.cli import app
from allo_usd.core.errors import EphemerisRangeError, EpochError, PlanError
from allo_usd.core.timefmt import format_utc, parse_utc
from allo_usd.plan.io import load_plan
from allo_usd.plan.model import Dates, Plan
from allo_usd.run.author import author
from allo_usd.scene.resolve import sun_and_bodies
from allo_usd.sky.ephemeris_range import DE421_END_UTC, DE421_START_UTC
from allo_usd.sky.model import compute_sky
from allo_usd.sky.orbit import Orbit

from tests.support.plans import small_plan

UTC = timezone.utc
POINT_NINE = datetime(2030, 1, 1, 0, 0, 0, 900000, tzinfo=UTC)
MICROS = datetime(2030, 1, 1, 0, 0, 0, 123456, tzinfo=UTC)


# ---------------------------------------------------------------------------------------------
# The one formatter and parser


@pytest.mark.parametrize("dt, text", [
    (datetime(2030, 1, 1, tzinfo=UTC), "2030-01-01T00:00:00Z"),          # whole seconds: bytes as before
    (datetime(2030, 12, 10, 23, 59, 59, tzinfo=UTC), "2030-12-10T23:59:59Z"),
    (POINT_NINE, "2030-01-01T00:00:00.9Z"),
    (MICROS, "2030-01-01T00:00:00.123456Z"),
    (datetime(2030, 1, 1, 0, 0, 0, 1, tzinfo=UTC), "2030-01-01T00:00:00.000001Z"),
    (datetime(999, 1, 1, 0, 0, 0, 10, tzinfo=UTC), "0999-01-01T00:00:00.00001Z"),
    (datetime(1, 1, 1, tzinfo=UTC), "0001-01-01T00:00:00Z"),
    (datetime(2030, 1, 1, 2, 0, 0, 500000, tzinfo=timezone(timedelta(hours=2))), "2030-01-01T00:00:00.5Z"),
])
def test_format_is_iso_utc_with_the_exact_fraction(dt, text):
    assert format_utc(dt) == text
    assert parse_utc(text) == dt and parse_utc(text).tzinfo == UTC


def test_every_microsecond_round_trips():
    rng = np.random.default_rng(16)
    t0 = datetime(1900, 1, 1, tzinfo=UTC)
    for us in rng.integers(0, 150 * 365 * 86_400 * 10**6, size=2000):
        dt = t0 + timedelta(microseconds=int(us))
        assert parse_utc(format_utc(dt)) == dt


@pytest.mark.parametrize("bad", ["2030-01-01T00:00:00", "2030-13-01T00:00:00Z", "yesterday", ""])
def test_parse_refuses_naive_or_malformed_text(bad):
    with pytest.raises(EpochError, match="fix: "):
        parse_utc(bad)
    with pytest.raises(EpochError, match="fix: "):
        format_utc(datetime(2030, 1, 1))


# ---------------------------------------------------------------------------------------------
# An authored tree records the instant it used


def _sky_translates(layer: Path) -> dict[str, np.ndarray]:
    """Each body's place and the sun lamp's +z (towards the Sun), composed."""
    stage = Usd.Stage.Open(str(layer))
    out = {}  # the stage stays referenced while its prims are read
    for body in ("Sun", "Earth", "Moon"):
        prim = stage.GetPrimAtPath(f"/World/Sky/{body}")
        m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
        out[body] = m[:3, 3]
    sun = stage.GetPrimAtPath("/World/Sky/SunLight")
    m = np.array(UsdGeom.Xformable(sun).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    out["SunLight"] = m[:3, 2]
    return out


def _angle(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))


@pytest.mark.parametrize("perilune", [POINT_NINE, MICROS], ids=["0.9s", "0.123456s"])
@pytest.mark.slow
def test_authored_layers_and_inspect_record_the_exact_perilune(tmp_path, perilune):
    out = tmp_path / "tree"
    plan = small_plan(perilune_epoch=perilune)
    (scene,) = author(plan, out, limit=1, progress=False).paths
    sky_layer = out / "sky" / "d000.usda"

    recorded = {}
    for layer in (sky_layer, scene):
        stage = Usd.Stage.Open(str(layer))
        world = stage.GetPrimAtPath("/World")
        recorded[layer] = (world.GetAttribute("allo:epoch").Get(), world.GetAttribute("allo:periluneEpoch").Get())
    assert Sdf.Layer.FindOrOpen(str(sky_layer)).customLayerData["allo"]["epoch"] == recorded[sky_layer][0]
    r = CliRunner().invoke(app, ["inspect", "--json", str(scene)])
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    recorded["inspect"] = (d["epoch"], d["perilune_epoch"])
    text = CliRunner().invoke(app, ["inspect", str(scene)]).output
    assert f"perilune {format_utc(perilune)}" in text

    for epoch, peri in recorded.values():
        assert parse_utc(peri) == perilune, peri
        assert parse_utc(epoch) == plan.dates.epochs()[0], epoch
    assert load_plan(out / "plan.toml").perilune_epoch == perilune
    assert f'"{format_utc(perilune)}"' in (out / "plan.toml").read_text()

    # The sky recomputed from the record alone is the authored sky.
    epoch, peri = recorded["inspect"]
    sun, bodies = sun_and_bodies(compute_sky([parse_utc(epoch)], Orbit(perilune_epoch=parse_utc(peri))), 0)
    authored = _sky_translates(scene)   # composed over the base stage, which orders the xformOps
    for name, body in bodies.items():
        assert _angle(authored[name], body.position) <= 1e-12, name
    assert _angle(authored["SunLight"], sun.direction) <= 1e-12
    # ... and not the sky of the whole second (the old record): the check can tell them apart.
    _, whole = sun_and_bodies(compute_sky([parse_utc(epoch)], Orbit(perilune_epoch=perilune.replace(microsecond=0))), 0)
    assert _angle(authored["Earth"], whole["Earth"].position) > 1e-8


# ---------------------------------------------------------------------------------------------
# Digits beyond the microsecond: truncated, the same way from every way of writing the plan


@pytest.mark.parametrize("name, text", [
    ("p.toml", 'name = "x"\nperilune_epoch = 2030-01-01T00:00:00.123456789Z\n'),
    ("p.toml", 'name = "x"\nperilune_epoch = "2030-01-01T00:00:00.123456789Z"\n'),
    ("p.yaml", "name: x\nperilune_epoch: 2030-01-01T00:00:00.123456789Z\n"),
    ("p.yaml", "name: x\nperilune_epoch: '2030-01-01T00:00:00.1234569Z'\n"),
])
def test_digits_beyond_the_microsecond_are_truncated(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    assert load_plan(tmp_path / name).perilune_epoch == MICROS


def test_a_perilune_without_timezone_is_refused(tmp_path):
    (tmp_path / "p.toml").write_text('name = "x"\nperilune_epoch = "2030-01-01T00:00:00.5"\n')
    with pytest.raises(PlanError, match="perilune_epoch.*fix: "):
        load_plan(tmp_path / "p.toml")


# ---------------------------------------------------------------------------------------------
# The DE421 range: what the errors print is what the checks accept


def test_the_plan_date_check_and_its_message_agree_at_both_ends():
    Dates(start=date(1899, 7, 29), days=1)
    Dates(start=date(2053, 10, 8), days=1)
    for start, days in ((date(1899, 7, 28), 1), (date(2053, 10, 8), 2)):
        with pytest.raises(ValueError) as info:
            Dates(start=start, days=days)
        assert "covers 1899-07-29 .. 2053-10-08" in str(info.value)
    with pytest.raises(ValueError, match="1899-07-29 .. 2053-10-08"):
        Plan.model_validate({"name": "x", "dates": {"start": "1899-07-28", "days": 1}})


def test_the_sky_accepts_the_printed_de421_instants_and_refuses_a_microsecond_beyond():
    lo, hi = parse_utc(DE421_START_UTC), parse_utc(DE421_END_UTC)
    sky = compute_sky([lo, hi])
    assert sky.epochs == (DE421_START_UTC, DE421_END_UTC)
    us = timedelta(microseconds=1)
    for outside in (lo - us, hi + us):
        with pytest.raises(EphemerisRangeError) as info:
            compute_sky([outside])
        assert f"{DE421_START_UTC} to {DE421_END_UTC}" in str(info.value)


# ---------------------------------------------------------------------------------------------
# The sky table and plot (allo-usd sky)


def test_the_sky_table_records_exact_epochs(tmp_path):
    from allo_usd.sky.report import write_sky_csv

    epochs = [POINT_NINE, MICROS + timedelta(days=1), datetime(2030, 1, 3, tzinfo=UTC)]
    sky = compute_sky(epochs, Orbit(perilune_epoch=MICROS))
    assert sky.orbit.as_dict()["perilune_epoch"] == "2030-01-01T00:00:00.123456Z"
    rows = write_sky_csv(sky, tmp_path / "sky.csv").read_text().splitlines()[1:]
    assert [parse_utc(r.split(",")[0]) for r in rows] == epochs
    assert rows[2].startswith("2030-01-03T00:00:00Z,")


def test_the_in_shadow_marker_sits_at_the_effective_irradiance():
    from allo_usd.sky.report import sky_figure

    sky = compute_sky(["2030-09-26T00:00:00Z", "2030-09-27T00:00:00Z"])   # the second: in the Moon's umbra
    assert list(sky.eclipse_state) == ["lit", "umbra"]
    ax = sky_figure(sky).axes[1]
    (marker,) = [ln for ln in ax.get_lines() if ln.get_label().startswith("in shadow")]
    assert "effective" in marker.get_label()
    assert list(marker.get_ydata()) == [float(sky.sun_irradiance_w_m2[1] * sky.lit_fraction[1])] == [0.0]
