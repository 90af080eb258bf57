"""A canonical log read in chunks in memory that does not grow with the file.

``StreamedLog`` is ``magkf.online.chunked.ChunkedLog`` (the same chunks, checks and one-line errors) but for
two things that held memory growing with the file:

* a Parquet file is opened without pyarrow's pre-buffering, which reads ahead and keeps the column chunks of
  the row groups still to come (a 4-hour 100 Hz log of 22 row groups: 225 MB of Arrow buffers at the peak,
  against 42 MB for a 1-hour one; without it 42 MB for both);
* the layout of a CSV file (``io.tables.check_layout``: the same fields on every line) is checked keeping the
  file's record lines as runs of consecutive lines (``RecordLines``: one pair per stretch between blank lines)
  instead of one number per record (up to 33 bytes per record at the peak of the check).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pandas as pd

from ..conventions import MAG, TIME
from ..errors import InputError
from ..online.chunked import ChunkedLog
from .tables import HEADER_ROWS, SCAN_BYTES, _check_header, _FieldScan, checked_table

__all__ = ["RecordLines", "StreamedLog", "record_lines"]


class StreamedLog(ChunkedLog):
    """``ChunkedLog`` reading a Parquet file row batch by row batch without reading ahead."""

    def _tables(self) -> Iterator[pd.DataFrame]:
        if not self.parquet:
            yield from self._csv_tables()
            return
        import pyarrow.parquet as pq

        name = self.source
        if not self.path.is_file():
            raise InputError("no such file", name)
        try:
            batches = pq.ParquetFile(self.path, pre_buffer=False).iter_batches(batch_size=self.rows)
            offset = 0
            for batch in batches:
                table = batch.to_pandas()
                table.attrs["rows"] = np.arange(offset, offset + len(table)) + HEADER_ROWS + 1
                offset += len(table)
                yield checked_table(table, name, (TIME, *MAG), (), "the file has no rows")
        except InputError:
            raise
        except Exception as exc:  # pyarrow raises several types for a damaged or foreign file
            raise InputError(f"not a readable Parquet file ({' '.join(str(exc).split())[:200]})", name) from None

    def _csv_tables(self) -> Iterator[pd.DataFrame]:
        """The raw chunks of a CSV file, their file rows in ``attrs["rows"]`` (``ChunkedLog``'s, the layout checked
        by ``record_lines``)."""
        name = self.source
        if not self.path.is_file():
            raise InputError("no such file", name)
        required = (TIME, *MAG)
        lines = None if self.checked else record_lines(self.path, name, required)
        try:
            reader = pd.read_csv(
                self.path, keep_default_na=False, na_values=[""], skipinitialspace=True, chunksize=self.rows
            )
            offset = 0
            for table in reader:
                rows = np.arange(offset, offset + len(table)) + HEADER_ROWS + 1
                table.attrs["rows"] = rows if lines is None else lines.at(rows - HEADER_ROWS - 1)
                offset += len(table)
                yield checked_table(table, name, required, (), "the file has a header but no data rows")
        except pd.errors.EmptyDataError:
            raise InputError("the file is empty", name) from None
        except (pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise InputError(f"not a readable CSV file ({' '.join(str(exc).split())})", name) from None


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
        self.runs: list[list[int]] = []

    def add(self, chunk: bytes) -> None:
        super().add(chunk)
        self._keep(self.lines.pop())

    def _keep(self, lines: np.ndarray) -> None:
        lines = lines[lines > HEADER_ROWS]
        if not len(lines):
            return
        breaks = np.flatnonzero(np.diff(lines) != 1) + 1
        for first, last in zip(np.r_[0, breaks], np.r_[breaks, len(lines)]):
            start, count = int(lines[first]), int(last - first)
            if self.runs and sum(self.runs[-1]) == start:
                self.runs[-1][1] += count
            else:
                self.runs.append([start, count])

    def record_lines(self) -> RecordLines:
        """The runs, once the file's last line (without a line end) is checked (``_FieldScan.records``)."""
        self._keep(self.records())
        return RecordLines(np.array(self.runs, np.int64))


def record_lines(path, name: str, required=()) -> RecordLines | None:
    """``io.tables.check_layout`` of the CSV file ``path`` (InputError naming ``name``, the row and the column for
    a header or a row out of shape) with its records' lines as runs; None for a file with quoted fields (left to
    the parser) or whose records are every line after the header."""
    scan = _RunScan(name, _check_header(path, name, required))
    with open(path, "rb") as f:
        while chunk := f.read(SCAN_BYTES):
            while chunk.endswith(b"\r") and (more := f.read(1)):  # a CR LF pair stays in one chunk
                chunk += more
            if b'"' in chunk:
                return None
            scan.add(chunk)
    lines = scan.record_lines()
    return None if lines.plain else lines
