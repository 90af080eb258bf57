"""A set of a log's epochs prepared a chunk at a time when read, rather than held prepared.

``prepare`` gives every epoch's arrays at once: about 180 bytes an epoch (the attitude, from which its matrices are
made when read, the field in two frames, its rate and acceleration, the heading axis). A diagnosis reads its epochs
a chunk at a time on each pass, so ``PreparedRows`` holds only where its epochs are in the log and their times (16
bytes an epoch of the set) and the log's reference field (an ``IgrfTrack``, a few numbers a knot, where the field
is IGRF's; 24 bytes an epoch of the log where the log gives it), and makes a chunk's arrays
again from the log when they are read (``Chunk``): the log's own columns read at the epochs, the others by
``prepare``'s rules (``prepare.body_arrays``, ``prepare.field_rates``) on the log's rows around the epochs with
``MARGIN`` rows either side, so that the rates by central differences are the whole log's to the last bit. A set
small enough (``HELD_BYTES``) is made once and held.

``LazyEpochData`` is the ``EpochData`` of such a set: its per-epoch arrays are ``ChunkedArray`` s, which give the
chunk's values for a slice of consecutive epochs (``a[i:j]``, what the effects read with ``rows``) and the whole
array for anything else (``np.asarray(a)``, an index array, arithmetic, an attribute such as ``a.T``): right in
every use, held whole only where a use asks for all of it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from ..conventions import ATTITUDE, MAG
from ..effects.base import EpochData
from ..io.drivelog import DriveLog
from .determined import CHUNK

__all__ = ["MARGIN", "HELD_BYTES", "PreparedRows", "Chunk", "ChunkData", "LazyEpochData", "ChunkedArray"]

#: Rows of the log prepared on either side of a chunk's: a prepared array's end rows have one-sided rates (as
#: the log's own ends), and the acceleration at a row reads the rate one row either side, so the rows two in from
#: the ends are the first whose rate and acceleration are the whole log's (``effects.base.rate_of_change``).
MARGIN = 2
#: Chunks kept prepared (the last read): a pass reads several arrays of the same chunk in turn.
KEPT_CHUNKS = 4
#: A set whose prepared arrays take at most this many bytes is prepared once, at its first read, and held: a
#: diagnosis reads its epochs on 20 to 40 passes, and preparing them again on each took a third more time on a
#: 15-minute 100 Hz log. A longer set is prepared a chunk at a time when read. 32 MiB holds a set of up to about
#: 130 000 epochs (22 minutes at 100 Hz).
HELD_BYTES = 32 * 2**20
#: Bytes an epoch of a set's prepared arrays (``PreparedLog``: the reading, the field in two frames, its rate and
#: acceleration, the attitude matrix, the heading axis, the statuses), and 8 more for each auxiliary column.
PREPARED_BYTES = 250
#: The arrays of an ``EpochData`` read a chunk at a time.
EPOCH_ARRAYS = ("field_body", "field_ned", "mag", "c_nb", "field_body_rate", "field_body_accel")


class PreparedRows:
    """The epochs ``index`` (n,) (positions in ``log``, increasing) of a log, prepared a chunk at a time when read.

    Parameters
    ----------
    log : DriveLog
        The log (held, not copied).
    ref : ndarray or IgrfTrack
        (N, 3) NED nT the log's reference field (``PreparedLog.ref``), or what makes it for the rows read
        (``prepare.reference_track``: a few numbers a knot); held.
    index : ndarray
        (n,) int the epochs of the set, positions in ``log``, increasing.
    m : ndarray or None
        (n, 3) nT readings to use instead of the log's (``EpochSet.less``); None: the log's.
    """

    def __init__(self, log: DriveLog, ref: np.ndarray, index, m=None, _columns=None):
        self.log, self.ref, self.m = log, ref, m
        self.index = np.asarray(index, np.int64)
        if len(self.index) > 1 and np.any(np.diff(self.index) <= 0):
            raise ValueError("the epochs of a PreparedRows set must be increasing positions in the log")
        self.columns = tuple(log.auxiliary)
        if _columns is None:  # the log's columns as arrays (views of the table's float64 blocks), and its times
            table = log.table
            arrays = {c: table[c].to_numpy(dtype=float) for c in (*MAG, *ATTITUDE, *self.columns) if c in table}
            _columns = (arrays, table.index.to_numpy(dtype=float))
        self.arrays, self.log_time = _columns
        self.time = self.log_time[self.index]
        # what the chunks read of the set: they hold it and not the set, whose cache holds them, so that a set let
        # go is freed at once with its chunks rather than by the cycle collector later (a diagnosis's trials let
        # go sets of a few chunks each, 24 MB on the hour's log)
        self._source = _Source(self.index, self.time, self.log_time, self.arrays, self.m, self.ref, self.columns)
        self.held = len(self.index) * (PREPARED_BYTES + 8 * len(self.columns)) <= HELD_BYTES
        self._whole = None  # a held set's chunk of every epoch, made at the first read
        self._kept: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.index)

    def subset(self, keep) -> PreparedRows:
        """The epochs ``keep`` (mask or increasing index) of this set."""
        m = None if self.m is None else self.m[keep]
        return PreparedRows(self.log, self.ref, self.index[keep], m, (self.arrays, self.log_time))

    def less(self, terms: np.ndarray) -> PreparedRows:
        """The same epochs with ``terms`` (n, 3) nT taken off the readings."""
        m = self.whole("m") - terms
        return PreparedRows(self.log, self.ref, self.index, m, (self.arrays, self.log_time))

    def chunk(self, start: int, stop: int) -> Chunk:
        """The set's epochs ``start`` to ``stop`` (a ``Chunk``): of a set ``held`` (its prepared arrays within
        ``HELD_BYTES``), a part of the chunk of every epoch, made at the first read and kept; else made from the
        log, the last ``KEPT_CHUNKS`` read kept."""
        if self.held:
            with self._lock:
                if self._whole is None:
                    self._whole = Chunk(self._source, 0, len(self))
            return self._whole.part(start, stop)
        key = (start, stop)
        with self._lock:
            if key in self._kept:
                self._kept.move_to_end(key)
                return self._kept[key]
        made = Chunk(self._source, start, stop)
        with self._lock:
            self._kept[key] = made
            while len(self._kept) > KEPT_CHUNKS:
                self._kept.popitem(last=False)
        return made

    def values(self, name: str, start: int, stop: int, column: bool = False) -> np.ndarray:
        """The array ``name`` (``Chunk.get``; ``column``: the log's auxiliary column of that name) of the epochs
        ``start`` to ``stop`` (of a set not held, more than ``CHUNK`` of them: made ``CHUNK`` at a time)."""
        if not self.held and stop - start > CHUNK:
            parts = [self.values(name, a, min(a + CHUNK, stop), column) for a in range(start, stop, CHUNK)]
            return np.concatenate(parts)
        return self.chunk(start, stop).get(name, column)

    def whole(self, name: str, column: bool = False) -> np.ndarray:
        """The array ``name`` (as ``values``) of every epoch of the set."""
        return self.values(name, 0, len(self), column)

    def array(self, name: str, column: bool = False) -> ChunkedArray:
        """The array ``name`` (as ``values``), read a chunk at a time."""
        return ChunkedArray(self, name, column)

    def data(self, R0=None) -> LazyEpochData:
        """The set's ``EpochData``, read a chunk at a time, with the calibration ``R0`` (3, 3) (None: the
        identity)."""
        return LazyEpochData(self, np.eye(3) if R0 is None else R0)


def _runs(rows: np.ndarray) -> list:
    """``(first, last)`` positions in ``rows`` (increasing log rows) of its runs: rows whose windows of ``MARGIN``
    rows either side touch or overlap, so that each run is prepared over one stretch of the log."""
    if not len(rows):
        return []
    cuts = np.flatnonzero(np.diff(rows) > 2 * MARGIN + 1) + 1
    edges = np.r_[0, cuts, len(rows)]
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


@dataclass(frozen=True)
class _Source:
    """What a ``Chunk`` reads of its ``PreparedRows`` set (the set's attributes of the same names)."""

    index: np.ndarray
    time: np.ndarray
    log_time: np.ndarray
    arrays: dict
    m: np.ndarray | None
    ref: object
    columns: tuple


class Chunk:
    """The epochs ``start`` to ``stop`` of a ``PreparedRows`` set (read through its ``_Source``), each array made
    when it is first read and kept (``get``, read-only): the log's columns read at the epochs; the attitude
    matrices, the body-frame field, the heading axis and the field's rates by ``prepare``'s rules
    (``prepare.body_arrays``, ``prepare.field_rates``) on the log's rows from each run of epochs' first to its last
    with ``MARGIN`` rows either side (a sparse set is not prepared over the rows between its runs), then taken at
    the epochs. An array no pass reads (the field's rates, where no effect uses them) is not made."""

    def __init__(self, rows: _Source, start: int, stop: int):
        self.rows, self.start, self.stop, self._parent = rows, start, stop, None
        self._made: dict = {}
        at = rows.index[start:stop]
        self.segments = []  # (lo, hi, take): a stretch of the log's rows and the epochs' positions in it
        for a, b in _runs(at):
            lo, hi = max(int(at[a]) - MARGIN, 0), min(int(at[b - 1]) + MARGIN + 1, len(rows.log_time))
            self.segments.append((lo, hi, _positions(at[a:b] - lo)))

    def __len__(self) -> int:
        return self.stop - self.start

    def part(self, start: int, stop: int) -> Chunk:
        """The epochs ``start`` to ``stop`` of this chunk's set (within this chunk), their arrays views of its."""
        out = Chunk.__new__(Chunk)
        out.rows, out.start, out.stop, out._parent, out._made, out.segments = self.rows, start, stop, self, {}, []
        return out

    def get(self, name: str, column: bool = False) -> np.ndarray:
        """The array ``name`` at the chunk's epochs (read-only): ``time``, ``m`` (the readings used), ``heading``
        (the heading axis) or an ``EpochData`` array (``EPOCH_ARRAYS``); with ``column``, the log's auxiliary
        column ``name``."""
        if self._parent is not None:
            offset = self.start - self._parent.start
            return self._parent.get(name, column)[offset : offset + len(self)]
        key = (column, name)
        if key not in self._made:
            values = self._make(name, column)
            values.flags.writeable = False
            self._made[key] = values
        return self._made[key]

    def _make(self, name: str, column: bool) -> np.ndarray:
        rows, epochs = self.rows, slice(self.start, self.stop)
        if column:
            return rows.arrays[name][_positions(rows.index[epochs])]
        if name == "time":
            return rows.time[epochs]
        if name == "m":
            return self.get("mag") if rows.m is None else rows.m[epochs]
        at = _positions(rows.index[epochs])
        if name == "mag":
            return np.column_stack([rows.arrays[c][at] for c in MAG])
        parts = [self._window(k, name)[take] for k, (_, _, take) in enumerate(self.segments)]
        if len(parts) == 1:
            return parts[0]
        return np.concatenate(parts) if parts else self._empty(name)

    def _empty(self, name: str) -> np.ndarray:
        return np.empty((0, 3, 3) if name == "c_nb" else (0, 3))

    def _window(self, k: int, name: str) -> np.ndarray:
        """The array ``name`` over the log's rows of segment ``k``: made once with the others of its rule."""
        key = ("window", k, name)
        if key not in self._made:
            from .prepare import body_arrays, field_rates

            lo, hi, _ = self.segments[k]
            rows = self.rows
            if name == "field_ned":  # the reference field: made once for the window, whence its epochs' and the rest
                self._made[key] = rows.ref[lo:hi]
            elif name in ("field_body_rate", "field_body_accel"):
                rates = field_rates(rows.log_time[lo:hi], self._window(k, "field_body"))
                for part, values in zip(("field_body_rate", "field_body_accel"), rates):
                    self._made[("window", k, part)] = values
            else:  # the attitude matrices, the body-frame field and the heading axis
                if all(c in rows.arrays for c in ATTITUDE):
                    attitude = np.column_stack([rows.arrays[c][lo:hi] for c in ATTITUDE])
                else:
                    attitude = np.full((hi - lo, 3), np.nan)
                ref = self._window(k, "field_ned")
                for part, values in zip(("c_nb", "field_body", "heading"), body_arrays(attitude, ref)):
                    self._made[("window", k, part)] = values
        return self._made[key]

    def data(self, R0: np.ndarray) -> ChunkData:
        """The chunk's ``EpochData`` with the calibration ``R0`` (3, 3), its arrays made when read."""
        return ChunkData(self, R0)


def _positions(at: np.ndarray):
    """``at`` (increasing integers) as a slice where they follow one another (views rather than copies)."""
    if len(at) and at[-1] - at[0] == len(at) - 1:
        return slice(int(at[0]), int(at[-1]) + 1)
    return at


class ChunkData:
    """The ``EpochData`` of a ``Chunk``: ``time``, ``columns`` and the arrays of ``EPOCH_ARRAYS`` are the chunk's
    (numpy arrays, made when first read), ``R0`` the calibration; ``take`` gives an ``EpochData``."""

    def __init__(self, chunk: Chunk, R0: np.ndarray):
        self.chunk, self.R0 = chunk, R0

    def __len__(self) -> int:
        return len(self.chunk)

    @property
    def columns(self) -> dict:
        return {c: self.chunk.get(c, column=True) for c in self.chunk.rows.columns}

    def __getattr__(self, name: str):
        if name == "time" or name in EPOCH_ARRAYS:
            return self.chunk.get(name)
        raise AttributeError(name)

    def take(self, index) -> EpochData:
        """The ``EpochData`` of the chunk's epochs ``index`` (None: all)."""
        data = EpochData(
            self.time, self.field_body, self.field_ned, self.columns, self.mag, self.c_nb, self.field_body_rate,
            self.R0, self.field_body_accel,
        )  # fmt: skip
        return data.take(index)


class ChunkedArray(np.lib.mixins.NDArrayOperatorsMixin):
    """A per-epoch array (n, ...) of a ``PreparedRows`` set, read a chunk at a time: a slice of consecutive epochs
    (``a[i:j]``, or ``a[i:j, ...]``) is made from the chunk prepared for them; anything else (an index array, a
    mask, ``np.asarray(a)``, arithmetic, an attribute of the array such as ``a.T``) from the whole array, made for
    the use and not kept."""

    def __init__(self, rows: PreparedRows, name: str, column: bool = False):
        self.rows, self.name, self.column = rows, name, column

    def __len__(self) -> int:
        return len(self.rows)

    def _first(self) -> np.ndarray:
        return self.rows.values(self.name, 0, min(1, len(self.rows)), self.column)

    @property
    def shape(self) -> tuple:
        return (len(self.rows), *self._first().shape[1:])

    @property
    def ndim(self) -> int:
        return self._first().ndim

    @property
    def dtype(self):
        return self._first().dtype

    def __getitem__(self, key):
        first, rest = (key[0], key[1:]) if isinstance(key, tuple) and key else (key, ())
        if isinstance(first, slice):
            start, stop, step = first.indices(len(self))
            if step == 1:
                values = self.rows.values(self.name, start, max(start, stop), self.column)
                return values[(slice(None), *rest)] if rest else values
        return np.asarray(self)[key]

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(np.asarray(self), name)

    def __array__(self, dtype=None, copy=None):
        whole = self.rows.whole(self.name, self.column)
        if copy:
            return np.array(whole, dtype=dtype, copy=True)
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        inputs = tuple(np.asarray(v) if isinstance(v, ChunkedArray) else v for v in inputs)
        return getattr(ufunc, method)(*inputs, **kwargs)


@dataclass(frozen=True)
class LazyEpochData:
    """The ``EpochData`` of a ``PreparedRows`` set, its per-epoch arrays read a chunk at a time (``ChunkedArray``);
    ``time`` (n,) UNIX s is held. ``take(rows)`` gives the data of the epochs ``rows`` (an effect computed epoch by
    epoch reads it)."""

    rows: PreparedRows
    R0: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def time(self) -> np.ndarray:
        return self.rows.time

    @property
    def columns(self) -> dict:
        return {name: self.rows.array(name, column=True) for name in self.rows.columns}

    def __getattr__(self, name: str):
        if name in EPOCH_ARRAYS:
            return self.rows.array(name)
        raise AttributeError(name)

    def take(self, index):
        """The data of the epochs ``index``: of a slice of consecutive epochs, the ``ChunkData`` of their chunk
        (its arrays made when read); of an integer array or a mask (None: all), an ``EpochData``."""
        if isinstance(index, slice) and index.indices(len(self))[2] == 1:
            a, b, _ = index.indices(len(self))
            return self.rows.chunk(a, max(a, b)).data(self.R0)
        chosen = np.arange(len(self))[slice(None) if index is None else index]
        return EpochData(
            self.time[chosen],
            *(self.rows.whole(f)[chosen] for f in ("field_body", "field_ned")),
            {c: self.rows.whole(c, column=True)[chosen] for c in self.rows.columns},
            *(self.rows.whole(f)[chosen] for f in ("mag", "c_nb", "field_body_rate")),
            self.R0,
            self.rows.whole("field_body_accel")[chosen],
        )
