"""Eclipse events over a span: a scan, then a vectorised bisection of every contact."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import numpy as np

from allo_usd.core.errors import SkyInputError
from allo_usd.sky.eclipse import ECLIPSE_STATES, LIT, SHADOW_BODIES, UMBRA
from allo_usd.sky.ephemeris import as_utc, check_range, finite_number, iso_utc, time_from_start
from allo_usd.sky.model import sky_geometry
from allo_usd.sky.orbit import Orbit


# ---------------------------------------------------------------------------------------------
# Eclipse search over a span (scan + vectorised bisection of every contact)


@dataclass(frozen=True)
class EclipseEvent:
    """One continuous shadow pass by one body (penumbral contact to penumbral contact)."""

    body: str
    start: str
    end: str
    duration_s: float
    umbra_s: float
    min_lit_fraction: float
    deepest_state: str
    truncated: bool  # started before or ended after the searched span


def _span_geometry(start: datetime, offsets_s: np.ndarray, orbit: Orbit, chunk: int = 100_000) -> dict[str, np.ndarray]:
    keys = ("eclipse_code.moon", "eclipse_code.earth", "lit_fraction.moon", "lit_fraction.earth", "both_occulting")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for lo in range(0, offsets_s.size, chunk):
        off = offsets_s[lo:lo + chunk]
        t = time_from_start(start, off)
        check_range(t, None)
        g = sky_geometry(t, orbit, body_light=False)
        for k in keys:
            parts[k].append(g[k])
    return {k: np.concatenate(v) for k, v in parts.items()}


def _contact_times(start, offsets, s_idx, e_idx, predicate, orbit, tol_s):
    """Refined start and end times of runs [s_idx, e_idx) of sampled offsets where `predicate` holds;
    a run touching either end of the sampled window keeps that end's sample time."""
    has_lo = s_idx > 0
    has_hi = e_idx < offsets.size
    t_start = offsets[s_idx].astype(np.float64)
    t_end = offsets[np.minimum(e_idx, offsets.size - 1)].astype(np.float64)
    t_start[has_lo] = _refine(start, offsets[s_idx[has_lo] - 1], offsets[s_idx[has_lo]], predicate, orbit, tol_s)
    t_end[has_hi] = _refine(start, offsets[e_idx[has_hi] - 1], offsets[e_idx[has_hi]], predicate, orbit, tol_s)
    return t_start, t_end


def _refine(start: datetime, lo: np.ndarray, hi: np.ndarray, pred, orbit: Orbit, tol_s: float) -> np.ndarray:
    """Bisect all brackets [lo, hi] (pred(lo) != pred(hi)) at once; returns crossing offsets."""
    if lo.size == 0:
        return lo.copy()
    lo, hi = lo.astype(np.float64).copy(), hi.astype(np.float64).copy()
    g_lo = pred(_span_geometry(start, lo, orbit))
    while np.max(hi - lo) > tol_s:
        mid = 0.5 * (lo + hi)
        g_mid = pred(_span_geometry(start, mid, orbit))
        same = g_mid == g_lo
        lo = np.where(same, mid, lo)
        hi = np.where(same, hi, mid)
    return 0.5 * (lo + hi)


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start/stop (exclusive) indices of True runs."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def eclipse_events(
    start: datetime, stop: datetime, orbit: Orbit = Orbit(), step_s: float = 60.0, tol_s: float = 0.5,
) -> tuple[list[EclipseEvent], dict]:
    """All Moon- and Earth-shadow passes in [start, stop): scan every ``step_s`` then bisect
    each contact to ``tol_s``. Passes shorter than ``step_s`` can be missed.

    Returns (events sorted by start, info dict with the scan size and how many samples had
    both bodies over the Sun).
    """
    start = as_utc(start, "start")
    stop = as_utc(stop, "stop")
    step_s = finite_number("step_s", step_s)
    tol_s = finite_number("tol_s", tol_s)
    if step_s <= 0 or tol_s <= 0:
        raise SkyInputError("step_s and tol_s must be positive")
    span = (stop - start).total_seconds()
    if span <= 0:
        raise SkyInputError(f"stop {stop} must be after start {start}")
    offsets = np.arange(0.0, span, step_s)
    g = _span_geometry(start, offsets, orbit)
    events: list[EclipseEvent] = []
    for bi, body in enumerate(SHADOW_BODIES):
        code = g[f"eclipse_code.{body}"]
        lit = g[f"lit_fraction.{body}"]
        s_idx, e_idx = _runs(code != LIT)
        if s_idx.size == 0:
            continue
        key = f"eclipse_code.{body}"

        def shadowed(gg, key=key):
            return gg[key] != LIT

        def umbral(gg, key=key):
            return gg[key] == UMBRA

        t_start, t_end = _contact_times(start, offsets, s_idx, e_idx, shadowed, orbit, tol_s)
        # Umbra contacts inside each pass.
        u_s, u_e = _runs(code == UMBRA)
        tu_s, tu_e = _contact_times(start, offsets, u_s, u_e, umbral, orbit, tol_s)
        for k in range(s_idx.size):
            inside = (u_s >= s_idx[k]) & (u_e <= e_idx[k])
            umbra_s = float(np.sum(tu_e[inside] - tu_s[inside]))
            seg = slice(s_idx[k], e_idx[k])
            deepest = int(np.max(code[seg]))
            events.append(EclipseEvent(
                body=body,
                start=iso_utc((start + timedelta(seconds=float(t_start[k]))).replace(microsecond=0)),
                end=iso_utc((start + timedelta(seconds=float(t_end[k]))).replace(microsecond=0)),
                duration_s=float(t_end[k] - t_start[k]),
                umbra_s=umbra_s,
                min_lit_fraction=float(np.min(lit[seg])),
                deepest_state=ECLIPSE_STATES[deepest],
                truncated=bool(s_idx[k] == 0 or e_idx[k] >= offsets.size),
            ))
    events.sort(key=lambda ev: ev.start)
    info = {"samples": int(offsets.size), "step_s": step_s, "tol_s": tol_s,
            "both_occulting_samples": int(np.count_nonzero(g["both_occulting"]))}
    return events, info
