"""The date range DE421 covers, as constants: plan validation needs it without opening the
ephemeris (tests/test_ephemeris_range.py checks them against skyfield-data's de421.bsp)."""

from __future__ import annotations

# Julian dates (TDB) of the common coverage of the file's Sun, Earth and Moon segments.
DE421_START_TDB_JD = 2414864.5  # 1899-07-29T00:00 TDB
DE421_END_TDB_JD = 2471184.5    # 2053-10-09T00:00 TDB

# The same instants in UTC (skyfield's builtin timescale), as ISO strings.
DE421_START_UTC = "1899-07-28T23:59:18Z"
DE421_END_UTC = "2053-10-08T23:58:51Z"
