"""Reading the canonical drive-log CSV into a validated, time-indexed structure.

See the data contract: ``time`` and ``mag_x, mag_y, mag_z`` are required; ``roll, pitch, yaw``
(degrees) give the attitude; ``lat, lon`` (``alt`` optional) or ``ref_n, ref_e, ref_d`` give the
reference field; ``dop`` (else ``pdop``, else ``hdop``) feeds the DOP gate; every other numeric column
is an auxiliary channel. An empty cell is a missing value: it is kept as NaN, never dropped.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
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
    likely_unit,
    to_nanotesla,
)
from ..errors import InputError
from ..status import Status
from .tables import file_row, read_csv, require_complete

MIN_EPOCHS = 2


def epoch_status(m, ref, has_attitude, dop, dop_max: float) -> np.ndarray:
    """Statuses (N,) known before filtering, the epoch rules of every log and of the real-time step.

    ``m`` (N, 3) raw magnetometer, ``ref`` (N, 3) reference field (NaN where there is none), ``has_attitude``
    (N,) bool, ``dop`` (N,) (NaN when not logged, which passes the gate). In order of precedence (the last
    rule that applies wins): ``missing_attitude``, ``gated_dop``, ``missing_position``, ``missing_mag``;
    otherwise ``used``. Codes from ``magkf.status.Status``.
    """
    base = np.full(len(m), Status.USED, dtype=np.int8)
    base[~np.asarray(has_attitude, bool)] = Status.MISSING_ATTITUDE
    base[np.asarray(dop, float) > dop_max] = Status.GATED_DOP
    base[~np.all(np.isfinite(ref), axis=1)] = Status.MISSING_POSITION
    base[~np.all(np.isfinite(m), axis=1)] = Status.MISSING_MAG
    return base


def select_dop(columns) -> np.ndarray | None:
    """The DOP the gate uses from a mapping of column arrays: ``dop``, else ``pdop``, else ``hdop`` (None if
    none is present). Where the chosen column is NaN at an epoch, the next one is taken there."""
    out = None
    for name in (DOP, PDOP, HDOP):
        if name in columns:
            v = np.asarray(columns[name], float)
            out = v if out is None else np.where(np.isfinite(out), out, v)
    return out


def read_sample(sample, names, time=None) -> dict[str, float]:
    """The values of ``names`` in one sample, as floats (NaN where absent, empty, None or not a number).

    ``sample`` is a mapping of column names to values: a dict, or a pandas row (``Series``). ``time`` (UNIX
    s) is taken from the argument if given, else from the sample's ``time`` entry, else from a pandas
    row's name (``DataFrame.iterrows`` and ``DriveLog.table`` rows carry the time as their index).
    """

    def number(name) -> float:
        try:
            return float(sample[name])
        except (KeyError, IndexError, TypeError, ValueError):
            return float("nan")

    out = {name: number(name) for name in names}
    if time is None:
        time = number(TIME)
        if not np.isfinite(time):
            time = getattr(sample, "name", None)
    try:
        out[TIME] = float(time)
    except (TypeError, ValueError):
        out[TIME] = float("nan")
    return out


class UnitWarning(UserWarning):
    """The magnetometer magnitudes look like another unit than the one given."""


@dataclass(frozen=True)
class DriveLog:
    """A drive log: ``table`` is a DataFrame indexed by ``time`` (UNIX s) with the file's columns,
    magnetic columns converted to nT; ``source`` names the file.

    Array properties have shape (N,) or (N, 3); missing values are NaN.
    """

    table: pd.DataFrame
    source: str = "log"

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
        return all(c in self.table for c in ATTITUDE)

    @property
    def attitude(self) -> np.ndarray:
        """(N, 3) ``roll, pitch, yaw`` in degrees (NaN throughout when the log has none)."""
        if not self.has_attitude:
            return np.full((len(self), 3), np.nan)
        return self.table[list(ATTITUDE)].to_numpy(dtype=float)

    @property
    def has_reference(self) -> bool:
        """True when the log supplies its own reference field ``ref_n, ref_e, ref_d``."""
        return all(c in self.table for c in REF)

    @property
    def has_position(self) -> bool:
        return LAT in self.table and LON in self.table

    def column(self, name: str, default: float = np.nan) -> np.ndarray:
        """(N,) values of a column, or ``default`` throughout when the log has no such column."""
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
    def auxiliary(self) -> list[str]:
        """Names of the auxiliary channels (every column without a fixed meaning)."""
        return [c for c in self.table.columns if c not in CORE_COLUMNS]

    def reference_ned(self, **kwargs) -> np.ndarray:
        """(N, 3) reference field in NED, nT: the log's ``ref_*`` columns, else IGRF at each epoch."""
        if self.has_reference:
            return self.table[list(REF)].to_numpy(dtype=float)
        from ..reference import igrf_ned

        return igrf_ned(self.time, *self.position.T, **kwargs)


def read_drive_log(path, mag_unit: str = "nT") -> DriveLog:
    """Read and validate a canonical drive-log CSV; magnetometer values in ``mag_unit`` become nT.

    Raises InputError (one line naming file, row and column) for a missing file or column, a
    non-numeric or non-finite cell, a missing or non-increasing time, an angle or position out of
    range, too few epochs or an unknown unit. Warns (``UnitWarning``) when the magnitudes look like
    another unit.
    """
    name = str(path)
    if mag_unit not in NT_PER_UNIT:
        raise InputError(f"unknown magnetic unit {mag_unit!r}; use one of {', '.join(NT_PER_UNIT)}", name)
    table = read_csv(path, required=(TIME, *MAG))
    if len(table) < MIN_EPOCHS:
        raise InputError(f"too few samples: {len(table)} epoch, a drive log needs at least {MIN_EPOCHS}", name)
    require_complete(table, (TIME,), name)
    t = table[TIME].to_numpy()
    not_increasing = np.flatnonzero(np.diff(t) <= 0)
    if not_increasing.size:
        i = int(not_increasing[0]) + 1
        raise InputError(f"time not strictly increasing ({t[i]!r} after {t[i - 1]!r})", name, file_row(i), TIME)
    attitude = [c for c in ATTITUDE if c in table]
    if 0 < len(attitude) < 3:
        missing = next(c for c in ATTITUDE if c not in table)
        raise InputError("attitude needs all of roll, pitch and yaw (or none of them)", name, 1, missing)
    if not ((LAT in table and LON in table) or all(c in table for c in REF)):
        missing = next(c for c in (LAT, LON) if c not in table)
        raise InputError("the log needs lat and lon (or ref_n, ref_e, ref_d) for the reference field", name, 1, missing)
    for column, lo, hi in ((PITCH, -90, 90), (ROLL, -180, 360), (YAW, -360, 360), (LAT, -90, 90), (LON, -180, 360)):
        if column in table:
            v = table[column].to_numpy()
            bad = np.flatnonzero((v < lo) | (v > hi))
            if bad.size:
                i = int(bad[0])
                raise InputError(f"value {v[i]!r} outside [{lo}, {hi}] degrees", name, file_row(i), column)
    mag = table[list(MAG)].to_numpy()
    complete = np.all(np.isfinite(mag), axis=1)
    if complete.any():
        median = float(np.median(np.linalg.norm(mag[complete], axis=1)))
        guess = likely_unit(median)
        if guess is not None and guess != mag_unit:
            warnings.warn(
                f"{name}: the magnetometer magnitudes (median {median:.4g}) look like {guess}, not "
                f"{mag_unit}; pass --mag-unit {guess} if they are",
                UnitWarning,
                stacklevel=2,
            )
    for c in MAG:
        table[c] = to_nanotesla(table[c].to_numpy(), mag_unit)
    table = table.set_index(TIME)
    return DriveLog(table=table, source=name)


def write_drive_log(table: pd.DataFrame, path) -> None:
    """Write a time-indexed table (or one with a ``time`` column) as canonical CSV, full precision."""
    out = table.reset_index() if table.index.name == TIME else table
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    out.to_csv(path, index=False, float_format="%.13g", na_rep="")
