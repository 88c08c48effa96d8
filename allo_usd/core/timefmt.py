"""Recorded times: the one formatter and the one parser of every UTC instant allo-usd writes or reads,
and how a duration the user gave (a time limit) is shown back (``seconds_text``).

Format (``format_utc``): ISO 8601 in UTC with a ``Z``, ``YYYY-MM-DDTHH:MM:SSZ`` when the instant
falls on a whole second (so layers of whole-second epochs keep their bytes), otherwise the
fraction's shortest exact digits, at most six: ``...T00:00:00.9Z``, ``...T00:00:00.123456Z``. A
Python datetime holds microseconds, and so does every recorded time: parsing the text back
(``parse_utc``) gives the same instant, to the microsecond. The sky layers' epochs, the perilune
epoch in layers, ``inspect`` and render JSON, and a tree's ``plan.toml`` all go through here.

Digits beyond the microsecond (``...00.123456789Z``) are dropped (truncated, not rounded): that is
what Python's ``datetime.fromisoformat``, ``tomllib`` and PyYAML all do with such a value, so a
plan's time means the same instant whether it is written as a TOML/YAML date-time or as a string.
The geometry, the layers and the record then all hold that truncated instant (a shift under 1 us,
under 2 mm along the orbit).
"""

from __future__ import annotations

from datetime import datetime, timezone

from allo_usd.core.errors import EpochError

EXAMPLE = "2030-01-01T00:00:00Z"


def format_utc(dt: datetime) -> str:
    """An aware datetime as the recorded text (see the module doc); naive datetimes are refused."""
    if not isinstance(dt, datetime) or dt.tzinfo is None or dt.tzinfo.utcoffset(dt) is None:
        raise EpochError(f"time {dt!r} is not a timezone-aware datetime; fix: give a UTC instant, e.g. {EXAMPLE}")
    dt = dt.astimezone(timezone.utc)
    text = f"{dt.year:04d}-{dt:%m-%dT%H:%M:%S}"   # strftime's %Y does not pad years before 1000
    if dt.microsecond:
        text += f".{dt.microsecond:06d}".rstrip("0")
    return text + "Z"


def parse_utc(text: str, what: str = "time") -> datetime:
    """Recorded (or plan) text as an aware UTC datetime: ISO 8601 with a ``Z`` or an offset. Naive
    text (no zone) is refused, never guessed; digits beyond the microsecond are truncated."""
    if not isinstance(text, str):
        raise EpochError(f"{what} {text!r} is not text; fix: write an ISO 8601 UTC instant, e.g. {EXAMPLE}")
    try:
        parsed = datetime.fromisoformat(text.strip())
    except ValueError:
        raise EpochError(f"{what} {text[:80]!r} is not an ISO 8601 date-time; fix: write e.g. {EXAMPLE}") from None
    if parsed.tzinfo is None or parsed.tzinfo.utcoffset(parsed) is None:
        raise EpochError(f"{what} {text[:80]!r} has no timezone; fix: write it in UTC with a Z, e.g. {EXAMPLE}")
    try:
        return parsed.astimezone(timezone.utc)
    except OverflowError:   # 9999-12-31T23:00-05:00 is past the calendar's end in UTC
        raise EpochError(f"{what} {text[:80]!r} is outside the calendar in UTC; fix: write a UTC instant, "
                         f"e.g. {EXAMPLE}") from None


def seconds_text(seconds: float) -> str:
    """A time limit as the user gave it, not rounded away: 0.5 -> "0.5 s", 600 -> "600 s", the default
    formula's 120.2304 -> "120.2 s" (to 0.1 s from 1 s up, 3 significant digits below)."""
    text = f"{seconds:.3g}" if seconds < 1 else f"{seconds:.1f}"
    if "." in text and "e" not in text:
        text = text.rstrip("0").rstrip(".")
    return f"{text} s"
