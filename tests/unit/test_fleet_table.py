"""The fleet's summary written from the journal a group of vehicles at a time (``magkf.fleet_table``): the same
table as made in one piece, whatever the groups and the order of the journal's parts; every file of the
dataset with the same columns and types; only the columns asked for read back."""

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from magkf.fleet import COMPARED, _table, _views, disagreements
from magkf.fleet_table import JOURNAL, SUMMARY, SUMMARY_CSV, part_name, read_summary, write_rows, write_summary


def rows(seed: int = 3) -> list:
    """Summary rows of 5 vehicles of 2 to 4 logs: estimates with standard deviations, an integer count, a
    failed log (no figures), and an effect's parameter only some logs have."""
    rng = np.random.default_rng(seed)
    out = []
    for v in range(5):
        for k in range(int(rng.integers(2, 5))):
            row = {"log": f"/f/V{v}/flight{k}.csv", "vehicle": f"V{v}", "error": "", "reused": bool(k % 2)}
            row.update({"format": "csv", "start_time": 1.78e9 + 3600 * k, "n_epochs": int(rng.integers(100, 200))})
            row.update({name: float(rng.normal()) for name in COMPARED})
            row.update({f"std_{name}": float(rng.uniform(0.5, 2.0)) for name in COMPARED})
            if v == 2:
                row["temperature_bias_x"] = float(rng.normal())
            out.append(row)
    out.append({"log": "/f/V1/bad.csv", "vehicle": "V1", "error": "/f/V1/bad.csv: row 2: 3 cells", "reused": False})
    return out


def arrange(frame: pd.DataFrame) -> pd.DataFrame:
    return disagreements(_table(frame), 0.01)


def journal(out, all_rows: list, batch: int, seed: int) -> list:
    """The rows written as journal parts of ``batch`` rows each, in a shuffled order of the logs."""
    (out / JOURNAL).mkdir(parents=True)
    order = np.random.default_rng(seed).permutation(len(all_rows))
    parts = []
    for k, i in enumerate(range(0, len(order), batch)):
        parts.append(out / JOURNAL / part_name(k))
        write_rows([all_rows[j] for j in order[i : i + batch]], parts[-1])
    return parts


def test_summary_in_groups_is_the_summary_in_one_piece(tmp_path):
    all_rows = rows()
    expected = arrange(pd.DataFrame(all_rows))
    tables = {}
    for limit, batch in ((6, 3), (10_000, 5)):
        out = tmp_path / f"limit{limit}"
        write_summary(out, journal(out, all_rows, batch, limit), arrange, _views(), limit=limit)
        files = sorted((out / SUMMARY).glob("part-*.parquet"))
        assert len(files) > 1 if limit == 6 else len(files) == 1
        assert len({pq.read_schema(f) for f in files}) == 1  # every file the same columns and types
        tables[limit] = read_summary(out)
        assert len(pd.read_csv(out / SUMMARY_CSV, keep_default_na=False)) == len(all_rows)
        pd.testing.assert_frame_equal(tables[limit], expected, check_dtype=False)
    pd.testing.assert_frame_equal(tables[6], tables[10_000])
    assert tables[6]["n_epochs"].dtype == float  # a failed log has no count: NaN, as in the table in one piece
    assert tables[6]["temperature_bias_x"].notna().sum() == sum("temperature_bias_x" in r for r in all_rows)


def test_columns_read_alone_and_an_earlier_single_file_replaced(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    pd.DataFrame({"log": ["old"]}).to_parquet(out / SUMMARY)  # the summary as an earlier magkf wrote it
    assert read_summary(out)["log"].tolist() == ["old"]
    all_rows = rows(seed=5)
    write_summary(out, journal(out, all_rows, 3, 1), arrange, _views(), limit=5)
    assert (out / SUMMARY).is_dir()
    few = read_summary(out, ["vehicle", "error", "no_such_column"])
    assert list(few.columns) == ["vehicle", "error"] and len(few) == len(all_rows)
    assert few["vehicle"].is_monotonic_increasing
    # no staging folder or file left (the journal is the caller's to remove)
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name != JOURNAL]


def test_csv_cells_quoted_only_where_needed(tmp_path):
    """The CSV as a spreadsheet writes it: the header and plain cells bare, only a cell holding a comma quoted."""
    out = tmp_path / "out"
    all_rows = rows(seed=7)
    all_rows[-1]["error"] = "/f/V1/bad.csv: row 2: 3 cells, 4 expected"
    write_summary(out, journal(out, all_rows, 4, 2), arrange, _views(), limit=6)
    lines = (out / SUMMARY_CSV).read_text(encoding="utf-8").splitlines()
    assert not lines[0].startswith('"') and lines[1].split(",")[1] == "V0"
    assert sum('"/f/V1/bad.csv: row 2: 3 cells, 4 expected"' in line for line in lines) == 1
    assert pd.read_csv(out / SUMMARY_CSV, keep_default_na=False)["error"].str.len().gt(0).sum() == 1


def test_only_this_hosts_dead_leftovers_are_removed(tmp_path):
    """A staging folder of a process of this host that is gone is removed; one of a live process, or of another
    host's process of any number (a shared folder), is left."""
    import os

    from magkf import fleet_table

    out = tmp_path / "out"
    out.mkdir()
    dead = 2**22 + 12345  # above the kernel's default pid_max (4 194 304): no such process
    names = {
        f".{SUMMARY}.{fleet_table._HOST}-{dead}-00000000.tmp": False,
        f".{SUMMARY}.{fleet_table._HOST}-{os.getpid()}-00000000.tmp": True,
        f".{SUMMARY}.otherhost{fleet_table._HOST}-{dead}-00000000.tmp": True,
    }
    for name in names:
        (out / name).mkdir()
    fleet_table._remove_dead_leftovers(out)
    assert {name: (out / name).exists() for name in names} == names
