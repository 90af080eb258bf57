"""Property tests of the table readers (``read_drive_log``, ``read_csv``, ``read_mapped``).

For any generated file a reader returns a valid result or raises InputError naming the file (and, where a
cell is at fault, its row, the line number counting the header as row 1, and its column); never another
exception; and the file is not changed. Valid files are generated, then corrupted: cells replaced by text,
NaN, inf, huge or out-of-range numbers or nothing, rows cut or lengthened, names repeated, times shuffled,
bytes inserted, Latin-1 text, a byte-order mark, CRLF or CR line ends, blank lines, no rows at all.
"""

from __future__ import annotations

import atexit
import copy
import csv
import io
import json
import math
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from datetime import UTC, date, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import assume, event, given, settings
from hypothesis import strategies as st

from magkf.conventions import ATTITUDE, CORE_COLUMNS, MAG, NT_PER_UNIT, REF
from magkf.errors import InputError
from magkf.io.columnmap import EXTENSION_FORMATS, load_column_map, read_mapped
from magkf.io.drivelog import (
    ALT_RANGE_M,
    DOP_MAX,
    MAG_MAX_NT,
    TIME_RANGE_S,
    TimeBaseWarning,
    UnitWarning,
    read_drive_log,
)
from magkf.io.tables import read_csv

#: One folder for every file these tests write (each test overwrites its own few names).
FOLDER = Path(tempfile.mkdtemp(prefix="magkf-property-"))
atexit.register(shutil.rmtree, FOLDER, ignore_errors=True)
PROPERTY = settings(max_examples=60, deadline=None, derandomize=True, database=None)

#: A cell that holds a number, as the data contract means it (the oracle of these tests).
NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
#: Cell texts that are not finite numbers (though Python's float reads some of them).
NOT_NUMBERS = (
    "NaN", "nan", "-nan", "inf", "-inf", "Infinity", "1e400", "-1e999", "True", "False", "0x1A", "1_000", "1e",
    ".", "-", "+", "N/A", "NULL", "abc", "1.2.3", "--1", "1d5", "µT", "45°", "é", "١٢٣", "½",
)  # fmt: skip
#: Odd cells that stay one cell of a comma-separated line, and then cells that do not.
PLAIN_ODD_CELLS = (*NOT_NUMBERS, "", " ", "1e308", "-1e12", "1e12", "-5", "0", "#", "\t")
ODD_CELLS = (*PLAIN_ODD_CELLS, "1,5", '"1"', '"', "\x00")
#: Ranges the drive-log contract gives each canonical column (mag in nT; ``time`` in UNIX s).
RANGES = {
    "roll": (-180.0, 360.0),
    "pitch": (-90.0, 90.0),
    "yaw": (-360.0, 360.0),
    "lat": (-90.0, 90.0),
    "lon": (-180.0, 360.0),
    "alt": ALT_RANGE_M,
    "dop": (0.0, DOP_MAX),
    **{c: (-MAG_MAX_NT, MAG_MAX_NT) for c in (*MAG, *REF)},
}
FORMATS = (repr, "{:.17g}".format, "{:.6e}".format, "{:.4f}".format, "{:+.3f}".format)
ANY_FORMAT = st.sampled_from(FORMATS)
AUX_NAME = st.from_regex(r"[a-z][a-z0-9_]{0,7}", fullmatch=True).filter(lambda s: s not in CORE_COLUMNS)


# ---------------------------------------------------------------- files
@dataclass
class Grid:
    """A comma-separated table as cell texts, and the magnetic unit its ``mag_*`` cells are in."""

    header: list[str]
    rows: list[list[str]]
    unit: str = "nT"

    def cells(self, name: str) -> list[str]:
        k = self.header.index(name)
        return [row[k] for row in self.rows]

    def values(self, name: str) -> np.ndarray:
        return np.array([value(c) for c in self.cells(name)], dtype=float)


@dataclass(frozen=True)
class Layout:
    """How a Grid becomes bytes: line end, byte-order mark, blank lines before data row k (k = number of
    rows: at the end; -1: before the header), spaces after each comma, encoding, bytes inserted."""

    newline: str = "\n"
    bom: bool = False
    blank_before: tuple[int, ...] = ()
    final_newline: bool = True
    pad: str = ""
    encoding: str = "utf-8"
    insertions: tuple[tuple[int, bytes], ...] = ()


def render(grid: Grid, layout: Layout = Layout()) -> tuple[bytes, list[int | None]]:
    """The file's bytes, and the line number of each data row (None where a row renders as a blank line)."""
    sep = "," + layout.pad
    lines: list[str] = [""] * layout.blank_before.count(-1) + [sep.join(grid.header)]
    at: list[int | None] = []
    for k, row in enumerate(grid.rows):
        lines += [""] * layout.blank_before.count(k)
        lines.append(sep.join(row))
        at.append(len(lines) if lines[-1] else None)
    lines += [""] * layout.blank_before.count(len(grid.rows))
    text = (
        ("\ufeff" if layout.bom else "") + layout.newline.join(lines) + (layout.newline if layout.final_newline else "")
    )
    data = text.encode(layout.encoding, errors="replace")
    for position, extra in layout.insertions:
        k = position % (len(data) + 1)
        data = data[:k] + extra + data[k:]
    return data, at


def line_count(data: bytes) -> int:
    return len(re.split(rb"\r\n|\r|\n", data))


def value(cell: str) -> float:
    """The number a cell holds (NaN when empty); fails the test for a cell that is not a number."""
    text = cell.strip()
    if not text:
        return math.nan
    assert NUMBER.fullmatch(text), f"the reader took {cell!r} for a number"
    return float(text)


def parse_back(data: bytes) -> Grid:
    """The table a reader that accepted ``data`` must have seen (Python's csv module as the oracle). A column
    without a name is called ``Unnamed: k`` (k from 0), as pandas calls it (the index column of a DataFrame
    written with ``to_csv``)."""
    text = data.decode("utf-8-sig")
    rows = [row for row in csv.reader(io.StringIO(text, newline=""), skipinitialspace=True) if row]
    return Grid([c.strip() or f"Unnamed: {k}" for k, c in enumerate(rows[0])], rows[1:])  # pandas names nameless ones


def attempt(data: bytes, name: str, read):
    """``read(path)`` of a file holding ``data``: its result or the InputError it raised, and the path. Any
    other exception fails the test; so does a change to the file."""
    path = FOLDER / name
    path.write_bytes(data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UnitWarning)
            warnings.simplefilter("ignore", TimeBaseWarning)
            result = read(path)
    except InputError as exc:
        result = exc
    assert path.read_bytes() == data, "the reader changed its input file"
    return result, str(path)


def check_error(error: InputError, path: str, data: bytes | None = None) -> None:
    """One line starting with the file's name; a row within the file (``data``: its bytes; None: a file that
    has no rows, as a column map) and a column as the text says."""
    text = str(error)
    assert error.source == path and text.startswith(f"{path}") and "\n" not in text, text
    if error.row is not None:
        assert data is not None and 1 <= error.row <= line_count(data), text
        assert f"row {error.row}," in text or f"row {error.row}:" in text, text
    if error.column is not None:
        assert f"column {error.column!r}" in text, text


# ---------------------------------------------------------------- canonical drive logs
def numbers(lo: float, hi: float) -> st.SearchStrategy[str]:
    """Cells holding numbers in [lo, hi], written in one of ``FORMATS``."""
    return st.builds(lambda v, f: f(v), st.floats(lo, hi), ANY_FORMAT)


def sometimes_empty(cells: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    return st.builds(lambda k, c: "" if k == 0 else c, st.integers(0, 5), cells)


@st.composite
def drive_logs(draw, min_rows: int = 2, max_rows: int = 6) -> Grid:
    """A valid canonical log: time, mag_x..z in a drawn unit (mag_x changing), and some of attitude, position,
    alt, dop, ref_n..d (ref_d of 1000 nT or more) and auxiliary columns in any order; empty cells anywhere but
    in time."""
    unit = draw(st.sampled_from(sorted(NT_PER_UNIT)))
    n = draw(st.integers(min_rows, max_rows))
    times = [draw(st.floats(TIME_RANGE_S[0], TIME_RANGE_S[1] - 30.0))]
    for _ in range(n - 1):
        times.append(times[-1] + draw(st.floats(1e-3, 4.0)))
    time_format = draw(st.sampled_from((repr, "{:.6f}".format)))
    columns = {"time": [time_format(t) for t in times]}
    scale = NT_PER_UNIT[unit]
    ranges = {c: (-1e5 / scale, 1e5 / scale) for c in MAG}
    if draw(st.booleans()):
        ranges.update({c: RANGES[c] for c in ATTITUDE})
    position, reference = draw(st.sampled_from([(True, False), (False, True), (True, True)]))
    if position:
        ranges.update({c: RANGES[c] for c in ("lat", "lon")})
        if draw(st.booleans()):
            ranges["alt"] = RANGES["alt"]
    if draw(st.booleans()):
        ranges["dop"] = RANGES["dop"]
    if reference:
        ranges.update({c: (-1e5, 1e5) for c in REF})
    for name, (lo, hi) in ranges.items():
        if name == "ref_d":  # a reference field of 1000 nT at least
            cells = st.builds(lambda v, sign, f: f(sign * v), st.floats(1e3, hi), st.sampled_from([1, -1]), ANY_FORMAT)
        elif name == "mag_x":  # not the same reading at every epoch: a sensor to calibrate
            cells = st.builds(lambda v, f: (v, f), st.floats(lo, hi), ANY_FORMAT)
        else:
            cells = numbers(lo, hi)
        columns[name] = draw(st.lists(sometimes_empty(cells), min_size=n, max_size=n))
    columns["mag_x"] = [c if c == "" else c[1](c[0] + 0.5 * i) for i, c in enumerate(columns["mag_x"])]
    finite = st.builds(lambda v, f: f(v), st.floats(allow_nan=False, allow_infinity=False), ANY_FORMAT)
    for name in draw(st.lists(AUX_NAME, max_size=3, unique=True)):
        columns[name] = draw(st.lists(sometimes_empty(finite), min_size=n, max_size=n))
    order = draw(st.permutations(list(columns)))
    return Grid(list(order), [[columns[c][i] for c in order] for i in range(n)], unit)


@st.composite
def layouts(draw, rows: int) -> Layout:
    """Benign layouts every reader must accept: LF or CRLF, a byte-order mark, blank lines, padding."""
    return Layout(
        newline=draw(st.sampled_from(["\n", "\r\n"])),
        bom=draw(st.booleans()),
        blank_before=tuple(draw(st.lists(st.integers(0, rows), max_size=3))),
        final_newline=draw(st.booleans()),
        pad=draw(st.sampled_from(["", " "])),
    )


@st.composite
def strange_layouts(draw, rows: int) -> Layout:
    """Layouts a reader may refuse: CR line ends, blank lines before the header, Latin-1 or UTF-16 text,
    random bytes inserted; and the benign ones."""
    return Layout(
        newline=draw(st.sampled_from(["\n", "\r\n", "\r"])),
        bom=draw(st.booleans()),
        blank_before=tuple(draw(st.lists(st.integers(-1 if draw(st.integers(0, 4)) == 0 else 0, rows), max_size=3))),
        final_newline=draw(st.booleans()),
        pad=draw(st.sampled_from(["", " ", "  "])),
        encoding=draw(st.sampled_from(["utf-8"] * 4 + ["latin-1", "utf-16"])),
        insertions=tuple(draw(st.lists(st.tuples(st.integers(0, 10_000), st.binary(min_size=1, max_size=3)))))
        if draw(st.integers(0, 3)) == 0
        else (),
    )


ANY_CELL = st.one_of(
    st.sampled_from(ODD_CELLS),
    st.text(max_size=6),
    st.floats().map(repr),
    st.integers(-(10**400), 10**400).map(str),
    numbers(-100.0, 100.0),
    st.just(""),
)
CORRUPTIONS = (
    "cell", "truncate", "extend", "duplicate_name", "rename", "drop_column", "shuffle_times", "repeat_time",
    "repeat_row", "drop_rows",
)  # fmt: skip


@st.composite
def corrupted(draw, tables: st.SearchStrategy[Grid]) -> tuple[Grid, Layout]:
    """A table from ``tables`` damaged up to three times, in a strange layout."""
    grid = draw(tables)
    header, rows = list(grid.header), [list(r) for r in grid.rows]

    def index(items) -> int:
        return draw(st.integers(0, len(items) - 1))

    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(CORRUPTIONS))
        if kind == "cell" and rows:
            row = rows[index(rows)]
            if row:
                row[index(row)] = draw(ANY_CELL)
        elif kind == "truncate" and rows:
            r = index(rows)
            rows[r] = rows[r][: draw(st.integers(0, max(len(rows[r]) - 1, 0)))]
        elif kind == "extend" and rows:
            rows[index(rows)] += draw(st.lists(ANY_CELL, min_size=1, max_size=3))
        elif kind == "duplicate_name" and len(header) > 1:
            i, j = draw(st.permutations(range(len(header))))[:2]
            header[j] = header[i]
        elif kind == "rename" and header:
            header[index(header)] = draw(ANY_CELL)
        elif kind == "drop_column" and header:
            k = index(header)
            del header[k]
            for row in rows:
                del row[k : k + 1]
        elif kind in ("shuffle_times", "repeat_time") and "time" in header and len(rows) > 1:
            k = header.index("time")
            if all(len(row) > k for row in rows):
                times = [row[k] for row in rows]
                if kind == "shuffle_times":
                    times = draw(st.permutations(times))
                else:
                    times[index(times)] = times[index(times)]
                for row, t in zip(rows, times):
                    row[k] = t
        elif kind == "repeat_row" and rows:
            rows.insert(index(rows), list(rows[index(rows)]))
        elif kind == "drop_rows":
            rows = []
    return Grid(header, rows, grid.unit), draw(strange_layouts(len(rows)))


def check_log(log, grid: Grid, path: str) -> None:
    """A DriveLog read from the table ``grid``: one epoch per data row, time finite and strictly increasing
    within the contract's dates, every cell's value (mag in nT) and every canonical column in its range."""
    assert log.source == path and len(log) == len(grid.rows)
    t = log.time
    assert np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)
    assert TIME_RANGE_S[0] <= t[0] and t[-1] <= TIME_RANGE_S[1]
    np.testing.assert_array_equal(t, grid.values("time"))
    scale = NT_PER_UNIT[grid.unit]
    np.testing.assert_array_equal(log.mag, np.column_stack([grid.values(c) * scale for c in MAG]))
    assert sorted(log.table.columns) == sorted(c for c in grid.header if c != "time")
    for name in log.table.columns:
        values = log.table[name].to_numpy()
        assert values.dtype == float
        if name not in MAG:
            np.testing.assert_array_equal(values, grid.values(name))
        if name in RANGES:
            lo, hi = RANGES[name]
            present = values[~np.isnan(values)]
            assert np.all((lo <= present) & (present <= hi)), (name, present)


# ---------------------------------------------------------------- read_drive_log
@pytest.mark.slow
@settings(PROPERTY, max_examples=50)
@given(st.data())
def test_a_valid_drive_log_reads_back_exactly(data):
    grid = data.draw(drive_logs())
    content, _ = render(grid, data.draw(layouts(len(grid.rows))))
    log, path = attempt(content, "log.csv", lambda p: read_drive_log(p, grid.unit))
    assert not isinstance(log, InputError), str(log)
    check_log(log, grid, path)


@pytest.mark.slow
@settings(PROPERTY, max_examples=120)
@given(corrupted(drive_logs(min_rows=1, max_rows=5)))
def test_a_damaged_drive_log_is_read_validly_or_refused_naming_the_file(case):
    grid, layout = case
    content, _ = render(grid, layout)
    log, path = attempt(content, "log.csv", lambda p: read_drive_log(p, grid.unit))
    event("refused" if isinstance(log, InputError) else "read")
    if isinstance(log, InputError):
        check_error(log, path, content)
        return
    back = parse_back(content)
    back.unit = grid.unit
    check_log(log, back, path)


def out_of_range(name: str, unit: str) -> st.SearchStrategy[str]:
    """Numbers beyond the contract's range for a canonical column (mag in ``unit``)."""
    lo, hi = TIME_RANGE_S if name == "time" else RANGES[name]
    if name in MAG:
        lo, hi = lo / NT_PER_UNIT[unit], hi / NT_PER_UNIT[unit]
    beyond = st.floats(max_value=lo, exclude_max=True, allow_infinity=False) | st.floats(
        min_value=hi, exclude_min=True, allow_infinity=False
    )
    return beyond.map(repr)


FAULTS = ("bad_cell", "out_of_range", "empty_time", "time_back", "ragged", "duplicate", "missing", "few_rows")


@pytest.mark.slow
@settings(PROPERTY, max_examples=100)
@given(st.data())
def test_every_fault_is_reported_at_its_row_and_column(data):
    """One fault in a valid log (in a benign layout): InputError at the faulty cell's row and column, at row 1
    and the column for a header fault, at the row alone for a row with the wrong number of fields."""
    grid = data.draw(drive_logs())
    fault = data.draw(st.sampled_from(FAULTS))
    r = data.draw(st.integers(0, len(grid.rows) - 1))
    expected_column = None
    if fault in ("bad_cell", "out_of_range"):
        names = [c for c in grid.header if fault == "bad_cell" or c in RANGES or c == "time"]
        expected_column = data.draw(st.sampled_from(names))
        bad = (
            data.draw(st.sampled_from(NOT_NUMBERS) | st.from_regex(r"[A-Za-z][A-Za-z0-9_.+-]{0,5}", fullmatch=True))
            if fault == "bad_cell"
            else data.draw(out_of_range(expected_column, grid.unit))
        )
        grid.rows[r][grid.header.index(expected_column)] = bad
    elif fault == "empty_time":
        expected_column = "time"
        grid.rows[r][grid.header.index("time")] = ""
    elif fault == "time_back":
        expected_column = "time"
        r = max(r, 1)
        k = grid.header.index("time")
        grid.rows[r][k] = grid.rows[data.draw(st.integers(0, r - 1))][k]
    elif fault == "ragged":
        row = grid.rows[r]
        if data.draw(st.booleans()):
            grid.rows[r] = row[: data.draw(st.integers(1, len(row) - 1))]
        else:
            grid.rows[r] = row + data.draw(st.lists(st.sampled_from(["1", "", "abc", "1e400"]), min_size=1, max_size=2))
        assume(",".join(grid.rows[r]))
    elif fault == "duplicate":
        i, j = data.draw(st.permutations(range(len(grid.header))))[:2]
        expected_column = grid.header[i]
        grid.header[j] = grid.header[i]
    elif fault == "missing":
        needed = ["time", *MAG]
        for group in (ATTITUDE, REF, ("lat", "lon") if "ref_n" not in grid.header else ()):
            needed += [c for c in group if c in grid.header]
        expected_column = data.draw(st.sampled_from(needed))
        k = grid.header.index(expected_column)
        del grid.header[k]
        for row in grid.rows:
            del row[k]
    elif fault == "few_rows":
        grid.rows = grid.rows[: data.draw(st.integers(0, 1))]
    content, at = render(grid, data.draw(layouts(len(grid.rows))))
    error, path = attempt(content, "log.csv", lambda p: read_drive_log(p, grid.unit))
    assert isinstance(error, InputError), f"{fault}: read without complaint"
    check_error(error, path, content)
    if fault in ("duplicate", "missing"):
        assert (error.row, error.column) == (1, expected_column), str(error)
    elif fault == "ragged":
        assert (error.row, error.column) == (at[r], None), str(error)
    elif fault == "few_rows":
        assert (error.row, error.column) == (None, None), str(error)
    else:
        if fault == "time_back":  # the first time not after its predecessor
            t = grid.values("time")
            r = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        assert (error.row, error.column) == (at[r], expected_column), str(error)


# ---------------------------------------------------------------- read_csv
NAME = (
    st.text(st.characters(categories=("L", "N"), include_characters=" _-.()[]/°µ"), min_size=1, max_size=6)
    .map(str.strip)
    .filter(bool)
)
TEXT_CELL = st.text(st.characters(exclude_characters=',"\r\n', exclude_categories=("Cs",)), max_size=6)


@dataclass
class Table:
    grid: Grid
    text_columns: list[str]
    required: list[str]


@st.composite
def tables(draw, odd: bool = True) -> Table:
    """Any table of numbers and text columns, with (``odd``) some odd cells, rows of the wrong length, a
    repeated name or a required column it does not have."""
    names = draw(st.lists(NAME, min_size=1, max_size=5, unique=True))
    text_columns = [c for c in names if draw(st.integers(0, 4)) == 0]
    n = draw(st.integers(0, 5))
    number = st.builds(lambda v, f: f(v), st.floats(allow_nan=False, allow_infinity=False), ANY_FORMAT)
    integer = st.integers(-(10**25), 10**25).map(str)
    cell = st.one_of(number, integer, st.just(""), *([st.sampled_from(PLAIN_ODD_CELLS)] if odd else []))
    rows = [[draw(TEXT_CELL if c in text_columns else cell) for c in names] for _ in range(n)]
    if not odd:
        return Table(Grid(names, rows), text_columns, [])
    if rows and draw(st.integers(0, 5)) == 0:
        r = draw(st.integers(0, n - 1))
        rows[r] = rows[r][:-1] if len(rows[r]) > 1 and draw(st.booleans()) else rows[r] + ["1"]
    header = list(names)
    if len(header) > 1 and draw(st.integers(0, 5)) == 0:
        header[-1] = header[0]
    required = draw(st.lists(st.sampled_from(names) | NAME, max_size=2))
    return Table(Grid(header, rows), text_columns, required)


def expected_faults(table: Table, at: list[int | None]) -> set[tuple]:
    """Every (row, column) an error of ``read_csv`` may name for this table (row None: no row; column None: the
    whole row): a repeated or missing column at row 1, a row of the wrong length, no rows, a cell that is not a
    finite number. Empty: a good table, which must be read."""
    header = table.grid.header
    faults = {(1, c) for k, c in enumerate(header) if c in header[:k]}
    faults |= {(1, c) for c in table.required if c not in header}
    rows = [(row, line) for row, line in zip(table.grid.rows, at) if line is not None]
    faults |= {(line, None) for row, line in rows if len(row) != len(header)}
    if not rows:
        faults.add((None, None))
    for k, column in enumerate(header):
        if column not in table.text_columns:
            for row, line in rows:
                text = row[k].strip() if k < len(row) else ""
                if text and not (NUMBER.fullmatch(text) and math.isfinite(float(text))):
                    faults.add((line, column))
    return faults


@pytest.mark.slow
@settings(PROPERTY, max_examples=150)
@given(st.data())
def test_read_csv_gives_the_cells_or_names_a_fault(data):
    table = data.draw(tables())
    content, at = render(table.grid, data.draw(layouts(len(table.grid.rows))))
    result, path = attempt(content, "table.csv", lambda p: read_csv(p, table.required, table.text_columns))
    faults = expected_faults(table, at)
    if isinstance(result, InputError):
        check_error(result, path, content)
        assert faults, f"a good table refused: {result}"
        assert (result.row, result.column) in faults, f"{result}; the faults: {faults}"
        return
    assert not faults, f"a table read despite the faults {faults}"
    rows = [row for row, line in zip(table.grid.rows, at) if line is not None]
    assert list(result.columns) == table.grid.header and len(result) == len(rows)
    for k, column in enumerate(table.grid.header):
        if column in table.text_columns:  # as written (after the blanks skipped after a comma); empty: missing
            for v, row in zip(result[column], rows):
                assert v == row[k].lstrip(" ") if row[k].strip(" ") else pd.isna(v), (v, row[k])
        else:
            assert result[column].to_numpy().dtype == float
            np.testing.assert_array_equal(result[column].to_numpy(), [value(row[k]) for row in rows])


@settings(PROPERTY, max_examples=100)
@given(corrupted(tables(odd=False).map(lambda table: Grid(table.grid.header, [r for r in table.grid.rows if r]))))
def test_read_csv_of_a_damaged_file_gives_finite_floats_or_refuses_naming_the_file(case):
    grid, layout = case
    content, _ = render(grid, layout)
    result, path = attempt(content, "table.csv", read_csv)
    event("refused" if isinstance(result, InputError) else "read")
    if isinstance(result, InputError):
        check_error(result, path, content)
        return
    back = parse_back(content)
    assert list(result.columns) == back.header and len(result) == len(back.rows) > 0
    for column in back.header:
        np.testing.assert_array_equal(result[column].to_numpy(dtype=float), back.values(column))


# ---------------------------------------------------------------- read_mapped
PER_SECOND = {"s": 1.0, "ms": 1.0e3, "us": 1.0e6, "ns": 1.0e9}
FILE_NAME = st.from_regex(r"[A-TV-Z][A-Za-z0-9_]{0,5}", fullmatch=True)  # U0, U1: unmapped columns
START = datetime(2024, 5, 1, 10, 20, 30, 250000, tzinfo=UTC)


class Raw(str):
    """TOML text written as it is (an integer too long for ``str(int)``)."""


def toml_value(v) -> str:
    if isinstance(v, Raw):
        return str.__str__(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (date, datetime)):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(map(toml_value, v)) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    return json.dumps(v)


def toml(document: dict) -> str:
    """A TOML text of a map: top-level values first, then one table per dict."""
    lines = [f"{json.dumps(k)} = {toml_value(v)}" for k, v in document.items() if not isinstance(v, dict)]
    for name, section in document.items():
        if isinstance(section, dict):
            lines += [f"[{json.dumps(name)}]", *(f"{json.dumps(k)} = {toml_value(v)}" for k, v in section.items())]
    return "\n".join(lines) + "\n"


@dataclass
class Mapped:
    """A text table, the column map (a TOML document) that reads it, and what the reader must return."""

    lines: list[str]
    names: list[str]  # the file's columns (column_1... when it has no header)
    cells: list[list[str]]  # as in the file
    document: dict
    expected: dict[str, np.ndarray]
    suffix: str


@st.composite
def mapped_tables(draw) -> Mapped:
    """A valid csv, tsv or whitespace-separated table with a preamble, comments, blank lines, decimal commas,
    a missing-value token, columns named or numbered, values in other units; and its map."""
    n = draw(st.integers(1, 5))
    fmt = draw(st.sampled_from(["csv", "tsv", "whitespace"]))
    delimiter = {"csv": draw(st.sampled_from([",", ";", "|"])), "tsv": "\t", "whitespace": None}[fmt]
    sep = delimiter or draw(st.sampled_from([" ", "  ", "\t", " \t"]))
    decimal = "." if delimiter == "," else draw(st.sampled_from([".", ","]))
    token = "*" if fmt == "whitespace" else draw(st.sampled_from(["", "NA", "*"]))
    comment = draw(st.sampled_from([None, "#"]))
    mag = draw(st.sampled_from(["nT", "uT", "mG", "G", "counts"]))
    scale = draw(st.floats(0.01, 100.0)) if mag == "counts" else NT_PER_UNIT[mag]
    ref = draw(st.sampled_from(["nT", "uT"])) if mag == "counts" else mag
    angles, latlon = draw(st.sampled_from(["deg", "rad"])), draw(st.sampled_from(["deg", "rad"]))
    time_unit, epoch = draw(st.sampled_from(sorted(PER_SECOND))), draw(st.sampled_from(["unix", "start"]))

    seconds = [draw(st.floats(0.0, 1.0e6)) + (START.timestamp() if epoch == "unix" else 0.0)]
    for _ in range(n - 1):
        seconds.append(seconds[-1] + draw(st.floats(1e-3, 2.0)))
    values = {"time": [s * PER_SECOND[time_unit] for s in seconds]}
    ranges = {c: (-1e5 / scale, 1e5 / scale) for c in MAG}
    for group in (ATTITUDE, ("lat", "lon"), REF):
        if draw(st.booleans()):
            ranges.update({c: RANGES[c] for c in group})
    for name in draw(st.sampled_from([(), ("alt",), ("dop",), ("alt", "dop", "temp_c")])):
        ranges[name] = RANGES.get(name, (-1e6, 1e6))
    radians = {c for c in ATTITUDE if angles == "rad"} | {c for c in ("lat", "lon") if latlon == "rad"}
    for name, (lo, hi) in ranges.items():
        if name in radians:
            lo, hi = math.radians(lo), math.radians(hi)
        elif name in REF:
            lo, hi = lo / NT_PER_UNIT[ref], hi / NT_PER_UNIT[ref]
        values[name] = [draw(st.floats(lo, hi)) if draw(st.integers(0, 5)) else math.nan for _ in range(n)]
    mapped = list(values)
    keep_unmapped = draw(st.booleans())
    for k in range(draw(st.integers(0, 2))):
        values[f"U{k}"] = [draw(st.floats(-1e3, 1e3)) for _ in range(n)]
    file_names = [f"{draw(FILE_NAME)}_{k}" for k in range(len(mapped))]  # unique by their number
    name_of = {**dict(zip(mapped, file_names)), **{c: c for c in values if c not in mapped}}
    order = draw(st.permutations(list(values)))
    header_line = draw(st.sampled_from(["default", "explicit", "none"]))
    names = [name_of[c] for c in order] if header_line != "none" else [f"column_{k + 1}" for k in range(len(order))]

    def text(name: str, v: float) -> str:
        if math.isnan(v):
            return token
        t = repr(v) if name == "time" else draw(st.sampled_from(FORMATS[:4]))(v)
        return t.replace(".", ",") if decimal == "," else t

    cells = [[text(c, values[c][i]) for c in order] for i in range(n)]
    preamble = draw(st.lists(st.text(st.characters(exclude_characters="\r\n", exclude_categories=("Cs",))), max_size=2))
    lines = list(preamble)
    if comment and draw(st.booleans()):
        lines.append("# a comment before the header")
    if header_line != "none":
        lines.append(("# " if comment and header_line == "explicit" and draw(st.booleans()) else "") + sep.join(names))
    header_number = len(lines)
    for row in cells:
        if draw(st.integers(0, 4)) == 0:
            lines.append(draw(st.sampled_from(["", "# between"] if comment else [""])))
        lines.append(sep.join(row) + (" # note" if comment and draw(st.integers(0, 3)) == 0 else ""))

    file_section = {"format": fmt} if draw(st.booleans()) else {}
    if fmt == "csv" and delimiter != ",":
        file_section["delimiter"] = delimiter
    if decimal == ",":
        file_section["decimal"] = ","
    if comment:
        file_section["comment"] = comment
    if preamble:
        file_section["skip_rows"] = len(preamble)
    if header_line != "default":
        file_section["header"] = header_number if header_line == "explicit" else 0
    if token:
        file_section["missing"] = ["", token] if fmt != "whitespace" else [token]
    columns = {}
    for name in mapped:
        position = order.index(name) + 1
        columns[name] = position if header_line == "none" or draw(st.integers(0, 3)) == 0 else names[position - 1]
    columns["keep_unmapped"] = keep_unmapped
    units = {"mag": mag, "angles": angles, "latlon": latlon, "time": time_unit, "time_epoch": epoch}
    if mag == "counts":
        units.update(mag_scale_nt_per_count=scale, ref=ref)
    if epoch == "start":
        units["start_utc"] = START
    document = {"description": "generated", "file": file_section, "columns": columns, "units": units}

    def read_back(name: str) -> np.ndarray:  # the numbers the file holds
        k = order.index(name)
        return np.array([math.nan if row[k] == token else float(row[k].replace(",", ".")) for row in cells])

    expected = {}
    for name in mapped:
        v = read_back(name)
        if name == "time":
            v = v / PER_SECOND[time_unit] + (START.timestamp() if epoch == "start" else 0.0)
        elif name in MAG and mag != "nT":
            v = v * scale
        elif name in REF and ref != "nT":
            v = v * NT_PER_UNIT[ref]
        elif name in radians:
            v = np.degrees(v)
        expected[name] = v
    if keep_unmapped:
        expected.update({names[order.index(c)]: read_back(c) for c in values if c not in mapped})
    suffix = {"csv": ".csv", "tsv": draw(st.sampled_from([".tsv", ".tab"])), "whitespace": ".txt"}[fmt]
    return Mapped(lines, names, cells, document, expected, suffix)


def read_through_map(data: bytes, suffix: str, map_text: bytes | str):
    """``read_mapped`` of a data file and a map file written side by side: the result or InputError, the two
    paths; fails on any other exception or a change to either file."""
    map_bytes = map_text.encode("utf-8") if isinstance(map_text, str) else map_text
    path, map_path = FOLDER / f"table{suffix}", FOLDER / "map.toml"
    path.write_bytes(data)
    map_path.write_bytes(map_bytes)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UnitWarning)
            result = read_mapped(path, map_path)
        cmap = load_column_map(map_path)
    except InputError as exc:
        result, cmap = exc, None
    assert path.read_bytes() == data and map_path.read_bytes() == map_bytes, "the reader changed a file"
    return result, cmap, str(path), str(map_path)


def check_mapped(result, data: bytes, path: str, map_path: str) -> None:
    """An error names the data file or the map file in one line; a table has one time per record, finite and
    strictly increasing, and only finite or missing values."""
    if isinstance(result, InputError):
        assert result.source in (path, map_path), str(result)
        check_error(result, result.source, data if result.source == path else None)
        return
    table, provenance = result
    assert provenance["file"] == path and provenance["map"] == map_path
    t = table["time"].to_numpy()
    assert list(table.columns[:4]) == ["time", *MAG] and len(t) > 0
    assert np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)
    for column in table.columns:
        assert table[column].to_numpy().dtype == float and not np.isinf(table[column].to_numpy()).any()


@pytest.mark.slow
@settings(PROPERTY, max_examples=60)
@given(mapped_tables(), st.sampled_from(["\n", "\r\n"]), st.booleans())
def test_a_valid_mapped_table_reads_back_exactly(case, newline, bom):
    data = (("\ufeff" if bom else "") + newline.join(case.lines) + newline).encode("utf-8")
    result, _, path, map_path = read_through_map(data, case.suffix, toml(case.document))
    assert not isinstance(result, InputError), str(result)
    check_mapped(result, data, path, map_path)
    table, _ = result
    assert set(table.columns) == set(case.expected)
    for name, values in case.expected.items():
        np.testing.assert_array_equal(table[name].to_numpy(), values, err_msg=name)


MAP_KEYS = {
    "file": ("format", "delimiter", "comment", "header", "skip_rows", "decimal", "encoding", "missing", "sheet"),
    "columns": ("time", *MAG, *ATTITUDE, "q0", "lat", "lon", "ref_n", "dop", "keep_unmapped", "aux"),
    "units": (
        "mag", "mag_scale_nt_per_count", "ref", "angles", "latlon", "time", "time_epoch", "start_utc", "date_utc",
        "quaternion_order", "quaternion_frame", "speed",
    ),
}  # fmt: skip
HUGE = (Raw("1" + "0" * 5000), Raw("-" + "9" * 400), Raw("9" * 400))
ODD_DATES = (date(2021, 6, 30), datetime(2024, 5, 1, 10, 20), datetime(9999, 12, 31, tzinfo=UTC), date(1, 1, 1))
#: Values a map key may be given that are wrong, or right in a way the generated table does not expect.
KEY_VALUES = {
    "format": ("csv", "tsv", "whitespace", "parquet", "xlsx", ""),
    "delimiter": (",", ";", "\t", " ", ".", "#", "ab", "", "\n"),
    "comment": ("#", ";", ",", ".", " ", "1", "e", "\r"),
    "header": (0, 1, 2, 3, 100, -1, True, 1.5, *HUGE),
    "skip_rows": (0, 1, 2, 100, -1, False, *HUGE),
    "decimal": (",", ".", ";", ""),
    "encoding": ("latin-1", "utf-16", "ascii", "cp037", "rot13", "hex", "base64", "zlib", "idna", "punycode", "x"),
    "missing": ([""], ["", "*"], "*", [1], [], ["0.0"], ["", "NaN", "inf"]),
    "mag": ("nT", "uT", "mG", "G", "T", "counts"),
    "mag_scale_nt_per_count": (0, -1.5, 1e300, math.nan, math.inf, True, "5", *HUGE),
    "ref": ("nT", "uT", "counts", ""),
    "angles": ("deg", "rad", "grad"),
    "latlon": ("deg", "rad", ""),
    "time": ("s", "ms", "us", "ns", "min"),
    "time_epoch": ("unix", "start", "seconds_of_day", "gps"),
    "start_utc": (*ODD_DATES, "2024-05-01T10:20:30Z", "not a date", 5),
    "date_utc": (*ODD_DATES, "2021-06-30", "30/06/2021", 5),
    "quaternion_order": ("wxyz", "xyzw", "zyx"),
    "quaternion_frame": ("body_to_ned", "ned_to_body", "x"),
    "keep_unmapped": (True, False, "yes", 1),
}
TOML_SCALARS = st.one_of(
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.sampled_from(HUGE),
    st.floats(),
    st.text(max_size=6),
    st.dates(),
    st.datetimes(timezones=st.sampled_from([None, UTC])),
)
TOML_VALUES = st.one_of(
    TOML_SCALARS, st.lists(TOML_SCALARS, max_size=3), st.dictionaries(st.text(max_size=3), TOML_SCALARS, max_size=2)
)


@st.composite
def damaged_maps(draw, case: Mapped) -> str | bytes:
    """The case's map, one to four keys set (often to a value chosen for that key), deleted or made a table; and
    sometimes its text re-encoded with a few bytes inserted."""
    document = copy.deepcopy(case.document)
    for _ in range(draw(st.integers(1, 4))):
        section = draw(st.sampled_from([*MAP_KEYS, None]))
        target = document if section is None else document.setdefault(section, {})
        if not isinstance(target, dict):
            continue
        action = draw(st.sampled_from(["set", "set", "set", "delete", "section"]))
        if action == "section":
            document[draw(st.sampled_from([*MAP_KEYS, "extra"]))] = draw(TOML_SCALARS)
        elif action == "delete" and target:
            del target[draw(st.sampled_from(sorted(target)))]
        elif section is None:
            target[draw(st.sampled_from(["description", "x"]))] = draw(TOML_VALUES)
        else:
            key = draw(st.sampled_from(MAP_KEYS[section]) | NAME)
            if section == "columns" and key != "keep_unmapped":
                special = st.sampled_from(case.names) | st.integers(-1, len(case.names) + 1) | st.sampled_from(HUGE)
            else:
                special = st.sampled_from(KEY_VALUES.get(key, HUGE))
            target[key] = draw(special if draw(st.integers(0, 3)) else TOML_VALUES)
    text = toml(document)
    if draw(st.integers(0, 4)) == 0:
        data = text.encode(draw(st.sampled_from(["utf-8", "latin-1", "utf-16"])), errors="replace")
        k = draw(st.integers(0, len(data)))
        return data[:k] + draw(st.binary(max_size=3)) + data[k:]
    return text


@pytest.mark.slow
@settings(PROPERTY, max_examples=100)
@given(st.data())
def test_a_damaged_column_map_is_used_validly_or_refused_naming_it(data):
    case = data.draw(mapped_tables())
    content = ("\n".join(case.lines) + "\n").encode("utf-8")
    map_text = data.draw(damaged_maps(case))
    result, cmap, path, map_path = read_through_map(content, case.suffix, map_text)
    check_mapped(result, content, path, map_path)
    event("refused" if isinstance(result, InputError) else "read")
    if isinstance(result, InputError) or cmap.time_epoch == "seconds_of_day":
        return
    table, _ = result
    assert file_format(cmap, case) != "csv" or cmap.decimal != (cmap.delimiter or ","), "decimal mark = delimiter"
    original = load_column_map_text(toml(case.document))
    layout = ("delimiter", "comment", "header", "skip_rows", "decimal", "encoding", "missing")
    if any(getattr(cmap, k) != getattr(original, k) for k in layout) or file_format(cmap, case) != file_format(
        original, case
    ):
        return  # another layout: the cells read are not those generated, and only the checks above apply
    assert len(table) == len(case.cells)

    def column(spec) -> np.ndarray:
        k = spec - 1 if isinstance(spec, int) else case.names.index(spec)
        return np.array([math.nan if row[k] in cmap.missing else float(row[k].replace(",", ".")) for row in case.cells])

    t = column(cmap.columns["time"]) / PER_SECOND[cmap.time]
    if cmap.time_epoch == "start":
        t = cmap.start_utc.timestamp() + t
    np.testing.assert_array_equal(table["time"].to_numpy(), t)
    for name in MAG:
        np.testing.assert_array_equal(table[name].to_numpy(), column(cmap.columns[name]) * cmap.mag_nt_per_unit)


def file_format(cmap, case: Mapped) -> str:
    return cmap.format or EXTENSION_FORMATS[case.suffix]


def load_column_map_text(text: str):
    path = FOLDER / "original.toml"
    path.write_text(text, encoding="utf-8")
    return load_column_map(path)


@pytest.mark.slow
@settings(PROPERTY, max_examples=80)
@given(st.data())
def test_a_damaged_mapped_table_is_read_validly_or_refused_naming_the_file(data):
    case = data.draw(mapped_tables())
    lines = list(case.lines)
    for _ in range(data.draw(st.integers(1, 3))):
        k = data.draw(st.integers(0, len(lines) - 1))
        kind = data.draw(st.sampled_from(["cell", "cell", "cut", "add", "line"]))
        sep = data.draw(st.sampled_from([",", ";", "|", "\t", " "]))
        cells = lines[k].split(sep)
        if kind == "cell":
            cells[data.draw(st.integers(0, len(cells) - 1))] = data.draw(ANY_CELL)
        elif kind == "cut":
            cells = cells[: data.draw(st.integers(0, len(cells)))]
        elif kind == "add":
            cells.append(data.draw(ANY_CELL))
        else:
            lines.insert(k, data.draw(st.text(max_size=8)))
            continue
        lines[k] = sep.join(cells)
    content, _ = render(Grid([lines[0]], [[line] for line in lines[1:]]), data.draw(strange_layouts(len(lines) - 1)))
    result, cmap, path, map_path = read_through_map(content, case.suffix, toml(case.document))
    check_mapped(result, content, path, map_path)
    event("refused" if isinstance(result, InputError) else "read")
    if isinstance(result, InputError):
        return
    table, _ = result
    found = records(content.decode("utf-8-sig"), cmap, file_format(cmap, case))
    assert len(table) == len(found), "one row per record"
    mag = table[list(MAG)].to_numpy()
    original = data_lines(case)
    for j, line in enumerate(found):  # the records left as generated read as generated
        if line in original:
            np.testing.assert_array_equal(mag[j], [case.expected[c][original[line]] for c in MAG])


def records(text: str, cmap, fmt: str) -> list[str]:
    """The record lines of a table as the map describes it: after ``skip_rows`` and the header line (given, or
    the first line neither blank nor a comment), every line that is neither."""
    blank = " \t" if fmt == "whitespace" else " "
    out, header = [], cmap.header
    for number, line in enumerate(re.split(r"\r\n|\r|\n", text), start=1):
        content = line.strip(blank)
        if number <= cmap.skip_rows or (header and number <= header):
            continue
        if not content or (cmap.comment and content.startswith(cmap.comment)):
            continue
        if header is None:
            header = number
            continue
        out.append(line)
    return out


def data_lines(case: Mapped) -> dict[str, int]:
    """The generated record lines, each with its row in the table."""
    found = records("\n".join(case.lines), load_column_map_text(toml(case.document)), EXTENSION_FORMATS[case.suffix])
    return {line: i for i, line in enumerate(found)}
