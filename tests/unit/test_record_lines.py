"""``ChunkedLog`` keeps a CSV file's record lines as runs (``io.tables.record_lines``): the file's non-blank lines
after the header, the same chunks and errors."""

import numpy as np
import pytest

from magkf.errors import InputError
from magkf.io.readers import read_log
from magkf.io.tables import record_lines
from magkf.online.chunked import ChunkedLog
from magkf.sim import DriveConfig, simulate_drive

HEADER = "time,mag_x,mag_y,mag_z,lat,lon"


def _lines(n: int, blank: set, end: str = "\n", last_end: bool = True) -> str:
    """A canonical CSV of ``n`` records at 1 Hz, with a blank line before each record numbered in ``blank``."""
    out = [HEADER]
    for i in range(n):
        if i in blank:
            out.append("")
        out.append(f"{1.7e9 + i:.1f},{20000 + i % 7},{1000 - i % 5},{40000 + i % 3},48.1,11.6")
    return end.join(out) + (end if last_end else "")


@pytest.mark.parametrize(
    ("blank", "end", "last_end"),
    [(set(), "\n", True), ({0, 5, 6, 40}, "\n", True), ({3, 99}, "\r\n", False), ({1, 2, 3}, "\r", True)],
)
def test_record_lines_are_the_non_blank_lines(tmp_path, blank, end, last_end):
    """Blank lines at the start, in runs and near the end, LF, CR LF and CR line ends, a last line without an
    end: every record's line, counted by Python's own line splitting (None: every line after the header)."""
    path = tmp_path / "log.csv"
    text = _lines(100, blank, end, last_end)
    path.write_bytes(text.encode())
    expected = [number for number, line in enumerate(text.splitlines(), start=1) if number > 1 and line]
    lines = record_lines(path, "log.csv", ("time",))
    if not blank:
        assert lines is None and np.array_equal(expected, np.arange(100) + 2)
    else:
        np.testing.assert_array_equal(lines.at(np.arange(100)), expected)


def test_a_bad_cell_after_blank_lines_names_its_line(tmp_path):
    """A cell that is not a number in a late chunk, blank lines before it: the whole reader's one line."""
    text = _lines(100, {10, 11, 50}).splitlines()
    bad = 2 + 80 + 3  # header, 80 records before it, 3 blank lines
    assert text[bad - 1].startswith(f"{1.7e9 + 80:.1f}")
    text[bad - 1] = text[bad - 1].replace(",48.1,", ",abc,")
    path = tmp_path / "log.csv"
    path.write_text("\n".join(text) + "\n")
    with pytest.raises(InputError) as whole:
        read_log(path)
    with pytest.raises(InputError) as chunked:
        list(ChunkedLog(path, rows=16))
    assert str(chunked.value) == str(whole.value) and f"row {bad}" in str(chunked.value)


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_the_chunks_are_the_whole_log(tmp_path, suffix):
    """Chunks of 333 rows of a CSV or Parquet log, put together: the table the whole reader reads."""
    import pandas as pd

    sim = simulate_drive(DriveConfig(duration_s=20, rate_hz=50, seed=2))
    path = tmp_path / f"log{suffix}"
    sim.write(path)
    whole = read_log(path).table
    chunks = [log.table for _, log in ChunkedLog(path, rows=333)]
    assert len(chunks) == 4
    pd.testing.assert_frame_equal(pd.concat(chunks), whole, check_dtype=False)
