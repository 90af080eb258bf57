"""``magkf check`` as a library: what the report says about real logs, the example drive and simulated drives."""

import json
from pathlib import Path

import numpy as np
import pytest

from magkf.conventions import ATTITUDE, MAG, TIME
from magkf.diagnostics.inspect import (
    MAX_LINES,
    MAX_WIDTH,
    SPHERE_CELLS,
    format_inspection,
    heading_span_deg,
    inspect_log,
    sphere_cell,
)
from magkf.io.drivelog import DriveLog
from magkf.io.readers import read_log
from magkf.sim import DriveConfig, simulate_drive

DATA = Path(__file__).resolve().parents[2] / "data"
REAL = DATA / "real"
CENTER = REAL / "ardupilot_box_center_0003.bin"
PILOT = REAL / "ardupilot_box_pilot_0004.bin"
PX4 = REAL / "px4_cubeorange_vtol_sample_log_small.ulg"
ALL_MODELS = ["magnitude", "vector", "both"]


def codes(report) -> set[str]:
    return {limit["code"] for limit in report["limits"]}


def assert_fits_screen(report) -> None:
    lines = format_inspection(report).splitlines()
    assert len(lines) <= MAX_LINES
    assert max(map(len, lines)) <= MAX_WIDTH


@pytest.fixture(scope="module")
def logs():
    return {name: read_log(path) for name, path in (("center", CENTER), ("pilot", PILOT), ("px4", PX4))}


@pytest.fixture(scope="module")
def planar():
    return simulate_drive(DriveConfig(motion="planar", duration_s=300, rate_hz=10, seed=3)).table


@pytest.mark.parametrize("name, samples, rate_hz", [("center", 465, 9.512), ("pilot", 979, 9.833)])
def test_ardupilot_logs(logs, name, samples, rate_hz):
    log = logs[name]
    report = inspect_log(log)
    assert report["format"] == "ardupilot-dataflash"
    assert report["epochs"]["start_utc"].startswith("2025-01-03T")
    assert report["epochs"]["end_utc"].startswith("2025-01-03T")
    assert report["epochs"]["count"] == samples == len(log)
    # The mean epoch rate is the reader's MAG rate (rounded there to 3 decimals); MAG is logged every 0.1 s
    # with a few longer intervals, hence 9.5 to 9.8 Hz rather than 10.
    assert report["epochs"]["rate_hz"] == pytest.approx(rate_hz, abs=1e-3)
    assert report["epochs"]["median_interval_s"] == pytest.approx(0.1, abs=1e-3)
    (stream,) = report["streams"]
    assert (stream["name"], stream["samples"], stream["rate_hz"], stream["used"]) == ("MAG[0]", samples, rate_hz, True)
    assert stream["span_s"] == pytest.approx((samples - 1) / rate_hz, abs=0.01)
    assert report["position"]["lat_deg"] == pytest.approx(51.64, abs=0.01)
    assert report["position"]["lon_deg"] == pytest.approx(-2.53, abs=0.01)
    assert report["models"] == ALL_MODELS
    assert report["units"]["magnetometer"]["autopilot_calibration"] == "undone"
    # Hand-flown box with roll and pitch within about 10 deg: reported as limiting, not as level.
    tilt = report["coverage"]["tilt_p95_deg"]
    assert 5.0 < tilt < 15.0
    assert "low_tilt" in codes(report) and "level" not in codes(report)
    text = next(lim["text"] for lim in report["limits"] if lim["code"] == "low_tilt")
    assert "tilt under 15 deg" in text
    json.dumps(report, allow_nan=False)
    assert_fits_screen(report)


def test_center_log_values(logs):
    report = inspect_log(logs["center"])
    e = report["epochs"]
    assert e["worst_interval_s"] == pytest.approx(1.511, abs=1e-3)
    assert (e["gaps"], e["longest_gap_s"]) == (1, pytest.approx(1.511, abs=1e-3))
    assert e["start_utc"] == "2025-01-03T13:45:53.619Z" and e["duration_s"] == pytest.approx(48.78, abs=0.01)
    mag = report["units"]["magnetometer"]
    # IGRF-14 at 51.64 N, 2.53 W in January 2025 is about 49 000 nT, inclination about 66.5 deg.
    assert mag["reference_magnitude_nt"] == pytest.approx(49_024, abs=5)
    assert mag["inclination_deg"] == pytest.approx(66.5, abs=0.1)
    assert mag["ratio"] == pytest.approx(mag["median_magnitude_nt"] / mag["reference_magnitude_nt"], rel=1e-4)
    assert 0.9 < mag["ratio"] < 1.25 and mag["verdict"].startswith("nT")


def test_pilot_fixless_share(logs):
    log = logs["pilot"]
    report = inspect_log(log)
    no_fix = int(np.isnan(log.table["lat"].to_numpy()).sum())
    assert no_fix == 812
    assert report["columns"]["position"]["share"] == pytest.approx(1 - no_fix / len(log), abs=1e-4)
    assert report["status"]["counts"]["missing_position"] == no_fix
    text = next(lim["text"] for lim in report["limits"] if lim["code"] == "no_fix")
    assert text.startswith(f"{no_fix} epochs (83 %) without a 3-D fix")
    # Only the 167 epochs with a fix are usable, and the vehicle hardly turned during them.
    assert report["coverage"]["vector_epochs"] == len(log) - no_fix - report["status"]["counts"]["missing_attitude"]
    assert report["coverage"]["heading_share"] < report["coverage"]["heading_share_all"]
    assert {"too_short", "heading"} <= codes(report)


def test_calibrated_field_is_flagged():
    report = inspect_log(read_log(CENTER, raw=False))
    mag = report["units"]["magnetometer"]
    assert mag["autopilot_calibration"] == "applied"
    # ArduPilot's calibration scales the field to the Earth's: within 1 % of IGRF.
    assert mag["ratio"] == pytest.approx(1.0, abs=0.01)
    assert "calibrated_field" in codes(report)


def test_px4_log(logs):
    report = inspect_log(logs["px4"])
    assert report["format"] == "px4-ulog" and report["software"] == "PX4 1.11.2"
    assert report["epochs"]["start_utc"].startswith("2021-04-21T")
    assert report["epochs"]["count"] == 6 and report["epochs"]["rate_hz"] == pytest.approx(1.0, abs=0.01)
    assert report["epochs"]["gaps"] == 0  # 1-s intervals of a 1-Hz stream are not gaps
    assert report["position"]["lat_deg"] == pytest.approx(63.417, abs=0.01)
    assert report["position"]["lon_deg"] == pytest.approx(10.408, abs=0.01)
    names = [s["name"] for s in report["streams"]]
    assert names == ["sensor_mag[0]", "sensor_mag[1]", "vehicle_magnetometer[0]"]
    assert [s["used"] for s in report["streams"]] == [False, True, False]  # PX4's primary one
    assert report["units"]["magnetometer"]["autopilot_calibration"] == "possibly applied"
    assert {"too_short", "level", "field_ratio"} <= codes(report)
    assert any("PX4's primary magnetometer" in note for note in report["notes"])
    assert_fits_screen(report)
    disabled = inspect_log(read_log(PX4, mag=0))
    assert [s["used"] for s in disabled["streams"]] == [True, False, False]
    assert "CAL_MAG0_EN = 0" in format_inspection(disabled)


def test_example_drive():
    report = inspect_log(read_log(DATA / "example_drive.csv"))
    assert report["format"] == "canonical-csv"
    assert report["time_base"].startswith("UNIX seconds, UTC")
    assert report["epochs"]["rate_hz"] == pytest.approx(20.0, abs=1e-3)
    cov = report["coverage"]
    assert cov["heading_share"] == 1.0 and cov["heading_span_deg"] > 355
    # 3-D motion (tilts up to about 50 deg) with a 64-deg inclination: the field direction stays in the
    # lower part of the sphere, yet visits 12 of the 20 cells (a level drive visits 2, see below).
    assert cov["sphere_share"] == pytest.approx(0.6)
    assert cov["tilt_p95_deg"] > 40
    assert report["models"] == ALL_MODELS
    assert not codes(report) & {"level", "low_tilt", "no_attitude", "too_short", "heading"}
    # 803 epochs of the bad-DOP stretches are above the default gate.
    assert report["status"]["counts"]["gated_dop"] == 803 and "dop" in codes(report)
    assert_fits_screen(report)


def test_level_simulated_drive(planar):
    report = inspect_log(DriveLog(planar))
    assert report["format"] == "table" and report["epochs"]["count"] == 3000
    assert report["coverage"]["tilt_p95_deg"] < 5.0
    assert report["coverage"]["sphere_share"] <= 0.15
    assert "level" in codes(report)
    text = next(lim["text"] for lim in report["limits"] if lim["code"] == "level")
    assert "third column of R" in text
    assert report["models"] == ALL_MODELS
    assert_fits_screen(report)


def test_without_attitude_only_magnitude(planar):
    report = inspect_log(DriveLog(planar.drop(columns=list(ATTITUDE))))
    assert report["models"] == ["magnitude"]
    assert "no_attitude" in codes(report) and "level" not in codes(report)
    assert report["columns"]["attitude"]["share"] == 0.0
    assert report["coverage"]["heading_share"] is None and report["coverage"]["vector_epochs"] == 0
    assert report["status"]["counts"]["used"] == 0
    assert_fits_screen(report)


def test_wrong_unit_and_gaps(planar):
    table = planar.assign(**{c: planar[c] / 1000.0 for c in MAG})  # microtesla read as nanotesla
    keep = np.ones(len(table), bool)
    keep[100:130] = False  # 3.1 s without epochs at 10 Hz
    report = inspect_log(DriveLog(table[keep]))
    assert report["units"]["magnetometer"]["ratio"] == pytest.approx(1e-3, rel=0.1)
    assert "1000 times too small" in report["units"]["magnetometer"]["verdict"]
    assert "unit" in codes(report)
    assert (report["epochs"]["gaps"], report["epochs"]["longest_gap_s"]) == (1, pytest.approx(3.1, abs=1e-6))


def test_no_position_no_model(planar):
    table = planar.assign(lat=np.nan, lon=np.nan)
    report = inspect_log(DriveLog(table))
    assert report["models"] == [] and {"no_model", "no_fix"} <= codes(report)
    assert report["units"]["magnetometer"]["ratio"] is None
    assert_fits_screen(report)


def test_screen_budget_with_many_notes(planar):
    notes = [f"note {i}: " + "a long explanation of something the reader did " * 4 for i in range(30)]
    report = inspect_log(DriveLog(planar, "drive.csv", {"format": "canonical-csv", "notes": notes}))
    assert len(report["notes"]) == 30
    text = format_inspection(report)
    assert_fits_screen(report)
    assert text.splitlines()[-1].endswith("... more in --json")
    # The report is JSON and renders the same after a round trip.
    assert format_inspection(json.loads(json.dumps(report, allow_nan=False))) == text


def test_sphere_cells_have_equal_area():
    rng = np.random.default_rng(7)
    n = 200_000
    share = np.bincount(sphere_cell(rng.standard_normal((n, 3))), minlength=SPHERE_CELLS) / n
    # Binomial standard deviation of each share: sqrt(0.05 * 0.95 / n) = 4.9e-4; 5 sigma.
    assert np.abs(share - 1 / SPHERE_CELLS).max() < 5 * np.sqrt(0.05 * 0.95 / n)


def test_heading_span():
    assert heading_span_deg([350.0, 10.0]) == pytest.approx(20.0)
    assert heading_span_deg([0.0, 90.0, 180.0]) == pytest.approx(180.0)
    assert heading_span_deg([42.0]) == 0.0


def test_table_stream_is_the_time_column(planar):
    log = DriveLog(planar)
    assert TIME not in log.table.columns
    assert inspect_log(log)["streams"][0]["name"] == "time column"


def test_an_attitude_that_never_changes_is_called_a_placeholder():
    """The example drive's field turns through 12 of 20 sphere cells; with its attitude replaced by zeros (a
    driver's identity quaternion) the screen says the attitude is a placeholder; with the real one it does not."""
    log = read_log(DATA / "example_drive.csv")
    assert "still_attitude" not in codes(inspect_log(log))
    still = DriveLog(log.table.assign(roll=0.0, pitch=0.0, yaw=0.0), log.source, log.provenance)
    report = inspect_log(still)
    text = next(lim["text"] for lim in report["limits"] if lim["code"] == "still_attitude")
    assert text.startswith("the attitude reads (0, 0, 0) deg at every epoch while the field turns through 12 of 20")
    assert_fits_screen(report)
