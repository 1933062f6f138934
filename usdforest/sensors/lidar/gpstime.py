"""GPS time of a UTC instant, as LAS 1.4 stores it (the Adjusted Standard GPS Time: seconds
since the GPS epoch 1980-01-06 00:00:00 UTC, counting leap seconds, minus 10^9)."""

from __future__ import annotations

from datetime import UTC, datetime

from usdforest.errors import UsdForestError

GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
ADJUSTMENT = 1e9  # LAS 1.4: "standard GPS Time (satellite GPS Time) minus 1 x 10^9"
# the UTC dates from which GPS time runs 1, 2, ... 18 s ahead of UTC (IERS Bulletin C); none
# has been announced after 2017
LEAP_SECONDS = (
    "1981-07-01", "1982-07-01", "1983-07-01", "1985-07-01", "1988-01-01", "1990-01-01",
    "1991-01-01", "1992-07-01", "1993-07-01", "1994-07-01", "1996-01-01", "1997-07-01",
    "1999-01-01", "2006-01-01", "2009-01-01", "2012-07-01", "2015-07-01", "2017-01-01",
)  # fmt: skip


def parse_utc(text: str, where: str = "start_time") -> datetime:
    """An ISO 8601 time with its zone (``2026-06-21T10:00:00Z``), or a one-line error."""
    try:
        t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise UsdForestError(
            f"{where}: {text!r} is not an ISO 8601 time (e.g. 2026-06-21T10:00:00Z)"
        ) from None
    if t.tzinfo is None:
        raise UsdForestError(f"{where}: {text!r} has no time zone (add Z for UTC)")
    t = t.astimezone(UTC)
    if t < GPS_EPOCH:
        raise UsdForestError(f"{where}: {text!r} is before the GPS epoch (1980-01-06)")
    return t


def gps_seconds(t: datetime) -> float:
    """Seconds of standard GPS time at UTC instant ``t`` (leap seconds counted)."""
    leaps = sum(t >= datetime.fromisoformat(d).replace(tzinfo=UTC) for d in LEAP_SECONDS)
    return (t - GPS_EPOCH).total_seconds() + leaps
