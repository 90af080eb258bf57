"""Logs long enough to be read in chunks by the commands that can (``apply``, ``convert``), and where their
outputs go while they are written piece by piece."""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from pathlib import Path

__all__ = ["STREAMED_EPOCHS", "read_in_chunks", "streamed_output"]

#: ``apply`` and ``convert`` read a canonical log of at least this many rows in chunks (about 17 minutes at 100 Hz):
#: they take as long as whole (a 4-hour log: 22 to 25 s either way) in a memory that does not grow with the log
#: (apply at a whole hour: 320 MB instead of 580 MB). Lower than ``calibrate``'s ``CHUNKED_EPOCHS``, whose chunked
#: path makes passes the whole-log path does not.
STREAMED_EPOCHS = 100_000


def read_in_chunks(args, rows: int | None = None) -> bool:
    """Whether the log of the command line ``args`` is read in chunks (``magkf.online.chunked.ChunkedLog``), as
    ``calibrate`` decides it but from ``STREAMED_EPOCHS`` rows on: a canonical CSV or Parquet file (not standard
    input, no column map, no ``--mag``, ``--site`` or ``--date``) of at least that many rows (or
    ``CHUNKED_EPOCHS``, where a test lowers it); ``rows`` another least number of rows (``calibrate``'s
    ``CHUNKED_EPOCHS``)."""
    from ..files import STDIO
    from ..io.readers import detect_format
    from ..online import chunked

    if args.file == STDIO or args.map is not None or args.mag is not None:
        return False
    if args.site is not None or args.date is not None:  # a log placed by the user is read whole
        return False
    if not Path(args.file).is_file():
        return False
    if (args.format or detect_format(args.file)) not in ("csv", "parquet"):
        return False
    least = min(STREAMED_EPOCHS, chunked.CHUNKED_EPOCHS) if rows is None else rows
    return chunked.estimated_rows(args.file) >= least


@contextmanager
def streamed_output(path, types: dict | None = None, quoted: bool | None = False, floats: bool = False):
    """``write(frame)`` for the pieces of one table written to ``path`` as ``io.drivelog.write_drive_log`` writes a
    table (Parquet for ``.parquet``, else CSV; ``types``, ``quoted`` and ``floats`` as ``FrameWriter`` takes
    them), or None for no ``path``. The file is a temporary until the block ends without an error (and, within
    ``magkf.files.committed``, until the command does); ``-``: standard output, copied there from a temporary
    file only once the block has ended without an error, so that a refusal or a bad row found late writes
    nothing."""
    from ..files import STDIO, standard_output, temporary_folder, written
    from ..io.drivelog import FrameWriter
    from ..io.tables import PARQUET_SUFFIXES

    if path is None:
        yield None
        return
    if path == STDIO:
        with temporary_folder() as folder:
            tmp = Path(folder) / "output.csv"
            with FrameWriter(tmp, types, quoted, parquet=False, floats=floats) as writer:
                yield writer.write
            out = standard_output()
            with open(tmp, encoding="utf-8") as f:
                shutil.copyfileobj(f, out)
            out.flush()
        return
    parquet = Path(path).suffix.lower() in PARQUET_SUFFIXES
    with written(path) as tmp:
        with FrameWriter(tmp, types, quoted, parquet=parquet, floats=floats) as writer:
            yield writer.write
