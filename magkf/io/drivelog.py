"""Reading the canonical drive-log CSV into a validated, time-indexed structure.

See the data contract: ``time`` and ``mag_x, mag_y, mag_z`` are required; ``roll, pitch, yaw``
(degrees) give the attitude; ``lat, lon`` (``alt`` optional) or ``ref_n, ref_e, ref_d`` give the
reference field; ``dop`` (else ``pdop``, else ``hdop``) feeds the DOP gate; every other numeric column
is an auxiliary channel. An empty cell is a missing value: it is kept as NaN, never dropped.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..conventions import (
    ALT,
    ATTITUDE,
    CORE_COLUMNS,
    DOP,
    HDOP,
    LAT,
    LON,
    MAG,
    NT_PER_UNIT,
    PDOP,
    PITCH,
    REF,
    ROLL,
    TIME,
    YAW,
    ColumnStack,
    likely_unit,
    to_nanotesla,
)
from ..errors import InputError
from ..status import select_dop
from .readers import LogReader
from .site import BOOT, place_at_site, timed_since_boot
from .tables import PARQUET_SUFFIXES, file_row, numeric_column, read_csv, require_complete, table_rows

__all__ = [
    "MIN_EPOCHS",
    "read_sample",
    "UnitWarning",
    "DriveLog",
    "TIME_RANGE_S",
    "ALT_RANGE_M",
    "MAG_MAX_NT",
    "DOP_MAX",
    "REF_MIN_NT",
    "RANGES",
    "MAX_GAP_S",
    "TimeBaseWarning",
    "check_time_base",
    "from_table",
    "whole_log_checks",
    "read_drive_log",
    "read_samples",
    "write_drive_log",
    "write_frames",
    "FrameWriter",
    "table_to_write",
]

MIN_EPOCHS = 2


def read_sample(sample, names, time=None) -> dict[str, float]:
    """The values of ``names`` in one sample, as floats (NaN where absent, empty, None or not a number).

    ``sample`` is a mapping of column names to values: a dict, or a pandas row (``Series``). ``time`` (UNIX
    s) is taken from the argument if given, else from the sample's ``time`` entry, else from a pandas
    row's name (``DataFrame.iterrows`` and ``DriveLog.table`` rows carry the time as their index).
    Raises InputError for a sample that is not such a mapping (a bare array names no columns), and for a
    number beyond the range a log may hold (``RANGES``; time: ``TIME_RANGE_S``).
    """
    out = dict(zip((*names, TIME), _sample_values(sample, names, time)))
    for name, (lo, hi, _) in ((TIME, (*TIME_RANGE_S, "s")), *RANGES.items()):  # a log would be refused
        v = out.get(name, math.nan)
        if math.isfinite(v) and not lo <= v <= hi:
            raise InputError(f"value {v!r} outside [{lo:g}, {hi:g}] (UNIX s, degrees, m, nT)", column=name)
    return out


def read_samples(samples, names) -> np.ndarray:
    """The values of ``names`` and the time in consecutive samples, as ``read_sample`` reads each: (k, len(names)
    + 1) floats, the time last (UNIX s).

    Raises InputError as ``read_sample`` does, naming the sample (counted from 0): one that is not a mapping,
    else the first value beyond its range.
    """
    rows = []
    for i, sample in enumerate(samples):
        try:
            rows.append(_sample_values(sample, names, None))
        except InputError as exc:
            raise InputError(f"sample {i}: {exc.message}") from None
    values = np.array(rows, float).reshape(-1, len(names) + 1)
    checked = [(len(names), TIME, (*TIME_RANGE_S, "s"))]
    checked += [(i, name, RANGES[name]) for i, name in enumerate(names) if name in RANGES]
    index = [i for i, _, _ in checked]
    lo, hi = (np.array([r[j] for _, _, r in checked]) for j in (0, 1))
    checked_values = values[:, index]
    with np.errstate(invalid="ignore"):
        bad = np.isfinite(checked_values) & ((checked_values < lo) | (checked_values > hi))
    if bad.any():
        row, col = (int(a[0]) for a in np.nonzero(bad))
        _, name, (low, high, _) = checked[col]
        v = float(values[row, index[col]])
        raise InputError(f"sample {row}: value {v!r} outside [{low:g}, {high:g}] (UNIX s, degrees, m, nT)", column=name)
    return values


def _sample_values(sample, names, time) -> list[float]:
    """The floats of ``names`` in ``sample`` and its time last (see ``read_sample``)."""
    if not hasattr(sample, "keys"):
        raise InputError(
            f"a sample maps column names to values (a dict or a pandas row), not a {type(sample).__name__}"
        )
    out = []
    for name in names:
        try:
            out.append(float(sample[name]))
        except (KeyError, IndexError, TypeError, ValueError, OverflowError):  # OverflowError: 10**400
            out.append(math.nan)
    if time is None:
        try:
            time = float(sample[TIME])
        except (KeyError, IndexError, TypeError, ValueError, OverflowError):
            time = math.nan
        if not math.isfinite(time):
            time = getattr(sample, "name", None)
    try:
        out.append(float(time))
    except (TypeError, ValueError, OverflowError):
        out.append(math.nan)
    return out


class UnitWarning(UserWarning):
    """The magnetometer magnitudes look like another unit than the one given."""


@dataclass(frozen=True)
class DriveLog:
    """A drive log: the canonical table of a log's epochs, where it came from and how it was read.

    Build one with ``from_table`` (the epoch contract) or a reader (``read_drive_log``,
    ``magkf.io.readers.read_log``). Array properties have shape (N,) or (N, 3); missing values are NaN.

    Parameters
    ----------
    table : pandas.DataFrame
        Indexed by ``time`` (UNIX s) with the canonical columns, magnetic columns converted to nT.
    source : str, optional
        Names the file.
    provenance : dict, optional
        Where each column came from and what the reader converted or undid (JSON-ready; see
        ``magkf.io.readers``).
    """

    table: pd.DataFrame
    source: str = "log"
    provenance: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.table)

    @property
    def time(self) -> np.ndarray:
        """(N,) UNIX seconds."""
        return self.table.index.to_numpy(dtype=float)

    @property
    def mag(self) -> np.ndarray:
        """(N, 3) raw magnetometer, nT, sensor axes."""
        return self.table[list(MAG)].to_numpy(dtype=float)

    @property
    def has_attitude(self) -> bool:
        """True when the log has the attitude columns ``roll, pitch, yaw``."""
        return all(c in self.table for c in ATTITUDE)

    @property
    def attitude(self) -> np.ndarray:
        """(N, 3) ``roll, pitch, yaw`` in degrees (NaN throughout when the log has none)."""
        if not self.has_attitude:
            return np.full((len(self), 3), np.nan)
        return self.table[list(ATTITUDE)].to_numpy(dtype=float)

    @property
    def attitude_columns(self):
        """``attitude`` as the table's own columns read side by side (``conventions.ColumnStack``, not copied), or the
        same NaN array where the log has none. What holds it (a prepared log) sees the table's columns themselves: a
        table changed in place afterwards would change its attitude too (magkf changes no log's table)."""
        if not self.has_attitude:
            return self.attitude
        return ColumnStack(*(self.table[c].to_numpy(dtype=float) for c in ATTITUDE))

    @property
    def has_reference(self) -> bool:
        """True when the log supplies its own reference field ``ref_n, ref_e, ref_d``."""
        return all(c in self.table for c in REF)

    @property
    def has_position(self) -> bool:
        """True when the log has the position columns ``lat, lon``."""
        return LAT in self.table and LON in self.table

    def column(self, name: str, default: float = np.nan) -> np.ndarray:
        """(N,) values of a column, or ``default`` throughout when the log has no such column.

        Parameters
        ----------
        name : str
            The column.
        default : float, optional
            The value throughout when the log has no such column.

        Returns
        -------
        numpy.ndarray
            (N,) float values.
        """
        if name in self.table:
            return self.table[name].to_numpy(dtype=float)
        return np.full(len(self), default, dtype=float)

    @property
    def position(self) -> np.ndarray:
        """(N, 3) latitude (deg), longitude (deg), height (m, 0 when absent)."""
        return np.column_stack([self.column(LAT), self.column(LON), self.column(ALT, 0.0)])

    @property
    def dop(self) -> np.ndarray:
        """(N,) DOP for the gate (``select_dop``); NaN when none is logged."""
        dop = select_dop({c: self.table[c] for c in (DOP, PDOP, HDOP) if c in self.table})
        return np.full(len(self), np.nan) if dop is None else dop

    @property
    def magnetometer(self) -> dict | None:
        """Which of an autopilot log's magnetometers was read, or None for a log that holds one.

        The reader's ``provenance["magnetometer"]`` with the log's ``format``; None for a canonical CSV or
        Parquet file.
        """
        mag = self.provenance.get("magnetometer")
        return None if not isinstance(mag, dict) else {"format": self.provenance.get("format"), **mag}

    @property
    def site(self) -> dict | None:
        """The place and date the user gave for a log without GNSS (``provenance["site"]``: ``given`` True,
        ``lat, lon, alt`` and ``start_utc`` as given), or None for a log placed by its own GNSS."""
        site = self.provenance.get("site")
        return dict(site) if isinstance(site, dict) else None

    @property
    def auxiliary(self) -> list[str]:
        """Names of the auxiliary channels (every column without a fixed meaning)."""
        return [c for c in self.table.columns if c not in CORE_COLUMNS]

    def reference_ned(self, **kwargs) -> np.ndarray:
        """(N, 3) reference field in NED, nT: the log's ``ref_*`` columns, else IGRF at each epoch.

        Parameters
        ----------
        **kwargs
            Passed to ``magkf.reference.igrf_ned`` (``knot_spacing_m``) when IGRF is evaluated.

        Returns
        -------
        numpy.ndarray
            (N, 3) north, east, down, nT.
        """
        if self.has_reference:
            return self.table[list(REF)].to_numpy(dtype=float)
        return self.reference_track(**kwargs)[:]

    def reference_track(self, **kwargs):
        """The reference field of ``reference_ned``, made for the epochs asked when read: ``track[rows]`` (a slice
        or increasing positions) is ``reference_ned()[rows]``, bit for bit.

        Parameters
        ----------
        **kwargs
            Passed to ``magkf.reference.IgrfTrack`` (``knot_spacing_m``) when IGRF is evaluated.

        Returns
        -------
        numpy.ndarray or magkf.reference.IgrfTrack
            The log's ``ref_*`` columns (N, 3) NED nT as an array, else the IGRF field along the log's track (a few
            numbers a knot, not 24 bytes an epoch).
        """
        if self.has_reference:
            return self.reference_ned()
        from ..reference import IgrfTrack

        position = self.column(LAT), self.column(LON), self.column(ALT, 0.0)  # the columns, not a copy of them
        return IgrfTrack(self.time, *position, **kwargs)


#: The time base a log must have: UNIX seconds between these dates (1990-01-01 and 2100-01-01 UTC).
TIME_RANGE_S = (631_152_000.0, 4_102_444_800.0)
#: Heights a vehicle's log may hold, m above the ellipsoid (below: a unit or a sentinel value, not a place).
ALT_RANGE_M = (-1_000.0, 100_000.0)
#: Largest magnetometer or reference component, nT (0.01 T: far beyond any vehicle's field).
MAG_MAX_NT = 1e7
#: Epochs a log needs before its attitude is judged to look like radians.
RADIANS_MIN_EPOCHS = 100
#: Least magnitude of a ``ref_*`` reference field, nT.
REF_MIN_NT = 1_000.0
#: Largest dilution of precision a log may hold (receivers report 99.99 for no fix).
DOP_MAX = 1_000.0
#: The range (lowest, highest, unit) a log's column is held to, by ``from_table`` (the magnetometer's in the
#: unit given) and for one sample by ``read_sample``.
RANGES = {
    PITCH: (-90.0, 90.0, "degrees"),
    ROLL: (-180.0, 360.0, "degrees"),
    YAW: (-360.0, 360.0, "degrees"),
    LAT: (-90.0, 90.0, "degrees"),
    LON: (-180.0, 360.0, "degrees"),
    ALT: (*ALT_RANGE_M, "m"),
    **{c: (0.0, DOP_MAX, "") for c in (DOP, PDOP, HDOP)},
    **{c: (-MAG_MAX_NT, MAG_MAX_NT, "nT") for c in (*MAG, *REF)},
}
#: A jump of the clock longer than this (s) is reported.
MAX_GAP_S = 5.0


#: Finer units a time in UNIX seconds may have been given in: (how many make a second, a column map's name).
_FINER_UNITS = {"milliseconds": (1e3, "ms"), "microseconds": (1e6, "us"), "nanoseconds": (1e9, "ns")}


class TimeBaseWarning(UserWarning):
    """The log's clock has a gap longer than ``MAX_GAP_S``."""


def check_time_base(t, name: str, row_of=None, max_gap_s: float = MAX_GAP_S) -> None:
    """Raise InputError for a time that is not UNIX seconds UTC between 1990 and 2100 (time since boot,
    milliseconds, a GPS week...) or that does not strictly increase; warn (``TimeBaseWarning``) at the first
    gap longer than ``max_gap_s``. ``row_of(i)`` gives the file row of epoch ``i`` (default: CSV rows)."""
    row_of = row_of or file_row
    t = np.asarray(t, float)
    lo, hi = TIME_RANGE_S
    bad = np.flatnonzero((t < lo) | (t > hi))
    if bad.size:
        i = int(bad[0])
        scaled = next((unit for unit, (per, _) in _FINER_UNITS.items() if lo <= t[i] / per <= hi), None)
        if t[i] < 1e7:
            hint = (
                "it looks like time since boot or since the start: give --date YYYY-MM-DD[THH:MM], the UTC at its "
                "zero, or UTC times"
            )
        elif scaled is not None:
            short = _FINER_UNITS[scaled][1]
            hint = f'it looks like UNIX {scaled}: give seconds (a column map: [units] time = "{short}")'
        else:
            hint = "it is not UNIX seconds (UTC)"
        raise InputError(f"time {float(t[i])!r} s is outside 1990 to 2100: {hint}", name, row_of(i), TIME)
    step = np.diff(t)
    not_increasing = np.flatnonzero(step <= 0)
    if not_increasing.size:
        i = int(not_increasing[0]) + 1
        raise InputError(
            f"time not strictly increasing ({float(t[i])!r} after {float(t[i - 1])!r})", name, row_of(i), TIME
        )
    gaps = np.flatnonzero(step > max_gap_s)
    if gaps.size > step.size / 2:  # most intervals are gaps: the time's unit, not the log, is the likely fault
        median = float(np.median(step))
        warnings.warn(
            f"{name}: the epochs are {median:.3g} s apart (median; {gaps.size} of {step.size} intervals longer than "
            f"{max_gap_s:g} s), slower than a magnetometer logs: check the time's unit (read as milliseconds, they "
            f"would be {median / 1000:.3g} s apart)",
            TimeBaseWarning,
            stacklevel=3,
        )
    elif gaps.size:
        i = int(gaps[0]) + 1
        warnings.warn(
            f"{name}: the clock jumps by {step[i - 1]:.3g} s at row {row_of(i)} ({gaps.size} gap(s) longer "
            f"than {max_gap_s:g} s); the filter's random walk spans each gap",
            TimeBaseWarning,
            stacklevel=3,
        )


def from_table(
    table: pd.DataFrame,
    source: str = "log",
    mag_unit: str = "nT",
    provenance: dict | None = None,
    row_of=None,
    whole: bool = True,
    site=None,
) -> DriveLog:
    """Validate a table with the canonical columns (``time`` a column, UNIX s) and build a ``DriveLog``;
    the epoch contract every reader goes through. Magnetometer values in ``mag_unit`` become nT.

    Raises InputError (one line naming source, row and column) for a missing column, a cell that is not a
    number, a missing or non-increasing time or one outside 1990 to 2100, an angle or position out of range,
    too few epochs or an unknown unit. Warns (``UnitWarning``) when the magnitudes look like another unit and
    (``TimeBaseWarning``) at a long gap. ``row_of(i)`` gives the file row of epoch ``i`` (CSV rows by
    default). The table is not copied when it needs no conversion.

    ``whole`` False: ``table`` is one chunk of a longer log (``magkf.online.chunked``), whose rows are checked
    alike; the checks of the whole log (its number of epochs, a magnetometer that never changes, the unit
    warnings) are left to the caller (``whole_log_checks``).

    ``site`` (``magkf.io.site.Site``, ``--site`` and ``--date``) places a log without GNSS, and a log timed since
    boot (``provenance["time_base"]`` "boot") is refused without one (``place_at_site``).
    """
    name = str(source)
    row_of = row_of or table_rows(table)  # blank lines of a CSV file counted
    provenance = dict(provenance or {})
    provenance["notes"] = list(provenance.get("notes") or [])  # the reader's own list is not changed
    table = _numbers(table, name, row_of)  # a cell that is not a number is named before any time is shifted
    declared = provenance.get("time_base") == BOOT
    if site is not None or declared or (timed_since_boot(table, provenance) and not _has_position(table)):
        table = place_at_site(table, provenance, site, name)  # refuses a log it cannot place, saying what to give
    _check_columns(table, name, mag_unit, whole)
    require_complete(table, (TIME,), name, row_of)
    check_time_base(table[TIME].to_numpy(dtype=float), name, row_of)
    _check_ranges(table, name, mag_unit, row_of)
    _check_reference(table, name, row_of)
    if whole:
        fix = _UNIT_FIX.get((provenance or {}).get("format"), "pass --mag-unit {unit} if they are")
        whole_log_checks(table, name, mag_unit, fix=fix)
    if mag_unit != "nT":
        table = table.assign(**{c: to_nanotesla(table[c].to_numpy(), mag_unit) for c in MAG})
    return DriveLog(table=table.set_index(TIME), source=name, provenance=dict(provenance or {}))


def _has_position(table: pd.DataFrame) -> bool:
    """Whether the table has latitude and longitude columns or a reference field (whatever their values)."""
    return (LAT in table and LON in table) or all(c in table for c in REF)


#: The groups of columns a table gives all or none of, and what it is told when it gives some.
_COLUMN_GROUPS = (
    (ATTITUDE, "attitude needs all of roll, pitch and yaw (or none of them)"),
    (REF, "a reference field needs all of ref_n, ref_e and ref_d (or none of them)"),
)


def _check_columns(table: pd.DataFrame, name: str, mag_unit: str, whole: bool) -> None:
    """InputError naming ``name`` (row 1 and the column where one is missing) for an unknown ``mag_unit``, a
    required column missing, too few epochs (a ``whole`` log), an attitude or reference field given in part, or
    neither a position nor a reference field."""
    if mag_unit not in NT_PER_UNIT:
        raise InputError(f"unknown magnetic unit {mag_unit!r}; use one of {', '.join(NT_PER_UNIT)}", name)
    missing = [c for c in (TIME, *MAG) if c not in table.columns]
    if missing:
        raise InputError(
            f"required column missing (the table has: {', '.join(map(str, table.columns))})", name, 1, missing[0]
        )
    if whole and len(table) < MIN_EPOCHS:
        raise InputError(f"too few samples: {len(table)} epoch, a drive log needs at least {MIN_EPOCHS}", name)
    for group, message in _COLUMN_GROUPS:
        missing = [c for c in group if c not in table]
        if 0 < len(missing) < len(group):
            raise InputError(message, name, 1, missing[0])
    if not ((LAT in table and LON in table) or all(c in table for c in REF)):
        missing = next(c for c in (LAT, LON) if c not in table)
        raise InputError(
            "the log needs lat and lon (or ref_n, ref_e, ref_d) for the reference field, or --site LAT,LON[,ALT] "
            "where it was recorded",
            name,
            1,
            missing,
        )


def _numbers(table: pd.DataFrame, name: str, row_of) -> pd.DataFrame:
    """``table`` with its columns that do not hold numbers (text, objects, booleans) converted to float by
    ``numeric_column``, which names the row (``row_of(i)``) and column of the first cell that is not a number;
    the table itself when every column is numeric already."""
    other = [
        c
        for c in table.columns
        if not pd.api.types.is_numeric_dtype(table[c].dtype) or pd.api.types.is_bool_dtype(table[c].dtype)
    ]
    if not other:
        return table
    return table.assign(**{c: numeric_column(table[c], name, c, row_of) for c in other})


def _check_ranges(table: pd.DataFrame, name: str, mag_unit: str, row_of) -> None:
    """InputError naming ``name``, the row (``row_of(i)``) and the column of the first value outside its
    ``RANGES`` (the magnetometer's in ``mag_unit``)."""
    scale = NT_PER_UNIT[mag_unit]
    for column, (lo, hi, unit) in RANGES.items():
        if column in MAG:  # in the unit the table is in
            lo, hi, unit = lo / scale, hi / scale, mag_unit
        if column in table:
            v = table[column].to_numpy(dtype=float)
            bad = np.flatnonzero((v < lo) | (v > hi))
            if bad.size:
                i = int(bad[0])
                raise InputError(
                    f"value {float(v[i])!r} outside [{lo:g}, {hi:g}] {unit}".rstrip(), name, row_of(i), column
                )


def _check_reference(table: pd.DataFrame, name: str, row_of) -> None:
    """InputError naming ``name``, the row (``row_of(i)``) and ``ref_n`` of the first reference field weaker
    than ``REF_MIN_NT``; nothing for a table without one."""
    if not all(c in table for c in REF):
        return
    ref = np.linalg.norm(table[list(REF)].to_numpy(dtype=float), axis=1)
    weak = np.flatnonzero(ref < REF_MIN_NT)
    if weak.size:
        i = int(weak[0])
        raise InputError(
            f"reference field of {ref[i]:.4g} nT, under {REF_MIN_NT:g} nT (the Earth's is 22 000 to 67 000)",
            name,
            row_of(i),
            REF[0],
        )


#: What to do about magnitudes that look like another unit, by the reader's ``format`` (``{unit}`` the unit
#: they look like): an autopilot log's reader knows the unit; a column map's reader warns itself (None).
_AUTOPILOT_FIX = "the log may hold another sensor's values, or a field scaled by the autopilot"
_UNIT_FIX = {
    "mapped-table": None,
    "px4-ulog": _AUTOPILOT_FIX,
    "ardupilot-dataflash": _AUTOPILOT_FIX,
    "mavlink-tlog": _AUTOPILOT_FIX,
    "ros1-bag": "the bag's MagneticField may not be in tesla, as sensor_msgs requires",
    "ros2-sqlite3": "the bag's MagneticField may not be in tesla, as sensor_msgs requires",
    "ros2-mcap": "the bag's MagneticField may not be in tesla, as sensor_msgs requires",
}


def whole_log_checks(
    table: pd.DataFrame,
    name: str,
    mag_unit: str = "nT",
    same_value: bool = True,
    fix: str | None = "pass --mag-unit {unit} if they are",
) -> None:
    """The checks of ``from_table`` that look at a whole log at once (``table`` in ``mag_unit``; a chunked reader
    passes its first chunk with ``same_value`` False and checks that one itself): InputError for a magnetometer
    reading the same value at every epoch; ``UnitWarning`` for magnitudes that look like another unit (``fix``:
    what to do about it, ``{unit}`` the unit they look like; None: the reader has warned already) and for
    attitude that looks like radians."""
    scan = _WholeLogScan(table, ATTITUDE if all(c in table for c in ATTITUDE) else ())
    if same_value and scan.complete > 1 and np.all(scan.mag_high == scan.mag_low):
        raise InputError("the magnetometer reads the same value at every epoch: no sensor to calibrate", name)
    if scan.complete:
        median = scan.median_norm()
        guess = likely_unit(median)
        if guess is not None and guess != mag_unit and fix is not None:
            warnings.warn(
                f"{name}: the magnetometer magnitudes (median {median:.4g}) look like {guess}, not "
                f"{mag_unit}; {fix.format(unit=guess)}",
                UnitWarning,
                stacklevel=4,
            )
    if scan.attitude and len(table) >= RADIANS_MIN_EPOCHS:
        if (
            max(scan.largest_angle[:2]) <= np.pi / 2 + 1e-9
            and scan.largest_angle[2] <= 2 * np.pi + 1e-9
            and scan.yaw_high - scan.yaw_low > 1.0
        ):
            warnings.warn(
                f"{name}: roll, pitch and yaw never leave +-pi/2, +-pi/2 and +-2 pi while yaw turns: they look like "
                "radians, and magkf reads degrees",
                UnitWarning,
                stacklevel=4,
            )


#: Rows ``whole_log_checks`` looks at a time.
_SCAN_ROWS = 1 << 16


class _WholeLogScan:
    """What ``whole_log_checks`` looks at, gathered ``_SCAN_ROWS`` rows at a time (no copy of the table's
    columns is made): over the rows with all three magnetometer axes, their number ``complete``, each axis's
    least and largest value ``mag_low``, ``mag_high`` (3,) and the magnitudes ``norms`` (complete,); with
    ``attitude`` (roll, pitch, yaw: all three columns, else empty), the largest absolute angle of each
    ``largest_angle`` (3,) and yaw's least and largest value (degrees or radians as read; NaN cells left out,
    0 where a column has no value)."""

    def __init__(self, table: pd.DataFrame, attitude):
        mag = [table[c].to_numpy(dtype=float) for c in MAG]
        self.attitude = list(attitude)
        angles = [table[c].to_numpy(dtype=float) for c in self.attitude]
        self.norms = np.empty(len(table))
        self.complete = 0
        self.mag_low, self.mag_high = np.full(3, np.inf), np.full(3, -np.inf)
        self.largest_angle, self.yaw_low, self.yaw_high = np.zeros(3), 0.0, 0.0
        for a in range(0, len(table), _SCAN_ROWS):
            m = np.column_stack([v[a : a + _SCAN_ROWS] for v in mag])
            m = m[np.all(np.isfinite(m), axis=1)]
            if len(m):
                self.mag_low = np.minimum(self.mag_low, m.min(axis=0))
                self.mag_high = np.maximum(self.mag_high, m.max(axis=0))
                self.norms[self.complete : self.complete + len(m)] = np.linalg.norm(m, axis=1)
                self.complete += len(m)
            if angles:
                chunk = np.column_stack([v[a : a + _SCAN_ROWS] for v in angles])
                self.largest_angle = np.fmax(self.largest_angle, np.nanmax(np.abs(chunk), axis=0, initial=0.0))
                self.yaw_low = min(self.yaw_low, np.nanmin(chunk[:, 2], initial=0.0))
                self.yaw_high = max(self.yaw_high, np.nanmax(chunk[:, 2], initial=0.0))
        self.norms = self.norms[: self.complete]

    def median_norm(self) -> float:
        """The median of ``norms`` (as ``np.median``), found by partitioning them in place (no copy)."""
        k = len(self.norms) // 2
        middle = [k - 1, k] if len(self.norms) % 2 == 0 else [k]
        self.norms.partition(middle)
        return float(np.mean(self.norms[middle]))


def read_drive_log(path, mag_unit: str = "nT", site=None) -> DriveLog:
    """Read and validate a canonical drive log, CSV or its Parquet twin (``.parquet``).

    Parameters
    ----------
    path : str or path-like
        The log file.
    mag_unit : str, optional
        The unit of its magnetometer values (``nT``, ``uT``, ``mG`` or ``G``), which become nT.
    site : magkf.io.site.Site, optional
        Place and clock of a log without ``lat, lon`` or UTC time (``--site``, ``--date``).

    Returns
    -------
    DriveLog
        The log, its provenance naming the format and the file.

    Raises
    ------
    InputError
        One line naming file, row and column, for a missing file or column, a non-numeric or non-finite
        cell, and everything ``from_table`` checks.
    """
    name = str(path)
    parquet = Path(path).suffix.lower() in PARQUET_SUFFIXES
    table = read_csv(path, required=(TIME, *MAG))
    provenance = {"format": "canonical-parquet" if parquet else "canonical-csv", "file": name}
    return from_table(table, name, mag_unit, provenance, site=site)


def table_to_write(table: pd.DataFrame, name: str) -> tuple[pd.DataFrame, np.ndarray]:
    """A canonical table about to be written as a log (``time`` a column or the index), checked: the frame with
    ``time`` as a column and the times (N,) s. Raises InputError for a missing ``time`` or magnetometer column
    or a time that is not finite and strictly increasing."""
    frame = table.reset_index() if TIME not in table.columns and table.index.name == TIME else table
    for column in (TIME, *MAG):
        if column not in frame:
            raise InputError(f"missing column {column!r}", name)
    t = frame[TIME].to_numpy(float)
    if len(t) == 0 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise InputError("time must be finite and strictly increasing", name, column=TIME)
    return frame, t


def write_drive_log(table: pd.DataFrame, path) -> None:
    """Write a time-indexed table (or one with a ``time`` column) as canonical CSV, or as Parquet when ``path``
    ends in ``.parquet``; ``-``: CSV on standard output. Replaced only once complete.

    The CSV is written by pyarrow (about fifteen times faster than pandas' ``to_csv``): numbers in their
    shortest form that reads back to the same value, an empty cell for a missing value, and ``time`` with six
    decimals (microseconds of UNIX time). Both are written ``WRITE_ROWS`` rows at a time, so that a long
    table is never held a second time in another form (a Parquet file has one row group per piece)."""
    import pyarrow as pa

    from ..files import STDIO

    # every piece gets the whole table's types (a text column empty in one piece is still text there)
    types = {
        name: None
        if pd.api.types.is_numeric_dtype(table[name])
        else pa.infer_type(table[name].dropna().to_numpy(dtype=object), from_pandas=True)
        for name in table.columns
    }
    # plain cells, as a spreadsheet writes them, unless a text cell holds a comma, a quote or a line end
    structural = r'[,"\r\n]'
    parquet = path != STDIO and Path(path).suffix.lower() in PARQUET_SUFFIXES
    quoted = not parquet and (
        any(table[c].astype(str).str.contains(structural).any() for c, kind in types.items() if kind is not None)
        or pd.Series([str(c) for c in table.columns]).str.contains(structural).any()
    )
    pieces = (table.iloc[i : i + WRITE_ROWS] for i in range(0, max(len(table), 1), WRITE_ROWS))
    write_frames(pieces, path, types, quoted)


def write_frames(frames, path, types: dict | None = None, quoted: bool = False, parquet: bool | None = None) -> None:
    """Write consecutive pieces ``frames`` (an iterable of time-indexed DataFrames, or with a ``time`` column, all
    with the same columns) of one table as ``write_drive_log`` writes a table, one piece at a time, so that a
    table of any length is written without being held: ``types`` the Arrow type of each column that is not
    numeric (None: numeric or inferred), ``quoted`` CSV cells quoted (a text cell holds a comma, a quote or a
    line end); ``parquet`` Parquet or CSV whatever the name (None: Parquet for ``.parquet``). Replaced only once
    complete."""
    import pyarrow as pa
    from pyarrow import csv

    from ..files import STDIO, standard_output, written

    types = types or {}
    if parquet is None:
        parquet = path != STDIO and Path(path).suffix.lower() in PARQUET_SUFFIXES
    pieces = (_arrow_piece(frame, time_as_text=not parquet, types=types) for frame in frames)
    if parquet:
        import pyarrow.parquet as pq

        with written(path) as tmp:
            first = next(pieces)
            with pq.ParquetWriter(tmp, first.schema) as writer:
                writer.write_table(first)
                for piece in pieces:
                    writer.write_table(piece)
        return
    options = csv.WriteOptions() if quoted else csv.WriteOptions(quoting_style="none", quoting_header="none")

    def write(sink) -> None:
        first = next(pieces)
        with csv.CSVWriter(sink, first.schema, write_options=options) as writer:
            writer.write_table(first)
            for piece in pieces:
                writer.write_table(piece)

    if path == STDIO:
        sink = pa.BufferOutputStream()
        write(sink)
        standard_output().write(sink.getvalue().to_pybytes().decode("utf-8"))
        standard_output().flush()
        return
    with written(path) as tmp:
        with pa.OSFile(str(tmp), "wb") as sink:
            write(sink)


class FrameWriter:
    """Consecutive pieces of one table written to the file ``path`` as ``write_frames`` writes them, each when
    the caller has it (``write``), so that a table computed piece by piece is never held: CSV, or Parquet (one
    row group per piece) with ``parquet``. ``types`` and ``quoted`` as for ``write_frames``; ``floats``: every
    numeric column written as float64 (pieces read from a CSV file one at a time may hold a column as integers
    in one piece and as decimals in the next; a Parquet file has one schema); ``quoted`` None: CSV cells quoted
    when a column's name holds a comma, a quote or a line end (a table of numbers, as ``write_drive_log``
    decides). ``path`` is written as it is (wrap it in ``magkf.files.written`` to have it replaced only once
    complete); ``close`` ends it, and a file given no piece holds no rows (an empty CSV file, or no file for
    Parquet)."""

    def __init__(
        self, path, types: dict | None = None, quoted: bool | None = False, parquet: bool = False, floats=False
    ):
        self.path, self.types, self.quoted, self.parquet, self.floats = str(path), types or {}, quoted, parquet, floats
        self.writer = self.sink = self.schema = None

    def write(self, frame: pd.DataFrame) -> None:
        """Append the rows ``frame`` (time-indexed, or with a ``time`` column; the columns of the first piece)."""
        if self.floats:
            numeric = [c for c in frame.columns if pd.api.types.is_numeric_dtype(frame[c]) and c not in self.types]
            frame = frame.astype(dict.fromkeys(numeric, float))
        piece = _arrow_piece(frame, time_as_text=not self.parquet, types=self.types)
        if self.writer is None:
            self.schema = piece.schema
            self.writer = self._open(piece.schema)
        elif piece.schema != self.schema:
            piece = piece.cast(self.schema)
        self.writer.write_table(piece)

    def _open(self, schema):
        if self.parquet:
            import pyarrow.parquet as pq

            return pq.ParquetWriter(self.path, schema)
        import pyarrow as pa
        from pyarrow import csv

        quoted = self.quoted
        if quoted is None:
            quoted = any(any(c in name for c in ',"\r\n') for name in schema.names)
        options = csv.WriteOptions() if quoted else csv.WriteOptions(quoting_style="none", quoting_header="none")
        self.sink = pa.OSFile(self.path, "wb")
        return csv.CSVWriter(self.sink, schema, write_options=options)

    def close(self) -> None:
        """End the file (its footer, for Parquet)."""
        if self.writer is not None:
            self.writer.close()
        if self.sink is not None:
            self.sink.close()
        self.writer = self.sink = None

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: Rows converted and written at a time by ``write_drive_log``.
WRITE_ROWS = 16_384


def _arrow_piece(frame: pd.DataFrame, time_as_text: bool, types: dict):
    """Rows of a time-indexed table (or one with a ``time`` column) as an Arrow table: ``time`` first (as text
    with six decimals for a CSV file); NaN a missing value (an empty CSV cell); ``types`` the Arrow type of
    each column that is not numeric (None: inferred)."""
    import pyarrow as pa

    out = frame.reset_index() if frame.index.name == TIME else frame
    columns = {}
    for name in out.columns:
        values = out[name]
        if name == TIME and time_as_text:
            columns[name] = pa.array(np.char.mod("%.6f", values.to_numpy(float)))
        else:
            kind = types.get(name)
            kind = pa.string() if kind is not None and pa.types.is_null(kind) else kind  # only empty cells
            columns[name] = pa.Array.from_pandas(values, type=kind)  # NaN becomes a missing value: an empty cell
    return pa.table(columns)


class AutopilotLog(LogReader):
    """A binary autopilot log holding several magnetometers: ``read_table`` gives the chosen one's epochs with
    attitude, position and DOP interpolated to them (``--mag``, ``raw``, ``max_gap_s``) and its provenance;
    ``instances`` lists the magnetometers. Binary logs have no rows: an epoch is named by its 1-based record
    number among the magnetometer's."""

    options = frozenset({"mag", "raw", "max_gap_s", "site"})

    @staticmethod
    def read_table(path, *, mag: int | None, raw: bool, max_gap_s: float) -> tuple[pd.DataFrame, dict]:
        """The canonical table and its provenance (implemented by each format); a log without GNSS gives its time
        since boot (``provenance["time_base"]`` "boot") and no position, which ``read`` places at ``site``."""
        raise NotImplementedError

    def read(self, path, site=None, **options) -> DriveLog:
        """The log at ``path`` through ``read_table`` (``options``: those of ``self.options`` but ``site``) and
        ``from_table``, placed at ``site`` (``magkf.io.site.Site``) where it has no GNSS."""
        table, provenance = self.read_table(path, **options)
        return from_table(table, str(path), "nT", provenance, row_of=lambda i: int(i) + 1, site=site)


class CanonicalCsv(LogReader):
    """magkf's canonical table as CSV (``docs/data-contract.md``), read by ``read_drive_log``."""

    name = "csv"
    title = "canonical CSV"
    extensions = (".csv",)
    options = frozenset({"mag_unit", "site"})

    def read(self, path, mag_unit: str = "nT", site=None) -> DriveLog:
        return read_drive_log(path, mag_unit, site)


class CanonicalParquet(CanonicalCsv):
    """The canonical table's Parquet twin (the same columns and units), read by ``read_drive_log``."""

    name = "parquet"
    title = "canonical Parquet"
    magic = (b"PAR1",)
    extensions = tuple(PARQUET_SUFFIXES)
