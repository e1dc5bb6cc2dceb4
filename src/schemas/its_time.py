"""ETSI ``TimestampIts``: TAI milliseconds since 2004-01-01T00:00:00.000 UTC (ETSI TS 102 894-2,
the CDD), to and from v2i's Unix nanoseconds (which, like UTC, do not count leap seconds).

TimestampIts = (Unix ms - Unix ms of 2004-01-01) + 1000 * (leap seconds inserted since 2004).
The CDD's own example: 2007-01-01T00:00:00 UTC is 94 694 401 000 (one leap second, 2005-12-31).

``LEAP_SECONDS``: the leap seconds inserted since 2004, from the IERS Bulletin C announcements
(IERS Earth Orientation Centre, https://hpiers.obspm.fr/iers/bul/bulc/Leap_Second.dat; TAI - UTC
32 s on 2004-01-01, 37 s since 2017-01-01). Bulletin C 70 (2025) announced none for 2025/2026: a
new one must be added here when announced.
"""

from __future__ import annotations

import bisect
import datetime as _dt

ITS_EPOCH_UNIX_MS = 1_072_915_200_000  # 2004-01-01T00:00:00Z in Unix ms


def _unix_ms(day: str) -> int:
    return int(_dt.datetime.fromisoformat(day).replace(tzinfo=_dt.timezone.utc).timestamp()) * 1000


# UTC days at whose end (23:59:60) a leap second was inserted since 2004 (IERS Bulletin C)
LEAP_SECOND_DAYS = ("2005-12-31", "2008-12-31", "2012-06-30", "2015-06-30", "2016-12-31")
# Unix ms from which each is counted (the next midnight)
_AFTER_UNIX_MS = tuple(_unix_ms(d) + 86_400_000 for d in LEAP_SECOND_DAYS)
# the same instants in TimestampIts (the i-th counts i seconds)
_AFTER_ITS_MS = tuple(t - ITS_EPOCH_UNIX_MS + 1000 * (i + 1) for i, t in enumerate(_AFTER_UNIX_MS))


def leap_seconds_at_unix_ms(unix_ms: int) -> int:
    """Leap seconds inserted between 2004-01-01 and a Unix time (ms)."""
    return bisect.bisect_right(_AFTER_UNIX_MS, unix_ms)


def its_ms(unix_ns: int) -> int:
    """TimestampIts (TAI ms since 2004) of a Unix time in ns, rounded to the ms."""
    unix_ms = (int(unix_ns) + 500_000) // 1_000_000
    return unix_ms - ITS_EPOCH_UNIX_MS + 1000 * leap_seconds_at_unix_ms(unix_ms)


def unix_ns(its: int) -> int:
    """Unix time in ns of a TimestampIts (the inverse of ``its_ms``; a time inside an inserted leap
    second maps onto the last Unix second before it)."""
    # leap seconds already counted at this TAI time: thresholds one second early take the leap second itself
    n = bisect.bisect_right(_AFTER_ITS_MS, int(its))
    inside = n < len(_AFTER_ITS_MS) and int(its) >= _AFTER_ITS_MS[n] - 1000
    unix_ms = int(its) + ITS_EPOCH_UNIX_MS - 1000 * n
    if inside:  # 23:59:60.xxx: the Unix clock repeats 23:59:59.xxx
        unix_ms -= 1000
    return unix_ms * 1_000_000
