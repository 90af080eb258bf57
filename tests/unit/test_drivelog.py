import warnings

import numpy as np
import pytest

from magkf.errors import InputError
from magkf.io.drivelog import UnitWarning, read_drive_log
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA

HEADER = "time,mag_x,mag_y,mag_z,roll,pitch,yaw,lat,lon"
GOOD = [
    "1780308000.00,20000,1000,43000,0,0,10,48.1,11.6",
    "1780308000.02,20010,1010,43010,0,0,11,48.1,11.6",
    "1780308000.04,20020,1020,43020,0,0,12,48.1,11.6",
]


def _write(tmp, lines, header=HEADER):
    path = tmp / "log.csv"
    path.write_text("\n".join([header, *lines]) + "\n")
    return path


def test_reads_the_example_log():
    log = read_drive_log(DATA / "example_drive.csv")
    assert len(log) == 12_000 and log.has_attitude and log.has_position
    assert log.auxiliary == ["speed_mps", "temp_c", "current_a"]
    assert np.all(np.diff(log.time) > 0) and log.mag.shape == (12_000, 3)


def test_round_trip_through_csv(tmp):
    sim = simulate_drive(DriveConfig(duration_s=20, rate_hz=10, seed=3))
    sim.write(tmp / "a.csv")
    log = read_drive_log(tmp / "a.csv")
    assert np.allclose(log.mag, sim.table[["mag_x", "mag_y", "mag_z"]].to_numpy(), atol=1e-6)
    assert np.allclose(log.time, sim.table.index.to_numpy(), atol=1e-3)


def test_empty_cells_are_kept_as_missing(tmp):
    path = _write(tmp, [GOOD[0], "1780308000.02,,1010,43010,,,,,", GOOD[2]])
    log = read_drive_log(path)
    assert len(log) == 3 and np.isnan(log.mag[1, 0]) and np.isnan(log.attitude[1]).all()


@pytest.mark.parametrize(
    "lines,header,where",
    [
        (GOOD, "time,mag_x,mag_y,roll,pitch,yaw,lat,lon", "row 1, column 'mag_z'"),
        ([GOOD[0], GOOD[1].replace("20010", "abc"), GOOD[2]], HEADER, "row 3, column 'mag_x'"),
        ([GOOD[0], GOOD[1], GOOD[2].replace("1020", "NaN")], HEADER, "row 4, column 'mag_y'"),
        ([GOOD[0], GOOD[1].replace("43010", "inf")], HEADER, "row 3, column 'mag_z'"),
        ([GOOD[0], GOOD[2], GOOD[1]], HEADER, "row 4, column 'time'"),
        ([GOOD[0], GOOD[0]], HEADER, "row 3, column 'time'"),
        ([GOOD[0], ",1,2,3,0,0,0,48,11"], HEADER, "row 3, column 'time'"),
        ([GOOD[0]], HEADER, "too few samples"),
        # a header one name short: pandas would take each row's first field as an index and shift the rest
        (GOOD, "time,mag_x,mag_y,mag_z,roll,pitch,lat,lon", "row 2: 9 fields where the header has 8"),
        ([",".join(g.split(",")[:6] + g.split(",")[7:]) for g in GOOD], HEADER.replace(",yaw", ""), "column 'yaw'"),
        (GOOD, "time,mag_x,mag_y,mag_z,roll,pitch,yaw,alt,dop", "row 1, column 'lat'"),
        ([GOOD[0], GOOD[1].replace(",0,0,11", ",0,95,11")], HEADER, "row 3, column 'pitch'"),
        ([], HEADER, "no data rows"),
    ],
)
def test_bad_input_names_file_row_and_column(tmp, lines, header, where):
    path = _write(tmp, lines, header)
    with pytest.raises(InputError, match=where) as err:
        read_drive_log(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_missing_file(tmp):
    with pytest.raises(InputError, match="no such file"):
        read_drive_log(tmp / "nothing.csv")


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_a_table_written_in_pieces_reads_back_whole(tmp, monkeypatch, suffix):
    """Written two rows at a time: a text column empty in the first piece, a boolean one with gaps and a header
    holding a comma come back as they were, in CSV (quoted where needed) and Parquet."""
    import pandas as pd

    import magkf.io.drivelog as drivelog

    monkeypatch.setattr(drivelog, "WRITE_ROWS", 2)
    t = 1.7e9 + np.array([0.5, 1.25, 2.0, 3.0, 4.0])
    table = pd.DataFrame(
        {
            "time": t,
            "mag_x": [1.0, np.nan, 3.0, 4.0, 5.0],
            "mag_y": [1.0, 2, 3, 4, 5],
            "mag_z": [1.0, 2, 3, 4, 5],
            "note": np.array([None, None, "a", "b,c", "d"], dtype=object),
            "a,b": [1.5, 2.5, 3.5, 4.5, 5.5],
        }
    ).set_index("time")
    path = tmp / f"log{suffix}"
    drivelog.write_drive_log(table, path)
    back = pd.read_parquet(path) if suffix == ".parquet" else pd.read_csv(path, keep_default_na=False, na_values=[""])
    assert np.allclose(back["time"], t, rtol=0, atol=1e-6)
    assert np.array_equal(back["mag_x"].isna(), table["mag_x"].isna().to_numpy())
    assert list(back["note"].fillna("")) == ["", "", "a", "b,c", "d"]
    assert np.allclose(back["a,b"], table["a,b"])


def test_a_unit_warning_says_what_the_reader_allows(tmp):
    """The advice follows the format: ``--mag-unit`` for a canonical table, nothing more from the epoch checks for a
    mapped table (its reader warns, naming the map's [units]), and no ``--mag-unit`` for an autopilot log, which
    states its unit."""
    from magkf.io.drivelog import from_table

    table = read_drive_log(_write(tmp, GOOD)).table.reset_index()
    table[["mag_x", "mag_y", "mag_z"]] /= 1000.0  # uT values
    with pytest.warns(UnitWarning, match="pass --mag-unit uT"):
        from_table(table, "a.csv", provenance={"format": "canonical-csv"})
    with pytest.warns(UnitWarning, match="look like uT") as caught:
        from_table(table, "a.bin", provenance={"format": "ardupilot-dataflash"})
    assert "--mag-unit" not in str(caught[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from_table(table, "a.tsv", provenance={"format": "mapped-table"})


def test_a_time_in_a_finer_unit_is_named():
    """UNIX milliseconds or microseconds are refused with the unit they look like; a log whose every interval is a
    gap is warned about its time's unit, not about one jump of its clock."""
    from magkf.io.drivelog import TimeBaseWarning, check_time_base

    t = 1.7e9 + np.arange(100) * 0.05
    for per, unit in ((1e3, "milliseconds"), (1e6, "microseconds")):
        with pytest.raises(InputError, match=f"looks like UNIX {unit}"):
            check_time_base(t * per, "log.csv")
    with pytest.warns(TimeBaseWarning, match=r"50 s apart .*99 of 99 .*0\.05 s apart"):
        check_time_base(1.7e9 + np.arange(100) * 50.0, "log.csv")
    with pytest.warns(TimeBaseWarning, match="the clock jumps by 60 s at row 52"):
        check_time_base(np.r_[t[:50], t[50:] + 60.0], "log.csv")


@pytest.mark.parametrize("name", ["table.csv", "table.parquet"])
def test_folder_given_as_a_table_is_named_a_folder(tmp, name):
    from magkf.io.tables import read_csv

    folder = tmp / name
    folder.mkdir()
    with pytest.raises(InputError, match="a folder, not a table file") as err:
        read_csv(folder)
    assert str(err.value).startswith(str(folder))
