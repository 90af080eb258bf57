"""A set of a log's epochs prepared a chunk at a time when read, rather than held prepared.

``prepare`` gives every epoch's arrays at once: about 250 bytes an epoch (the attitude matrix, the field in two
frames, its rate and acceleration, the heading axis). A diagnosis reads its epochs a chunk at a time on each pass,
so ``PreparedRows`` holds only where its epochs are in the log, their times and the log's reference field (40
bytes an epoch), and prepares the epochs of a chunk again from the log when they are read, by ``prepare``'s own
rules (``prepare_arrays``) on the chunk's rows of the log with ``MARGIN`` rows either side, so that the rates by
central differences are the whole log's to the last bit.

``LazyEpochData`` is the ``EpochData`` of such a set: its per-epoch arrays are ``ChunkedArray`` s, which give the
chunk's values for a slice of consecutive epochs (``a[i:j]``, what the effects read with ``rows``) and the whole
array for anything else (``np.asarray(a)``, an index array, arithmetic): right in every use, held whole only
where a use asks for all of it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from ..config import FilterConfig
from ..conventions import ATTITUDE, MAG
from ..effects.base import EpochData
from ..io.drivelog import DriveLog
from ..status import DOP_ORDER, select_dop
from .determined import CHUNK

__all__ = ["MARGIN", "PreparedRows", "LazyEpochData", "ChunkedArray"]

#: Rows of the log prepared on either side of a chunk's: the field's acceleration at an epoch reads its rate two
#: rows away, whose central difference reads the field one row further (``effects.base.rate_of_change``).
MARGIN = 3
#: Chunks kept prepared (the last read): a pass reads several arrays of the same chunk in turn.
KEPT_CHUNKS = 4
#: The arrays of an ``EpochData`` read a chunk at a time.
EPOCH_ARRAYS = ("field_body", "field_ned", "mag", "c_nb", "field_body_rate", "field_body_accel")


class PreparedRows:
    """The epochs ``index`` (n,) (positions in ``log``, increasing) of a log, prepared a chunk at a time when read.

    Parameters
    ----------
    log : DriveLog
        The log (held, not copied).
    ref : ndarray
        (N, 3) NED nT the log's reference field (``PreparedLog.ref``; held).
    index : ndarray
        (n,) int the epochs of the set, positions in ``log``, increasing.
    config : FilterConfig
        Gives ``prepare``'s rules their settings.
    m : ndarray or None
        (n, 3) nT readings to use instead of the log's (``EpochSet.less``); None: the log's.
    """

    def __init__(self, log: DriveLog, ref: np.ndarray, index, config: FilterConfig, m=None):
        self.log, self.ref, self.config, self.m = log, ref, config, m
        self.index = np.asarray(index, np.int64)
        self.time = log.time[self.index]
        self.columns = tuple(log.auxiliary)
        # the log's columns as arrays (views of the table's float blocks: nothing copied), cut for each chunk
        table = log.table
        self._arrays = {
            c: table[c].to_numpy(dtype=float) for c in (*MAG, *ATTITUDE, *self.columns, *DOP_ORDER) if c in table
        }
        self._log_time = table.index.to_numpy(dtype=float)
        self._kept: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.index)

    def subset(self, keep) -> PreparedRows:
        """The epochs ``keep`` (mask or index) of this set."""
        return PreparedRows(self.log, self.ref, self.index[keep], self.config, None if self.m is None else self.m[keep])

    def less(self, terms: np.ndarray) -> PreparedRows:
        """The same epochs with ``terms`` (n, 3) nT taken off the readings."""
        m = np.concatenate([self.chunk(a, min(a + CHUNK, len(self))).m for a in range(0, len(self), CHUNK)])
        return PreparedRows(self.log, self.ref, self.index, self.config, m - terms)

    def chunk(self, start: int, stop: int):
        """The ``PreparedLog`` of the set's epochs ``start`` to ``stop`` (its ``m`` the readings used), prepared
        from the log's rows from the first's to the last's with ``MARGIN`` rows either side; the last
        ``KEPT_CHUNKS`` read are kept."""
        key = (start, stop)
        with self._lock:
            if key in self._kept:
                self._kept.move_to_end(key)
                return self._kept[key]
        prepared = self._prepared(start, stop)
        with self._lock:
            self._kept[key] = prepared
            while len(self._kept) > KEPT_CHUNKS:
                self._kept.popitem(last=False)
        return prepared

    def _prepared(self, start: int, stop: int):
        from .prepare import prepare_arrays

        rows = self.index[start:stop]
        if not len(rows):
            rows = self.index[:1]  # an empty chunk: the arrays' shapes from one epoch, none of its values
        lo, hi = max(int(rows[0]) - MARGIN, 0), min(int(rows[-1]) + MARGIN + 1, len(self.log))
        cut = {c: v[lo:hi] for c, v in self._arrays.items()}
        m = np.column_stack([cut[c] for c in MAG])
        attitude = np.column_stack([cut[c] for c in ATTITUDE]) if all(c in cut for c in ATTITUDE) else None
        if attitude is None:
            attitude = np.full((hi - lo, 3), np.nan)
        dop = select_dop(cut)
        dop = np.full(hi - lo, np.nan) if dop is None else dop
        columns = {c: cut[c] for c in self.columns}
        prep = prepare_arrays(self._log_time[lo:hi], m, self.ref[lo:hi], attitude, dop, columns, self.config)
        at = rows[: stop - start] - lo
        consecutive = len(at) and at[-1] - at[0] == len(at) - 1  # views rather than copies
        prep = prep.take(slice(int(at[0]), int(at[-1]) + 1) if consecutive else at)
        if self.m is not None:
            prep = type(prep)(self.m[start:stop], *(getattr(prep, f) for f in _PREPARED_AFTER_M))
        return prep

    def values(self, name: str, start: int, stop: int) -> np.ndarray:
        """The array ``name`` (an ``EpochData`` array, ``"m"``, ``"heading"`` or an auxiliary column) of the
        epochs ``start`` to ``stop`` (more than ``CHUNK`` of them: made ``CHUNK`` at a time)."""
        if stop - start > CHUNK:
            return np.concatenate([self.values(name, a, min(a + CHUNK, stop)) for a in range(start, stop, CHUNK)])
        prep = self.chunk(start, stop)
        if name in ("m", "heading"):
            return getattr(prep, name)
        if name in EPOCH_ARRAYS:
            return getattr(prep.data, name)
        return prep.data.columns[name]

    def whole(self, name: str) -> np.ndarray:
        """The array ``name`` (as ``values``) of every epoch of the set, made a chunk at a time."""
        return self.values(name, 0, len(self))

    def array(self, name: str) -> ChunkedArray:
        """The array ``name`` (as ``values``), read a chunk at a time."""
        return ChunkedArray(self, name)

    def data(self, R0=None) -> LazyEpochData:
        """The set's ``EpochData``, read a chunk at a time, with the calibration ``R0`` (3, 3) (None: the
        identity)."""
        return LazyEpochData(self, np.eye(3) if R0 is None else R0)


_PREPARED_AFTER_M = ("ref", "ref_mag", "c_nb", "has_attitude", "dop", "base", "data", "heading")


class ChunkedArray(np.lib.mixins.NDArrayOperatorsMixin):
    """A per-epoch array (n, ...) of a ``PreparedRows`` set, read a chunk at a time: a slice of consecutive epochs
    (``a[i:j]``, or ``a[i:j, ...]``) is made from the chunk prepared for them; anything else (an index array, a
    mask, ``np.asarray(a)``, arithmetic) from the whole array, made for the use and not kept."""

    def __init__(self, rows: PreparedRows, name: str):
        self.rows, self.name = rows, name

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def shape(self) -> tuple:
        return (len(self.rows), *self.rows.values(self.name, 0, min(1, len(self.rows))).shape[1:])

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def dtype(self):
        return self.rows.values(self.name, 0, min(1, len(self.rows))).dtype

    def __getitem__(self, key):
        first, rest = (key[0], key[1:]) if isinstance(key, tuple) and key else (key, ())
        if isinstance(first, slice):
            start, stop, step = first.indices(len(self))
            if step == 1:
                values = self.rows.values(self.name, start, max(start, stop))
                return values[(slice(None), *rest)] if rest else values
        return np.asarray(self)[key]

    def __array__(self, dtype=None, copy=None):
        whole = self.rows.whole(self.name)
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        inputs = tuple(np.asarray(v) if isinstance(v, ChunkedArray) else v for v in inputs)
        return getattr(ufunc, method)(*inputs, **kwargs)


@dataclass(frozen=True)
class LazyEpochData:
    """The ``EpochData`` of a ``PreparedRows`` set, its per-epoch arrays read a chunk at a time (``ChunkedArray``);
    ``time`` (n,) UNIX s is held. ``take(rows)`` gives the ``EpochData`` of the epochs ``rows`` (an effect computed
    epoch by epoch reads it)."""

    rows: PreparedRows
    R0: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def time(self) -> np.ndarray:
        return self.rows.time

    @property
    def columns(self) -> dict:
        return {name: self.rows.array(name) for name in self.rows.columns}

    def __getattr__(self, name: str):
        if name in EPOCH_ARRAYS:
            return self.rows.array(name)
        raise AttributeError(name)

    def take(self, index) -> EpochData:
        """The ``EpochData`` of the epochs ``index`` (a slice, an integer array or a mask; None: all)."""
        if isinstance(index, slice) and index.indices(len(self))[2] == 1:
            a, b, _ = index.indices(len(self))
            data = self.rows.chunk(a, max(a, b)).data
            return EpochData(**{**{f: getattr(data, f) for f in data.__dataclass_fields__}, "R0": self.R0})
        chosen = np.arange(len(self))[slice(None) if index is None else index]
        return EpochData(
            self.time[chosen],
            *(np.asarray(self.rows.array(f))[chosen] for f in ("field_body", "field_ned")),
            {c: np.asarray(self.rows.array(c))[chosen] for c in self.rows.columns},
            *(np.asarray(self.rows.array(f))[chosen] for f in ("mag", "c_nb", "field_body_rate")),
            self.R0,
            np.asarray(self.rows.array("field_body_accel"))[chosen],
        )
