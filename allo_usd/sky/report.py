"""A year's sky at a glance: CSV table and a multi-panel PNG, both written atomically.

``write_sky_report(sky, csv_path, png_path)`` is what ``allo-usd sky`` calls. Matplotlib is
driven through its object API on an Agg canvas, so the global backend is left alone.

The table has one row per epoch of the Sky (a render day). The distance panel does not join those
rows: the orbit's 6.56-day period is close to a whole number of days and a perilune pass lasts
hours, so daily samples alias it into a slow false wave that misses perilune. It draws
``distance_curve`` instead, the same orbit model sampled every DISTANCE_STEP_S, and marks the epochs.
"""

from __future__ import annotations

import csv
import math
import os
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

from allo_usd.core.errors import SkyInputError
from allo_usd.core.files import atomic_path
from allo_usd.core.timefmt import format_utc, parse_utc
from allo_usd.sky.model import BODIES, Sky
from allo_usd.core import fixedmath as fm

CSV_COLUMNS = (
    "date",
    "station_moon_distance_km",
    "sun_irradiance_w_m2",
    "lit_fraction",
    "effective_irradiance_w_m2",
    "eclipse_state",
    "eclipse_body",
    "sun_angular_diameter_deg",
    "earth_angular_diameter_deg",
    "moon_angular_diameter_deg",
)


DISTANCE_STEP_S = 900.0   # the distance panel's sampling: 15 min, about 630 samples per orbit


def distance_curve(sky: Sky, step_s: float = DISTANCE_STEP_S) -> tuple[list[datetime], np.ndarray]:
    """(UTC times, station-Moon distance in km) from the earliest to the latest epoch of `sky`, every
    `step_s` seconds and at the latest epoch: what the plot's distance panel draws as its line. The distance is
    the orbit model's (allo_usd.sky.orbit: the ellipse's radius, which the Earth-Moon frame's turning
    does not change), so at the sky's own epochs it is the table's `station_moon_distance_km`."""
    if not (math.isfinite(step_s) and step_s > 0):
        raise SkyInputError(f"step_s must be a positive number of seconds, got {step_s!r}")
    epochs = [parse_utc(e, "epoch") for e in sky.epochs]
    start, end = min(epochs), max(epochs)
    span = (end - start).total_seconds()
    offsets = np.arange(0.0, span, step_s) if span > 0 else np.zeros(0)
    offsets = np.append(offsets, span)
    since = (start - sky.orbit.perilune_epoch).total_seconds() + offsets
    position, _ = sky.orbit.rotating_state(since)
    times = [start + timedelta(seconds=float(o)) for o in offsets]
    return times, fm.norm(position, axis=1) / 1e3


def _rows(sky: Sky) -> list[list[str]]:
    rows = []
    for i, epoch in enumerate(sky.epochs):
        diam = {b: math.degrees(2.0 * float(sky.angular_radius_rad[b][i])) for b in BODIES}
        irr = float(sky.sun_irradiance_w_m2[i])
        lit = float(sky.lit_fraction[i])
        rows.append([
            epoch,
            f"{float(sky.station_moon_distance_m[i]) / 1e3:.3f}",
            f"{irr:.3f}",
            f"{lit:.6f}",
            f"{irr * lit:.3f}",
            str(sky.eclipse_state[i]),
            str(sky.eclipse_body[i]),
            f"{diam['sun']:.6f}",
            f"{diam['earth']:.6f}",
            f"{diam['moon']:.6f}",
        ])
    return rows


def write_sky_csv(sky: Sky, csv_path: str | os.PathLike) -> Path:
    path = Path(csv_path)
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(CSV_COLUMNS)
        writer.writerows(_rows(sky))
    return path


def write_sky_png(sky: Sky, png_path: str | os.PathLike, dpi: int = 110) -> Path:
    path = Path(png_path)
    with atomic_path(path) as tmp:
        sky_figure(sky).savefig(tmp, format="png", dpi=dpi)
    return path


def sky_figure(sky: Sky):
    """The plot's matplotlib Figure (on an Agg canvas): distance, irradiance, lit fraction, sizes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    dates = [parse_utc(e, "epoch") for e in sky.epochs]
    eclipsed = np.asarray(sky.eclipse_state) != "lit"

    fig = Figure(figsize=(11, 10), constrained_layout=True)
    FigureCanvasAgg(fig)
    axes = fig.subplots(4, 1, sharex=True)
    o = sky.orbit
    fig.suptitle(
        f"Sky at the station, {sky.epochs[0][:10]} .. {sky.epochs[-1][:10]} ({len(sky)} epochs; "
        f"NRHO approx, perilune {format_utc(o.perilune_epoch)}; DE421 {sky.positions})"
    )

    ax = axes[0]
    times, km = distance_curve(sky)
    ax.plot(times, km, "-", lw=0.5, color="C0", label=f"orbit, every {DISTANCE_STEP_S / 60:g} min")
    ax.plot(dates, np.asarray(sky.station_moon_distance_m) / 1e3, ".", ms=4, color="C1",
            label="table epochs (render days, 00:00 UTC)")
    ax.axhline(o.perilune_radius_m / 1e3, color="0.6", lw=0.8, ls="--")
    ax.axhline(o.apolune_radius_m / 1e3, color="0.6", lw=0.8, ls="--")
    ax.set_ylabel("station-Moon\ndistance (km)")
    ax.legend(loc="lower right", fontsize=8)

    ax = axes[1]
    irr = np.asarray(sky.sun_irradiance_w_m2)
    ax.plot(dates, irr, lw=1.0, label="unocculted 1361 (1 AU/d)^2")
    if eclipsed.any():   # drawn where the light is: the effective irradiance, joined to the unocculted
        idx = np.flatnonzero(eclipsed)
        effective = irr[idx] * np.asarray(sky.lit_fraction)[idx]
        ax.vlines([dates[i] for i in idx], effective, irr[idx], colors="r", lw=0.6, ls=":")
        ax.plot([dates[i] for i in idx], effective, "rx", ms=6,
                label="in shadow: effective = unocculted x lit fraction")
        for i, e in zip(idx, effective):
            ax.annotate(f"{e:.0f}", (dates[i], e), fontsize=7, color="r", xytext=(4, 2), textcoords="offset points")
    ax.set_ylabel("Sun irradiance\n(W/m^2)")
    ax.legend(loc="center left", fontsize=8)   # clear of an in-shadow marker, which may sit at 0

    ax = axes[2]
    ax.plot(dates, sky.lit_fraction, ".", ms=3)
    for i in np.flatnonzero(eclipsed):
        ax.annotate(f"{sky.eclipse_state[i]} ({sky.eclipse_body[i]})", (dates[i], float(sky.lit_fraction[i])),
                    fontsize=7, rotation=90, va="bottom", ha="center", xytext=(0, 4), textcoords="offset points")
    ax.set_ylim(-0.05, 1.35)
    ax.set_ylabel("lit fraction")
    ax.set_title(f"{int(eclipsed.sum())} of {len(sky)} epochs in shadow", fontsize=9)

    ax = axes[3]
    for b in BODIES:
        ax.semilogy(dates, np.degrees(2.0 * np.asarray(sky.angular_radius_rad[b])), lw=1.0, label=b)
    ax.set_ylabel("angular diameter\n(deg)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("date (UTC)")
    return fig


def write_sky_report(sky: Sky, csv_path: str | os.PathLike, png_path: str | os.PathLike) -> tuple[Path, Path]:
    """Write the CSV table and the PNG overview of ``sky``; returns both paths."""
    if not isinstance(sky, Sky):
        raise SkyInputError(f"write_sky_report needs a Sky from compute_sky, got {type(sky).__name__}")
    return write_sky_csv(sky, csv_path), write_sky_png(sky, png_path)
