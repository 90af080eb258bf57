"""Logs without GNSS and folders of logs through the command line: ``--site``/``--date`` and ``check FOLDER``."""

import json
import shutil

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.io.drivelog import write_drive_log
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA, run_cli

pytestmark = pytest.mark.slow

REAL = DATA / "real"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A 5-minute drive as a bench log: time since boot, no position (with GNSS, the same drive)."""
    d = tmp_path_factory.mktemp("bench")
    table = simulate_drive(DriveConfig(duration_s=300, rate_hz=10, seed=8, dop_bad_stretches=0)).table.reset_index()
    write_drive_log(table, d / "gnss.csv")
    boot = table.drop(columns=["lat", "lon", "alt"]).assign(time=table["time"] - table["time"].iloc[0] + 30.0)
    write_drive_log(boot, d / "bench.csv")
    return d


def test_a_bench_log_calibrates_at_the_site_given(bench, tmp_path):
    out = tmp_path / "cal.json"
    proc = run_cli("calibrate", bench / "bench.csv", "--site", "48.1,11.6,500", "--date", "2026-06-01", "-o", out)
    assert proc.returncode == 0, proc.stderr
    site = Calibration.load(out).site
    assert site == {"given": True, "lat": 48.1, "lon": 11.6, "alt": 500.0, "start_utc": "2026-06-01T00:00:00Z"}


def test_a_bench_log_without_a_site_is_refused_in_one_line(bench):
    proc = run_cli("calibrate", bench / "bench.csv", "--date", "2026-06-01", "-o", bench / "x.json")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"magkf: error: {bench / 'bench.csv'}: the log has no GNSS position (nor a reference field): give --site "
        "LAT,LON[,ALT] where it was recorded"
    ]


def test_check_on_a_folder_gives_one_line_per_log(bench, tmp_path):
    folder = tmp_path / "logs"
    folder.mkdir()
    for name in ("ardupilot_box_center_0003.bin", "px4_cubeorange_vtol_sample_log_small.ulg"):
        shutil.copy(REAL / name, folder / name)
    shutil.copy(bench / "gnss.csv", folder / "drive.csv")
    (folder / "junk.csv").write_text("a,b\n1,2\n")
    proc = run_cli("check", folder)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert [line.split()[0] for line in lines[:-1]] == [
        "ardupilot_box_center_0003.bin",
        "drive.csv",
        "junk.csv",
        "px4_cubeorange_vtol_sample_log_small.ulg",
    ]
    assert lines[-1] == "3 of 4 logs readable; 1 refused"
    assert "ardupilot-dataflash  ArduPlane V4.2.3 (55685c43)" in lines[0]
    assert lines[2].split(None, 1)[1] == "refused: row 1, column 'time': required column missing (the header has: a, b)"
    entries = json.loads(run_cli("check", folder, "--json").stdout)
    assert [e["format"] for e in entries] == ["ardupilot-dataflash", "canonical-csv", None, "px4-ulog"]
    assert [len(e["magnetometers"]) for e in entries] == [1, 1, 0, 3]  # a table: its one time column
    assert all(e["models"] == ["magnitude", "vector", "both"] for e in entries if e["error"] is None)
    assert np.isclose(entries[1]["duration_s"], 299.9)


def test_a_southern_site_a_glob_and_binary_data(bench, tmp_path):
    """``--site -33.9,151.2`` is a value, not an option; one glob pattern checks every log it names; a binary file
    named like a table is refused as binary, not with its bytes printed as a header."""
    proc = run_cli("check", bench / "bench.csv", "--site", "-33.9,151.2", "--date", "2026-06-01", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["position"]["lat_deg"] == -33.9
    proc = run_cli("check", str(bench / "*.csv"))
    assert proc.returncode == 0 and proc.stdout.strip().splitlines()[-1] == "1 of 2 logs readable; 1 refused"
    (tmp_path / "junk.csv").write_bytes(bytes(range(256)) * 4)
    proc = run_cli("check", tmp_path / "junk.csv")
    assert proc.returncode == 2 and proc.stderr == (
        f"magkf: error: {tmp_path / 'junk.csv'}: binary data, not a text table: a log of another format (give "
        "--format), or a MATLAB or other file to read through a column map (--map, docs/column-maps.md)\n"
    )
