"""The date range DE421 covers, as constants: plan validation needs it without opening the
ephemeris (tests/plan/test_light_imports.py checks them against skyfield-data's de421.bsp)."""

from __future__ import annotations

# Julian dates (TDB) of the common coverage of the file's Sun, Earth and Moon segments.
DE421_START_TDB_JD = 2414864.5  # 1899-07-29T00:00 TDB
DE421_END_TDB_JD = 2471184.5    # 2053-10-09T00:00 TDB

# The same instants in UTC (skyfield's builtin timescale), as recorded times (allo_usd.core.timefmt):
# the first and the last whole microsecond inside the range (1899-07-28T23:59:17.8167249 and
# 2053-10-08T23:58:50.8176705 UTC, rounded inwards), so an error that prints them prints instants
# the range check accepts (a whole-second "23:58:51Z" would lie 0.18 s past the end).
DE421_START_UTC = "1899-07-28T23:59:17.816725Z"
DE421_END_UTC = "2053-10-08T23:58:50.81767Z"
