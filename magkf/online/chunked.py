"""Calibration of a canonical log of any length, in chunks: memory that does not grow with the log.

``calibrate_file(path, config, ...)`` runs the calibration ``calibrate_log(read_log(path), ...)`` runs, over a
canonical CSV or Parquet file read ``rows`` rows at a time, in passes over the file:

1. **scan**: every chunk is read and validated as ``read_drive_log`` validates a whole log (one-line errors
   naming the file, the row and the column; time strictly increasing across chunk edges), prepared
   (``prepare.prepare``: reference field, attitude, statuses) and its statuses before filtering kept on
   disk; the log's first stretch is kept for the start of the run (``prepare.prepare_run``: the bootstrap);
2. **fit sample** (bootstrapped, with attitude): the evenly spaced usable epochs of the starting noise's fit
   (``prepare.fit_positions``), the same epochs as the whole-log path takes;
3. **noise scale** (bootstrapped): the residuals of the usable epochs at that fit, for the starting noise
   (``prepare.start_levels``); of every usable epoch up to ``SCALE_EPOCHS``, beyond that of ``SCALE_RUNS``
   evenly spaced runs of consecutive usable epochs, ``SCALE_EPOCHS`` in all;
4. **filter**: the forward pass (``run.ForwardPass``) piece by piece, each piece made of whole blocks; the
   state and covariance after each block are written to a temporary directory; with ``smooth``, the
   Rauch-Tung-Striebel pass goes backwards over them ``SMOOTH_BLOCKS`` blocks at a time;
5. **table**: the per-epoch table (``results.states_frame``) is written to ``states`` piece by piece as it
   is computed, and the residual sums of the summary (``results.FitSums``) are added up.

Pieces overlap their neighbours by ``OVERLAP_S`` seconds (at least ``MARGIN_ROWS`` epochs), so that what uses
neighbouring epochs (the rate of change of the body-frame field and its rate, ``effects.base.rate_of_change``;
a time lag's interpolation up to ``OVERLAP_S``) is computed as over the whole log. What is held is the
chunk being worked on, the bootstrap's stretch, the fit sample (at most ``prepare.FIT_EPOCHS`` epochs), the
scale's residuals (at most ``SCALE_EPOCHS``) and a few numbers per block (the learned noise, the block
ends: 64 bytes per block); per-epoch results and per-block states are on disk.

Differences from the whole-log path: the IGRF reference is interpolated between knots laid along each
chunk rather than along the whole log (``reference.igrf_ned``: below 0.05 nT either way); the unit and
radians warnings look at the first chunk only; a bootstrap whose first stretch is too short or turns too
little falls back to the stretch kept (``HEAD_EPOCHS`` at most) rather than to the whole log; and the
starting noise's scale is taken over at most ``SCALE_EPOCHS`` usable epochs.
"""

from __future__ import annotations

import time as _time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from ..blas import one_thread
from ..calibration import Calibration
from ..config import FilterConfig
from ..conventions import MAG, TIME
from ..errors import InputError
from ..files import temporary_folder
from ..io.drivelog import MAX_GAP_S, MIN_EPOCHS, DriveLog, TimeBaseWarning, from_table, whole_log_checks, write_frames
from ..io.tables import PARQUET_SUFFIXES, csv_chunks, parquet_chunks, record_lines
from ..status import Status
from ..timing import NO_PHASES
from .prepare import (
    PreparedLog,
    RunSetup,
    concat_prepared,
    configured_noise,
    effect_spread,
    fit_positions,
    horizontal_squared,
    magnitude_residuals,
    mark_missing_columns,
    prepare,
    prepare_run,
    residual_parts,
    robust_linear_fit,
    start_levels,
    start_rows,
)
from .results import CalibrationRun, FitSums, RunTrace, epoch_columns, states_frame, summarise
from .run import ForwardPass, filter_trace, held_reference, whole_log_options
from .smoother import rts_smooth

__all__ = [
    "CHUNK_ROWS",
    "CHUNKED_EPOCHS",
    "estimated_rows",
    "states_format",
    "OVERLAP_S",
    "MARGIN_ROWS",
    "HEAD_EPOCHS",
    "SCALE_EPOCHS",
    "SCALE_RUNS",
    "SMOOTH_BLOCKS",
    "ChunkedLog",
    "Piece",
    "overlapping",
    "pieces",
    "Spill",
    "calibrate_file",
]

#: Rows read at a time: a piece pays a fixed cost (reading, the reference field's knots, its overlap), so it is
#: larger than the whole-log path's table chunk (``prepare.CHUNK``).
CHUNK_ROWS = 65_536
#: Logs of at least this many epochs are calibrated in chunks by ``magkf calibrate``: the whole-log path holds
#: about 1.3 kB per epoch at its peak (1.3 GB here), the chunked path a constant few hundred MB, at the cost
#: of reading the file five times.
CHUNKED_EPOCHS = 1_000_000
#: Seconds of log a piece shares with each neighbour (a time lag is interpolated exactly up to this).
OVERLAP_S = 2.0
#: Least epochs a piece shares with each neighbour: central differences of the field and of its rate.
MARGIN_ROWS = 2
#: Most epochs kept for the bootstrap's first stretch.
HEAD_EPOCHS = 1_048_576
#: Most usable epochs whose residuals make the starting noise's scale, and the runs they are taken in beyond.
SCALE_EPOCHS = 1_048_576
SCALE_RUNS = 32
#: Blocks smoothed at a time in the backward pass.
SMOOTH_BLOCKS = 8_192


class ChunkedLog:
    """A canonical CSV or Parquet log read ``rows`` rows at a time; iterating gives ``(first row index,
    DriveLog)`` of each chunk, validated as ``read_drive_log`` validates a whole log (rows named by their line
    in the file), time strictly increasing across chunk edges, the whole log's checks done on the way
    (``whole_log_checks``: the magnetometer's range over every chunk, the unit warnings on the first)."""

    def __init__(self, path, mag_unit: str = "nT", rows: int = CHUNK_ROWS, cache=None):
        self.path, self.mag_unit, self.rows = Path(path), mag_unit, int(rows)
        self.source = str(path)
        self.parquet = self.path.suffix.lower() in PARQUET_SUFFIXES
        self.provenance = {"format": "canonical-parquet" if self.parquet else "canonical-csv", "file": self.source}
        self.checked = False  # True once read through: later passes neither warn nor scan the layout again
        # With a ``cache`` folder, the first reading keeps each validated chunk there as a binary array, which
        # later readings take instead of parsing the file again; ``reference`` (a ``Spill`` of (3,) rows, set by
        # ``pieces``) the reference field of every epoch, added to the chunks read from the cache.
        self.cache = None if cache is None else Path(cache)
        self.cached, self.columns, self.reference = [], None, None

    def _from_cache(self) -> Iterator[tuple[int, DriveLog]]:
        from ..conventions import REF

        for offset, file in self.cached:
            values = np.load(file)
            table = pd.DataFrame(values[:, 1:], index=pd.Index(values[:, 0], name=TIME), columns=self.columns)
            if self.reference is not None:
                ref = self.reference.read(offset, offset + len(table))
                table = table.assign(**{c: ref[:, k] for k, c in enumerate(REF)})
            yield offset, DriveLog(table, self.source, self.provenance)

    def _tables(self) -> Iterator[pd.DataFrame]:
        """The raw chunks, their file rows in ``attrs["rows"]``."""
        name = self.source
        if not self.path.is_file():
            raise InputError("no such file", name)
        required = (TIME, *MAG)
        if self.parquet:
            yield from parquet_chunks(self.path, name, self.rows, required)
            return
        # the layout checked on the first reading, the record lines kept as runs between blank lines (one number
        # a record held up to 33 bytes a record at the peak of the check); None: a record's line is its number
        lines = None if self.checked else record_lines(self.path, name, required)
        yield from csv_chunks(self.path, name, self.rows, required, lines=lines)

    def __iter__(self) -> Iterator[tuple[int, DriveLog]]:
        if self.checked and self.cache is not None:
            yield from self._from_cache()
            return
        self.cached = []
        checks = _ReadChecks(self.source, quiet=self.checked)
        offset = 0
        for table in self._tables():
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                log = from_table(table, self.source, self.mag_unit, self.provenance, whole=False)  # rows from attrs
            log.table.attrs.clear()  # the rows are this chunk's only
            checks.edge(log.time, table.attrs["rows"])
            checks.pass_on(caught)
            if offset == 0 and not self.checked:  # the unit warnings from the first chunk
                whole_log_checks(table, self.source, self.mag_unit, same_value=False)
            checks.extent(log.mag)
            if self.cache is not None:
                self._keep(offset, log)
            yield offset, log
            offset += len(log.time)
        checks.finish(offset)
        self.checked = True

    def _keep(self, offset: int, log: DriveLog) -> None:
        """Keep the validated chunk ``log`` (its first epoch the log's ``offset``-th) in the cache folder."""
        file = self.cache / f"chunk{len(self.cached)}.npy"
        np.save(file, np.column_stack([log.time, log.table.to_numpy(float)]))
        self.cached.append((offset, file))
        self.columns = list(log.table.columns)


class _ReadChecks:
    """The checks of a log read in chunks that span the chunks (``ChunkedLog``): time strictly increasing across
    their edges, a clock gap warned about once, the chunks' own warnings passed on (not when ``quiet``: a later
    reading of a checked log), and the magnetometer's range over the whole log (``finish``). ``name`` the file."""

    def __init__(self, name: str, quiet: bool):
        self.name, self.quiet = name, quiet
        self.last_t, self.gap_warned = None, False
        self.lo = self.hi = None
        self.complete_epochs = 0

    def edge(self, t, rows) -> None:
        """Check the chunk of times ``t`` (k,) UNIX s, at the file's ``rows`` (k,), against the chunk before."""
        last_t = self.last_t
        if last_t is not None and len(t):
            if not t[0] > last_t:
                raise InputError(
                    f"time not strictly increasing ({float(t[0])!r} after {last_t!r})", self.name, int(rows[0]), TIME
                )
            if t[0] - last_t > MAX_GAP_S and not (self.gap_warned or self.quiet):
                self.gap_warned = True
                warnings.warn(
                    f"{self.name}: the clock jumps by {t[0] - last_t:.3g} s at row {int(rows[0])}; the filter's random "
                    "walk spans each gap",
                    TimeBaseWarning,
                    stacklevel=3,
                )
        self.last_t = float(t[-1]) if len(t) else last_t

    def pass_on(self, caught) -> None:
        """Warn again the warnings ``caught`` reading a chunk (a clock gap once in the whole log)."""
        for w in [] if self.quiet else caught:
            if not (issubclass(w.category, TimeBaseWarning) and self.gap_warned):
                self.gap_warned |= issubclass(w.category, TimeBaseWarning)
                warnings.warn(w.message, w.category, stacklevel=3)

    def extent(self, mag) -> None:
        """Add the readings ``mag`` (k, 3) nT of a chunk to the range of the complete ones."""
        complete = mag[np.all(np.isfinite(mag), axis=1)]
        self.complete_epochs += len(complete)
        if len(complete):
            self.lo = complete.min(axis=0) if self.lo is None else np.minimum(self.lo, complete.min(axis=0))
            self.hi = complete.max(axis=0) if self.hi is None else np.maximum(self.hi, complete.max(axis=0))

    def finish(self, n_epochs: int) -> None:
        """The whole log's checks once its ``n_epochs`` epochs are read: enough of them, a magnetometer that moves."""
        if n_epochs < MIN_EPOCHS:
            raise InputError(f"too few samples: {n_epochs} epoch, a drive log needs at least {MIN_EPOCHS}", self.name)
        if self.complete_epochs > 1 and np.all(self.hi == self.lo):
            raise InputError("the magnetometer reads the same value at every epoch: no sensor to calibrate", self.name)


@dataclass(frozen=True)
class Piece:
    """Consecutive epochs of a log as one piece of a pass: ``prep`` the epochs from ``start`` (their index in the
    log) with the margins shared with the neighbours, its own epochs ``lo`` to ``hi`` (indices into ``prep``),
    ``index`` the times of ``prep``'s epochs."""

    start: int
    prep: PreparedLog
    lo: int
    hi: int
    index: pd.Index

    @property
    def own(self) -> PreparedLog:
        return self.prep.take(slice(self.lo, self.hi))

    @property
    def epochs(self) -> slice:
        """The piece's own epochs, as indices into the log."""
        return slice(self.start + self.lo, self.start + self.hi)


def overlapping(log: ChunkedLog, seconds: float, margin: int, cut=None) -> Iterator[tuple]:
    """The chunks of ``log`` each with ``seconds`` (at least ``margin`` epochs) of its neighbours on either side:
    ``(start, chunk, table, lo, hi)``, ``table`` the rows of the chunk read (``chunk``, a ``DriveLog``) with those
    carried from the one before, its first the log's ``start``-th, and its own epochs ``lo`` to ``hi``. Every epoch
    of the log is own to exactly one, in order. ``cut(t, hi, origin)`` may move a chunk's end ``hi`` back (to
    where a filter block starts; ``t`` the table's times, ``origin`` the log's first time)."""
    carry, context, origin = None, 0, None
    chunks = iter(log)
    current = next(chunks, None)
    while current is not None:
        following = next(chunks, None)
        offset, chunk = current
        table = chunk.table if carry is None else pd.concat([carry, chunk.table])
        start = offset - (0 if carry is None else len(carry))
        t = table.index.to_numpy(float)
        origin = t[0] if origin is None else origin
        lo, hi = context, len(t)
        if following is not None:
            hi = min(len(t) - margin, int(np.searchsorted(t, t[-1] - seconds)))
            if cut is not None and hi > 0:
                hi = cut(t, hi, origin)
            hi = max(hi, lo)
        if hi > lo:
            yield start, chunk, table, lo, hi
        if following is not None:
            keep = max(min(hi - margin, int(np.searchsorted(t, t[hi] - seconds))), 0)
            carry, context = table.iloc[keep:], hi - keep
        current = following


def pieces(log: ChunkedLog, config: FilterConfig, R0=None, reference: Spill | None = None) -> Iterator[Piece]:
    """The log in pieces of whole blocks (``config.block_s``, counted from the log's first time), each prepared
    with the ``OVERLAP_S`` seconds (at least ``MARGIN_ROWS`` epochs) around it (``overlapping``); ``R0`` (3, 3) the
    calibration the effects' data carry (``prepare.with_initial_R``). The same file gives the same pieces every
    time. ``reference`` (a ``Spill`` of (3,) rows): the reference field of the pieces' own epochs is appended to
    it, and the log's later readings carry it (``ChunkedLog.reference``): IGRF is evaluated once."""

    def at_block(t, hi, origin):  # where the block of epoch hi starts
        if config.block_s <= 0:
            return hi
        block_id = np.floor((t - origin) / config.block_s)
        return int(np.searchsorted(block_id, block_id[hi]))

    for start, chunk, table, lo, hi in overlapping(log, OVERLAP_S, MARGIN_ROWS, at_block):
        if reference is not None and chunk.has_reference:
            reference = None  # the log's own: nothing to keep
        if reference is not None:
            log.reference = reference  # read back by the later readings only
        prep = prepare(DriveLog(table, log.source), config)
        if R0 is not None:
            prep = replace(prep, data=replace(prep.data, R0=R0))
        if reference is not None:
            reference.append(prep.ref[lo:hi])
        yield Piece(start, prep, lo, hi, table.index)


class Spill:
    """An array of rows of ``shape`` and ``dtype`` in a file of the directory ``folder``: appended to, written at
    and read back by row, never held whole."""

    def __init__(self, folder, name: str, dtype, shape=()):
        self.file = Path(folder) / f"{name}.bin"
        self.dtype, self.shape = np.dtype(dtype), tuple(shape)
        self.row_bytes = self.dtype.itemsize * int(np.prod(self.shape, dtype=np.int64))
        self.rows = 0
        self.file.touch()

    def append(self, rows) -> None:
        with open(self.file, "ab") as f:
            np.ascontiguousarray(rows, self.dtype).tofile(f)
        self.rows += len(rows)

    def write_at(self, row: int, rows) -> None:
        with open(self.file, "r+b") as f:
            f.seek(row * self.row_bytes)
            np.ascontiguousarray(rows, self.dtype).tofile(f)

    def read(self, a: int, b: int) -> np.ndarray:
        count = max(b - a, 0) * int(np.prod(self.shape, dtype=np.int64))
        out = np.fromfile(self.file, self.dtype, count=count, offset=a * self.row_bytes)
        return out.reshape((-1, *self.shape))


def estimated_rows(path) -> int:
    """The number of records of a canonical CSV (from its size and its first lines' length) or Parquet file."""
    path = Path(path)
    if path.suffix.lower() in PARQUET_SUFFIXES:
        import pyarrow.parquet as pq

        try:
            return int(pq.ParquetFile(path).metadata.num_rows)
        except Exception:  # not Parquet after all: the reader will say what it is
            return 0
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
        lines = head.count(b"\n")
        return int(path.stat().st_size * max(lines - 1, 0) / max(len(head), 1)) if lines > 1 else lines
    except OSError:
        return 0


def states_format(path) -> bool:
    """Whether the per-epoch states of a long log go to ``path`` as Parquet: unless its name ends in ``.csv``."""
    return Path(path).suffix.lower() != ".csv"


def _scale_positions(n_usable: int) -> np.ndarray:
    """Positions among ``n_usable`` usable epochs whose residuals make the starting noise's scale: all of them up
    to ``SCALE_EPOCHS``, else ``SCALE_RUNS`` evenly spaced runs of consecutive ones, ``SCALE_EPOCHS`` in all."""
    if n_usable <= SCALE_EPOCHS:
        return np.arange(n_usable)
    length = SCALE_EPOCHS // SCALE_RUNS
    starts = np.linspace(0, n_usable - length, SCALE_RUNS).astype(np.int64)
    return (starts[:, None] + np.arange(length)).ravel()


def _select(positions: np.ndarray, first: int, local: np.ndarray) -> np.ndarray:
    """Of the epochs ``local`` (indices into a piece) numbered ``first``, ``first + 1``... among the log's usable
    epochs, those at ``positions`` (sorted)."""
    a, b = np.searchsorted(positions, [first, first + len(local)])
    return local[positions[a:b] - first]


@one_thread
def calibrate_file(
    path,
    config: FilterConfig = FilterConfig(),
    init: Calibration | None = None,
    effects=(),
    smooth: bool = False,
    states=None,
    states_parquet: bool | None = None,
    mag_unit: str = "nT",
    rows: int = CHUNK_ROWS,
    progress=None,
    phases=NO_PHASES,
) -> CalibrationRun:
    """Calibrate the canonical CSV or Parquet log ``path`` as ``calibrate_log`` does, in chunks of ``rows`` rows
    (see the module's passes); ``states`` a file the per-epoch table is written to as it is computed (CSV, or
    Parquet for ``.parquet``; ``states_parquet`` True or False: whatever the name). Returns a
    ``CalibrationRun`` whose ``states`` and ``fit`` are None (the per-epoch table is in ``states``)."""
    started = _time.perf_counter()
    with temporary_folder() as folder:  # removed on any exit; a later run removes it after SIGKILL
        log = ChunkedLog(path, mag_unit, rows, cache=folder)
        with phases("scan (read, reference field, statuses)"):
            scan = _scan(log, config, effects, init, folder)
        with phases("start (bootstrap, noise)"):
            setup = _start(log, config, init, effects, scan)
            est = setup.estimator(config)
        loop_started = _time.perf_counter()
        out = _filter_pass(log, config, setup, est, scan, folder, smooth, progress)
        loop_s = _time.perf_counter() - loop_started
        phases.add("filter loop", loop_s)
        if smooth:
            with phases("smoother"):
                out.xs, out.stds = _smooth(folder, out.xs, out.Ps, out.dt, setup.layout.q_rate())
        with phases("whole-log estimate"):
            whole = _whole_log(log, config, setup, est, out, init, scan.median_step_s)
        trace = filter_trace(
            est,
            setup,
            scan.median_step_s,
            whole=whole,
            **dict.fromkeys(("xs", "stds", "status", "updated", "nis")),  # on disk, in ``out``
            elapsed_s=0.0,
            smoothed=smooth,
            loop_s=loop_s,
            noise=out.noise,
            stops=out.stops,
        )
        with phases("per-epoch table and summary"):
            sums = _table_pass(log, config, setup, trace, out, (states, states_parquet))
        trace = replace(trace, elapsed_s=_time.perf_counter() - started)
        layout = setup.layout
        summary, cal, effect_values = summarise(
            log.source, config, layout, setup.P0, trace, sums, np.diff(out.stops, prepend=0)
        )
    filter_last = summary.filter_state is not None
    return CalibrationRun(
        cal,
        trace.x,
        trace.P,
        layout.names,
        None,
        summary,
        effect_values,
        None,
        filter_x=trace.filter_x if filter_last else None,
        filter_P=trace.filter_P if filter_last else None,
    )


def _whole_log(log: ChunkedLog, config: FilterConfig, setup: RunSetup, est, out: _Filtered, init, step_s: float):
    """The whole-log estimate (``whole_log.fit_whole_log_parts``) over the epochs the filter pass updated with,
    the log read again piece by piece for each of the solver's passes."""
    from .whole_log import filter_estimate, fit_whole_log_parts, wandering

    moving = wandering(setup.layout)
    if moving:
        return filter_estimate(est.x, est.P, moving)
    status, updated = out.per_epoch["status"], out.per_epoch["updated"]

    def parts():
        for piece in pieces(log, config, setup.R0):
            a, b = piece.epochs.start, piece.epochs.stop
            code = status.read(a, b)
            yield piece.own, updated.read(a, b) & ((code == Status.USED) | (code == Status.MISSING_ATTITUDE))

    options = whole_log_options(setup, est, config, held_reference(None, init, None), step_s, log.source)
    return fit_whole_log_parts(parts, setup.layout, est.x, **options)


def _start(log: ChunkedLog, config: FilterConfig, init, effects, scan: _Scan) -> RunSetup:
    """The start of the run (``prepare.prepare_run``) from the scan's first stretch, with the starting noise of
    passes 2 and 3 (``_start_noise``); the setup keeps no epochs (its ``prep`` is None: pieces are read again)."""
    head, scan.head = scan.head, None

    def noise_start(layout, x0, attitude: bool):
        return _start_noise(log, config, scan, layout, x0, layout.R(x0), attitude)

    setup = prepare_run(
        head, config, init, effects, log.source, any_attitude=scan.any_attitude, noise_start=noise_start
    )
    return replace(setup, prep=None)


@dataclass
class _Filtered:
    """What the filter pass (pass 4) leaves: on disk, the states ``xs`` (K, n), their standard deviations ``stds``
    (K, n) and (with smoothing) covariances ``Ps`` (K, n, n) after each block, and the per-epoch ``status``,
    ``updated`` and ``nis`` (``per_epoch``); held, per block, the learned ``noise`` (K, 4), the ``stops`` (K,)
    one past each block's last epoch and the time ``dt`` (K,) s each block's prediction covered."""

    xs: Spill
    stds: Spill
    Ps: Spill | None
    per_epoch: dict
    noise: np.ndarray
    stops: np.ndarray
    dt: np.ndarray


def _filter_pass(log, config, setup: RunSetup, est, scan: _Scan, folder, smooth: bool, progress) -> _Filtered:
    """Pass 4: the forward pass (``run.ForwardPass``) of ``est`` piece by piece, its results written to ``folder``."""
    n = setup.layout.size
    xs_file, stds_file = Spill(folder, "xs", float, (n,)), Spill(folder, "stds", float, (n,))
    Ps_file = Spill(folder, "Ps", float, (n, n)) if smooth else None
    per_epoch = {
        "status": Spill(folder, "status", np.int8),
        "updated": Spill(folder, "updated", bool),
        "nis": Spill(folder, "nis", float),
    }
    noise_b, stops, dt = [], [], []
    forward = ForwardPass(est, setup.model, setup.R0, config, scan.origin)
    for piece in pieces(log, config, setup.R0):
        status, updated, nis, xs_b, Ps_b, noise_k, stops_k, dt_k = forward.run(
            piece.own, scan.base.read(piece.epochs.start, piece.epochs.stop)
        )
        for key, values in zip(per_epoch, (status, updated, nis)):
            per_epoch[key].append(values)
        xs_file.append(xs_b)
        stds_file.append(np.sqrt(np.einsum("bii->bi", Ps_b)))
        if smooth:
            Ps_file.append(Ps_b)
        noise_b.append(noise_k)
        stops.append(stops_k + piece.epochs.start)
        dt.append(dt_k)
        if progress is not None:
            progress(piece.epochs.stop / scan.n_epochs)
    return _Filtered(
        xs_file, stds_file, Ps_file, per_epoch, np.concatenate(noise_b), np.concatenate(stops), np.concatenate(dt)
    )


@dataclass
class _Scan:
    """What the scan found: the statuses before filtering (on disk), the epochs, the usable ones (used; used or
    without attitude), the first stretch, whether any epoch has attitude, the log's first time and median
    time step."""

    base: Spill
    n_epochs: int
    n_used: int
    n_magnitude: int
    head: PreparedLog | None
    any_attitude: bool
    origin: float
    median_step_s: float


def _scan(log: ChunkedLog, config: FilterConfig, effects, init, folder) -> _Scan:
    """Pass 1: validate, prepare and keep the statuses, the counts and the bootstrap's stretch."""
    from ..spilled_median import SpilledMedian  # it reads its numbers from a Spill of this module

    base_file, steps = Spill(folder, "base", np.int8), SpilledMedian(folder, "steps")
    n_epochs = n_used = n_magnitude = 0
    any_attitude, origin, last_t = False, None, None
    head = _Head(config, effects, init is not None)
    reference = None if log.cache is None else Spill(folder, "reference", float, (3,))
    for piece in pieces(log, config, reference=reference):
        own = piece.own
        base = mark_missing_columns(own, effects, log.source)
        base_file.append(base)
        t = own.time
        origin = t[0] if origin is None else origin
        steps.add(np.diff(t) if last_t is None else np.diff(np.concatenate([[last_t], t])))
        last_t = t[-1]
        n_epochs += len(own)
        n_used += int(np.count_nonzero(base == Status.USED))
        n_magnitude += int(np.count_nonzero((base == Status.USED) | (base == Status.MISSING_ATTITUDE)))
        any_attitude |= bool(own.has_attitude.any())
        head.add(own)
    median_step = steps.value() if steps.count else 0.0
    return _Scan(base_file, n_epochs, n_used, n_magnitude, head.prepared(), any_attitude, float(origin), median_step)


class _Head:
    """The log's first stretch, kept for the start of the run (``prepare.prepare_run``): the pieces up to
    ``config.bootstrap_s`` after both the first good epoch (used, the linear ``effects``' channels present) and
    the first usable one (used or without attitude), at most ``HEAD_EPOCHS`` epochs; the first piece alone when
    the run starts ``from_calibration`` (no bootstrap)."""

    def __init__(self, config: FilterConfig, effects, from_calibration: bool):
        self.span_s, self.from_calibration = config.bootstrap_s, from_calibration
        self.columns = [c for e in effects if e.linear for c in e.columns]
        self.parts, self.epochs, self.done = [], 0, False
        self.first_good = self.first_cand = None

    def add(self, own: PreparedLog) -> None:
        """Keep the piece ``own`` (its own epochs) while the stretch is not complete."""
        if self.done:
            return
        self.parts.append(own)
        self.epochs += len(own)
        t = own.time
        good = own.base == Status.USED
        for c in self.columns:
            good &= np.isfinite(own.data.columns[c])
        cand = (own.base == Status.USED) | (own.base == Status.MISSING_ATTITUDE)
        if self.first_good is None and good.any():
            self.first_good = t[np.argmax(good)]
        if self.first_cand is None and cand.any():
            self.first_cand = t[np.argmax(cand)]
        found = self.first_good is not None and self.first_cand is not None
        self.done = (
            self.from_calibration
            or (found and t[-1] > max(self.first_good, self.first_cand) + self.span_s)
            or self.epochs >= HEAD_EPOCHS
        )

    def prepared(self) -> PreparedLog | None:
        """The stretch as one ``PreparedLog`` (None: no piece)."""
        return concat_prepared(self.parts) if self.parts else None


def _start_noise(log, config, scan: _Scan, layout, x0, R0, attitude: bool):
    """Passes 2 and 3: the starting noise and the robust whole-log start (``prepare.start_noise``) from the fit
    sample and the residual scale."""
    start = configured_noise(config)
    x = x0
    if attitude:
        if scan.n_used < 50:
            return start, x0
        positions = fit_positions(scan.n_used)
        m, H, seen = [], [], 0
        for piece in pieces(log, config, R0):
            usable = np.flatnonzero(scan.base.read(piece.epochs.start, piece.epochs.stop) == Status.USED)
            chosen = _select(positions, seen, usable)
            rows = start_rows(layout, x0, piece.prep.data, piece.own.m[chosen], piece.lo + chosen)
            m.append(rows[0])
            H.append(rows[1])
            seen += len(usable)
        x = robust_linear_fit(
            np.concatenate(m), np.concatenate(H), x0, start.along_var, prior_std=effect_spread(layout)
        )
        del m, H
        wanted = _scale_positions(scan.n_used)
    else:
        if scan.n_magnitude < 10:
            return start, x0
        wanted = _scale_positions(scan.n_magnitude)
    parts, ref_mag, ref, seen = [], [], [], 0
    for piece in pieces(log, config, R0):
        base = scan.base.read(piece.epochs.start, piece.epochs.stop)
        ok = (base == Status.USED) if attitude else (base == Status.USED) | (base == Status.MISSING_ATTITUDE)
        usable = np.flatnonzero(ok)
        chosen = _select(wanted, seen, usable)
        take = piece.own.take(chosen)
        parts.append(
            residual_parts(piece.prep, layout, x, R0, piece.lo + chosen) if attitude else magnitude_residuals(take, x0)
        )
        ref_mag.append(take.ref_mag)
        ref.append(take.ref)
        seen += len(usable)
    parts = np.concatenate(parts)
    along, cross = (parts[:, 0], parts[:, 1:]) if attitude else (parts, None)
    return start_levels(along, cross, np.concatenate(ref_mag), horizontal_squared(np.concatenate(ref)), config), x


def _smooth(folder, xs_file: Spill, Ps_file: Spill, dt, q_rate) -> tuple[Spill, Spill]:
    """The Rauch-Tung-Striebel pass (``smoother.rts_smooth``) backwards over the stored block states,
    ``SMOOTH_BLOCKS`` at a time; the smoothed states and standard deviations, on disk."""
    K, n = xs_file.rows, xs_file.shape[0]
    xs_out, stds_out = Spill(folder, "xs_smoothed", float, (n,)), Spill(folder, "stds_smoothed", float, (n,))
    xs_out.rows = stds_out.rows = K
    after = None  # the smoothed state and covariance of the block after the stretch
    for b in range(K, 0, -SMOOTH_BLOCKS):
        a = max(b - SMOOTH_BLOCKS, 0)
        xs, Ps = xs_file.read(a, b), Ps_file.read(a, b)
        if after is not None:
            xs, Ps = np.concatenate([xs, after[0][None]]), np.concatenate([Ps, after[1][None]])
        xs, Ps = rts_smooth(xs, Ps, dt[a : a + len(xs)], q_rate)
        xs_out.write_at(a, xs[: b - a])
        stds_out.write_at(a, np.sqrt(np.einsum("bii->bi", Ps[: b - a])))
        after = xs[0], Ps[0]
    return xs_out, stds_out


def _table_pass(log, config, setup: RunSetup, trace: RunTrace, out: _Filtered, states) -> FitSums:
    """Pass 5: the per-epoch table of every piece (written to ``states``, ``(path, parquet)``, if given) and the
    residual sums."""
    layout, x0, R0 = setup.layout, setup.x0, setup.R0
    xs_file, stds_file, per_epoch, K = out.xs, out.stds, out.per_epoch, out.xs.rows
    sums = FitSums(rows=trace.nis_rows)
    stops = trace.stops
    own_prior = trace.smoothed
    # nonlinear effects are evaluated at the whole log's last per-epoch state, as over a whole log
    last_own = xs_file.read(K - 1, K)[0]
    last_prior = last_own if own_prior else (xs_file.read(K - 2, K - 1)[0] if K > 1 else np.asarray(x0, float))
    names = layout.names

    def frames():
        for piece in pieces(log, config, R0):
            ext = np.arange(piece.start, piece.start + len(piece.prep))
            block = np.searchsorted(stops, ext, side="right")
            first = max(int(block[0]) - 1, 0)
            part_trace = replace(
                trace, xs=xs_file.read(first, int(block[-1]) + 1), stds=stds_file.read(first, int(block[-1]) + 1)
            )
            xs, stds, ned_i, mag_i, ned_f, mag_f = epoch_columns(
                piece.prep, block - first, layout, part_trace, x0, own_prior, (last_prior, last_own)
            )
            own = slice(piece.lo, piece.hi)
            a, b = piece.epochs.start, piece.epochs.stop
            status, updated, nis = (per_epoch[key].read(a, b) for key in ("status", "updated", "nis"))
            ned_f, mag_f, ned_i = (v[own].astype(np.float32) for v in (ned_f, mag_f, ned_i))  # as in the table
            sums.add(status, updated, nis, piece.prep.has_attitude[own], ned_f, mag_f, ned_i)
            noise = trace.noise[block[own]]
            yield states_frame(
                piece.index[own],
                names,
                status,
                updated,
                nis,
                xs[own].astype(np.float32),
                stds[own].astype(np.float32),
                np.column_stack([ned_i, mag_i[own]]),
                noise,
            )

    if states[0] is None:
        for _ in frames():
            pass
    else:
        import pyarrow as pa

        write_frames(frames(), states[0], {"status": pa.string()}, parquet=states[1])
    return sums
