"""Validated reading of the numeric CSV files in the data contract.

Every check names the file, the row (the line number in the file, header = row 1) and the column.
An empty cell is a missing value (NaN); any other cell must be a finite number.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pandas as pd

from ..allocator import release_free_memory
from ..errors import InputError

__all__ = [
    "HEADER_ROWS",
    "PARQUET_SUFFIXES",
    "file_row",
    "table_rows",
    "read_csv",
    "csv_chunks",
    "parquet_chunks",
    "read_parquet",
    "record_lines",
    "RecordLines",
    "checked_table",
    "numeric_column",
    "require_complete",
    "require_rows",
]

HEADER_ROWS = 1
#: File endings of Parquet tables, read wherever a CSV is.
PARQUET_SUFFIXES = (".parquet", ".pq")


def file_row(index: int) -> int:
    """The file line number of data row ``index`` (0-based), counting the header as row 1."""
    return int(index) + HEADER_ROWS + 1


def table_rows(table: pd.DataFrame):
    """``row_of(i)``, the file row of data row ``i`` of a table ``read_csv`` read: its line number, blank lines
    counted (kept in ``table.attrs["rows"]`` when the file has blank lines between records), else ``file_row``."""
    rows = table.attrs.get("rows")
    return file_row if rows is None else (lambda i: int(rows[i]))


def read_csv(path, required: Iterable[str] = (), text_columns: Iterable[str] = ()) -> pd.DataFrame:
    """Read a comma-separated file into a DataFrame of floats (text columns kept as text).

    Parameters
    ----------
    path : str or Path
        The file.
    required : column names that must be present.
    text_columns : columns that hold text (for example ``plane``) and are not converted.

    Raises
    ------
    InputError
        Missing file, missing or duplicated column, non-numeric or non-finite cell, no data rows. The file is
        converted ``READ_ROWS`` records at a time, and the cell named is the first bad one of the first chunk
        that has one (in that chunk, column by column).
    """
    path = Path(path)
    name = str(path)
    if path.suffix.lower() in PARQUET_SUFFIXES:  # the Parquet twin of a CSV file is read alike
        return read_parquet(path, required, text_columns)
    _check_is_file(path, name)
    required, text_columns = tuple(required), tuple(text_columns)
    lines = record_lines(path, name, required)  # the records' lines where blank lines lie among them, else None
    chunks = csv_chunks(path, name, READ_ROWS, required, text_columns, lines)
    table = _joined_chunks(chunks, text_columns, name, "the file has a header but no data rows")
    if lines is not None:
        table.attrs["rows"] = lines.at(np.arange(len(table)))  # blank lines (which pandas skips) among the records
    return table


#: Records ``read_csv`` and ``read_parquet`` convert at a time: the parser's working memory is a chunk's, not the
#: file's (a 24-hour log at 100 Hz, 8.64 million records of 14 columns, peaked at 3.4 GB read whole as CSV for
#: a table of 0.97 GB).
READ_ROWS = 1 << 15


def csv_chunks(path, name: str, rows: int, required=(), text_columns=(), lines=None):
    """The CSV file ``path`` parsed ``rows`` records at a time, each chunk checked as ``checked_table`` checks a
    whole table (InputError naming ``name``, the row and the column), its records' file lines in
    ``attrs["rows"]`` (``lines``, a ``RecordLines``, where blank lines lie among the records; None: every line
    after the header is a record)."""
    try:
        with pd.read_csv(
            path,
            keep_default_na=False,
            na_values=[""],
            skipinitialspace=True,
            dtype={c: str for c in text_columns},
            chunksize=rows,
        ) as chunks:
            offset = 0
            for chunk in chunks:
                index = np.arange(offset, offset + len(chunk))
                chunk.attrs["rows"] = index + HEADER_ROWS + 1 if lines is None else lines.at(index)
                offset += len(chunk)
                yield checked_table(chunk, name, required, text_columns, "the file has a header but no data rows")
    except pd.errors.EmptyDataError:
        raise InputError("the file is empty", name) from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise InputError(f"not a readable CSV file ({' '.join(str(exc).split())})", name) from None


def _joined_chunks(chunks, text_columns, name: str, empty: str) -> pd.DataFrame:
    """One table of the checked ``chunks`` (DataFrames), a column at a time: each chunk's columns copied out (the
    chunk's own block let go), then each column's pieces joined (``_joined``), so that the table's memory is
    held once and one column's twice at most. InputError ``empty`` naming ``name`` where there is no chunk."""
    columns: dict = {}
    for chunk in chunks:
        for column in chunk.columns:
            piece = chunk[column]
            if column in text_columns:  # a Series, which keeps the text's dtype
                piece = piece.reset_index(drop=True)
                piece.attrs = {}  # not the chunk's rows
            else:
                piece = np.array(piece.to_numpy(), copy=True)
            columns.setdefault(column, []).append(piece)
    if not columns:
        raise InputError(empty, name)
    return pd.DataFrame({c: _joined(columns.pop(c)) for c in list(columns)}, copy=False)


def _joined(pieces: list):
    """A column's ``pieces`` (arrays, or Series of text) joined into one; the pieces' memory, freed, is given back
    to the system (``release_free_memory``): a chunk's column (256 KiB) lies under the allocator's mmap threshold,
    and the heap would keep the pieces of every column resident beside the joined table (a 24-hour log at 100 Hz
    peaked at 2.1 GB read, for a table of 0.97 GB)."""
    if len(pieces) == 1:
        return pieces[0]
    joined = pd.concat(pieces, ignore_index=True) if isinstance(pieces[0], pd.Series) else np.concatenate(pieces)
    pieces.clear()
    release_free_memory()
    return joined


def _check_is_file(path: Path, name: str) -> None:
    """InputError naming ``name`` unless ``path`` is a file: a folder is told apart from a missing file."""
    if path.is_dir():
        raise InputError("a folder, not a table file: give the file inside it", name)
    if not path.is_file():
        raise InputError("no such file", name)


def read_parquet(path, required: Iterable[str] = (), text_columns: Iterable[str] = ()) -> pd.DataFrame:
    """Read a Parquet table into a DataFrame of floats, with the checks of ``read_csv``; rows are named as the
    CSV twin's would be (record i is row i + 2, the header being row 1)."""
    path = Path(path)
    name = str(path)
    _check_is_file(path, name)
    required, text_columns = tuple(required), tuple(text_columns)
    chunks = parquet_chunks(path, name, READ_ROWS, required, text_columns)
    return _joined_chunks(chunks, text_columns, name, "the file has no rows")


def parquet_chunks(path, name: str, rows: int, required=(), text_columns=()):
    """The Parquet file ``path`` converted ``rows`` records at a time, each chunk checked as ``checked_table``
    checks a whole table (InputError naming ``name``, the row and the column), its rows named as the CSV twin's
    would be in ``attrs["rows"]`` (record i is row i + 2, the header being row 1). A file without rows is checked
    as an empty table (its columns first)."""
    import pyarrow.parquet as pq

    try:
        # without pre-buffering, which reads ahead and keeps the row groups still to come (on a 4-hour 100 Hz log
        # 225 MB of Arrow buffers at the peak, against 42 MB without)
        file = pq.ParquetFile(path, pre_buffer=False)
        offset = 0
        for batch in file.iter_batches(batch_size=rows):
            chunk = batch.to_pandas()
            chunk.attrs["rows"] = np.arange(offset, offset + len(chunk)) + HEADER_ROWS + 1
            offset += len(chunk)
            yield checked_table(chunk, name, required, text_columns, "the file has no rows")
        if offset == 0:
            checked_table(
                file.schema_arrow.empty_table().to_pandas(), name, required, text_columns, "the file has no rows"
            )
    except InputError:
        raise
    except Exception as exc:  # pyarrow raises several types for a damaged or foreign file
        raise InputError(f"not a readable Parquet file ({' '.join(str(exc).split())[:200]})", name) from None


#: Bytes of a CSV file scanned at a time for its field counts.
SCAN_BYTES = 1 << 22


def _scanned(path: Path, scan) -> bool:
    """Feed the bytes of the file ``path`` to ``scan`` (``_FieldScan``) in pieces of ``SCAN_BYTES``; False (the scan
    stopped) at a quoted field, which is left to the parser."""
    with open(path, "rb") as f:
        while chunk := f.read(SCAN_BYTES):
            while chunk.endswith(b"\r") and (more := f.read(1)):  # a CR LF pair stays in one chunk
                chunk += more
            if b'"' in chunk:
                return False
            scan.add(chunk)
    return True


def _check_header(path: Path, name: str, required) -> int:
    """The number of fields in the header (line 1); InputError naming ``name``, row 1 and the column for a
    column named twice or a ``required`` one missing."""
    import csv

    with open(path, encoding="utf-8-sig", errors="replace", newline="") as f:  # pandas skips a byte-order mark
        line = f.readline()
    if "\x00" in line or "\ufffd" in line:
        raise InputError(
            "binary data, not a text table: a log of another format (give --format), or a MATLAB or other file "
            "to read through a column map (--map, docs/column-maps.md)",
            name,
        )
    header = next(csv.reader([line]), [])
    seen = set()
    for column in (c.strip() for c in header):
        if column in seen:
            raise InputError("the column appears twice in the header", name, 1, column)
        seen.add(column)
    missing = [c for c in required if c not in seen]
    if missing and header:
        raise InputError(f"required column missing (the header has: {', '.join(header)})", name, 1, missing[0])
    return len(header)


def _line_ends(data: np.ndarray, chunk: bytes) -> np.ndarray:
    """Positions of the line ends (LF, CR LF or CR; the LF of a pair) in the bytes ``data`` of ``chunk``."""
    if b"\r" not in chunk:  # LF alone: a third of the cost
        return np.flatnonzero(data == ord("\n"))
    newline = data == ord("\n")
    return np.flatnonzero(newline | (data == ord("\r")) & ~np.r_[newline[1:], False])


class _FieldScan:
    """The fields of every line of a CSV file without quotes, counted by commas chunk by chunk: InputError
    (naming ``name`` and the line) at the first non-blank line after the header with other than ``fields``."""

    def __init__(self, name: str, fields: int):
        self.name, self.fields = name, fields
        #: Lines ended so far, and the commas and bytes of the line running on past the last chunk.
        self.line, self.commas_in_line, self.length_of_line = 0, 0, 0
        #: Line numbers (1-based) of the non-blank lines, one array per chunk.
        self.lines: list[np.ndarray] = []

    def add(self, chunk: bytes) -> None:
        """Count the fields of the lines in the next ``chunk`` of the file."""
        data = np.frombuffer(chunk, dtype=np.uint8)
        ends = _line_ends(data, chunk)
        commas_before_end = np.searchsorted(np.flatnonzero(data == ord(",")), ends)  # commas before each end
        starts = np.r_[0, ends[:-1] + 1] if ends.size else np.zeros(0, int)
        counts = np.diff(commas_before_end, prepend=0)
        lengths = ends - starts
        if ends.size:  # the line running on from the last chunk
            counts[0] += self.commas_in_line
            lengths[0] += self.length_of_line
        content = lengths > (data[np.maximum(ends - 1, 0)] == ord("\r"))  # blank lines are skipped
        self.lines.append(self.line + np.flatnonzero(content) + 1)
        bad = np.flatnonzero(content & (counts + 1 != self.fields))
        bad = bad[(self.line + bad) > 0]  # the header itself
        if bad.size:
            k = int(bad[0])
            raise InputError(
                f"{int(counts[k]) + 1} fields where the header has {self.fields}", self.name, self.line + k + 1, None
            )
        self.line += ends.size
        tail = data[ends[-1] + 1 :] if ends.size else data
        self.commas_in_line = int(np.count_nonzero(tail == ord(","))) + (0 if ends.size else self.commas_in_line)
        self.length_of_line = len(tail) + (0 if ends.size else self.length_of_line)

    def records(self) -> np.ndarray:
        """The line numbers of the records, once the file's last line (without a line end) is checked."""
        if self.length_of_line and self.commas_in_line + 1 != self.fields and self.line > 0:
            raise InputError(
                f"{self.commas_in_line + 1} fields where the header has {self.fields}", self.name, self.line + 1, None
            )
        lines = self.lines + ([np.array([self.line + 1])] if self.length_of_line else [])
        lines = np.concatenate(lines) if lines else np.zeros(0, int)
        return lines[lines > 1]


def checked_table(table: pd.DataFrame, name: str, required, text_columns, empty: str) -> pd.DataFrame:
    """``table`` with stripped, unique column names, the ``required`` ones present, at least one row, and every
    column but ``text_columns`` converted to finite floats (NaN where empty); InputError otherwise."""
    table.columns = [str(c).strip() for c in table.columns]
    seen = set()
    for column in table.columns:
        if column in seen:
            raise InputError("the column appears twice in the header", name, 1, column)
        seen.add(column)
    missing = [c for c in required if c not in table.columns]
    if missing:
        raise InputError(f"required column missing (the header has: {', '.join(table.columns)})", name, 1, missing[0])
    if len(table) == 0:
        raise InputError(empty, name)
    text = set(text_columns)
    for column in table.columns:
        if column in text:
            table[column] = table[column].astype(str)
        else:
            table[column] = numeric_column(table[column], name, column, table_rows(table))
    return table


def numeric_column(values: pd.Series, source: str, column: str, row_of=file_row) -> np.ndarray:
    """Convert one column to float, raising InputError at the first non-numeric or non-finite cell (``row_of(i)``:
    the file row of cell ``i``). ``True`` and ``False`` are not numbers; a blank cell is a missing value."""
    if pd.api.types.is_numeric_dtype(values.dtype) and not pd.api.types.is_bool_dtype(values.dtype):
        out = values.to_numpy(dtype=float)
    else:  # as text: pandas makes True/False booleans, and keeps "" in a column holding huge integers
        text = pd.Series([str(v).strip() if p else "" for v, p in zip(values, values.notna())], dtype=object)
        present = (text != "").to_numpy()
        text = text.where(present, None)
        try:
            out = pd.to_numeric(text, errors="coerce").to_numpy(dtype=float)
        except OverflowError:  # an integer beyond the float range among other cells: cell by cell
            out = np.array([_number(t) for t in text], dtype=float)
        bad = np.isnan(out) & present
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            cell = values.iloc[i]
            cell = str(cell) if isinstance(cell, bool | np.bool_) else cell  # as written, in a column of booleans too
            raise InputError(
                f"not a number: {cell!r} (leave the cell empty for a missing value)", source, row_of(i), column
            )
    infinite = np.isinf(out)
    if infinite.any():
        i = int(np.flatnonzero(infinite)[0])
        raise InputError("not a finite number (leave the cell empty for a missing value)", source, row_of(i), column)
    return out


def _number(text) -> float:
    """A cell's number (NaN for none, inf for an integer beyond the float range)."""
    if text is None:
        return np.nan
    try:
        return float(pd.to_numeric(text, errors="coerce"))
    except OverflowError:
        return np.inf


def require_complete(table: pd.DataFrame, columns: Iterable[str], source: str, row_of=None) -> None:
    """Raise InputError naming the first empty cell among ``columns`` (``row_of(i)``: the file row of data row
    ``i``; by default ``table_rows(table)``)."""
    row_of = row_of or table_rows(table)
    for column in columns:
        empty = np.isnan(table[column].to_numpy(dtype=float))
        if empty.any():
            i = int(np.flatnonzero(empty)[0])
            raise InputError("empty cell where a value is required", source, row_of(i), column)


def require_rows(table: pd.DataFrame, minimum: int, source: str, what: str) -> None:
    """Raise InputError when ``table`` has fewer than ``minimum`` rows."""
    if len(table) < minimum:
        raise InputError(f"too few samples: {len(table)} rows, {what} needs at least {minimum}", source)


class RecordLines:
    """The file lines (1-based) of a CSV file's records as ``runs`` (k, 2): the first line and the number of lines
    of each stretch of consecutive record lines."""

    def __init__(self, runs: np.ndarray):
        self.runs = np.asarray(runs, np.int64).reshape(-1, 2)
        self.before = np.concatenate([[0], np.cumsum(self.runs[:, 1])])  # records before each run

    def at(self, index: np.ndarray) -> np.ndarray:
        """The lines of the records ``index`` (n,) (0-based, in the order of the file)."""
        run = np.searchsorted(self.before, index, side="right") - 1
        return self.runs[run, 0] + (index - self.before[run])

    @property
    def plain(self) -> bool:
        """Whether the records are every line after the header (no blank line): a record's line is its number."""
        return len(self.runs) == 0 or (len(self.runs) == 1 and self.runs[0, 0] == HEADER_ROWS + 1)


class _RunScan(_FieldScan):
    """``io.tables``' scan of a CSV file's fields, keeping the record lines as runs (``RecordLines``)."""

    def __init__(self, name: str, fields: int):
        super().__init__(name, fields)
        self.runs: list[np.ndarray] = []  # (k, 2) arrays: first line and number of lines of each run

    def add(self, chunk: bytes) -> None:
        super().add(chunk)
        self._keep(self.lines.pop())

    def _keep(self, lines: np.ndarray) -> None:
        """Add the record lines ``lines`` (ascending) as runs, the first joined to the last run kept when it
        continues it (16 bytes a run: a file with a blank line after every record has a run a record)."""
        lines = lines[lines > HEADER_ROWS]
        if not len(lines):
            return
        firsts = np.r_[0, np.flatnonzero(np.diff(lines) != 1) + 1]
        runs = np.column_stack([lines[firsts], np.diff(np.r_[firsts, len(lines)])]).astype(np.int64)
        if self.runs and self.runs[-1][-1].sum() == runs[0, 0]:
            last = self.runs[-1]
            last[-1, 1] += runs[0, 1]
            runs = runs[1:]
        if len(runs):
            self.runs.append(runs)

    def record_lines(self) -> RecordLines:
        """The runs, once the file's last line (without a line end) is checked (``_FieldScan.records``)."""
        self._keep(self.records())
        return RecordLines(np.concatenate(self.runs) if self.runs else np.zeros((0, 2), np.int64))


def record_lines(path, name: str, required=()) -> RecordLines | None:
    """Check the layout of the CSV file ``path`` and give its records' lines (the lines after the header that are
    not blank) as runs. Raises InputError naming ``name``, the row and the column for a header naming a column twice
    or lacking a ``required`` one, or a row with fewer or more fields than the header (pandas would fill a short row
    with empty cells, or take a long row's first field as an index). None for a file with quoted fields (left to
    the parser) or whose records are every line after the header."""
    scan = _RunScan(name, _check_header(path, name, required))
    if not _scanned(path, scan):
        return None
    lines = scan.record_lines()
    return None if lines.plain else lines
