"""GPS time to UTC: the GPS week and time of week of a GNSS receiver as UNIX seconds.

GPS time counts SI seconds from the GPS epoch, 1980-01-06 00:00:00 UTC (UNIX 315 964 800 s), without
leap seconds; receivers and autopilot logs give it as a week number since that epoch and the milliseconds
into the week (the week starting at Sunday 00:00:00 GPS time). UTC has been held behind GPS time by
the leap seconds inserted since 1980, so

    UTC = GPS - (GPS - UTC offset at that instant).

The offset table (``LEAP_SECONDS``) lists the dates at which the offset stepped up by one second,
as announced in IERS Bulletin C (https://www.iers.org/IERS/EN/Publications/Bulletins/bulletins.html;
history in ``Leap_Second.dat`` of the IERS Earth Orientation Centre) and broadcast in the GPS navigation
message as Delta t_LS (IS-GPS-200, section 20.3.3.5.2.4). The last step is 2017-01-01, after which
GPS - UTC = 18 s; a leap second announced later must be added to the table.

A leap second is inserted at the end of the UTC day before each listed date (23:59:60). UNIX time has
no such second: GPS instants inside an inserted second map onto the first second of the new day.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

__all__ = ["GPS_EPOCH_UNIX", "LEAP_SECONDS", "SECONDS_PER_WEEK", "gps_to_unix", "leap_seconds"]

#: UNIX time (s) of the GPS epoch, 1980-01-06 00:00:00 UTC.
GPS_EPOCH_UNIX = 315_964_800.0
SECONDS_PER_WEEK = 604_800.0

#: (first UTC date with the new offset, GPS - UTC in seconds from that date on); IERS Bulletin C.
LEAP_SECONDS = (
    ("1981-07-01", 1),
    ("1982-07-01", 2),
    ("1983-07-01", 3),
    ("1985-07-01", 4),
    ("1988-01-01", 5),
    ("1990-01-01", 6),
    ("1991-01-01", 7),
    ("1992-07-01", 8),
    ("1993-07-01", 9),
    ("1994-07-01", 10),
    ("1996-01-01", 11),
    ("1997-07-01", 12),
    ("1999-01-01", 13),
    ("2006-01-01", 14),
    ("2009-01-01", 15),
    ("2012-07-01", 16),
    ("2015-07-01", 17),
    ("2017-01-01", 18),
)


def _steps_gps_seconds() -> tuple[np.ndarray, np.ndarray]:
    """The GPS seconds (since the GPS epoch) at which each offset of ``LEAP_SECONDS`` takes effect, and
    the offsets. The step to ``n`` s happens when UTC reaches midnight of its date, i.e. at GPS time
    ``UTC midnight + n``."""
    dates = np.array([datetime.fromisoformat(d).replace(tzinfo=UTC).timestamp() for d, _ in LEAP_SECONDS])
    offsets = np.array([n for _, n in LEAP_SECONDS], float)
    return dates - GPS_EPOCH_UNIX + offsets, offsets


_STEPS_GPS_S, _OFFSETS_S = _steps_gps_seconds()


def leap_seconds(gps_seconds) -> np.ndarray:
    """GPS - UTC offset (s) at GPS times ``gps_seconds`` (seconds since the GPS epoch, any shape).

    0 before 1981-07-01, 18 since 2017-01-01. Returns float seconds of the same shape.
    """
    g = np.asarray(gps_seconds, float)
    idx = np.searchsorted(_STEPS_GPS_S, g, side="right")
    return np.concatenate(([0.0], _OFFSETS_S))[idx]


def gps_to_unix(week, ms) -> np.ndarray:
    """UNIX seconds (UTC) of GPS week numbers ``week`` and milliseconds of week ``ms`` (broadcast shapes).

    ``week`` is the full week count since 1980-01-06 (no 1024-week roll-over), as ArduPilot logs it.
    The leap seconds of each instant's own date are removed (see ``leap_seconds``).
    """
    gps_s = np.asarray(week, float) * SECONDS_PER_WEEK + np.asarray(ms, float) / 1000.0
    return GPS_EPOCH_UNIX + gps_s - leap_seconds(gps_s)
