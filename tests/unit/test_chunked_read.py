"""``read_csv`` and ``read_parquet`` convert a file a chunk at a time (``io.tables.READ_ROWS`` records) and join
the columns: the same table and the same one-line errors as a whole-file read, and the table's memory held once;
``whole_log_checks`` looks at the log a chunk at a time too."""

import tracemalloc
import warnings

import numpy as np
import pandas as pd
import pytest

from magkf.errors import InputError
from magkf.io import drivelog, tables
from magkf.io.drivelog import UnitWarning, whole_log_checks
from magkf.io.tables import read_csv, read_parquet

ROWS = 7  # records a chunk in these tests: chunk edges fall among the blank lines and the bad cells


def _whole(path, text_columns=()) -> pd.DataFrame:
    """The file read whole by pandas with ``read_csv``'s options, every other column as float."""
    table = pd.read_csv(
        path, keep_default_na=False, na_values=[""], skipinitialspace=True, dtype=dict.fromkeys(text_columns, str)
    )
    return table.astype({c: float for c in table.columns if c not in text_columns})


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(tables, "READ_ROWS", ROWS)


def test_the_chunks_make_the_whole_table(tmp_path, small_chunks):
    """Blank lines across chunk edges, a text column, and a column empty over whole chunks: the table pandas reads
    whole, bit for bit, and each record's file line kept where blank lines lie among them."""
    rng = np.random.default_rng(3)
    lines, records = ["time, x ,plane,gap"], []
    for i in range(40):
        if i in {0, 6, 7, 20}:
            lines.append("")
        records.append(len(lines) + 1)
        gap = "" if i < 15 else f"{rng.normal():.17g}"
        lines.append(f"{1.7e9 + i},{rng.normal() * 1e4:.17g},{'xy' if i % 3 else 'z'},{gap}")
    path = tmp_path / "t.csv"
    path.write_text("\n".join(lines) + "\n")
    table = read_csv(path, required=("time",), text_columns=("plane",))
    expected = _whole(path, ("plane",))
    expected.columns = [c.strip() for c in expected.columns]
    pd.testing.assert_frame_equal(table, expected, check_exact=True)
    np.testing.assert_array_equal(table.attrs["rows"], records)


@pytest.mark.parametrize(("cell", "record", "message"), [("abc", 17, "not a number"), ("inf", 30, "not a finite")])
def test_a_bad_cell_in_a_later_chunk_names_its_row(tmp_path, small_chunks, cell, record, message):
    """The error names the file line of the cell (blank lines counted) and its column, whichever chunk it is in."""
    lines = ["time,mag_x"] + [f"{1.7e9 + i},{i}" for i in range(40)]
    lines[1 + record] = f"{1.7e9 + record},{cell}"
    lines.insert(5, "")  # one blank line before the bad record: its line is one further down
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=message) as caught:
        read_csv(path)
    assert (caught.value.row, caught.value.column) == (record + 3, "mag_x")


def test_the_parquet_chunks_make_the_whole_table(tmp_path, small_chunks):
    """A Parquet file read in chunks: the table pandas reads whole; a bad value's row named as its CSV twin's."""
    rng = np.random.default_rng(4)
    frame = pd.DataFrame({"time": 1.7e9 + np.arange(30.0), "mag_x": rng.normal(size=30), "plane": ["xy"] * 30})
    path = tmp_path / "t.parquet"
    frame.to_parquet(path)
    pd.testing.assert_frame_equal(read_parquet(path, text_columns=("plane",)), frame, check_exact=True)
    frame.loc[23, "mag_x"] = np.inf
    frame.to_parquet(path)
    with pytest.raises(InputError, match="not a finite") as caught:
        read_parquet(path, text_columns=("plane",))
    assert (caught.value.row, caught.value.column) == (25, "mag_x")


def test_a_parquet_file_without_rows_is_checked_for_its_columns_first(tmp_path):
    """No rows and a required column missing: the missing column is named, as a whole-file read named it."""
    path = tmp_path / "empty.parquet"
    pd.DataFrame({"time": np.zeros(0)}).to_parquet(path)
    with pytest.raises(InputError, match="required column missing"):
        read_parquet(path, required=("time", "mag_x"))
    with pytest.raises(InputError, match="the file has no rows"):
        read_parquet(path, required=("time",))


def test_the_table_is_held_once(tmp_path, monkeypatch):
    """Traced at its peak (numpy's allocations; the parser's own are not traced), reading holds the table, one
    column of it again while its pieces are joined, and a few chunks: 1.16 tables here, where pandas reading the
    file whole held 1.27 traced (and the 24-hour log's read peaked at 3.5 times its table in all)."""
    monkeypatch.setattr(tables, "READ_ROWS", 4096)
    n, columns = 200_000, 8
    rng = np.random.default_rng(5)
    frame = pd.DataFrame(rng.normal(size=(n, columns)), columns=[f"c{k}" for k in range(columns)])
    path = tmp_path / "big.csv"
    frame.to_csv(path, index=False)
    table_bytes = n * columns * 8
    chunk_bytes = 4096 * columns * 8
    tracemalloc.start()
    try:
        table = read_csv(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert table.shape == (n, columns)
    assert peak < table_bytes * (1 + 1 / columns) + 4 * chunk_bytes, (peak, table_bytes)  # 1.27 tables before


def test_the_whole_log_checks_in_chunks(monkeypatch):
    """Over chunks of 7 rows, with gaps in the magnetometer and attitude: the median magnitude, the axes' ranges and
    the angles' extremes of the whole arrays, and the checks' outcomes."""
    monkeypatch.setattr(drivelog, "_SCAN_ROWS", 7)
    rng = np.random.default_rng(6)
    n = 101
    mag = rng.normal(0.3, 0.05, size=(n, 3))  # gauss-sized magnitudes: a unit warning
    mag[[3, 50, 99], 1] = np.nan
    angles = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.linspace(-3, 3, n)])
    angles[10:30] = np.nan  # a whole chunk without attitude
    table = pd.DataFrame(np.column_stack([mag, angles]), columns=["mag_x", "mag_y", "mag_z", "roll", "pitch", "yaw"])
    scan = drivelog._WholeLogScan(table, ("roll", "pitch", "yaw"))
    complete = mag[np.all(np.isfinite(mag), axis=1)]
    assert scan.complete == len(complete)
    np.testing.assert_array_equal(scan.mag_low, complete.min(axis=0))
    np.testing.assert_array_equal(scan.mag_high, complete.max(axis=0))
    assert scan.median_norm() == np.median(np.linalg.norm(complete, axis=1))
    np.testing.assert_array_equal(scan.largest_angle, np.nanmax(np.abs(angles), axis=0))
    assert (scan.yaw_low, scan.yaw_high) == (-3.0, 3.0)
    monkeypatch.setattr(drivelog, "RADIANS_MIN_EPOCHS", 10)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        whole_log_checks(table, "log.csv")
    said = [str(w.message) for w in caught if issubclass(w.category, UnitWarning)]
    assert len(said) == 2 and "look like G" in said[0] and "look like radians" in said[1]
    table[["mag_x", "mag_y", "mag_z"]] = [1.0, 2.0, 3.0]
    with pytest.raises(InputError, match="the same value at every epoch"):
        whole_log_checks(table, "log.csv")


def test_a_chunk_of_booleans_is_named_as_written(tmp_path, small_chunks):
    """A chunk whose cells are all True or False (pandas reads it as booleans): the cell is named as written."""
    lines = ["time,mag_x"] + [f"{1.7e9 + i},{i}" for i in range(14)] + [f"{1.7e9 + 14 + i},True" for i in range(7)]
    path = tmp_path / "bool.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="not a number: 'True'") as caught:
        read_csv(path)
    assert (caught.value.row, caught.value.column) == (16, "mag_x")
