"""The tables of the offline calibrations: magkf's CSV (or Parquet), or any table through a column map.

``magkf ellipsoid`` reads samples of a sensor, ``magkf sinefit`` a turntable run. Either reads magkf's CSV by
its column names, or, with ``--map MAP.toml``, any layout a column map describes (``docs/column-maps.md``: a
preamble, no header, whitespace or other delimiters, a MATLAB matrix). A text file that is not magkf's CSV
and comes without a map is refused in one line that names the map to write (``magkf.io.sniff``): magkf does
not guess which column is which axis.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import pandas as pd

from ..errors import InputError
from ..io.columnmap import read_mapped_table
from ..io.sniff import suggest_map
from ..io.tables import PARQUET_SUFFIXES, read_csv, require_complete, table_rows

__all__ = ["read_offline_table"]


def read_offline_table(
    path,
    required: Sequence[str],
    column_map=None,
    text_columns: Sequence[str] = (),
    mag_unit: str | None = None,
    left_out: Sequence[str] = (),
    fix: str = "",
) -> tuple[pd.DataFrame, Callable[[int], int]]:
    """The table of an offline calibration, with every ``required`` cell present.

    Parameters
    ----------
    path : str or Path
        magkf's CSV or Parquet table, or, with ``column_map``, any table the map describes.
    required : sequence of str
        The columns needed (canonical names, or the map's keys); those not in ``text_columns`` must hold a
        number in every record.
    column_map : str, Path or ColumnMap, optional
        Reads ``path`` through the map (``read_mapped_table``): the magnetometer columns then come in nT.
    text_columns : sequence of str
        Columns holding text (a turntable run's ``plane``).
    mag_unit : str, optional
        The unit the command was told the magnetometer columns are in: with a map only ``None`` or ``"nT"``
        (the map's ``[units] mag`` says the unit).
    left_out : sequence of str, optional
        Sensor columns the calibration would leave out (``mag_z`` of a two-axis fit chosen by default): a table
        that holds one is refused rather than read without it, with ``fix``, what to give instead, in words.
    fix : str, optional
        The options that would make it work, for the refusal of a ``left_out`` column.

    Returns
    -------
    table : pandas.DataFrame
        One row per record; the ``required`` columns as floats (``text_columns`` as text).
    row_of : callable
        ``row_of(i)``: the file row of record ``i``, as errors name it.

    Raises
    ------
    InputError
        One line naming the file, row and column: a missing column or an empty or non-numeric cell; for a text
        file that is not magkf's CSV and no map, the map that would read it.
    """
    required = list(required)
    name = str(path)
    if column_map is not None:
        if mag_unit not in (None, "nT"):
            raise InputError(f"--mag-unit {mag_unit} does not apply with --map: the map's [units] mag says the unit")
        table, _, rows = read_mapped_table(path, column_map, required, text_columns)

        def row_of(i: int) -> int:
            return int(rows[i])

    else:
        table = _read_canonical(path, required, text_columns)
        row_of = table_rows(table)
    dropped = [c for c in left_out if c in table.columns]
    if dropped:
        raise InputError(f"the table holds {', '.join(dropped)}, which the fit would leave out: {fix}", name)
    numeric = [c for c in required if c not in text_columns]
    require_complete(table, numeric, name, row_of)
    return table, row_of


def _read_canonical(path, required: list[str], text_columns) -> pd.DataFrame:
    """magkf's CSV or Parquet table; InputError naming the map to write for a text table in another layout."""
    if str(path).lower().endswith(".mat"):
        columns = ", ".join(f"{column} = {k}" for k, column in enumerate(required, start=1))
        raise InputError(
            'a MATLAB file: read it with --map MAP.toml, MAP.toml holding [file] variable = "NAME" (the matrix of '
            f"records) and [columns] naming which of its columns hold {', '.join(required)} by 1-based number, "
            f"e.g. {columns} (docs/column-maps.md)",
            str(path),
        )
    try:
        return read_csv(path, required=required, text_columns=text_columns)
    except InputError as exc:
        if str(path).lower().endswith(PARQUET_SUFFIXES) or exc.message == "no such file":
            raise
        suggestion = suggest_map(path, required)
        if suggestion is None:
            raise
        raise InputError(suggestion, str(path)) from None
