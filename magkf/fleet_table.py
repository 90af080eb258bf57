"""A fleet's summary on disk, written a part at a time so that no process holds every row of a large fleet.

While a fleet runs, each batch of logs gives its rows to the worker that ran it, which writes them as one
Parquet file, ``DIR/rows/part-NNNNNN.parquet`` (``write_rows``; NNNNNN is the batch's number): the run's
journal, which the client never gathers. Once every batch is done, ``write_summary`` makes the summary from
the journal, a group of vehicles at a time (each group at most ``PART_ROWS`` rows, a vehicle never split):
the rows of the group are read, put in their columns' order and sorted, given the per-vehicle views that
need all of a vehicle's logs (``views``, such as ``magkf.fleet.disagreements``), and written as one file of
the Parquet dataset ``DIR/summary.parquet/part-NNNNNN.parquet`` (files in the summary's order, every file
with the same columns and types) and appended to ``DIR/summary.csv``. The dataset replaces the earlier
summary only once complete, and the journal is then removed.

``read_summary(DIR, columns)`` reads the dataset (or a summary written as one file by an earlier magkf),
all of it or only the columns asked for: the fleet's views read only the few columns they use.
"""

from __future__ import annotations

import os
import secrets
import shutil
import socket
from pathlib import Path

import pandas as pd

__all__ = ["JOURNAL", "SUMMARY", "SUMMARY_CSV", "PART_ROWS", "part_name", "write_rows", "read_summary", "write_summary"]

#: The folder of the journal (each batch's rows), under the output folder: a name with a leading dot, which no
#: vehicle's folder has (``fleet._safe`` strips them), so that removing it never removes a vehicle's outputs.
JOURNAL = ".journal"
#: The summary's Parquet dataset (a folder) and its CSV file, under the output folder.
SUMMARY = "summary.parquet"
SUMMARY_CSV = "summary.csv"
#: The most rows of one file of the summary's dataset (a vehicle with more logs is one file of its own).
PART_ROWS = 10_000
#: Columns that hold text (an empty cell: "").
TEXT = (
    "log",
    "vehicle",
    "error",
    "format",
    "verdict",
    "undetermined",
    "recommended_effects",
    "warnings",
    "output",
    "worker",
    "disagreement",
)


def part_name(index: int) -> str:
    """The file name of part ``index`` (0-based) of the journal or of the summary's dataset."""
    return f"part-{index:06d}.parquet"


def write_rows(rows: list, path) -> None:
    """Write ``rows`` (summary rows as dicts) as one Parquet file at ``path``, replaced only once complete."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from .files import written

    table = pa.Table.from_pandas(pd.DataFrame(rows), preserve_index=False)
    with written(path) as tmp:
        pq.write_table(table, tmp)


def read_summary(out_dir, columns=None) -> pd.DataFrame:
    """The summary of the fleet written into ``out_dir`` (the whole table, or only ``columns``, those it has),
    rows in the summary's order. Raises FileNotFoundError when there is none."""
    import pyarrow.parquet as pq

    path = Path(out_dir) / SUMMARY
    if not path.exists():
        raise FileNotFoundError(f"{path}: no fleet summary here")
    if columns is not None:
        present = set(pq.read_schema(_first_file(path)).names)
        columns = [c for c in columns if c in present]
    return pq.read_table(path, columns=columns).to_pandas()


def _first_file(path: Path) -> Path:
    """The file of a summary that is one file, or the first file of a dataset."""
    return path if path.is_file() else min(p for p in path.glob("part-*.parquet"))


def _index(parts: list) -> tuple[pd.DataFrame, dict]:
    """``(index, types)``: each row's ``vehicle`` and the number of the journal ``parts`` (paths) holding it,
    and the Arrow type of every column of the parts (their union, in order of first appearance)."""
    import pyarrow.parquet as pq

    vehicles, numbers, seen = [], [], {}
    for number, part in enumerate(parts):
        schema = pq.read_schema(part)
        for name, kind in zip(schema.names, schema.types):
            seen.setdefault(name, []).append(kind)
        column = pq.read_table(part, columns=["vehicle"]).column("vehicle").to_pylist()
        vehicles.extend(column)
        numbers.extend([number] * len(column))
    index = pd.DataFrame({"vehicle": vehicles, "part": numbers})
    return index, {name: _merged(name, kinds) for name, kinds in seen.items()}


def _merged(name: str, kinds: list):
    """One Arrow type for the column ``name`` that the journal's parts hold as ``kinds``."""
    import pyarrow as pa

    if name in TEXT:
        return pa.string()
    known = {k for k in kinds if not pa.types.is_null(k)}
    if not known:
        return pa.float64()  # missing in every row (a figure a log could not give: NaN, or null in row.json)
    if len(known) == 1:
        return known.pop()
    if any(pa.types.is_string(k) or pa.types.is_large_string(k) for k in known):
        return pa.string()
    return pa.float64()


def _groups(index: pd.DataFrame, limit: int) -> list[list]:
    """The vehicles in sorted order cut into consecutive groups of at most ``limit`` rows (a vehicle with more
    rows is a group of its own)."""
    counts = index.groupby("vehicle", sort=True).size()
    groups, current, size = [], [], 0
    for vehicle, n in counts.items():
        if current and size + n > limit:
            groups.append(current)
            current, size = [], 0
        current.append(vehicle)
        size += n
    if current:
        groups.append(current)
    return groups


def _rows_of(group: list, index: pd.DataFrame, parts: list) -> pd.DataFrame:
    """The rows of the vehicles ``group`` read from the journal ``parts`` that hold them, one part at a time."""
    import pyarrow.parquet as pq

    wanted = set(group)
    numbers = sorted(index.loc[index["vehicle"].isin(wanted), "part"].unique())
    frames = []
    for number in numbers:
        frame = pq.read_table(parts[number]).to_pandas()
        frames.append(frame[frame["vehicle"].isin(wanted)])
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _arrow(frame: pd.DataFrame, schema):
    """``frame`` as an Arrow table of exactly ``schema`` (columns it lacks are empty)."""
    import pyarrow as pa

    arrays = []
    for name, kind in zip(schema.names, schema.types):
        values = frame[name] if name in frame else pd.Series([None] * len(frame), dtype=object)
        if pa.types.is_string(kind):
            values = values.astype(object).where(values.notna(), None).map(lambda v: v if v is None else str(v))
        elif pa.types.is_boolean(kind):
            values = values.astype(object).where(values.notna(), None)
        elif values.dtype == object:
            values = pd.to_numeric(values, errors="coerce")
        arrays.append(pa.array(values.to_numpy(), type=kind, from_pandas=True))
    return pa.Table.from_arrays(arrays, schema=schema)


def write_summary(out_dir, parts: list, arrange, views: dict, limit: int = PART_ROWS) -> Path:
    """Make the summary of ``out_dir`` from the journal files ``parts`` (paths, in the order of the logs), a
    group of at most ``limit`` rows of whole vehicles at a time: ``arrange(frame)`` gives a group's rows in the
    summary's columns and order with the per-vehicle views added (``views``: the Arrow type of each column it
    adds). Writes the dataset ``SUMMARY`` and ``SUMMARY_CSV``, each replacing the earlier one once complete;
    returns the dataset's path."""
    import pyarrow as pa

    out = Path(out_dir)
    _remove_dead_leftovers(out)
    index, types = _index(parts)
    names = list(arrange(pd.DataFrame(columns=list(types))).columns)
    kinds = {**types, **views}
    schema = pa.schema([(name, pa.string() if name in TEXT else kinds.get(name, pa.float64())) for name in names])
    tag = f"{_HOST}-{os.getpid()}-{secrets.token_hex(4)}"
    staging = out / f".{SUMMARY}.{tag}.tmp"
    staging.mkdir()
    csv_tmp = out / f".{SUMMARY_CSV}.{tag}.tmp"
    try:
        _write_groups(staging, csv_tmp, schema, (_rows_of(g, index, parts) for g in _groups(index, limit)), arrange)
        # the dataset first, then the CSV: a run stopped between the two leaves the new dataset beside the old CSV,
        # which the next run replaces, never a new CSV beside an old dataset that readers take as the summary
        _swap(staging, out / SUMMARY)
        os.replace(csv_tmp, out / SUMMARY_CSV)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        csv_tmp.unlink(missing_ok=True)
    return out / SUMMARY


def _write_groups(staging: Path, csv_tmp: Path, schema, groups, arrange) -> None:
    """Each group's rows arranged and written as the next file of the dataset in ``staging`` and appended to the
    CSV ``csv_tmp`` (by pandas: a cell is quoted only where it holds a comma, a quote or a line end, as a
    spreadsheet writes it)."""
    import pyarrow.parquet as pq

    with open(csv_tmp, "w", encoding="utf-8", newline="") as csv_file:
        written_any = False
        for k, rows in enumerate(groups):
            table = _arrow(arrange(rows), schema)
            pq.write_table(table, staging / part_name(k))
            table.to_pandas().to_csv(csv_file, header=not written_any, index=False, lineterminator="\n")
            written_any = True
        if not written_any:  # no log: one empty file keeps the dataset's columns
            empty = _arrow(pd.DataFrame(columns=schema.names), schema)
            pq.write_table(empty, staging / part_name(0))
            empty.to_pandas().to_csv(csv_file, index=False, lineterminator="\n")


#: This machine's name as it goes into a staging name (dots and dashes out of it: the name's fields are split on them).
_HOST = "".join(c for c in socket.gethostname() if c.isalnum()) or "host"


def _swap(new: Path, target: Path) -> None:
    """The folder ``new`` moved onto ``target`` (a folder, an earlier magkf's file, or nothing)."""
    if not target.exists():
        os.replace(new, target)
        return
    old = target.with_name(f".{target.name}.{_HOST}-{os.getpid()}-{secrets.token_hex(4)}.old")
    os.replace(target, old)
    os.replace(new, target)
    if old.is_dir():
        shutil.rmtree(old, ignore_errors=True)
    else:
        old.unlink()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove_dead_leftovers(out: Path) -> None:
    """The staging folders and files that a killed run of this host left in ``out`` (its process gone); another
    host's, on a shared folder, are left alone."""
    for path in out.glob(".summary.*"):
        fields = path.name.split(".")[-2].split("-")  # .summary.<kind>.<host>-<pid>-<hex>.<tmp or old>
        if len(fields) != 3 or fields[0] != _HOST or not fields[1].isdigit() or _alive(int(fields[1])):
            continue
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
