"""The layouts published calibration sets come in, read through a column map: a preamble, comment lines, no
header, whitespace, tab and semicolon delimiters, MATLAB matrices (v7.3 through h5py in both orientations, v5
through scipy), records at a fixed rate; each read back to the same table as magkf's CSV, the offline commands
reading them with --map, and the refusals word for word."""

from __future__ import annotations

import re
import warnings
from datetime import UTC, datetime
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import scipy.io

from magkf.cli import main
from magkf.errors import InputError
from magkf.io.columnmap import ColumnMap, load_column_map, read_mapped, read_mapped_table
from magkf.io.drivelog import UnitWarning
from magkf.io.site import Site
from magkf.offline.ellipsoid import EllipsoidCalibrator, parameter_names, patent_matrix
from magkf.offline.reading import read_offline_table
from magkf.offline.sinefit import read_turntable

ROOT = Path(__file__).resolve().parents[2]
TURNTABLE = ROOT / "data" / "turntable_example.csv"
START = datetime(2024, 5, 1, 10, 20, 30, 250000, tzinfo=UTC)
N = 60


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def truth_records(n: int = N, seed: int = 7) -> np.ndarray:
    """(n, 4) records ``[t, x, y, z]``: UNIX time at 10 Hz with jitter, a field of about 50 000 nT; seeded."""
    rng = np.random.default_rng(seed)
    t = START.timestamp() + 0.1 * np.arange(n) + rng.uniform(0, 0.01, n)
    mag = rng.normal([20000.0, -3000.0, 45000.0], 500.0, (n, 3))
    return np.column_stack([t, mag])


def text_lines(records: np.ndarray, sep: str) -> list[str]:
    """One line per record, each number printed with ``repr`` (read back exactly)."""
    return [sep.join(repr(float(v)) for v in row) for row in records]


CANONICAL_MAP = '[columns]\ntime = "time"\nmag_x = "mag_x"\nmag_y = "mag_y"\nmag_z = "mag_z"\n'
BY_POSITION = "[columns]\ntime = 1\nmag_x = 2\nmag_y = 3\nmag_z = 4\n"


def canonical(tmp_path: Path, records: np.ndarray) -> tuple[pd.DataFrame, dict]:
    path = tmp_path / "canonical.csv"
    write(path, "\n".join(["time,mag_x,mag_y,mag_z", *text_lines(records, ",")]) + "\n")
    return read_mapped(path, write(tmp_path / "canonical.toml", CANONICAL_MAP))


def layout_preamble(tmp_path, records):
    """Two lines of preamble, then a header with other names, comma-separated."""
    lines = ["Calibration set 7, sensor HMC-2", "recorded by the bench logger", "t,bx,by,bz", *text_lines(records, ",")]
    toml = '[file]\nskip_rows = 2\n[columns]\ntime = "t"\nmag_x = "bx"\nmag_y = "by"\nmag_z = "bz"\n'
    return write(tmp_path / "preamble.csv", "\n".join(lines) + "\n"), toml, [1, 2, 3]


def layout_comments(tmp_path, records):
    """Comment lines (with the comment character) before a header that is itself commented, and a blank line."""
    lines = ["% set 7", "% units nT", "", "% t x y z", *text_lines(records, " ")]
    toml = '[file]\ncomment = "%"\nheader = 4\ndelimiter = "whitespace"\n' + BY_POSITION
    return write(tmp_path / "comments.dat", "\n".join(lines) + "\n"), toml, [1, 2, 3, 4]


def layout_headerless_whitespace(tmp_path, records):
    """No header at all, blanks and tabs between the numbers, a two-line preamble."""
    lines = ["SET 7", "x y z in nT", *(line.replace(" ", " \t ") for line in text_lines(records, "  "))]
    toml = '[file]\nskip_rows = 2\nheader = 0\ndelimiter = "whitespace"\n' + BY_POSITION
    return write(tmp_path / "headerless.txt", "\n".join(lines) + "\n"), toml, [1, 2]


def layout_tab_named(tmp_path, records):
    """Tabs in a ``.txt`` file (its extension says whitespace): ``delimiter = "tab"`` decides."""
    lines = ["time\tx\ty\tz", *text_lines(records, "\t")]
    toml = '[file]\ndelimiter = "tab"\n[columns]\ntime = "time"\nmag_x = "x"\nmag_y = "y"\nmag_z = "z"\n'
    return write(tmp_path / "tabs.txt", "\n".join(lines) + "\n"), toml, [1]


def layout_semicolon(tmp_path, records):
    """Semicolons with decimal commas, no header."""
    lines = [line.replace(",", ";").replace(".", ",") for line in text_lines(records, ",")]
    toml = '[file]\ndelimiter = "semicolon"\ndecimal = ","\nheader = 0\n' + BY_POSITION
    return write(tmp_path / "semicolons.csv", "\n".join(lines) + "\n"), toml, []


def write_mat73(
    path: Path, variables: dict, matlab_class: bool = True, classes: dict | None = None, matlab_header: bool = True
) -> Path:
    """A MATLAB v7.3 file as MATLAB lays it out: a 512-byte header (its first 116 bytes saying the version, bytes
    124-127 the version 0x0200 and "IM") before HDF5, each array stored as given (MATLAB writes the transpose of
    its N x k matrix, shape (k, N)); ``classes`` names a variable's MATLAB class other than ``double`` (MATLAB
    stores text as ``char``: UTF-16 code units); ``matlab_header`` False: plain HDF5, as h5py writes it."""
    with h5py.File(path, "w", userblock_size=512 if matlab_header else 0) as f:
        for name, value in variables.items():
            dataset = f.create_dataset(name, data=value)
            if matlab_class:
                dataset.attrs["MATLAB_class"] = np.bytes_((classes or {}).get(name, "double"))
    if not matlab_header:
        return path
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Sat May  1 10:20:30 2024 HDF5 schema 1.00 ."
    header = header.ljust(116, b" ") + b"\0" * 8 + b"\x00\x02IM"
    with open(path, "r+b") as f:
        f.write(header.ljust(512, b"\0"))
    return path


def layout_mat73_matlab(tmp_path, records):
    """v7.3 as MATLAB writes an N x 4 matrix: the HDF5 dataset is (4, N)."""
    path = write_mat73(tmp_path / "set_t.mat", {"data": records.T, "info": np.array([[1.0]])})
    return path, '[file]\nvariable = "data"\n' + BY_POSITION, []


def layout_mat73_beside_settings(tmp_path, records):
    """v7.3 with a scalar and a vector saved beside the matrix: the only matrix is taken without naming it."""
    variables = {"data": records.T, "gain": np.array([[1.0]]), "offsets": np.array([[0.1, 0.2, 0.3]]).T}
    return write_mat73(tmp_path / "set_s.mat", variables), BY_POSITION, []


def layout_mat73_rows(tmp_path, records):
    """Plain HDF5 written by h5py with records as rows, (N, 4): the only matrix, so no variable named."""
    path = write_mat73(tmp_path / "set_n.mat", {"data": records}, matlab_class=False, matlab_header=False)
    return path, BY_POSITION, []


def layout_mat5(tmp_path, records):
    """MATLAB v5 (scipy.io.savemat), the matrix inside a struct: ``variable = "set.data"``."""
    path = tmp_path / "set5.mat"
    scipy.io.savemat(path, {"set": {"data": records, "name": "bench"}})
    return path, '[file]\nvariable = "set.data"\n' + BY_POSITION, []


LAYOUTS = [
    layout_preamble,
    layout_comments,
    layout_headerless_whitespace,
    layout_tab_named,
    layout_semicolon,
    layout_mat73_matlab,
    layout_mat73_beside_settings,
    layout_mat73_rows,
    layout_mat5,
]


@pytest.mark.parametrize("layout", LAYOUTS, ids=lambda f: f.__name__.removeprefix("layout_"))
def test_each_layout_reads_back_to_the_canonical_table(tmp_path, layout):
    """Every number is printed with repr (or stored as float64), so the tables agree exactly."""
    records = truth_records()
    expected, _ = canonical(tmp_path, records)
    path, toml, _ = layout(tmp_path, records)
    table, provenance = read_mapped(path, write(tmp_path / "layout.toml", toml))
    pd.testing.assert_frame_equal(table, expected, check_exact=True)
    np.testing.assert_array_equal(table["time"], records[:, 0])
    assert provenance["time_base"] == "UNIX seconds (UTC)"
    if path.suffix == ".mat":
        assert provenance["file_format"] == "mat" and "records" in provenance["notes"][0]


def test_rows_in_errors_count_the_preamble_and_the_header(tmp_path):
    """A bad cell on line 9 of a headerless file with a two-line preamble is row 9; in a MATLAB matrix, record i
    (from 0) is row i + 1, as MATLAB numbers it."""
    records = truth_records()
    path, toml, _ = layout_headerless_whitespace(tmp_path, records)
    lines = path.read_text().splitlines()
    lines[8] = lines[8].split()[0] + " 12.3.4 1 2"
    write(path, "\n".join(lines) + "\n")
    with pytest.raises(InputError) as err:
        read_mapped(path, write(tmp_path / "m.toml", toml))
    assert str(err.value) == f"{path}, row 9, column 'column_2': not a number: '12.3.4'"
    bad = records.copy()
    bad[4, 2] = np.inf
    mat = write_mat73(tmp_path / "bad.mat", {"data": bad.T})
    with pytest.raises(InputError) as err:
        read_mapped(mat, ColumnMap({"time": 1, "mag_x": 2, "mag_y": 3, "mag_z": 4}))
    assert str(err.value) == f"{mat}, row 5, column 'column_3': not a finite number: inf"


# ---------------------------------------------------------------- known truth through the offline commands
TRUTH3 = (np.array([1.1, 0.9, 1.05]), np.radians([2.0, -3.0, 1.5]), np.array([0.2, -0.1, 0.3]))


def test_ellipsoid_fit_of_a_headerless_whitespace_file_with_a_preamble_equals_the_canonical_fit(tmp_path, capsys):
    """The same samples as magkf's CSV and as ``x y z`` lines after a preamble: the same numbers read, so the same
    fit, bit for bit; and the fit finds the truth within 5 of its own standard errors (noise 0.002 on a unit
    sphere, 600 samples)."""
    rng = np.random.default_rng(11)
    k, angles, b = TRUTH3
    u = rng.normal(size=(600, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    X = u @ patent_matrix(k, angles).T + b + rng.normal(scale=0.002, size=u.shape)
    rows = [" ".join(repr(float(v)) for v in row) for row in X]
    write(tmp_path / "set.csv", "\n".join(["mag_x,mag_y,mag_z", *(r.replace(" ", ",") for r in rows)]) + "\n")
    write(tmp_path / "set.txt", "\n".join(["Published set 3", "x y z (normalised)", *rows]) + "\n")
    cmap = write(
        tmp_path / "set.toml",
        '[file]\nskip_rows = 2\nheader = 0\ndelimiter = "whitespace"\n[columns]\nmag_x = 1\nmag_y = 2\nmag_z = 3\n',
    )
    canonical_table, _ = read_offline_table(tmp_path / "set.csv", ["mag_x", "mag_y", "mag_z"])
    mapped_table, row_of = read_offline_table(tmp_path / "set.txt", ["mag_x", "mag_y", "mag_z"], cmap)
    assert row_of(0) == 3
    fits = [
        EllipsoidCalibrator(3, 1.0).fit(t[["mag_x", "mag_y", "mag_z"]].to_numpy()).result_
        for t in (canonical_table, mapped_table)
    ]
    np.testing.assert_array_equal(fits[0].R, fits[1].R)
    np.testing.assert_array_equal(fits[0].b, fits[1].b)
    truth = dict(zip(parameter_names(3), np.concatenate([k, np.degrees(angles), b])))
    for name, value in truth.items():
        assert abs(fits[1].parameters[name] - value) < 5 * fits[1].standard_errors[name], name

    assert main(["ellipsoid", str(tmp_path / "set.txt"), "--map", str(cmap), "--json"]) == 0
    through_cli = capsys.readouterr().out
    assert main(["ellipsoid", str(tmp_path / "set.csv"), "--json"]) == 0
    assert capsys.readouterr().out == through_cli.replace(str(tmp_path / "set.txt"), str(tmp_path / "set.csv"))


def test_sinefit_reads_a_turntable_run_through_a_map(tmp_path):
    """The example turntable run as whitespace text after a preamble, plane and angle in other columns, the
    field in uT: the same table as magkf's CSV in nT (values printed to the nT's 1e-6, so equal to 1e-9 nT)."""
    table = pd.read_csv(TURNTABLE)
    lines = ["# turntable run 2", "# angle plane bx by bz (uT)"]
    lines += [
        f"{row.angle_deg!r} {row.plane} {row.mag_x / 1000!r} {row.mag_y / 1000!r} {row.mag_z / 1000!r}"
        for row in table.itertuples()
    ]
    path = write(tmp_path / "run.dat", "\n".join(lines) + "\n")
    toml = (
        '[file]\ncomment = "#"\nheader = 0\n[columns]\nangle_deg = 1\nplane = 2\nmag_x = 3\nmag_y = 4\nmag_z = 5\n'
        '[units]\nmag = "uT"\n'
    )
    mapped = read_turntable(path, column_map=write(tmp_path / "run.toml", toml))
    expected = read_turntable(TURNTABLE)
    assert list(mapped["plane"]) == list(expected["plane"])
    for column in ("angle_deg", "mag_x", "mag_y", "mag_z"):
        np.testing.assert_allclose(mapped[column], expected[column], rtol=0, atol=1e-9)


# ---------------------------------------------------------------- a fixed sample rate
RATE_MAP = "[columns]\nmag_x = 1\nmag_y = 2\nmag_z = 3\n[file]\nheader = 0\n[units]\nrate_hz = 100\n"


def test_rate_hz_gives_exact_times_from_start_utc(tmp_path):
    """Record k is at start_utc + k / rate_hz: the same float expression, so equal exactly."""
    records = truth_records(250)
    path = write(tmp_path / "r.csv", "\n".join(text_lines(records[:, 1:], ",")) + "\n")
    toml = RATE_MAP + 'start_utc = "2024-05-01T10:20:30.25Z"\n'
    table, provenance = read_mapped(path, write(tmp_path / "r.toml", toml))
    np.testing.assert_array_equal(table["time"], START.timestamp() + np.arange(250) / 100.0)
    assert table["time"].iloc[100] - table["time"].iloc[0] == pytest.approx(1.0, abs=2.4e-7)  # one ULP near 1.7e9 s
    assert provenance["columns"]["time"] == "record number / 100 Hz from 2024-05-01T10:20:30.250000Z"
    assert provenance["units"]["rate_hz"] == 100


def test_rate_hz_without_a_start_is_time_since_boot_placed_by_date(tmp_path):
    """Without start_utc the times are k / rate_hz since the first record and the time base is "boot"; the drive
    log asks for --date, and with it the times are that UTC plus k / rate_hz."""
    from magkf.io.columnmap import MappedTable

    records = truth_records(50)
    path = write(tmp_path / "r.csv", "\n".join(text_lines(records[:, 1:], ",")) + "\n")
    cmap = write(tmp_path / "r.toml", RATE_MAP)
    table, provenance = read_mapped(path, cmap)
    np.testing.assert_array_equal(table["time"], np.arange(50) / 100.0)
    assert provenance["time_base"] == "boot" and "--date places it in UTC" in provenance["notes"][-1]
    assert "lat" not in table
    with pytest.raises(InputError) as err:
        MappedTable().read(path, map=cmap)
    assert str(err.value).startswith(f"{path}: the log has no GNSS time (its clock counts from boot)")
    site = Site(lat=48.1, lon=11.6, start=START.timestamp())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnitWarning)
        log = MappedTable().read(path, map=cmap, site=site)
    np.testing.assert_array_equal(log.time, START.timestamp() + np.arange(50) / 100.0)
    assert log.provenance["time_base"].startswith("given: --date")


def test_a_time_since_the_start_without_start_utc_is_boot_and_still_checked(tmp_path):
    """A time column counted from the start, no start_utc: time base "boot", the values as given (ms -> s); a
    time that goes back is still refused at its row and column."""
    lines = ["t_ms,x,y,z", "0,1,2,3", "10,1,2,3", "20,1,2,3"]
    toml = '[columns]\ntime = "t_ms"\nmag_x = "x"\nmag_y = "y"\nmag_z = "z"\n'
    toml += '[units]\ntime = "ms"\ntime_epoch = "start"\n'
    cmap = write(tmp_path / "m.toml", toml)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnitWarning)
        table, provenance = read_mapped(write(tmp_path / "a.csv", "\n".join(lines) + "\n"), cmap)
        np.testing.assert_array_equal(table["time"], [0.0, 0.01, 0.02])
        assert provenance["time_base"] == "boot"
        bad = write(tmp_path / "b.csv", "\n".join([*lines, "15,1,2,3"]) + "\n")
        with pytest.raises(InputError) as err:
            read_mapped(bad, cmap)
    assert str(err.value) == f"{bad}, row 5, column 't_ms': time not strictly increasing (15.0 after 20.0)"


# ---------------------------------------------------------------- refusals, word for word
def refusal(call) -> str:
    with pytest.raises(InputError) as err, warnings.catch_warnings():
        warnings.simplefilter("ignore", UnitWarning)
        call()
    text = str(err.value)
    assert "\n" not in text
    return text


def test_map_refusals(tmp_path):
    def load(text):
        return lambda: load_column_map(write(tmp_path / "m.toml", text))

    m = tmp_path / "m.toml"
    assert refusal(load(BY_POSITION + "[units]\nrate_hz = 100\n")) == (
        f"{m}: [units] rate_hz: the records are timed twice: map [columns] time or give [units] rate_hz, not both"
    )
    assert refusal(load("[columns]\nmag_x = 1\n[units]\nrate_hz = 0\n")) == (
        f"{m}: [units] rate_hz: 0 is not a sample rate in (0, 1e+06] Hz"
    )
    assert refusal(load('[columns]\nmag_x = 1\n[units]\nrate_hz = 10\ntime = "ms"\n')) == (
        f"{m}: [units] time: 'ms' does not apply with [units] rate_hz"
    )
    assert refusal(load('[file]\ndelimiter = "spaces"\n' + BY_POSITION)) == (
        f"{m}: [file] delimiter: 'spaces' is neither a single character nor one of whitespace, tab, comma, semicolon"
    )
    assert refusal(load('[file]\nformat = "tsv"\ndelimiter = ";"\n' + BY_POSITION)) == (
        f"{m}: [file] delimiter ';' contradicts [file] format = 'tsv' for this map: give one of them"
    )
    assert refusal(load('[file]\nformat = "mat"\nskip_rows = 2\n' + BY_POSITION)) == (
        f"{m}: [file] skip_rows does not apply to this map, a MATLAB file"
    )
    assert refusal(load('[file]\nformat = "csv"\nvariable = "data"\n' + BY_POSITION)) == (
        f"{m}: [file] variable applies only to MATLAB .mat files, not to this map"
    )


def test_table_refusals(tmp_path):
    records = truth_records(8)
    path = write(tmp_path / "h.txt", "\n".join(text_lines(records, " ")) + "\n")
    by_name = ColumnMap({"time": 1, "mag_x": "x", "mag_y": 3, "mag_z": 4}, header=0)
    assert refusal(lambda: read_mapped(path, by_name)) == (
        f"{path}, row 1, column 'x': no such column, asked for by [columns] mag_x in column map (the file has: "
        "column_1, column_2, column_3, column_4); it has no header: give the 1-based column number, e.g. 2"
    )
    by_position = ColumnMap({"time": 1, "mag_x": 2, "mag_y": 3, "mag_z": 4})
    square = write_mat73(tmp_path / "sq.mat", {"data": records[:4]})
    assert refusal(lambda: read_mapped(square, by_position)) == (
        f"{square}: variable 'data' is 4 x 4: records and channels cannot be told apart by shape "
        "(magkf takes the records along the longer dimension)"
    )
    two = write_mat73(tmp_path / "two.mat", {"a": records, "b": records})
    assert refusal(lambda: read_mapped(two, by_position)) == (
        f'{two}: several numeric matrices (the file holds: a, b): name one with [file] variable = "NAME" in the '
        "column map"
    )
    named = ColumnMap({"time": 1, "mag_x": 2, "mag_y": 3, "mag_z": 4}, variable="c")
    assert refusal(lambda: read_mapped(two, named)) == f"{two}: no variable 'c' (the file holds: a, b)"
    code_units = np.frombuffer("abc".encode("utf-16-le"), np.uint16).reshape(3, 1)
    text = write_mat73(tmp_path / "text.mat", {"data": code_units}, classes={"data": "char"})
    assert refusal(lambda: read_mapped(text, dataclass_variable(by_position, "data"))) == (
        f"{text}: variable 'data' is a MATLAB char array, not numbers: a column map reads a real numeric matrix"
    )
    cplx = tmp_path / "c.mat"
    scipy.io.savemat(cplx, {"z": records + 1j})
    assert refusal(lambda: read_mapped(cplx, by_position)) == (
        f'{cplx}: no numeric matrices (the file holds: z): name one with [file] variable = "NAME" in the column map'
    )
    assert refusal(lambda: read_mapped(cplx, dataclass_variable(by_position, "z"))) == (
        f"{cplx}: variable 'z' is a complex array: a column map reads a real numeric matrix"
    )
    fake = write(tmp_path / "fake.mat", "t,x,y,z\n1,2,3,4\n")
    message = refusal(lambda: read_mapped(fake, by_position))
    assert message.startswith(f"{fake}: not a MATLAB .mat file (")
    assert message.endswith("): save it in MATLAB with save(..., '-v7.3') or export the matrix as CSV")


def dataclass_variable(cmap: ColumnMap, variable: str) -> ColumnMap:
    import dataclasses

    return dataclasses.replace(cmap, variable=variable)


def test_offline_refusals(tmp_path, capsys):
    """A headerless ``x y z`` file without --map: one line naming the map to write; --mag-unit with a map."""
    records = truth_records(20)[:, 1:]
    path = write(tmp_path / "xyz.txt", "Set 1\n" + "\n".join(text_lines(records, " ")) + "\n")
    assert refusal(lambda: read_offline_table(path, ["mag_x", "mag_y", "mag_z"])) == (
        f"{path}: not magkf's CSV layout (3 columns separated by whitespace; no header line; 1 line before the "
        "records): if its columns are mag_x, mag_y, mag_z in that order, read it with --map MAP.toml, MAP.toml "
        'holding [file] delimiter = "whitespace", header = 0, skip_rows = 1 and [columns] mag_x = 1, mag_y = 2, '
        "mag_z = 3 (docs/column-maps.md)"
    )
    assert main(["ellipsoid", str(path)]) == 2
    assert capsys.readouterr().err.strip().startswith(f"magkf: error: {path}: not magkf's CSV layout")
    cmap = ColumnMap({"mag_x": 1, "mag_y": 2, "mag_z": 3}, header=0, skip_rows=1, delimiter="whitespace")
    table, _ = read_offline_table(path, ["mag_x", "mag_y", "mag_z"], cmap)
    np.testing.assert_array_equal(table[["mag_x", "mag_y", "mag_z"]].to_numpy(), records)
    assert refusal(lambda: read_offline_table(path, ["mag_x"], cmap, mag_unit="uT")) == (
        "--mag-unit uT does not apply with --map: the map's [units] mag says the unit"
    )
    assert refusal(lambda: read_mapped_table(path, cmap, ["angle_deg"])) == (
        f"{cmap.source}: [columns] angle_deg: required: say which file column holds it"
    )


# ---------------------------------------------------------------- the documented examples, as printed
DOCS = ROOT / "docs" / "column-maps.md"


def documented_layouts() -> dict[str, tuple[str | None, str]]:
    """Heading -> (data, map) of each example under "Layouts of published calibration sets"."""
    doc = DOCS.read_text(encoding="utf-8")
    section = doc[doc.index("## Layouts of published calibration sets") : doc.index("## The offline commands")]
    out = {}
    for part in section.split("\n### ")[1:]:
        heading = part.splitlines()[0]
        data = re.findall(r"```\n(.*?)```", part, flags=re.DOTALL)
        toml = re.findall(r"```toml\n(.*?)```", part, flags=re.DOTALL)
        out[heading] = (data[0] if data else None, toml[0])
    return out


def test_every_documented_layout_reads_the_same_field(tmp_path):
    """The text examples hold the same two or three samples; read through their maps they give the same field
    in nT (the uT one to the storage precision of its decimals, 1e-12 relative) and their times."""
    layouts = documented_layouts()
    assert len(layouts) == 6
    field = np.array([[21034.5, -1220.3, 43012.8], [21031.9, -1218.7, 43015.1], [21030.2, -1219.9, 43013.6]])
    start = datetime(2023, 3, 14, 10, tzinfo=UTC).timestamp()
    for k, (heading, (data, toml)) in enumerate(layouts.items()):
        cmap = write(tmp_path / f"{k}.toml", toml)
        expected = field
        if data is None:  # the MATLAB example: its matrix (more records than channels) written as MATLAB would
            expected = np.tile(field, (2, 1))
            records = np.column_stack([start + 0.1 * np.arange(6), expected])
            path = write_mat73(tmp_path / "set.mat", {"data": records.T})
        else:
            path = write(tmp_path / f"{k}.csv", data)  # the maps that need another delimiter say so
        table, _ = read_mapped(path, cmap)
        n = len(table)
        mag = table[["mag_x", "mag_y", "mag_z"]]
        np.testing.assert_allclose(mag, expected[:n], rtol=1e-12, atol=0, err_msg=heading)
        step = 0.01 if "sample rate" in heading else 0.1
        np.testing.assert_allclose(table["time"], start + step * np.arange(n), rtol=0, atol=1e-6, err_msg=heading)


@pytest.mark.parametrize(
    "suffix, file_keys, sep",
    [
        (".txt", 'delimiter = ";"', ";"),  # the extension says whitespace; the delimiter decides
        (".csv", 'delimiter = "tab"', "\t"),
        (".dat", 'delimiter = "comma"', ","),
        (".csv", 'format = "csv"\ndelimiter = "\\t"', "\t"),
        (".txt", 'format = "tsv"\ndelimiter = "tab"', "\t"),
        (".csv", 'format = "whitespace"\ndelimiter = "whitespace"', " \t "),
        (".weird", 'delimiter = "semicolon"', ";"),
    ],
)
def test_delimiter_and_format_agree_whatever_the_extension(tmp_path, suffix, file_keys, sep):
    records = truth_records(12)
    expected, _ = canonical(tmp_path, records)
    path = write(tmp_path / f"d{suffix}", "\n".join(["t x y z".replace(" ", sep), *text_lines(records, sep)]) + "\n")
    toml = f'[file]\n{file_keys}\n[columns]\ntime = "t"\nmag_x = "x"\nmag_y = "y"\nmag_z = "z"\n'
    cmap = write(tmp_path / "m.toml", toml)
    table, _ = read_mapped(path, cmap)
    pd.testing.assert_frame_equal(table, expected, check_exact=True)


def test_a_struct_field_of_a_v73_file_is_named_with_a_dot(tmp_path):
    """MATLAB saves a struct as an HDF5 group: ``variable = "cal.data"`` reads its field ``data``."""
    records = truth_records()
    path = tmp_path / "struct.mat"
    with h5py.File(path, "w") as f:
        f.create_group("cal").create_dataset("data", data=records.T)
        f.create_dataset("cal/gain", data=np.array([[1.0, 2.0]]))
    table, provenance = read_mapped(
        path, dataclass_variable(ColumnMap({"time": 1, "mag_x": 2, "mag_y": 3, "mag_z": 4}), "cal.data")
    )
    np.testing.assert_array_equal(table[["time", "mag_x", "mag_y", "mag_z"]].to_numpy(), records)
    assert provenance["notes"][0] == (
        f"MATLAB v7.3 (HDF5) variable 'cal.data', stored 4 x {N}: {N} records (its columns) of 4 channels"
    )


@pytest.mark.parametrize(
    "lines, found, keys",
    [
        (
            ["Set 9", "recorded 2023", "mag_x,mag_y,mag_z", "1,2,3", "4,5,6"],
            "3 columns separated by commas; the header on line 3; 2 lines before the header",
            '[file] skip_rows = 2 and [columns] mag_x = "mag_x", mag_y = "mag_y", mag_z = "mag_z"',
        ),
        (
            ["mag_x;mag_y;mag_z", "1;2;3", "4;5;6"],
            "3 columns separated by semicolons; the header on line 1",
            '[file] delimiter = ";" and [columns] mag_x = "mag_x", mag_y = "mag_y", mag_z = "mag_z"',
        ),
        (
            ["t\tbx\tby\tbz", "0\t1\t2\t3", "1\t4\t5\t6"],
            "4 columns separated by tabs; the header on line 1",
            '[file] delimiter = "tab" and [columns] one key per column of mag_x, mag_y, mag_z naming its column '
            "(by name or 1-based position)",
        ),
        (
            ["1.5,2.5,3.5", "4.5,5.5,6.5"],
            "3 columns separated by commas; no header line",
            "if its columns are mag_x, mag_y, mag_z in that order, read it with --map MAP.toml, MAP.toml holding "
            "[file] header = 0 and [columns] mag_x = 1, mag_y = 2, mag_z = 3",
        ),
    ],
)
def test_a_table_in_another_layout_is_refused_naming_its_map(tmp_path, lines, found, keys):
    path = write(tmp_path / "set.csv", "\n".join(lines) + "\n")
    message = refusal(lambda: read_offline_table(path, ["mag_x", "mag_y", "mag_z"]))
    assert message.startswith(f"{path}: not magkf's CSV layout ({found}): ")
    assert message.endswith(f"{keys} (docs/column-maps.md)")


def test_magkf_csv_with_a_bad_cell_keeps_its_own_error(tmp_path):
    """A file in magkf's layout is not sent to a map: its own error (row and column) stands."""
    path = write(tmp_path / "set.csv", "mag_x,mag_y,mag_z\n1,2,3\n4,x5,6\n")
    assert refusal(lambda: read_offline_table(path, ["mag_x", "mag_y", "mag_z"])) == (
        f"{path}, row 3, column 'mag_y': not a number: 'x5' (leave the cell empty for a missing value)"
    )


def test_a_v5_file_with_every_kind_of_variable_is_read_and_a_damaged_one_refused(tmp_path):
    """A v5 file holding complex, sparse, logical, text, empty, cell and struct variables beside the records is
    read; one whose data element has a type code outside MATLAB's, or whose matrix says it is complex without an
    imaginary part (both crash ``scipy.io.loadmat``, scipy/scipy#25349), is refused in one line."""
    import scipy.sparse

    records = truth_records()
    cell = np.empty((1, 2), dtype=object)
    cell[0, 0], cell[0, 1] = records[:2], "text"
    others = {
        "c": records[:3] + 1j,
        "sp": scipy.sparse.random(5, 5, density=0.3, format="csc", random_state=1),
        "flags": records[:3] > 0,
        "label": "bench 2",
        "empty": np.zeros((0, 3)),
        "cell": cell,
        "settings": {"gain": 2.0, "name": "x"},
    }
    for compressed in (False, True):
        scipy.io.savemat(tmp_path / "all.mat", {"data": records, **others}, do_compression=compressed)
        table, _ = read_mapped(
            tmp_path / "all.mat", ColumnMap({"time": 1, "mag_x": 2, "mag_y": 3, "mag_z": 4}, variable="data")
        )
        np.testing.assert_array_equal(table[["time", "mag_x", "mag_y", "mag_z"]].to_numpy(), records)

    scipy.io.savemat(tmp_path / "one.mat", {"data": records})
    good = (tmp_path / "one.mat").read_bytes()
    name = good.index(b"data")  # a small element (type, size, "data"); the real part's tag follows it
    flags = name - 28  # the flags' 8 bytes, then the dimensions' tag and 8 bytes, then the name's 4-byte tag
    assert good[flags] == 6  # mxDOUBLE_CLASS
    cases = {
        name + 4: (157, "a damaged data element"),  # the real part's type: not a MATLAB type
        flags + 1: (good[flags + 1] | 0x08, "a matrix whose parts do not match its class"),  # complex flag
    }
    by_position = ColumnMap({"time": 1, "mag_x": 2, "mag_y": 3, "mag_z": 4})
    for at, (value, what) in cases.items():
        damaged = bytearray(good)
        damaged[at] = value
        path = tmp_path / f"damaged_{at}.mat"
        path.write_bytes(bytes(damaged))
        assert refusal(lambda path=path: read_mapped(path, by_position)).startswith(
            f"{path}: not a readable MATLAB v5 file ({what} at byte "
        )


def test_a_matlab_file_without_a_map_is_refused_naming_the_map(tmp_path):
    path = write_mat73(tmp_path / "set.mat", {"data": truth_records().T})
    assert refusal(lambda: read_offline_table(path, ["mag_x", "mag_y", "mag_z"])) == (
        f'{path}: a MATLAB file: read it with --map MAP.toml, MAP.toml holding [file] variable = "NAME" (the matrix '
        "of records) and [columns] naming which of its columns hold mag_x, mag_y, mag_z by 1-based number, e.g. "
        "mag_x = 1, mag_y = 2, mag_z = 3 (docs/column-maps.md)"
    )
