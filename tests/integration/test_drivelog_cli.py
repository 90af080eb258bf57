"""The canonical drive log through the ``magkf`` command: bad cells and units end with exit status 2 and one
line naming file, row and column; ``--mag-unit`` is refused where the log states its unit (run as a command;
the reader itself is tested in ``tests/unit/test_drivelog.py``)."""

import warnings

import pytest

from magkf.errors import InputError
from magkf.io.drivelog import UnitWarning, read_drive_log

from ..conftest import DATA, run_cli
from ..unit.test_drivelog import GOOD, HEADER, _write


@pytest.mark.parametrize(
    "lines,header,where",
    [
        ([GOOD[0], GOOD[1].replace("20010", "abc"), GOOD[2]], HEADER, "row 3, column 'mag_x'"),
        ([GOOD[0], GOOD[2], GOOD[1]], HEADER, "row 4, column 'time'"),
    ],
)
def test_bad_input_exit_status_2_one_line(tmp, lines, header, where):
    path = _write(tmp, lines, header)
    (tmp / "cal.json").write_text('{"R": [[1,0,0],[0,1,0],[0,0,1]], "b": [0,0,0]}')
    proc = run_cli("apply", path, "--cal", tmp / "cal.json")
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and where in proc.stderr and str(path) in proc.stderr


def test_units_are_converted_and_suspicious_units_warned(tmp):
    ut = [
        ",".join([p[0], str(float(p[1]) / 1000), str(float(p[2]) / 1000), str(float(p[3]) / 1000), *p[4:]])
        for p in (line.split(",") for line in GOOD)
    ]
    path = _write(tmp, ut)
    with pytest.warns(UnitWarning, match="look like uT"):
        read_drive_log(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        log = read_drive_log(path, mag_unit="uT")
    assert log.mag[0, 0] == pytest.approx(20_000.0)
    with pytest.raises(InputError, match="unknown magnetic unit"):
        read_drive_log(path, mag_unit="T")
    proc = run_cli("apply", path, "--cal", "x.json", "--mag-unit", "T")
    assert proc.returncode == 2 and "invalid choice" in proc.stderr


@pytest.mark.parametrize(
    "log",
    [
        "real/ardupilot_box_center_0003.bin",
        pytest.param("real/px4_cubeorange_vtol_sample_log_small.ulg", marks=pytest.mark.slow),
    ],
)
def test_mag_unit_is_refused_where_the_log_states_its_unit(log):
    proc = run_cli("check", DATA / log, "--mag-unit", "uT")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert str(DATA / log) in proc.stderr and "--mag-unit applies to a canonical table" in proc.stderr


def test_mag_unit_is_refused_with_a_column_map(tmp):
    survey_map = DATA.parent / "docs" / "examples" / "survey_map.toml"
    path = tmp / "survey.tsv"
    path.write_text("time\tx\ty\tz\n")
    proc = run_cli("check", path, "--map", survey_map, "--mag-unit", "uT")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "its column map's [units] mag" in proc.stderr
