"""Validated reading of the numeric CSV files in the data contract.

Every check names the file, the row (the line number in the file, header = row 1) and the column.
An empty cell is a missing value (NaN); any other cell must be a finite number.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputError

__all__ = [
    "HEADER_ROWS",
    "PARQUET_SUFFIXES",
    "file_row",
    "read_csv",
    "read_parquet",
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
        Missing file, missing or duplicated column, non-numeric or non-finite cell, no data rows.
    """
    path = Path(path)
    name = str(path)
    if path.suffix.lower() in PARQUET_SUFFIXES:  # the Parquet twin of a CSV file is read alike
        return read_parquet(path, required, text_columns)
    if not path.is_file():
        raise InputError("no such file", name)
    try:
        table = pd.read_csv(
            path, keep_default_na=False, na_values=[""], skipinitialspace=True, dtype={c: str for c in text_columns}
        )
    except pd.errors.EmptyDataError:
        raise InputError("the file is empty", name) from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise InputError(f"not a readable CSV file ({' '.join(str(exc).split())})", name) from None
    return _checked(table, name, required, text_columns, "the file has a header but no data rows")


def read_parquet(path, required: Iterable[str] = (), text_columns: Iterable[str] = ()) -> pd.DataFrame:
    """Read a Parquet table into a DataFrame of floats, with the checks of ``read_csv``; rows are named as the
    CSV twin's would be (record i is row i + 2, the header being row 1)."""
    path = Path(path)
    name = str(path)
    if not path.is_file():
        raise InputError("no such file", name)
    try:
        table = pd.read_parquet(path)
    except Exception as exc:  # pyarrow raises several types for a damaged or foreign file
        raise InputError(f"not a readable Parquet file ({' '.join(str(exc).split())[:200]})", name) from None
    return _checked(table, name, required, text_columns, "the file has no rows").reset_index(drop=True)


def _checked(table: pd.DataFrame, name: str, required, text_columns, empty: str) -> pd.DataFrame:
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
            table[column] = numeric_column(table[column], name, column)
    return table


def numeric_column(values: pd.Series, source: str, column: str) -> np.ndarray:
    """Convert one column to float, raising InputError at the first non-numeric or non-finite cell."""
    if pd.api.types.is_numeric_dtype(values.dtype) and not pd.api.types.is_bool_dtype(values.dtype):
        out = values.to_numpy(dtype=float)
    else:
        out = pd.to_numeric(values, errors="coerce").to_numpy(dtype=float)
        bad = np.isnan(out) & values.notna().to_numpy()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"not a number: {values.iloc[i]!r} (leave the cell empty for a missing value)",
                source,
                file_row(i),
                column,
            )
    infinite = np.isinf(out)
    if infinite.any():
        i = int(np.flatnonzero(infinite)[0])
        raise InputError("not a finite number (leave the cell empty for a missing value)", source, file_row(i), column)
    return out


def require_complete(table: pd.DataFrame, columns: Iterable[str], source: str) -> None:
    """Raise InputError naming the first empty cell among ``columns``."""
    for column in columns:
        empty = np.isnan(table[column].to_numpy(dtype=float))
        if empty.any():
            i = int(np.flatnonzero(empty)[0])
            raise InputError("empty cell where a value is required", source, file_row(i), column)


def require_rows(table: pd.DataFrame, minimum: int, source: str, what: str) -> None:
    """Raise InputError when ``table`` has fewer than ``minimum`` rows."""
    if len(table) < minimum:
        raise InputError(f"too few samples: {len(table)} rows, {what} needs at least {minimum}", source)
