"""A fixed place and start time for a log without GNSS: ``--site LAT,LON[,ALT]`` and ``--date``.

A bench, indoor or tethered log has a magnetometer and often an attitude, but no GNSS position or time: its
reference field is the IGRF field at a place and date the user knows. A reader that finds no GNSS returns its
epochs with ``time`` in seconds since boot (``provenance["time_base"] == "boot"``) and no ``lat``/``lon``
columns; ``place_at_site`` then sets the log at the given site (every epoch at one place) and its clock at the
given start (the UTC at which its clock read zero), and records both in the provenance as given, not measured
(``provenance["site"]``, which ``DriveLog.site`` and the calibration file carry on).

IGRF changes by a few nT a year (secular variation of up to about 100 nT/yr, https://www.ncei.noaa.gov/products/
world-magnetic-model): a date right to the month is enough, a time of day only orders the epochs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np
import pandas as pd

from ..conventions import ALT, LAT, LON, REF, TIME
from ..errors import InputError

__all__ = ["Site", "parse_site", "parse_date", "place_at_site", "timed_since_boot", "BOOT", "UNIX_1990"]

#: ``provenance["time_base"]`` of a log whose time is seconds since the vehicle booted, not UTC.
BOOT = "boot"
#: 1990-01-01T00:00Z in UNIX s: a time column before it cannot be UTC (the canonical table's lower bound).
UNIX_1990 = 631_152_000.0


@dataclass(frozen=True)
class Site:
    """Where and when a log without GNSS was recorded, as the user gave it.

    Attributes
    ----------
    lat, lon : float or None
        Degrees (WGS-84); None when only the date was given.
    alt : float
        Metres above the ellipsoid (0 when not given; 1 km moves the field by about 0.05 %).
    start : float or None
        UTC at which the log's clock read zero (its boot, for an autopilot log), UNIX s; None when only the
        place was given. A log's epoch at ``t`` s since boot is at ``start + t`` (so a log read in chunks is
        placed alike).
    """

    lat: float | None = None
    lon: float | None = None
    alt: float = 0.0
    start: float | None = None

    @property
    def has_place(self) -> bool:
        """Whether a latitude and longitude were given."""
        return self.lat is not None and self.lon is not None

    def as_dict(self) -> dict:
        """The JSON-able record of what was given (``given`` True: not measured)."""
        out: dict = {"given": True}
        if self.has_place:
            out |= {"lat": self.lat, "lon": self.lon, "alt": self.alt}
        if self.start is not None:
            out["start_utc"] = datetime.fromtimestamp(self.start, UTC).isoformat().replace("+00:00", "Z")
        return out


def parse_site(text: str | None, date: str | None = None) -> Site | None:
    """The ``Site`` of ``--site LAT,LON[,ALT]`` (degrees, degrees, metres) and ``--date`` (``parse_date``);
    None when neither is given. InputError (naming the option) for a value that is not one."""
    if text is None and date is None:
        return None
    start = parse_date(date) if date is not None else None
    if text is None:
        return Site(start=start)
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"--site {text!r}: give LAT,LON[,ALT] in degrees and metres (e.g. 52.1,-1.3,95)") from None
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise InputError(f"--site {text!r}: give LAT,LON[,ALT] in degrees and metres (e.g. 52.1,-1.3,95)")
    lat, lon, alt = (*values, 0.0)[:3]
    if not (-90 <= lat <= 90 and -180 <= lon <= 360 and -1000 <= alt <= 100_000):
        raise InputError(f"--site {text!r}: latitude in [-90, 90], longitude in [-180, 360], altitude in m")
    return Site(lat=lat, lon=lon, alt=alt, start=start)


def parse_date(text: str) -> float:
    """UNIX s of ``YYYY-MM-DD`` or ``YYYY-MM-DDTHH:MM[:SS]`` (UTC, or with an offset such as ``+02:00``);
    InputError naming ``--date`` for anything else or a year outside 1990 to 2100."""
    try:
        when = datetime.fromisoformat(str(text).strip())
    except ValueError:
        raise InputError(f"--date {text!r}: give YYYY-MM-DD or YYYY-MM-DDTHH:MM (UTC)") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    if not 1990 <= when.year < 2100:
        raise InputError(f"--date {text!r}: the year must lie in 1990 to 2099")
    return when.timestamp()


def timed_since_boot(table: pd.DataFrame, provenance: dict) -> bool:
    """Whether the table's time is not UTC: the reader says so (``time_base`` "boot"), or every time lies before
    1990 (a logger's seconds since boot)."""
    if provenance.get("time_base") == BOOT:
        return True
    t = pd.to_numeric(table[TIME], errors="coerce").to_numpy(dtype=float) if TIME in table else np.array([])
    return t.size > 0 and bool(np.nanmax(t, initial=-np.inf) < UNIX_1990)


def _no_position(table: pd.DataFrame) -> bool:
    """Whether the table has neither a reference field nor any latitude and longitude."""
    if all(c in table for c in REF):
        return False
    if LAT not in table or LON not in table:
        return True
    lat = pd.to_numeric(table[LAT], errors="coerce").to_numpy(dtype=float)
    return not np.isfinite(lat).any()


def place_at_site(table: pd.DataFrame, provenance: dict, site: Site | None, source: str) -> pd.DataFrame:
    """``table`` with its clock and place set from ``site`` where the log has none of its own (a log's own GNSS
    time and position are kept, and a note says the option was not used).

    Parameters
    ----------
    table : pandas.DataFrame
        A reader's canonical table; ``time`` in UNIX s, or in s since boot (``provenance["time_base"]`` "boot",
        or every time before 1990).
    provenance : dict
        The reader's provenance; gains ``site`` (what was given) and notes, and ``time_base`` when the clock is
        set. Changed in place.
    site : Site or None
        What the user gave.
    source : str
        The log, as messages name it.

    Returns
    -------
    pandas.DataFrame
        The table with ``time`` in UNIX s (``site.start`` plus the log's time since boot) and ``lat``,
        ``lon``, ``alt`` at the site on every epoch; a table that needs neither unchanged.

    Raises
    ------
    InputError
        A log timed since boot without ``--date``, or without a position or reference field and without
        ``--site``: one line naming the log and what to give.
    """
    boot, unplaced = timed_since_boot(table, provenance), _no_position(table)
    given = site or Site()
    notes = provenance.setdefault("notes", [])
    if boot and given.start is None:
        also = " and --site LAT,LON[,ALT] (no GNSS position either)" if unplaced and not given.has_place else ""
        raise InputError(
            "the log has no GNSS time (its clock counts from boot), which the reference field needs: give --date "
            f"YYYY-MM-DD[THH:MM], the UTC at its boot (the day is enough){also}",
            source,
        )
    if unplaced and not given.has_place:
        raise InputError(
            "the log has no GNSS position (nor a reference field): give --site LAT,LON[,ALT] where it was recorded",
            source,
        )
    if site is None:
        return table
    columns: dict = {}
    if given.start is not None:
        if boot:
            t = pd.to_numeric(table[TIME], errors="coerce").to_numpy(dtype=float)
            columns[TIME] = given.start + t
            provenance["time_base"] = f"given: --date {given.as_dict()['start_utc']} plus the log's time since boot"
            notes.append("UTC is the --date given (the log's clock at zero) plus the log's time, not measured")
        else:
            _unused(notes, "--date not used: the log's own time is UTC", source)
    if given.has_place and unplaced:
        n = len(table)
        columns |= {LAT: np.full(n, given.lat), LON: np.full(n, given.lon), ALT: np.full(n, given.alt)}
        notes.append(f"position: the --site given ({given.lat:g}, {given.lon:g}, {given.alt:g} m), not measured")
    elif given.has_place:
        _unused(notes, "--site not used: the log has its own GNSS position", source)
    if columns:
        provenance["site"] = given.as_dict()
    return table.assign(**columns) if columns else table


def _unused(notes: list, text: str, source: str) -> None:
    """An option given but not used, added to the reader's ``notes`` and said (``Note``): the log's own measurement
    is kept, which the user who gave the option may not expect."""
    import warnings

    from ..errors import Note

    notes.append(text)
    warnings.warn(Note(f"{source}: {text}"), stacklevel=3)
