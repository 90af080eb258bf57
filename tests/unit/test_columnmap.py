"""Reading any table through a column map: values against seeded synthetic truth, row numbers in errors,
and a property test (values come back exactly, or InputError, and the file is never changed)."""

from __future__ import annotations

import dataclasses
import re
import tempfile
import warnings
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from magkf.conventions import NT_PER_UNIT, euler_to_dcm, ned_to_body, wrap_deg
from magkf.errors import InputError
from magkf.io.columnmap import ColumnMap, load_column_map, read_mapped
from magkf.io.drivelog import UnitWarning

ROOT = Path(__file__).resolve().parents[2]
SURVEY_MAP = ROOT / "docs" / "examples" / "survey_map.toml"
DOCS = ROOT / "docs" / "column-maps.md"
# The ULP of a UNIX time near 1.7e9 s is 2.4e-7 s; sums of a day offset and seconds of day agree to a few ULP.
TIME_TOL = 1e-6


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def midnight(day: str) -> float:
    return datetime.fromisoformat(day).replace(tzinfo=UTC).timestamp()


# ---------------------------------------------------------------- the survey layout
def survey_truth(rng: np.random.Generator, n: int, t0_sod: float) -> dict[str, np.ndarray]:
    """A straight survey line at 5 Hz: attitude, reference field (IGRF-like plus an anomaly) and a fluxgate
    reading m = R C_nb^T B_ned + b + noise, with a seeded generator."""
    t = t0_sod + 0.2 * np.arange(n)
    pitch = 2.0 + np.cumsum(rng.normal(0, 0.05, n))
    roll = -1.0 + np.cumsum(rng.normal(0, 0.08, n))
    yaw = (87.3 + np.cumsum(rng.normal(0, 0.02, n))) % 360
    ref = np.array([17402.5, -301.3, 47388.9]) + rng.normal(0, 3.0, (n, 3))
    r_true = np.array([[1.02, 0.01, -0.004], [0.006, 0.985, 0.012], [-0.003, 0.008, 1.01]])
    body = ned_to_body(euler_to_dcm(yaw, pitch, roll), ref)
    mag = body @ r_true.T + np.array([120.0, -85.0, 240.0]) + rng.normal(0, 1.0, (n, 3))
    return {
        "time": t % 86400,
        "x": mag[:, 0],
        "y": mag[:, 1],
        "z": mag[:, 2],
        "pitch": pitch,
        "roll": roll,
        "yaw": yaw,
        "ref_n": ref[:, 0],
        "ref_e": ref[:, 1],
        "ref_d": ref[:, 2],
    }


SURVEY_FORMATS = {
    "time": "%.2f",
    "x": "%.3f",
    "y": "%.3f",
    "z": "%.3f",
    "pitch": "%.4f",
    "roll": "%.4f",
    "yaw": "%.4f",
    "ref_n": "%.2f",
    "ref_e": "%.2f",
    "ref_d": "%.2f",
}


def write_survey(path: Path, truth: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Write the survey extract (tab-separated); return the printed values, exactly as floats."""
    names = list(SURVEY_FORMATS)
    cells = {c: [SURVEY_FORMATS[c] % v for v in truth[c]] for c in names}
    lines = ["\t".join(names)] + ["\t".join(cells[c][i] for c in names) for i in range(len(truth["time"]))]
    write(path, "\n".join(lines) + "\n")
    return {c: np.array([float(s) for s in cells[c]]) for c in names}


@pytest.mark.parametrize("t0_sod, crosses", [(45296.0, False), (86400.0 - 7.3, True)])
def test_survey_extract_through_the_example_map(tmp_path, t0_sod, crosses):
    rng = np.random.default_rng(20210630)
    truth = survey_truth(rng, 120, t0_sod)
    printed = write_survey(tmp_path / "line_1040.tsv", truth)
    cmap = dataclasses.replace(load_column_map(SURVEY_MAP), date_utc="2021-06-30")
    table, prov = read_mapped(tmp_path / "line_1040.tsv", cmap)

    assert list(table.columns) == ["time", "mag_x", "mag_y", "mag_z", "roll", "pitch", "yaw", "ref_n", "ref_e", "ref_d"]
    assert len(table) == 120
    day = (np.arange(120) * 0.2 + t0_sod >= 86400).astype(float)
    assert day.any() == crosses
    expected_time = midnight("2021-06-30") + printed["time"] + 86400.0 * day
    np.testing.assert_allclose(table["time"], expected_time, rtol=0, atol=TIME_TOL)
    assert np.all(np.diff(table["time"]) > 0.19)  # 5 Hz, also across midnight
    for canonical, column in [
        ("mag_x", "x"),
        ("mag_y", "y"),
        ("mag_z", "z"),
        ("roll", "roll"),
        ("pitch", "pitch"),
        ("yaw", "yaw"),
        ("ref_n", "ref_n"),
        ("ref_e", "ref_e"),
        ("ref_d", "ref_d"),
    ]:
        np.testing.assert_array_equal(table[canonical].to_numpy(), printed[column])  # exact: no conversion
        step = float(SURVEY_FORMATS[column][2:-1])
        np.testing.assert_allclose(table[canonical], truth[column], rtol=0, atol=0.5 * 10**-step + 1e-9)
    assert prov["format"] == "mapped-table" and prov["map"] == str(SURVEY_MAP)
    assert prov["columns"]["mag_x"] == "x (nT)" and prov["columns"]["pitch"] == "pitch (deg)"
    assert ("1 midnight rollover" in prov["time_base"]) == crosses
    if crosses:
        first_next_day = int(np.argmax(day))
        assert f"the first at row {first_next_day + 2}" in prov["time_base"]


def test_survey_map_without_a_date_takes_the_day_from_date(tmp_path):
    """Seconds of day with no ``[units] date_utc``: refused without ``--date``; with ``--date`` (its midnight UTC
    the zero) the same times as a map that gives the date, across midnight too."""
    from magkf.io.readers import read_log
    from magkf.io.site import Site, parse_date

    write_survey(tmp_path / "s.tsv", survey_truth(np.random.default_rng(1), 60, 86_390.0))
    with pytest.raises(InputError, match=r"s\.tsv: the log has no GNSS time .* give --date"):
        read_log(tmp_path / "s.tsv", map=SURVEY_MAP)
    dated = dataclasses.replace(load_column_map(SURVEY_MAP), date_utc="2021-06-30")
    placed = read_log(tmp_path / "s.tsv", map=SURVEY_MAP, site=Site(start=parse_date("2021-06-30")))
    np.testing.assert_array_equal(placed.time, read_log(tmp_path / "s.tsv", map=dated).time)
    assert placed.time[-1] - midnight("2021-06-30") > 86_400.0  # the record crossed midnight


# ---------------------------------------------------------------- CSV: quaternion, counts, ms since start
@pytest.mark.parametrize("attitude", ["quaternion xyzw body_to_ned", "quaternion xyzw ned_to_body", "euler rad"])
def test_csv_quaternion_counts_and_milliseconds_since_start(tmp_path, attitude):
    rng = np.random.default_rng(7)
    n = 60
    yaw, pitch, roll = rng.uniform(0, 360, n), rng.uniform(-60, 60, n), rng.uniform(-170, 170, n)
    counts = rng.integers(-2000, 2000, (n, 3))
    t_ms = np.cumsum(rng.integers(5, 30, n))
    lat, lon = np.radians(rng.uniform(50, 52, n)).tolist(), np.radians(rng.uniform(-3, -2, n)).tolist()
    scale = 6.6667  # nT per count
    if attitude.startswith("quaternion"):
        q_xyzw = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True).as_quat()
        assert np.allclose(Rotation.from_quat(q_xyzw).as_matrix(), euler_to_dcm(yaw, pitch, roll))
        if attitude.endswith("ned_to_body"):
            q_xyzw[:, :3] *= -1
        att_header, att_cells = "qx,qy,qz,qw", [",".join(f"{v:.9f}" for v in q) for q in q_xyzw]
        att_map = 'q0 = "qx"\nq1 = "qy"\nq2 = "qz"\nq3 = "qw"'
        frame = attitude.split()[-1]
        att_units = f'quaternion_order = "xyzw"\nquaternion_frame = "{frame}"'
    else:
        att_header = "phi,theta,psi"
        att_cells = [",".join(repr(float(np.radians(a))) for a in rpy) for rpy in zip(roll, pitch, yaw)]
        att_map, att_units = 'roll = "phi"\npitch = "theta"\nyaw = "psi"', 'angles = "rad"'
    lines = [f"t_ms,{att_header},cx,cy,cz,lat_r,lon_r,T_board"]
    for i in range(n):
        lines.append(
            f"{t_ms[i]},{att_cells[i]},{counts[i, 0]},{counts[i, 1]},{counts[i, 2]},"
            f"{lat[i]!r},{lon[i]!r},{20 + i * 0.1:.1f}"
        )
    write(tmp_path / "log.csv", "\n".join(lines) + "\n")
    write(
        tmp_path / "map.toml",
        f"""
[columns]
time = "t_ms"
mag_x = "cx"
mag_y = "cy"
mag_z = "cz"
lat = "lat_r"
lon = "lon_r"
temp_c = "T_board"
{att_map}
[units]
mag = "counts"
mag_scale_nt_per_count = {scale}
time = "ms"
time_epoch = "start"
start_utc = "2024-05-01T10:20:30.250Z"
latlon = "rad"
{att_units}
""",
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnitWarning)  # random counts are not an Earth-like field
        table, prov = read_mapped(tmp_path / "log.csv", tmp_path / "map.toml")
    start = datetime(2024, 5, 1, 10, 20, 30, 250000, tzinfo=UTC).timestamp()
    np.testing.assert_allclose(table["time"], start + t_ms / 1000.0, rtol=0, atol=TIME_TOL)
    np.testing.assert_array_equal(table[["mag_x", "mag_y", "mag_z"]].to_numpy(), counts * scale)
    np.testing.assert_array_equal(table["lat"], np.degrees(lat))
    np.testing.assert_array_equal(table["lon"], np.degrees(lon))
    np.testing.assert_array_equal(table["temp_c"], [float(f"{20 + i * 0.1:.1f}") for i in range(n)])
    # Quaternion components printed to 5e-10 move an angle by at most about 1e-9 rad (6e-8 deg) at |pitch| <= 60.
    tol = 1e-6 if attitude.startswith("quaternion") else 1e-12
    assert np.max(np.abs(wrap_deg(table["yaw"] - yaw))) < tol
    assert np.max(np.abs(table["pitch"] - pitch)) < tol
    assert np.max(np.abs(wrap_deg(table["roll"] - roll))) < tol
    if attitude.startswith("quaternion"):
        assert np.all((table["yaw"] >= 0) & (table["yaw"] < 360))
        assert prov["columns"]["yaw"].startswith("qx, qy, qz, qw (quaternion xyzw")
    assert prov["columns"]["mag_x"] == "cx (counts x 6.6667 nT/count)"
    assert prov["time_base"] == "milliseconds since 2024-05-01T10:20:30.250000Z"
    assert prov["units"]["mag"] == "counts" and prov["units"]["mag_scale_nt_per_count"] == scale


# ---------------------------------------------------------------- whitespace with comments
WHITESPACE_MAP = """
[file]
format = "whitespace"
comment = "#"
missing = ["*"]
[columns]
time = "t"
mag_x = "bx"
mag_y = "by"
mag_z = "bz"
[units]
mag = "uT"
"""

WHITESPACE_LINES = [
    "# magnetometer test, bench 3",  # 1
    "# units: s uT uT uT degC",  # 2
    "  t      bx      by     bz    temp_c   note",  # 3: header
    "1000.0  20.125  1.500  44.250  21.5  ok",  # 4
    "# operator changed the cable",  # 5
    "",  # 6
    "1000.5  20.130  *      44.260  21.6  ok  # no y sample",  # 7
    "1001.0  20.120  1.510  44.240  *     ok",  # 8
]


def test_whitespace_file_with_comment_lines(tmp_path):
    write(tmp_path / "bench.txt", "\n".join(WHITESPACE_LINES) + "\n")
    write(tmp_path / "map.toml", WHITESPACE_MAP)
    table, prov = read_mapped(tmp_path / "bench.txt", tmp_path / "map.toml")
    np.testing.assert_array_equal(table["time"], [1000.0, 1000.5, 1001.0])
    np.testing.assert_array_equal(table["mag_x"], [20.125 * 1000, 20.130 * 1000, 20.120 * 1000])
    np.testing.assert_array_equal(table["mag_y"], [1.5 * 1000, np.nan, 1.51 * 1000])
    np.testing.assert_array_equal(table["temp_c"], [21.5, 21.6, np.nan])  # unmapped numeric column carried
    assert "note" not in table and prov["ignored"]["note"] == "unmapped text column"
    assert prov["columns"]["mag_y"] == "by (uT x 1000 -> nT)"


@pytest.mark.parametrize("line, column, bad", [(4, "bx", "20.1.25"), (7, "bz", "44.2x"), (8, "by", "abc")])
def test_whitespace_bad_cell_is_reported_at_its_file_line(tmp_path, line, column, bad):
    lines = list(WHITESPACE_LINES)
    names = lines[2].split()
    cells = lines[line - 1].split("#")[0].split()
    cells[names.index(column)] = bad
    lines[line - 1] = "  ".join(cells)
    path = write(tmp_path / "bench.txt", "\n".join(lines) + "\n")
    write(tmp_path / "map.toml", WHITESPACE_MAP)
    with pytest.raises(InputError) as err:
        read_mapped(path, tmp_path / "map.toml")
    assert (err.value.source, err.value.row, err.value.column) == (str(path), line, column)
    assert str(err.value) == f"{path}, row {line}, column '{column}': not a number: '{bad}'"


def test_skipped_preamble_and_explicit_commented_header_keep_file_line_numbers(tmp_path):
    text = "Logger XY-3\nserial 42\n# t;x;y;z\n0;1,5;2;3\n\n100;1,5;2,25;bad\n"
    path = write(tmp_path / "log.csv", text)
    write(
        tmp_path / "map.toml",
        '[file]\ndelimiter = ";"\ndecimal = ","\ncomment = "#"\nskip_rows = 2\n'
        'header = 3\n[columns]\ntime = "t"\nmag_x = "x"\nmag_y = 3\nmag_z = "z"\n'
        '[units]\ntime = "ms"\n',
    )
    with pytest.raises(InputError) as err:
        read_mapped(path, tmp_path / "map.toml")
    assert (err.value.row, err.value.column) == (6, "z")
    write(path, text.replace("bad", "3,5"))
    table, prov = read_mapped(path, tmp_path / "map.toml")
    np.testing.assert_array_equal(table["time"], [0.0, 0.1])
    np.testing.assert_array_equal(table[["mag_x", "mag_y", "mag_z"]].to_numpy(), [[1.5, 2, 3], [1.5, 2.25, 3.5]])
    assert prov["columns"]["mag_y"] == "y (nT)"  # the map named it by position


# ---------------------------------------------------------------- Parquet
def test_parquet_file(tmp_path):
    rng = np.random.default_rng(11)
    n = 40
    t = 1.7e9 + np.cumsum(rng.uniform(0.05, 0.15, n))
    mag = rng.normal(0, 300, (n, 3)) + [180.0, -20.0, 450.0]  # mG, about 50 000 nT
    mag[5, 1] = np.nan
    current = pa.array([float(v) if i != 9 else None for i, v in enumerate(rng.uniform(0, 12, n))])
    pq.write_table(
        pa.table(
            {
                "ts": t,
                "mx": mag[:, 0],
                "my": mag[:, 1],
                "mz": mag[:, 2],
                "r": rng.uniform(-5, 5, n),
                "p": rng.uniform(-5, 5, n),
                "h": rng.uniform(0, 360, n),
                "I_bus": current,
                "sats": pa.array(rng.integers(5, 20, n), pa.int32()),
                "mode": pa.array(["AUTO"] * n),
            }
        ),
        tmp_path / "log.parquet",
    )
    write(
        tmp_path / "map.toml",
        '[columns]\ntime = "ts"\nmag_x = "mx"\nmag_y = "my"\nmag_z = "mz"\n'
        'roll = "r"\npitch = "p"\nyaw = "h"\ncurrent_a = "I_bus"\n[units]\nmag = "mG"\n',
    )
    table, prov = read_mapped(tmp_path / "log.parquet", tmp_path / "map.toml")
    source = pq.read_table(tmp_path / "log.parquet").to_pydict()
    np.testing.assert_array_equal(table["time"], t)
    np.testing.assert_array_equal(table[["mag_x", "mag_y", "mag_z"]].to_numpy(), mag * 100.0)
    np.testing.assert_array_equal(table["yaw"], source["h"])
    np.testing.assert_array_equal(table["current_a"], [np.nan if v is None else v for v in source["I_bus"]])
    np.testing.assert_array_equal(table["sats"], source["sats"])  # unmapped integer column carried
    assert "mode" not in table and prov["file_format"] == "parquet"

    pq.write_table(
        pa.table({"ts": t, "mx": mag[:, 0], "my": np.where(np.arange(n) == 17, np.inf, mag[:, 1]), "mz": mag[:, 2]}),
        tmp_path / "bad.parquet",
    )
    write(tmp_path / "map2.toml", '[columns]\ntime = "ts"\nmag_x = "mx"\nmag_y = "my"\nmag_z = "mz"\n')
    with pytest.raises(InputError) as err:
        read_mapped(tmp_path / "bad.parquet", tmp_path / "map2.toml")
    assert (err.value.row, err.value.column) == (19, "my")  # record 17 is row 19, as in the CSV twin


# ---------------------------------------------------------------- errors name file, row, column (or map and key)
BASIC_MAP = '[columns]\ntime = "t"\nmag_x = "x"\nmag_y = "y"\nmag_z = "z"\n'
BASIC_CSV = "t,x,y,z\n1.0,20000,100,40000\n2.0,20001,101,40001\n3.0,20002,102,40002\n"


def basic(tmp_path, csv=BASIC_CSV, toml=BASIC_MAP):
    return write(tmp_path / "log.csv", csv), write(tmp_path / "map.toml", toml)


@pytest.mark.parametrize(
    "csv, toml, row, column, words",
    [
        (BASIC_CSV, BASIC_MAP.replace('"y"', '"Y_nT"'), 1, "Y_nT", ["[columns] mag_y", "map.toml", "t, x, y, z"]),
        (BASIC_CSV.replace("20001", "2O001"), BASIC_MAP, 3, "x", ["not a number: '2O001'"]),
        (BASIC_CSV.replace("101", "NaN"), BASIC_MAP, 3, "y", ["not a number: 'NaN'"]),
        (BASIC_CSV.replace("102", "inf"), BASIC_MAP, 4, "y", ["not a finite number: inf"]),
        (BASIC_CSV.replace("2.0,", ","), BASIC_MAP, 3, "t", ["empty time cell"]),
        (BASIC_CSV.replace("3.0,", "1.5,"), BASIC_MAP, 4, "t", ["not strictly increasing"]),
        (BASIC_CSV.replace("40001", "40001,7"), BASIC_MAP, 3, None, ["5 fields where the header has 4"]),
        ("t,x,y,z,aux\n1,2e4,0,4e4,5\n2,2e4,0,4e4,x\n", BASIC_MAP, 3, "aux", ["keep_unmapped = false"]),
        ("t,x,y,z\n1,2e4,0,4e4,9\n2,2e4,0,4e4\n", BASIC_MAP, 2, None, ["more fields than the header"]),
        (
            "t,x,y,z,qw,qx,qy,qz\n1,2e4,0,4e4,1,0,0,0\n2,2e4,0,4e4,0,0,0,0\n",
            BASIC_MAP + 'q0 = "qw"\nq1 = "qx"\nq2 = "qy"\nq3 = "qz"\n',
            3,
            "qw",
            ["quaternion is zero"],
        ),
    ],
)
def test_bad_table_errors(tmp_path, csv, toml, row, column, words):
    path, cmap = basic(tmp_path, csv, toml)
    with pytest.raises(InputError) as err, warnings.catch_warnings():
        warnings.simplefilter("ignore", UnitWarning)
        read_mapped(path, cmap)
    text = str(err.value)
    assert "\n" not in text
    if row is not None:
        assert (err.value.source, err.value.row) == (str(path), row)
        assert text.startswith(f"{path}, row {row}")
    if column is not None:
        assert err.value.column == column and f"column '{column}'" in text
    for word in words:
        assert word in text


def test_seconds_of_day_decrease_shorter_than_half_a_day_is_an_error(tmp_path):
    path, cmap = basic(
        tmp_path,
        "t,x,y,z\n86000,1,2,3\n50000,1,2,3\n",
        BASIC_MAP + '[units]\ntime_epoch = "seconds_of_day"\ndate_utc = 2021-06-30\n',
    )
    match = r"row 3, column 't': time not strictly increasing .*midnight rollover"
    with pytest.raises(InputError, match=match), warnings.catch_warnings():
        warnings.simplefilter("ignore", UnitWarning)
        read_mapped(path, cmap)


@pytest.mark.parametrize(
    "toml, words",
    [
        (BASIC_MAP + '[units]\nmag = "nanotesla"\n', ["[units] mag", "'nanotesla'", "nT, uT, mG, G, counts"]),
        (BASIC_MAP + '[units]\nangle = "rad"\n', ["[units] angle: unknown key"]),
        (BASIC_MAP + '[unit]\nmag = "uT"\n', ["unknown key 'unit'"]),
        (BASIC_MAP + '[file]\ndelim = ";"\n', ["[file] delim: unknown key"]),
        (BASIC_MAP + '[units]\nmag = "counts"\n', ["[units] mag_scale_nt_per_count"]),
        (BASIC_MAP + "[units]\nmag_scale_nt_per_count = 2.0\n", ["[units] mag_scale_nt_per_count", "only applies"]),
        (BASIC_MAP + '[units]\ntime_epoch = "start"\nstart_utc = "yesterday"\n', ["[units] start_utc", "ISO 8601"]),
        (BASIC_MAP + '[units]\ntime = "min"\n', ["[units] time", "'min'"]),
        (BASIC_MAP + '[units]\nquaternion_order = "zyxw"\n', ["[units] quaternion_order"]),
        (BASIC_MAP + 'roll = "r"\n', ["[columns] pitch", "roll, pitch, yaw"]),
        (BASIC_MAP + 'mag_x = "x"\n', ["not valid TOML"]),
        (BASIC_MAP + '[file]\ncomment = "//"\n', ["[file] comment", "single character"]),
        (BASIC_MAP + '[file]\nencoding = "rot13"\n', ["[file] encoding", "unknown text encoding 'rot13'"]),
        (BASIC_MAP + '[file]\nencoding = "hex"\n', ["[file] encoding", "unknown text encoding 'hex'"]),
        (BASIC_MAP + '[file]\nencoding = "x"\n', ["[file] encoding", "unknown text encoding 'x'"]),
    ],
)
def test_bad_map_errors_name_the_map_file_and_key(tmp_path, toml, words):
    _, cmap = basic(tmp_path, toml=toml)
    with pytest.raises(InputError) as err:
        load_column_map(cmap)
    assert err.value.source == str(cmap) and str(err.value).startswith(f"{cmap}: ")
    for word in words:
        assert word in str(err.value)


@pytest.mark.parametrize(
    "toml, words",
    [
        (BASIC_MAP.replace('mag_z = "z"\n', ""), ["[columns] mag_z: required: say which file column holds it"]),
        (BASIC_MAP.replace('time = "t"\n', ""), ["[columns] time: required", "or give [units] rate_hz"]),
    ],
)
def test_a_drive_log_needs_time_and_magnetometer_columns_named_by_the_map(tmp_path, toml, words):
    """Which columns are required is the reader's to say: a drive log needs ``time`` (or ``rate_hz``) and the three
    magnetometer axes; the map itself loads (an offline calibration may need other columns)."""
    path, cmap = basic(tmp_path, toml=toml)
    load_column_map(cmap)
    with pytest.raises(InputError) as err:
        read_mapped(path, cmap)
    assert err.value.source == str(cmap) and str(err.value).startswith(f"{cmap}: ")
    for word in words:
        assert word in str(err.value)


def test_headerless_file_by_position_and_unit_warning(tmp_path):
    path = write(tmp_path / "raw.csv", "1.5,20.1,1.2,44.0,7\n2.5,20.2,1.3,44.1,8\n")
    cmap = ColumnMap({"time": 1, "mag_x": 2, "mag_y": 3, "mag_z": 4}, header=0, keep_unmapped=False)
    with pytest.warns(UnitWarning, match=r"median 48\.\d+ nT after conversion\) look like uT, not nT"):
        table, prov = read_mapped(path, cmap)
    np.testing.assert_array_equal(table["mag_x"], [20.1, 20.2])
    assert list(table.columns) == ["time", "mag_x", "mag_y", "mag_z"]
    assert prov["columns"]["time"] == "column_1 (UNIX seconds (UTC))"
    assert prov["ignored"] == {"column_5": "unmapped (keep_unmapped = false)"}
    table, _ = read_mapped(path, dataclasses.replace(cmap, mag="uT"))  # no warning once the unit is right
    np.testing.assert_array_equal(table["mag_z"], [44.0 * 1000, 44.1 * 1000])


def test_missing_files(tmp_path):
    path, cmap = basic(tmp_path)
    with pytest.raises(InputError, match=r"nowhere\.toml: no such column map file"):
        read_mapped(path, tmp_path / "nowhere.toml")
    with pytest.raises(InputError, match=r"nowhere\.csv: no such file"):
        read_mapped(tmp_path / "nowhere.csv", cmap)
    with pytest.raises(InputError, match=r"set \[file\] format"):
        read_mapped(write(tmp_path / "log.weird", BASIC_CSV), cmap)
    with pytest.raises(InputError, match=r"\[file\] delimiter does not apply .* Parquet"):
        pq.write_table(pa.table({"t": [1.0]}), tmp_path / "x.parquet")
        read_mapped(tmp_path / "x.parquet", write(tmp_path / "m2.toml", '[file]\ndelimiter = ";"\n' + BASIC_MAP))


def test_documented_complete_example_reads(tmp_path):
    """The complete example in docs/column-maps.md: its data and its map, exactly as printed there."""
    doc = DOCS.read_text(encoding="utf-8")
    section = doc[doc.index("## A complete example") : doc.index("## The survey example")]
    data, toml = re.findall(r"```(?:toml)?\n(.*?)```", section, flags=re.DOTALL)
    path = write(tmp_path / "logger.csv", data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnitWarning)
        table, prov = read_mapped(path, write(tmp_path / "logger.toml", toml))
    assert list(table.columns) == [
        "time",
        "mag_x",
        "mag_y",
        "mag_z",
        "roll",
        "pitch",
        "yaw",
        "lat",
        "lon",
        "alt",
        "temp_c",
    ]
    start = datetime(2024, 5, 1, 10, 20, 30, 250000, tzinfo=UTC).timestamp()
    np.testing.assert_allclose(table["time"], [start, start + 0.1], rtol=0, atol=TIME_TOL)
    np.testing.assert_array_equal(table["mag_x"], [2145 * 6.6667, 2151 * 6.6667])
    np.testing.assert_array_equal(table["alt"], [102.5, 102.6])
    np.testing.assert_array_equal(table["temp_c"], [31.2, np.nan])
    np.testing.assert_allclose(table["lat"], np.degrees([0.895456, 0.895456]))
    # q = (x, y, z, w) ~ (0.012, -0.003, 0.707, 0.707): a quarter turn about down, yaw about 90 deg
    assert np.all(np.abs(table["yaw"] - 90) < 1.0) and np.all(np.abs(table["roll"]) < 2.0)
    assert prov["columns"]["mag_x"] == "mx (counts x 6.6667 nT/count)"
    assert prov["time_base"] == "milliseconds since 2024-05-01T10:20:30.250000Z"
    assert prov["ignored"] == {"flags": "unmapped text column"}


def test_documented_survey_example_reads(tmp_path):
    doc = DOCS.read_text(encoding="utf-8")
    data = re.findall(r"```\n(.*?)```", doc[doc.index("## The survey example") :], flags=re.DOTALL)[0]
    cmap = dataclasses.replace(load_column_map(SURVEY_MAP), date_utc="2021-06-30")
    table, _ = read_mapped(write(tmp_path / "line.tsv", data), cmap)
    expected = [midnight("2021-06-30") + 86399.2, midnight("2021-06-30") + 86399.4, midnight("2021-07-01") + 0.6]
    np.testing.assert_allclose(table["time"], expected, rtol=0, atol=TIME_TOL)
    np.testing.assert_array_equal(table["pitch"], [2.1034, 2.1102, 2.1187])
    np.testing.assert_array_equal(table["ref_d"], [47388.90, 47388.95, 47388.97])


# ---------------------------------------------------------------- property test
TEXT_CELLS = ("abc", "1.2.3", "--", "0x1G")
NUMBER = st.one_of(st.floats(allow_nan=False, allow_infinity=False), st.just(float("nan")))


@st.composite
def tables(draw):
    """Columns in random order and file format; numbers with NaNs, sometimes one text cell, sometimes
    unsorted time."""
    n = draw(st.integers(1, 12))
    time = draw(st.lists(st.floats(-1e12, 1e12, allow_nan=False), min_size=n, max_size=n, unique=True))
    if draw(st.integers(0, 3)):
        time = sorted(time)
    columns = {"t": time}
    for name in ("bx", "by", "bz", "aux1"):
        columns[name] = draw(st.lists(NUMBER, min_size=n, max_size=n))
    if not draw(st.integers(0, 3)):
        name = draw(st.sampled_from(list(columns)))
        columns[name][draw(st.integers(0, n - 1))] = draw(st.sampled_from(TEXT_CELLS))
    order = draw(st.permutations(list(columns)))
    fmt = draw(st.sampled_from(["csv", "tsv", "whitespace", "parquet"]))
    mag_unit = draw(st.sampled_from(list(NT_PER_UNIT)))
    time_unit = draw(st.sampled_from(["s", "ms", "us"]))
    return {c: columns[c] for c in order}, fmt, mag_unit, time_unit


def write_table(path: Path, columns: dict[str, list], fmt: str) -> None:
    n = len(next(iter(columns.values())))
    if fmt == "parquet":
        arrays = {}
        for name, cells in columns.items():
            if any(isinstance(v, str) for v in cells):
                arrays[name] = pa.array([None if isinstance(v, float) and np.isnan(v) else str(v) for v in cells])
            else:
                arrays[name] = pa.array(cells, pa.float64())
        pq.write_table(pa.table(arrays), path)
        return
    sep = {"csv": ",", "tsv": "\t", "whitespace": "  "}[fmt]
    missing = "NaN" if fmt == "whitespace" else ""

    def cell(v):
        return v if isinstance(v, str) else (missing if np.isnan(v) else repr(v))

    lines = [sep.join(columns)] + [sep.join(cell(columns[c][i]) for c in columns) for i in range(n)]
    path.write_text("\n".join(lines) + "\n")


@settings(max_examples=50, deadline=None, derandomize=True, database=None)
@given(tables())
def test_property_values_come_back_exactly_or_input_error(generated):
    columns, fmt, mag_unit, time_unit = generated
    file_section = '[file]\nmissing = ["NaN"]\n' if fmt == "whitespace" else ""
    cmap = load_column_map_text(
        file_section
        + BASIC_MAP.replace('"x"', '"bx"').replace('"y"', '"by"').replace('"z"', '"bz"')
        + f'[units]\nmag = "{mag_unit}"\ntime = "{time_unit}"\n'
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / ("table.txt" if fmt == "whitespace" else f"table.{fmt}")
        write_table(path, columns, fmt)
        before = path.read_bytes()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UnitWarning)
                table, _ = read_mapped(path, cmap)
        except InputError:
            table = None
        assert path.read_bytes() == before
    if table is None:
        return
    factor = {"s": 1.0, "ms": 1e3, "us": 1e6}[time_unit]
    np.testing.assert_array_equal(table["time"], np.asarray(columns["t"], float) / factor)
    for canonical, name in (("mag_x", "bx"), ("mag_y", "by"), ("mag_z", "bz")):
        np.testing.assert_array_equal(table[canonical], np.asarray(columns[name], float) * NT_PER_UNIT[mag_unit])
    aux = columns["aux1"]
    if "aux1" in table:
        np.testing.assert_array_equal(table["aux1"], np.asarray(aux, float))
    else:
        assert all(isinstance(v, str) or np.isnan(v) for v in aux) and any(isinstance(v, str) for v in aux)


def load_column_map_text(text: str) -> ColumnMap:
    with tempfile.TemporaryDirectory() as tmp:
        return load_column_map(write(Path(tmp) / "map.toml", text))


@pytest.mark.parametrize("value", ["true", "3", '"NaN"', "{ a = 1 }"])
def test_missing_that_is_not_a_list_of_strings_is_refused_naming_it(tmp_path, value):
    """``[file] missing`` must be a list of strings: a boolean or a number is refused as such, not a TypeError."""
    write(
        tmp_path / "map.toml",
        f'[file]\nmissing = {value}\n[columns]\ntime = "t"\nmag_x = "x"\nmag_y = "y"\nmag_z = "z"\n',
    )
    with pytest.raises(InputError, match=r"\[file\] missing: .* is not a list of strings"):
        load_column_map(tmp_path / "map.toml")


@pytest.mark.parametrize(
    "extra, warned", [("hop", "hdop"), ("currnt_a", "current_a"), ("T_board", None), ("temp_k", None)]
)
def test_a_column_one_slip_from_a_known_one_is_warned(tmp_path, extra, warned):
    """A [columns] key one slip away from a column with a meaning (that the map does not map) is warned with the
    nearest name; other names, and a second channel beside its first (mag_x2 beside mag_x), are taken silently."""
    import warnings

    from magkf.io.columnmap import load_column_map

    path = tmp_path / "map.toml"
    path.write_text(f'[columns]\ntime = "t"\nmag_x = "x"\nmag_x2 = "x2"\n{extra} = "e"\n')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_column_map(path)
    said = [str(w.message) for w in caught]
    if warned is None:
        assert said == []
    else:
        assert said == [
            f"{path}: [columns] {extra} is not one of magkf's columns and is read as an auxiliary "
            f"channel; did you mean {warned}?"
        ]
