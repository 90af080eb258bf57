"""Logs of every format through the command line: read_log's door, convert, export, the time base and the
one-line errors (seeded)."""

import json

import numpy as np
import pandas as pd
import pytest

from magkf.calibration import Calibration
from magkf.io.autopilot import apply_ardupilot, apply_px4, read_param_file
from magkf.io.drivelog import read_drive_log
from magkf.io.readers import detect_format, read_log
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA, cli_json, run_cli

REAL = DATA / "real"
ULOG = REAL / "px4_cubeorange_vtol_sample_log_small.ulg"
DATAFLASH = REAL / "ardupilot_box_center_0003.bin"


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    sim = simulate_drive(DriveConfig(duration_s=120, rate_hz=10, seed=21))
    path = tmp_path_factory.mktemp("drive") / "drive.csv"
    sim.write(path)
    return sim, path


def test_formats_are_detected_by_content_not_name(tmp):
    assert detect_format(ULOG) == "ulog" and detect_format(DATAFLASH) == "dataflash"
    renamed = tmp / "log.csv"
    renamed.write_bytes(DATAFLASH.read_bytes())
    assert detect_format(renamed) == "dataflash"
    assert read_log(renamed).provenance["format"] == "ardupilot-dataflash"


@pytest.mark.slow
def test_convert_to_parquet_and_back_is_lossless(drive, tmp):
    _, path = drive
    out = tmp / "drive.parquet"
    summary = cli_json("convert", path, "-o", out)
    assert summary["epochs"] == 1200 and (tmp / "drive.parquet.provenance.json").is_file()
    a, b = read_drive_log(path), read_log(out)
    assert b.provenance["format"] == "canonical-parquet"
    pd.testing.assert_frame_equal(a.table, b.table)
    csv = tmp / "again.csv"
    cli_json("convert", out, "-o", csv)
    pd.testing.assert_frame_equal(a.table, read_drive_log(csv).table)


@pytest.mark.slow
def test_binary_logs_convert_with_their_provenance(tmp):
    out = tmp / "ap.csv"
    cli_json("convert", DATAFLASH, "-o", out)
    provenance = json.loads((tmp / "ap.csv.provenance.json").read_text())
    assert provenance["format"] == "ardupilot-dataflash"
    assert "MAG" in provenance["columns"]["mag_x"]
    log = read_drive_log(out)
    assert pd.Timestamp(log.time[0], unit="s").date().isoformat() == "2025-01-03"


@pytest.mark.slow
@pytest.mark.parametrize("path", [ULOG, DATAFLASH])
def test_every_command_reads_binary_logs(path, tmp):
    cal = tmp / "cal.json"
    Calibration(R=np.eye(3), b=np.zeros(3)).save(cal)
    out = cli_json("apply", path, "--cal", cal)
    assert out["n_epochs"] > 0


@pytest.mark.slow
def test_calibrate_reads_the_same_log_from_csv_and_parquet(drive, tmp):
    _, path = drive
    out = tmp / "d.parquet"
    cli_json("convert", path, "-o", out)
    a = cli_json("calibrate", path, "--quiet")
    b = cli_json("calibrate", out, "--quiet")
    assert a["R"] == b["R"] and a["b"] == b["b"] and a["status_counts"] == b["status_counts"]


def test_states_in_parquet(drive, tmp):
    _, path = drive
    states = tmp / "states.parquet"
    cli_json("calibrate", path, "--quiet", "--states", states)
    table = pd.read_parquet(states)
    assert len(table) == 1200 and "status" in table and table["status"].notna().all()


def _one_line_error(proc, *fragments):
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.strip().splitlines() if not line.startswith("magkf: warning:")]
    assert len(lines) == 1 and lines[0].startswith("magkf: error:"), proc.stderr  # warnings may come before
    for f in fragments:
        assert f in lines[0], lines[0]


def _retimed(sim, path, time):
    """The simulated log written to ``path`` with its time column replaced by ``time(t)`` (t: UNIX s, (N,))."""
    table = sim.table.reset_index()
    table["time"] = time(table["time"].to_numpy())
    table.to_csv(path, index=False)
    return path


def _since_boot(t):
    return t - t[0]


def test_time_since_boot_is_refused_with_advice(drive, tmp):
    sim, _ = drive
    path = _retimed(sim, tmp / "boot.csv", _since_boot)
    _one_line_error(run_cli("calibrate", path), str(path), "row 2", "'time'", "time since boot")


def test_time_in_milliseconds_is_refused(drive, tmp):
    sim, _ = drive
    path = _retimed(sim, tmp / "ms.csv", lambda t: t * 1000.0)
    _one_line_error(run_cli("convert", path, "-o", tmp / "out.csv"), str(path), "outside 1990 to 2100")


def test_a_long_gap_is_reported(drive, tmp):
    sim, _ = drive
    path = _retimed(sim, tmp / "gap.csv", lambda t: t + 60.0 * (np.arange(len(t)) >= 600))
    proc = run_cli("calibrate", path, "--quiet")
    assert proc.returncode == 0
    assert "clock jumps by 60.1 s at row 602" in proc.stderr


@pytest.mark.parametrize("kind", ["not_a_log", "truncated_ulog", "map_missing_column", "no_utc_ulog"])
def test_unreadable_inputs_are_one_line_errors(kind, tmp, drive):
    if kind == "not_a_log":
        path = tmp / "x.ulg"
        path.write_bytes(b"\x00\x01garbage" * 100)
        _one_line_error(run_cli("calibrate", path), str(path))
    elif kind == "truncated_ulog":
        path = tmp / "t.ulg"
        path.write_bytes(ULOG.read_bytes()[:300])
        _one_line_error(run_cli("calibrate", path), str(path))
    elif kind == "map_missing_column":
        sim, _ = drive
        path = tmp / "survey.txt"
        sim.table.reset_index()[["time", "mag_x"]].to_csv(path, sep="\t", index=False)
        _one_line_error(
            run_cli("check", path, "--map", DATA.parent / "docs/examples/survey_map.toml"), str(path), "row 1"
        )
    else:
        from magkf.io.ulog import write_ulog

        sim, _ = drive
        path = tmp / "noutc.ulg"
        write_ulog(sim.table.reset_index().drop(columns=["lat", "lon", "alt", "dop"]), path)
        _one_line_error(run_cli("calibrate", path), str(path), "UTC")


def test_a_truncated_dataflash_log_reads_up_to_the_damage(tmp):
    path = tmp / "cut.bin"
    data = DATAFLASH.read_bytes()
    path.write_bytes(data[: len(data) // 2 + 7])
    proc = run_cli("convert", path, "-o", tmp / "cut.csv")
    assert proc.returncode == 0, proc.stderr
    assert "magkf: warning:" in proc.stderr and str(path) in proc.stderr
    whole = read_log(DATAFLASH)
    cut = read_drive_log(tmp / "cut.csv")
    assert 0.3 * len(whole) < len(cut) < 0.7 * len(whole)


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_export_round_trip_through_the_command_line(autopilot, tmp):
    rng = np.random.default_rng(3)
    A = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    S = 0.5 * (A + A.T)  # symmetric: no rotation for the autopilot to lose
    b = rng.normal(scale=2000.0, size=3)
    cal = Calibration(R=np.linalg.inv(S), b=b)
    path = tmp / "cal.json"
    cal.save(path)
    out = tmp / "cal.param"
    summary = cli_json("export", path, "--to", autopilot, "-o", out)
    assert summary["residual_rotation_deg"] < 1e-6
    values = read_param_file(out)
    m = rng.normal(scale=30000.0, size=(50, 3))
    if autopilot == "ardupilot":
        field = apply_ardupilot(values, m / 100.0) * 100.0  # mG
    else:
        field = apply_px4(values, m / 1e5) * 1e5  # gauss
    assert np.allclose(field, cal.correct(m), rtol=1e-9, atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize(
    "path,expected",
    [
        (ULOG, ["px4-ulog", "2021-04-21", "lat 63.4"]),
        (DATAFLASH, ["ardupilot-dataflash", "2025-01-03", "lat 51.64", "x100 -> nT", "calibration undone"]),
        (REAL / "ardupilot_box_pilot_0004.bin", ["2025-01-03", "without a 3-D fix", "lon -2.52"]),
    ],
)
def test_check_prints_one_screen_per_sample_log(path, expected):
    proc = run_cli("check", path)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) <= 40 and max(map(len, lines)) <= 100
    for text in expected:
        assert text in proc.stdout, text
    report = cli_json("check", path)
    assert report["models"] and "limits" in report


@pytest.mark.slow
@pytest.mark.parametrize(
    "command,name",
    [
        (["sinefit", "--field", "50000", "--inclination", "43"], "turntable_example.csv"),
        (["ellipsoid", "--columns", "mx,my,mz"], "ckexplorer_acc_mag_log.csv"),
    ],
)
def test_offline_commands_read_parquet_like_csv(command, name, tmp):
    table = pd.read_csv(DATA / name)
    path = tmp / (name.removesuffix(".csv") + ".parquet")
    table.to_parquet(path, index=False)
    from_csv = cli_json(command[0], DATA / name, *command[1:])
    from_parquet = cli_json(command[0], path, *command[1:])
    assert from_csv["R"] == from_parquet["R"] and from_csv["b"] == from_parquet["b"]


def test_mag_all_on_a_table_is_its_one_magnetometer(drive):
    _, path = drive
    proc = run_cli("calibrate", path, "--mag", "all", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "magnetometer None" not in proc.stdout and "R[1]" in proc.stdout


def test_mag_all_goes_on_past_a_magnetometer_it_cannot_calibrate():
    proc = run_cli("calibrate", ULOG, "--mag", "all", "--quiet")  # 6 s, still: neither calibrates
    assert proc.stdout.count("not calibrated:") == 2 and str(ULOG) in proc.stdout
    assert proc.returncode == 2 and proc.stderr.startswith("magkf: error: " + str(ULOG))


def test_mag_on_a_table_is_refused(drive):
    _, path = drive
    _one_line_error(run_cli("check", path, "--mag", "7"), str(path), "--mag applies to ULog and DataFlash")


def test_errors_print_plain_numbers(drive, tmp):
    sim, _ = drive
    path = _retimed(sim, tmp / "boot.csv", _since_boot)
    proc = run_cli("check", path)
    assert "np.float64" not in proc.stderr and "time 0.0 s" in proc.stderr


def test_the_canonical_csv_keeps_microseconds(tmp):
    from magkf.io.drivelog import write_drive_log

    table = pd.DataFrame(
        {
            "time": 1780308000.0 + np.array([0.0, 0.000001, 0.123457]),
            "mag_x": [1.0, 1.5, 2.0],
            "mag_y": 2.0,
            "mag_z": 3.0,
            "lat": 48.0,
            "lon": 11.0,
        }
    )
    write_drive_log(table, tmp / "us.csv")
    assert np.array_equal(read_drive_log(tmp / "us.csv").time, table["time"].to_numpy())


def test_a_closed_pipe_ends_quietly():
    import subprocess
    import sys

    proc = subprocess.run(
        f"{sys.executable} -m magkf check {DATAFLASH} | head -1", shell=True, capture_output=True, text=True
    )
    assert "Traceback" not in proc.stderr and proc.stdout.startswith("magkf check")


@pytest.mark.slow
def test_export_writes_the_compass_the_calibration_came_from(tmp):
    """A calibration from an autopilot log records its magnetometer, and export writes that compass's
    parameters unless told otherwise: ArduPilot's MAG instance i as compass i + 1, PX4's CAL_MAGn slot of the
    magnetometer's device_id; a calibration of another autopilot's log, or of none, gets the first compass."""
    from magkf.io.dataflash import write_dataflash

    sim = simulate_drive(DriveConfig(duration_s=300, rate_hz=10, seed=8))
    write_dataflash(sim.table, tmp / "flight.bin")
    cli_json("calibrate", tmp / "flight.bin", "-o", tmp / "ap.json")
    cal = Calibration.load(tmp / "ap.json")
    assert cal.magnetometer["format"] == "ardupilot-dataflash" and cal.magnetometer["instance"] == 0
    assert Calibration.from_dict(cal.to_dict()).magnetometer == cal.magnetometer  # kept through the file
    assert cli_json("export", tmp / "ap.json", "--to", "ardupilot", "-o", tmp / "a.param")["instance"] == 1
    second = cal.to_dict() | {
        "magnetometer": {"format": "ardupilot-dataflash", "instance": 1}
    }  # no parameter set known
    (tmp / "ap2.json").write_text(json.dumps(second))
    assert (
        "COMPASS_OFS2_X" in cli_json("export", tmp / "ap2.json", "--to", "ardupilot", "-o", tmp / "b.param")["values"]
    )
    assert cli_json("export", tmp / "ap2.json", "--to", "px4", "-o", tmp / "c.param")["instance"] == 0
    assert (
        cli_json("export", tmp / "ap2.json", "--to", "ardupilot", "--instance", 3, "-o", tmp / "d.param")["instance"]
        == 3
    )
    px4 = cal.to_dict() | {
        "magnetometer": {"format": "px4-ulog", "instance": 1, "device_id": 592905, "calibration_index": 1}
    }
    (tmp / "px4.json").write_text(json.dumps(px4))
    summary = cli_json("export", tmp / "px4.json", "--to", "px4", "-o", tmp / "p.param")
    assert summary["instance"] == 1 and "CAL_MAG1_XOFF" in summary["values"] and "592905" in summary["instance_chosen"]
    bare = Calibration(R=cal.R, b=cal.b)
    bare.save(tmp / "bare.json")
    assert cli_json("export", tmp / "bare.json", "--to", "px4", "-o", tmp / "q.param")["instance"] == 0
