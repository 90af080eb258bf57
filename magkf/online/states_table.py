"""The per-epoch table of a run (``CalibrationRun.states``), kept as what it is made of and built when read.

Within a filter block every epoch has the block's state and standard deviations (smoothed or not), and the
noise learned up to the block's end. The table keeps them once a block, with the blocks' ends, and per epoch
only what differs from one epoch to the next: the status (int8), the update flag, the NIS and the residuals
before the epoch (float32). That is 22 bytes an epoch, and ``8 n + 24`` bytes a block for ``n`` states
(float32 states and standard deviations, the block's end, the learned noise), where the whole table of a run
with the 12 states of ``R`` and ``b`` is about 140 bytes an epoch.

A column (``table["b_x"]``), a few columns (``table[["b_x", "b_y"]]``) or a stretch of rows
(``table.iloc[a:b]``, ``table.frame(rows)``) is built when asked for, with exactly the values and types the
whole table has (``states_frame``); ``write_drive_log(table, path)`` writes it a stretch of rows at a time.
The whole DataFrame is built by ``frame()``; a pandas method the table does not have itself (``loc``,
``describe``, ...) builds it once and keeps it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..status import STATUS_NAMES, status_names

__all__ = ["NOISE_COLUMNS", "RESIDUAL_COLUMNS", "StatesTable", "states_frame", "status_codes"]

#: Names of the learned-noise columns of the per-epoch table.
NOISE_COLUMNS = ("noise_sensor_nt", "noise_attitude_deg", "noise_heading_deg", "noise_inflation")
#: Names of the residual columns (before each epoch: north, east, down, magnitude; nT).
RESIDUAL_COLUMNS = ("residual_n", "residual_e", "residual_d", "residual_mag")


def states_frame(index, names, status, updated, nis, xs, stds, residuals, noise=None) -> pd.DataFrame:
    """The per-epoch table (see ``CalibrationRun.states``) of the epochs ``index``: ``residuals`` (k, 4) before each
    epoch (north, east, down, magnitude; nT); ``noise`` (k, 4) the learned noise after each epoch's block (None: no
    such columns). Float32 arrays are taken as they are, without a copy."""
    frames = [
        pd.DataFrame({"status": status_names(status), "updated": updated, "nis": nis.astype(np.float32)}, index=index),
        pd.DataFrame(xs, columns=names, index=index, copy=False),
        pd.DataFrame(stds, columns=[f"std_{name}" for name in names], index=index, copy=False),
        pd.DataFrame(residuals.astype(np.float32, copy=False), columns=RESIDUAL_COLUMNS, index=index, copy=False),
    ]
    if noise is not None:
        frames.append(
            pd.DataFrame(noise.astype(np.float32, copy=False), columns=NOISE_COLUMNS, index=index, copy=False)
        )
    return pd.concat(frames, axis=1)


def _status_array(codes):
    """The names of the status codes ``codes`` (k,) as the string array a DataFrame column of them holds (taken
    from the names' own array: no Python string a value)."""
    names = pd.Series(list(STATUS_NAMES)).array  # the string type pandas gives a column of names
    return names.take(np.asarray(codes, np.intp))


def status_codes(states) -> np.ndarray:
    """(N,) int8 the epochs' status codes (positions in ``STATUS_NAMES``) of a run's per-epoch table ``states``: a
    ``StatesTable``'s own array (not a copy: a column of names made into a ``pandas.Categorical`` costs tens of
    bytes an epoch while it is made), or those of a DataFrame's ``status`` column of names (-1: not a status)."""
    if isinstance(states, StatesTable):
        return states.codes
    return pd.Index(STATUS_NAMES).get_indexer(states["status"]).astype(np.int8)  # -1: not a status


class StatesTable:
    """The per-epoch table of a run, built from its blocks when read (see the module's docstring).

    Parameters
    ----------
    index : pandas.Index
        (N,) the epochs' times (the log's index).
    names : list of str
        (n,) the state names.
    status : numpy.ndarray
        (N,) int8 status codes (``magkf.status.Status``).
    updated : numpy.ndarray
        (N,) bool, whether the epoch updated the estimate.
    nis : numpy.ndarray
        (N,) normalised innovation squared (kept as float32, as the table gives it).
    block_xs, block_stds : numpy.ndarray
        (K, n) the state and its standard deviations after each block (kept as float32, as the table gives them).
    stops : numpy.ndarray or None
        (K,) one past the last epoch of each block (None: one block per epoch).
    residuals : numpy.ndarray
        (N, 4) float32 residuals before each epoch: north, east, down (NED) and magnitude, nT.
    noise : numpy.ndarray or None, optional
        (K, 4) the noise learned after each block (sensor nT, tilt deg, heading deg, inflation; kept as float32),
        or None for a run without such columns.
    """

    def __init__(self, index, names, status, updated, nis, block_xs, block_stds, stops, residuals, noise=None):
        self.index = index
        self.names = list(names)
        self._status = np.asarray(status, np.int8)
        self._updated = np.asarray(updated, bool)
        self._nis = np.asarray(nis, np.float32)
        self._xs = np.asarray(block_xs, np.float32)
        self._stds = np.asarray(block_stds, np.float32)
        self._stops = None if stops is None else np.asarray(stops, np.int64)
        self._residuals = np.asarray(residuals, np.float32)
        self._noise = None if noise is None else np.asarray(noise, np.float32)
        self._whole = None
        # every column: (where its values are, which column of it)
        sources = {"status": ("status", 0), "updated": ("updated", 0), "nis": ("nis", 0)}
        sources |= {name: ("xs", j) for j, name in enumerate(self.names)}
        sources |= {f"std_{name}": ("stds", j) for j, name in enumerate(self.names)}
        sources |= {name: ("residuals", j) for j, name in enumerate(RESIDUAL_COLUMNS)}
        if self._noise is not None:
            sources |= {name: ("noise", j) for j, name in enumerate(NOISE_COLUMNS)}
        self._sources = sources
        self.columns = pd.Index(list(sources))

    def __len__(self) -> int:
        return len(self._status)

    def __contains__(self, name) -> bool:
        return name in self._sources

    @property
    def codes(self) -> np.ndarray:
        """(N,) int8 the status codes (positions in ``STATUS_NAMES``), the array the table holds (read only)."""
        codes = self._status.view()
        codes.flags.writeable = False
        return codes

    def __iter__(self):
        return iter(self.columns)

    @property
    def shape(self) -> tuple[int, int]:
        """(N, number of columns), as the DataFrame's."""
        return len(self), len(self.columns)

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays the table keeps (its index, shared with the log, not counted)."""
        held = (self._status, self._updated, self._nis, self._xs, self._stds, self._residuals)
        extra = [a for a in (self._stops, self._noise) if a is not None]
        return int(sum(a.nbytes for a in (*held, *extra)))

    def blocks(self, rows=None) -> np.ndarray:
        """The block of each of the epochs ``rows`` (a slice, integer positions or a mask; None: every epoch)."""
        positions = np.arange(len(self))
        if rows is not None:
            positions = positions[rows]
        if self._stops is None:
            return positions
        return np.searchsorted(self._stops, positions, side="right")

    def _per_block(self, values, rows):
        """``values`` (K, ...) of every epoch of ``rows`` (None: every epoch, by repeating each block's)."""
        if rows is None:
            if self._stops is None:
                return values
            return np.repeat(values, np.diff(self._stops, prepend=0), axis=0)
        return values[self.blocks(rows)]

    def column_values(self, name: str, rows=None) -> np.ndarray:
        """The values (k,) of the column ``name`` at the epochs ``rows`` (None: every epoch): the status as a string
        array of names (as the DataFrame's column holds it), the others as the table holds them (bool, float32)."""
        if name not in self._sources:
            raise KeyError(name)
        kind, j = self._sources[name]
        per_epoch = {"status": self._status, "updated": self._updated, "nis": self._nis}
        if kind in per_epoch:
            values = per_epoch[kind] if rows is None else per_epoch[kind][rows]
            return _status_array(values) if kind == "status" else values
        if kind == "residuals":
            return self._residuals[:, j] if rows is None else self._residuals[rows, j]
        by_block = {"xs": self._xs, "stds": self._stds, "noise": self._noise}[kind]
        return self._per_block(by_block[:, j], rows)

    def frame(self, rows=None, columns=None) -> pd.DataFrame:
        """The DataFrame of the epochs ``rows`` (a slice, integer positions or a mask; None: every epoch) with every
        column, or with the columns ``columns`` (a list of names) in that order."""
        index = self.index if rows is None else self.index[rows]
        if columns is not None:
            return pd.DataFrame({name: self.column_values(name, rows) for name in columns}, index=index)
        pick = slice(None) if rows is None else rows
        blocks = None if rows is None and self._stops is None else self.blocks(rows)
        xs, stds, noise = self._xs, self._stds, self._noise
        if blocks is not None:
            xs, stds, noise = xs[blocks], stds[blocks], (None if noise is None else noise[blocks])
        return states_frame(
            index, self.names, self._status[pick], self._updated[pick], self._nis[pick], xs, stds,
            self._residuals[pick], noise,
        )  # fmt: skip

    def pieces(self, rows: int = 16_384):
        """The whole table as consecutive DataFrames of at most ``rows`` epochs (at least one, maybe empty)."""
        for start in range(0, max(len(self), 1), rows):
            yield self.frame(slice(start, start + rows))

    def __getitem__(self, key):
        """A column as a Series (``table["b_x"]``), columns as a DataFrame (``table[["b_x", "b_y"]]``); any other
        key as the whole DataFrame takes it."""
        if isinstance(key, str):
            return pd.Series(self.column_values(key), index=self.index, name=key, copy=False)
        if isinstance(key, (list, pd.Index)) and all(isinstance(k, str) for k in key):
            return self.frame(columns=list(key))
        return self.whole()[key]

    @property
    def iloc(self) -> _Rows:
        """Rows by position, as ``DataFrame.iloc`` gives them, built for those rows only."""
        return _Rows(self)

    def whole(self) -> pd.DataFrame:
        """The whole DataFrame, built once and kept (what pandas methods the table does not have go to)."""
        if self._whole is None:
            self._whole = self.frame()
        return self._whole

    @property
    def values(self) -> np.ndarray:
        """The whole table's values, as ``DataFrame.values`` (builds the whole table)."""
        return self.whole().values

    def to_numpy(self, *args, **kwargs) -> np.ndarray:
        """As ``DataFrame.to_numpy`` (builds the whole table)."""
        return self.whole().to_numpy(*args, **kwargs)

    def __array__(self, dtype=None, copy=None):
        """``numpy.asarray(table)``: the whole table's values, as for a DataFrame."""
        values = self.whole().to_numpy()
        return values if dtype is None else values.astype(dtype)

    def __getattr__(self, name: str):
        if name.startswith("_"):  # not built for private names (copies and pickles look for them)
            raise AttributeError(name)
        if name in self._sources:
            return self[name]
        return getattr(self.whole(), name)

    def __repr__(self) -> str:
        return f"StatesTable({len(self)} epochs, {len(self.columns)} columns, {self.nbytes} bytes held)"


class _Rows:
    """``StatesTable.iloc``: rows by position (an integer, a slice, positions or a mask; or ``(rows, columns)``)."""

    def __init__(self, table: StatesTable):
        self.table = table

    def __getitem__(self, key):
        if isinstance(key, tuple):
            rows, columns = key
            return self[rows].iloc[columns] if isinstance(rows, (int, np.integer)) else self[rows].iloc[:, columns]
        if isinstance(key, (int, np.integer)):
            position = int(key) + (len(self.table) if key < 0 else 0)
            if not 0 <= position < len(self.table):
                raise IndexError("single positional indexer is out-of-bounds")
            return self.table.frame([position]).iloc[0]
        return self.table.frame(key)
