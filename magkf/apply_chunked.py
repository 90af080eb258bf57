"""A calibration applied to a canonical log of any length, chunk by chunk: memory that does not grow with the log.

``apply_file(path, cal, write)`` gives every epoch of the canonical CSV or Parquet log ``path`` what
``apply.apply_calibration`` gives it over the whole log, read ``rows`` rows at a time
(``magkf.online.chunked.ChunkedLog``: each chunk validated as the whole reader validates a log, errors naming
the file, the row and the column), each chunk's rows handed to ``write`` (a ``FrameWriter``'s ``write``) as
soon as they are computed. What the command judges and prints is gathered on the way: the statuses' counts,
the calibrated magnitudes' mean and standard deviation (combined chunk by chunk), and, kept on disk for exact
medians (``SpilledMedian``), the magnitudes (``plausibility.check_applied``), the log's field
(``plausibility.log_field_nt``: the medians of its reference field, or of its position and time) and, for a
calibration in the readings' own units, the calibrated readings' radius (``plausibility.check_loaded``).

**Chunk edges.** Each chunk is computed with ``OVERLAP_S`` seconds (and at least ``MARGIN_ROWS`` epochs) of
its neighbours on either side, and only its own epochs are written: the rate of the body-frame field and of
that rate (central differences) and a time lag's interpolation (up to ``OVERLAP_S`` beyond the largest stored
parameter in seconds) see the epochs they see over the whole log. A stored wandering offset
(``bias_drift``) subtracts its path at each epoch's time; whether the log is the one the path was learned on
is decided over the whole log first (``OwnLog``: one more reading of the log, from a binary copy of its
chunks), as ``drift_path.same_log`` decides it over a whole log.

**Differences from the whole-log path.** Where the log has no ``ref_*`` columns, IGRF is interpolated
between knots laid along each chunk rather than along the whole log (``reference.igrf_ned``; below 0.05 nT
in the field, as in ``magkf.online.chunked``); with ``ref_*`` columns every value is the whole path's. The
summary's mean and standard deviation agree to rounding (summed chunk by chunk). The unit and radians
warnings look at the first chunk only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .apply import apply_calibration
from .calibration import Calibration
from .conventions import ALT, LAT, LON, REF
from .files import temporary_folder
from .io.drivelog import DriveLog
from .online import chunked
from .online.chunked import OVERLAP_S, ChunkedLog
from .spilled_median import SpilledMedian

__all__ = ["MARGIN_ROWS", "AppliedFile", "OwnLog", "apply_file", "overlap_s"]

#: Least epochs each chunk shares with each neighbour: the rate of the field's rate reaches two epochs away, a
#: time lag's spline two usable epochs beyond its delayed time.
MARGIN_ROWS = 8


def overlap_s(cal: Calibration) -> float:
    """Seconds of log each chunk shares with each neighbour for ``cal``: ``OVERLAP_S`` beyond the largest
    stored parameter in seconds (a time lag interpolates the field that far away)."""
    lags = [abs(float(v)) for e in cal.effects for v, u in zip(e.values, e.units) if u == "s" and np.isfinite(v)]
    return OVERLAP_S + max(lags, default=0.0)


class OwnLog:
    """Whether a log read in chunks is the one each stored wandering effect's path was learned on, as
    ``drift_path.same_log`` decides over the whole log: every fingerprint epoch within the log's times found
    (the first epoch at or after it within the tolerance) with its reading within ``SAME_READING_NT``, and at
    least one found. ``add`` each chunk's own epochs in order; ``flags`` (k,) one per stored effect (None for
    an effect that does not wander or holds no fingerprint)."""

    def __init__(self, cal: Calibration):
        self.samples = [_fingerprint(e.wander) for e in cal.effects]
        self.within = [0] * len(self.samples)
        self.matched = [True] * len(self.samples)
        self.first = self.last = None

    @property
    def needed(self) -> bool:
        """Whether any stored effect has a fingerprint to look for."""
        return any(s is not None for s in self.samples)

    def add(self, time: np.ndarray, mag: np.ndarray) -> None:
        """The next chunk's epochs at ``time`` (n,) UNIX s with raw readings ``mag`` (n, 3) nT."""
        from .online.drift_path import SAME_READING_NT

        if not len(time):
            return
        after = -np.inf if self.last is None else self.last
        self.first = time[0] if self.first is None else self.first
        for k, sample in enumerate(self.samples):
            if sample is None:
                continue
            s_time, s_mag = sample
            here = (s_time > after) & (s_time <= time[-1]) & (s_time >= self.first)
            if not here.any():
                continue
            within = s_time[here]
            at = np.clip(np.searchsorted(time, within), 0, len(time) - 1)
            found = np.abs(time[at] - within) <= 1e-6 * np.maximum(np.abs(within), 1.0)
            close = np.all(np.abs(mag[at] - s_mag[here]) <= SAME_READING_NT, axis=1)
            self.within[k] += len(within)
            self.matched[k] &= bool(np.all(found & close))
        self.last = time[-1]

    @property
    def flags(self) -> list:
        return [None if s is None else (bool(n) and m) for s, n, m in zip(self.samples, self.within, self.matched)]


def _fingerprint(wander: dict | None):
    """The fingerprint epochs ``(time (k,), readings (k, 3))`` of a stored path, None without any."""
    sample = (wander or {}).get("fingerprint") or {}
    s_time = np.asarray(sample.get("time", []), float)
    if wander is None or not len(s_time):
        return None
    return s_time, np.asarray(sample.get("mag", []), float).reshape(-1, 3)


class _FieldMedians:
    """The medians ``plausibility.log_field_nt`` takes of a whole log, gathered chunk by chunk on disk: of the
    reference field's magnitude (a log with ``ref_*``), else of latitude, longitude, height and time."""

    def __init__(self, folder, rows: int):
        self.parts = {name: SpilledMedian(folder, f"field_{name}", rows) for name in ("ref", LAT, LON, ALT, "time")}
        self.columns = None

    def add(self, table: pd.DataFrame) -> None:
        if self.columns is None:
            self.columns = set(table.columns)
        if all(c in table for c in REF):
            self.parts["ref"].add(np.linalg.norm(table[list(REF)].to_numpy(float), axis=1))
            return
        for name in (LAT, LON, ALT):
            if name in table:
                self.parts[name].add(table[name].to_numpy(float))
        self.parts["time"].add(table.index.to_numpy(float))

    def value(self) -> float:
        """The log's field magnitude, nT, as ``log_field_nt`` gives it (NaN: no reference field, no position)."""
        from .reference import field_at

        if self.columns is not None and all(c in self.columns for c in REF):
            return self.parts["ref"].value()
        if not (self.parts[LAT].count and self.parts[LON].count):
            return float("nan")
        alt = self.parts[ALT].value() if self.parts[ALT].count else 0.0
        lat, lon, time = (self.parts[name].value() for name in (LAT, LON, "time"))
        return float(field_at(lat, lon, alt, time)["magnitude_nt"])


@dataclass
class _Moments:
    """Count, mean and sum of squared deviations of numbers added in pieces (Chan's pairwise combination)."""

    n: int = 0
    mean: float = 0.0
    m2: float = 0.0

    def add(self, values: np.ndarray) -> None:
        values = values[np.isfinite(values)]
        if not len(values):
            return
        n_b, mean_b = len(values), float(np.mean(values))
        m2_b = float(np.sum((values - mean_b) ** 2))
        n = self.n + n_b
        delta = mean_b - self.mean
        self.mean += delta * n_b / n
        self.m2 += m2_b + delta**2 * self.n * n_b / n
        self.n = n

    @property
    def std(self) -> float:
        """The sample standard deviation (as ``pandas.Series.std``: one degree of freedom taken)."""
        return float(np.sqrt(self.m2 / (self.n - 1))) if self.n > 1 else float("nan")


@dataclass
class AppliedFile:
    """What ``apply_file`` gathered: ``n_epochs``; the statuses' ``counts`` (by status, in the order
    ``pandas.Series.value_counts`` gives them); the calibrated magnitudes' ``mean_nt`` and ``std_nt`` and their
    median ``median_nt`` (over the finite ones; NaN without any); the log's field ``field_nt``
    (``log_field_nt``); ``radius`` the median magnitude of the readings calibrated by a calibration in their
    own units (NaN for one in nT); the log's ``provenance``."""

    n_epochs: int
    counts: dict
    mean_nt: float
    std_nt: float
    median_nt: float
    field_nt: float
    radius: float
    provenance: dict = field(default_factory=dict)


def apply_file(
    path,
    cal: Calibration,
    write: Callable[[pd.DataFrame], None] | None = None,
    mag_unit: str = "nT",
    rows: int | None = None,
    ready: Callable[[], None] | None = None,
) -> AppliedFile:
    """Apply ``cal`` to every epoch of the canonical CSV or Parquet log ``path`` in chunks of ``rows`` rows.

    Parameters
    ----------
    path : str or path-like
        The log.
    cal : Calibration
        The calibration, with its stored effects (registered: ``effects.load_effect_file``).
    write : callable, optional
        Given each chunk's rows of ``apply.apply_calibration``'s table (time-indexed DataFrame), in order.
    mag_unit : str
        The unit of the log's magnetometer columns.
    rows : int, optional
        Rows read at a time (default ``magkf.online.chunked.CHUNK_ROWS``).
    ready : callable, optional
        Called once the log's first chunk is read and validated, before anything is computed (user effects are
        loaded then).

    Returns
    -------
    AppliedFile
        The figures the command judges and prints.

    Raises
    ------
    InputError
        A cell, a row or the whole log that the reader refuses (naming the file, the row and the column), or
        what ``apply_calibration`` raises.
    """
    rows = chunked.CHUNK_ROWS if rows is None else int(rows)
    with temporary_folder() as folder:
        own = OwnLog(cal)
        log = ChunkedLog(path, mag_unit, rows, cache=folder if own.needed else None)
        if own.needed:  # decided over the whole log before any drift is subtracted
            for _, chunk in log:
                own.add(chunk.time, chunk.mag)
        flags = own.flags if own.needed else None
        gather = _Gather(folder, rows, cal)
        for _, chunk, table, lo, hi in chunked.overlapping(log, overlap_s(cal), MARGIN_ROWS):
            piece = DriveLog(table, log.source, chunk.provenance)
            if ready is not None:
                ready()
                ready = None
            out = apply_calibration(piece, cal, flags).iloc[lo:hi]
            gather.add(piece.table.iloc[lo:hi], out)
            if write is not None:
                write(out)
            gather.provenance = piece.provenance
        return gather.result()


class _Gather:
    """The figures of ``AppliedFile`` gathered chunk by chunk (medians on disk in ``folder``)."""

    def __init__(self, folder, rows: int, cal: Calibration):
        self.n, self.counts, self.moments = 0, {}, _Moments()
        self.magnitude = SpilledMedian(folder, "magnitude", rows)
        self.field = _FieldMedians(folder, rows)
        self.cal = cal if getattr(cal, "field_unit", "nT") != "nT" else None
        self.radius = SpilledMedian(folder, "radius", rows)
        self.provenance = {}

    def add(self, table: pd.DataFrame, out: pd.DataFrame) -> None:
        self.n += len(out)
        for status, count in out["status"].value_counts(sort=False).items():  # in the order they first come
            self.counts[str(status)] = self.counts.get(str(status), 0) + int(count)
        magnitude = out["magnitude_nt"].to_numpy(float)
        self.moments.add(magnitude)
        self.magnitude.add(magnitude)
        self.field.add(table)
        if self.cal is not None:
            self.radius.add(_calibrated_radius(self.cal, DriveLog(table).mag))

    def result(self) -> AppliedFile:
        counts = pd.Series(self.counts, dtype=np.int64).sort_values(ascending=False, kind="stable").to_dict()
        return AppliedFile(
            self.n,
            counts,
            self.moments.mean if self.moments.n else float("nan"),
            self.moments.std,
            self.magnitude.value(),
            self.field.value(),
            self.radius.value() if self.cal is not None else float("nan"),
            self.provenance,
        )


def _calibrated_radius(cal: Calibration, mag: np.ndarray) -> np.ndarray:
    """The magnitudes (n,) of the complete readings ``mag`` (n, 3) calibrated by ``cal`` (``R^-1 (m - b)``), as
    ``plausibility`` takes their median; none for a singular or not finite ``R``."""
    m = mag[np.isfinite(mag).all(axis=1)]
    R = np.asarray(cal.R, float)
    if not len(m) or not np.isfinite(R).all() or abs(np.linalg.det(R)) == 0:
        return np.empty(0)
    return np.linalg.norm(np.linalg.solve(R, (m - np.asarray(cal.b, float)).T), axis=0)
