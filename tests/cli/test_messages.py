"""What a new user trips over: messages that say what is wrong and how to
mend it, and a sky plot whose distance panel is drawn at a sampling that resolves the orbit."""

from __future__ import annotations

import inspect
import re
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from allo_usd.core.errors import AlloError, PlanError
from allo_usd.plan.io import load_plan, make_plan, save_plan
from allo_usd.plan.model import demo_plan

ROOT = Path(__file__).resolve().parents[2]
BRACKET_OBJ = ROOT / "examples" / "bring_your_own" / "bracket.obj"   # millimetres, 900 x 400 x 300


def readme_hazard_block() -> str:
    """The `[[anomalies.assets]]` block of docs/guide/bring_your_own.md (section "Your own hazards")."""
    section = (ROOT / "docs" / "guide" / "bring_your_own.md").read_text().split("### Your own hazards", 1)[1]
    return re.search(r"```toml\n(.*?)```", section, re.S).group(1)


# ------------------------------------------------------------------ a written plan takes an appended block

def test_the_readmes_hazard_block_appends_to_a_demo_plan(tmp_path):
    """`allo-usd plan --demo` writes its anomaly list as [[anomalies.assets]] blocks, so the README's block
    can be appended (an inline `assets = [...]` made that "Cannot mutate immutable namespace")."""
    path = save_plan(demo_plan(), tmp_path / "demo.toml")
    assert "[[anomalies.assets]]" in path.read_text() and "assets = [" not in path.read_text()
    path.write_text(path.read_text() + "\n" + readme_hazard_block())
    plan = load_plan(path)
    assert [a.id for a in plan.anomalies.assets] == ["power_drill", "wrench", "bracket"]
    again = load_plan(save_plan(plan, tmp_path / "again.toml"))   # colours as a sub-table round-trip
    assert again == plan and again.anomalies.assets[-1].colors == {"red": (0.8, 0.05, 0.05)}


def test_a_block_appended_to_an_inline_array_is_named(tmp_path):
    path = tmp_path / "plan.toml"
    path.write_text('name = "x"\n\n[anomalies]\nassets = [{ id = "power_drill" }]\n\n[station]\ntrack_sun = true\n\n'
                    '[[anomalies.assets]]\nid = "wrench"\n')
    with pytest.raises(PlanError) as err:
        load_plan(path)
    msg = str(err.value)
    assert "immutable namespace" not in msg and "\n" not in msg
    assert "line 9 adds a table to anomalies.assets, which is written inline earlier" in msg
    assert "fix: write each entry of anomalies.assets as its own [[anomalies.assets]] block" in msg


def test_a_duplicate_anomaly_id_is_named():
    with pytest.raises(PlanError, match=r"anomaly id 'power_drill' is listed twice \(a plan from `allo-usd plan "
                                        r"--demo` lists it already\); fix:"):
        make_plan({"name": "x", "anomalies": {"assets": ["power_drill", "wrench", "power_drill"]}})


# ------------------------------------------------------------------ variants without colors

def test_a_variant_without_its_colour_is_named_as_undefined():
    hazard = {"id": "bracket", "file": "hazards/bracket.stl", "units": "mm", "up_axis": "z",
              "variants": ["default", "red"]}
    with pytest.raises(PlanError) as err:
        make_plan({"name": "x", "anomalies": {"assets": [hazard]}})
    msg = str(err.value)
    assert "variant 'red' is not defined" in msg and "the plan gives it no colors" in msg
    assert "fix: define it in colors, e.g. colors = { red = [0.8, 0.05, 0.05] }" in msg
    assert "must be distinct names among default" not in msg


# ------------------------------------------------------------------ asset import

def test_asset_import_names_the_valid_up_axes(tmp_path):
    from allo_usd.cli import app

    r = CliRunner().invoke(app, ["asset", "import", str(BRACKET_OBJ), "--out", str(tmp_path), "--up-axis", "w"])
    assert r.exit_code != 0 and isinstance(r.exception, AlloError)
    msg = str(r.exception)
    assert "up axis 'w' is not one of x, y, z, -x, -y, -z or auto" in msg and "--up-axis" in msg
    assert "re-export" not in msg
    assert not list(tmp_path.iterdir())   # refused before anything is read or written


@pytest.mark.parametrize("label, limit", [("station", "0.01-500 m a station"),
                                          ("anomaly", "0.01-20 m a hazard near the station")])
def test_asset_import_of_a_millimetre_file_without_units_is_refused_by_size(tmp_path, label, limit):
    """The plan path's size check (allo_usd.usd.hazard.check_size), naming the unit it read."""
    from allo_usd.cli import app

    r = CliRunner().invoke(app, ["asset", "import", str(BRACKET_OBJ), "--out", str(tmp_path / "a"), "--label", label])
    assert r.exit_code != 0 and isinstance(r.exception, PlanError), r.output
    msg = str(r.exception)
    assert "measures 900 m along its longest side with units 'm' (--units auto: an OBJ file does not say its unit)" in msg
    assert limit in msg and "fix: give the unit the file is in (--units mm" in msg
    assert not (tmp_path / "a" / "bracket.usda").exists()
    r = CliRunner().invoke(app, ["asset", "import", str(BRACKET_OBJ), "--out", str(tmp_path / "b"), "--label", label,
                                 "--units", "mm"])
    assert r.exit_code == 0, r.output
    assert "unit mm, up axis y, 24 triangles, 0.9 x 0.3 x 0.4 m" in r.output


def test_the_plan_path_and_asset_import_share_one_size_check(tmp_path):
    from allo_usd.usd import hazard

    with pytest.raises(PlanError, match=r"anomaly 'bracket': .* measures 900 m along its longest side with units 'm', "
                                        r"outside the 0.01-20 m a hazard near the station may measure; fix: give the "
                                        r"unit the file is in \(units = \"mm\""):
        hazard.load_hazard(BRACKET_OBJ, "bracket", "m", "y")
    src = inspect.getsource(hazard) + inspect.getsource(__import__("allo_usd.cli", fromlist=["x"]))
    assert src.count("along its longest side") == 1


# ------------------------------------------------------------------ parser messages: one line

@pytest.mark.parametrize("text", [
    "name: x\nposes:\n" + "".join(" " * i + "a:\n" for i in range(1, 60)) + " " * 60 + "1\n",   # nesting
    "name: " + "[" * 100 + "]" * 100 + "\n",
    "name: [1, 2\n",                                              # PyYAML's four-line refusal
    "name: x\n  bad: : y\n",
])
def test_yaml_refusals_are_one_line(tmp_path, text):
    path = tmp_path / "plan.yaml"
    path.write_text(text)
    with pytest.raises(PlanError) as err:
        load_plan(path)
    msg = str(err.value)
    assert "\n" not in msg and "<unicode string>" not in msg, msg
    assert re.search(r"at line \d+", msg) and "fix" in msg


# ------------------------------------------------------------------ the sky plot's distance panel

@pytest.fixture(scope="module")
def sky():
    from allo_usd.sky.ephemeris import default_epochs
    from allo_usd.sky.model import compute_sky
    from allo_usd.sky.orbit import Orbit

    return compute_sky(default_epochs(2030, 21), Orbit())


def test_the_distance_panel_resolves_the_orbit(sky):
    from allo_usd.core.timefmt import parse_utc
    from allo_usd.sky.report import distance_curve

    times, km = distance_curve(sky)
    start, end = parse_utc(sky.epochs[0]), parse_utc(sky.epochs[-1])
    steps = np.diff([(t - start).total_seconds() for t in times])
    assert times[0] == start and times[-1] == end and steps.max() <= 3600.0 and steps.min() > 0
    # at the table's epochs it is the table's distance
    daily = np.asarray(sky.station_moon_distance_m) / 1e3
    at = {t: d for t, d in zip(times, km)}
    np.testing.assert_allclose([at[start + timedelta(days=i)] for i in range(len(sky))], daily, rtol=1e-9)
    # every perilune pass in the span is drawn near its true radius; the daily samples miss them
    o = sky.orbit
    rp, period = o.perilune_radius_m / 1e3, timedelta(days=o.period_days)
    passes = [o.perilune_epoch + k * period for k in range(1, 4)]
    assert all(start < p < end for p in passes)
    for p in passes:
        near = [d for t, d in zip(times, km) if abs((t - p).total_seconds()) < 6 * 3600]
        assert min(near) < 1.05 * rp, (p, min(near))
    assert sorted(daily)[1] > 2 * rp   # only the first epoch (a perilune) is near it in the daily table


def test_the_plot_draws_the_curve_and_marks_the_epochs(sky):
    from allo_usd.sky.report import distance_curve, sky_figure

    times, km = distance_curve(sky)
    lines = sky_figure(sky).axes[0].get_lines()
    drawn = [ln for ln in lines if len(ln.get_xdata()) == len(times)]
    assert len(drawn) == 1 and np.array_equal(drawn[0].get_ydata(), km) and drawn[0].get_linestyle() == "-"
    marks = [ln for ln in lines if len(ln.get_xdata()) == len(sky) and ln.get_marker() == "."]
    assert len(marks) == 1 and marks[0].get_linestyle() == "None"
    np.testing.assert_array_equal(marks[0].get_ydata(), np.asarray(sky.station_moon_distance_m) / 1e3)


# ------------------------------------------------------------------ author --out says layers

def test_author_writes_layers_to_out_layers_by_default():
    from allo_usd import cli

    assert inspect.signature(cli.author).parameters["out"].default.default == Path("out/layers")
