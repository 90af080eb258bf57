"""Raw, the vehicle's own calibration and magkf's where a user looks: ``magkf report`` and ``magkf fleet`` on
simulated DataFlash logs whose COMPASS_* parameters hold the true soft iron and an offset off by a known amount
(``tests.unit.test_baseline.dataflash_drive``), and a canonical CSV log that holds no calibration of its own."""

import html
import re

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.diagnostics.baseline import RAW, VEHICLE, compare_calibrations, vehicle_calibration
from magkf.fleet import BASELINE_COLUMNS, find_logs, improvement_lines, run_fleet
from magkf.io.readers import read_log
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import run_cli
from ..unit.test_baseline import dataflash_drive


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """V1: two DataFlash flights with the vehicle's calibration in their parameters; V2: one CSV drive."""
    root = tmp_path_factory.mktemp("baseline_fleet")
    (root / "V1").mkdir()
    (root / "V2").mkdir()
    for seed in (4, 5):
        dataflash_drive(root / "V1" / f"flight{seed}.bin", seed=seed, duration_s=240.0)
    config = DriveConfig(duration_s=240.0, rate_hz=10, seed=6, disturbances=0)
    simulate_drive(config).write(root / "V2" / "drive.csv")
    return root


def _cells(page: str, label: str) -> list[str]:
    """The cells of the table row that starts with ``label``."""
    row = re.search(rf"<tr><td>{re.escape(html.escape(label))}</td>(.*?)</tr>", page)
    assert row is not None, label
    return re.findall(r"<td>([^<]*)</td>", row.group(1))


@pytest.mark.slow
def test_report_compares_raw_the_vehicle_s_calibration_and_magkf_s(fleet, tmp_path):
    log_path = fleet / "V1" / "flight4.bin"
    proc = run_cli("report", log_path, "-o", tmp_path / "r.html", "--quiet")
    assert proc.returncode == 0, proc.stderr
    page = (tmp_path / "r.html").read_text()
    sections = re.findall(r"<h2>([^<]+)</h2>", page)
    assert sections[:4] == ["Noise and verdict", "Gates", "Estimate", "Field before and after calibration"]
    assert "<h3>Raw, the vehicle's own calibration and magkf's</h3>" in html.unescape(page)
    overview = html.unescape(page[: page.index("<h2>")])
    assert "magkf's calibration improves on the calibration the vehicle flies by" in overview
    assert "Before: raw reading (no calibration); after: magkf's calibration." in html.unescape(page)
    # the table's raw and vehicle rows are the baseline's, to the digits shown
    log = read_log(log_path)
    vehicle, _ = vehicle_calibration(log)
    expected = compare_calibrations(log, {RAW: None, VEHICLE: vehicle}).summary
    for name, label in ((RAW, "raw reading, no calibration"), (VEHICLE, "the vehicle's own calibration")):
        cells = _cells(page, label)
        assert cells[0] == f"{expected.loc[name, 'magnitude_rms_nt']:.1f}"
        assert cells[1] == f"{expected.loc[name, 'heading_rms_deg']:.2f}"
    magkf = [float(c) for c in _cells(page, "magkf's calibration")[:2]]
    # magkf's fit is at the noise (30 nT) and the log's whole-mG storage (29 nT RMS): far below the offset's 170
    assert magkf[0] < 0.5 * expected.loc[VEHICLE, "magnitude_rms_nt"]
    alts = [html.unescape(a) for a in re.findall(r'<img alt="([^"]*)"', page)]
    compared = [
        a for a in alts if "raw reading, no calibration; the vehicle's own calibration; magkf's calibration" in a
    ]
    assert len(compared) == 2 and all("in nT" in a and "in deg" in a for a in compared)


@pytest.mark.slow
def test_fleet_rows_and_summary_compare_with_the_vehicle_s_calibration(fleet, tmp_path):
    summary = run_fleet(find_logs([fleet]), tmp_path / "out", plot=False).summary
    assert (summary["error"] == "").all(), summary["error"].tolist()
    assert set(BASELINE_COLUMNS) <= set(summary.columns)
    v1, v2 = summary[summary["vehicle"] == "V1"], summary[summary["vehicle"] == "V2"]
    assert len(v1) == 2 and len(v2) == 1
    assert np.allclose(v1["improvement_nt"], v1["vehicle_magnitude_rms_nt"] - v1["magnitude_rms_nt"])
    assert np.allclose(v1["improvement_deg"], v1["vehicle_heading_rms_deg"] - v1["heading_rms_deg"])
    # the vehicle's offset is 374 nT off: about 170 nT RMS of magnitude against magkf's noise-level tens
    assert (v1["vehicle_magnitude_rms_nt"] > 120.0).all() and (v1["improvement_nt"] > 80.0).all()
    assert (
        v2[["vehicle_magnitude_rms_nt", "vehicle_heading_rms_deg", "improvement_nt", "improvement_deg"]]
        .isna()
        .all(axis=None)
    )
    assert np.isfinite(v2["magnitude_rms_nt"]).all() and np.isfinite(v2["heading_rms_deg"]).all()
    lines = improvement_lines(summary)
    median = float(np.median(v1["improvement_nt"]))
    flies = "the calibration the vehicle flies"
    assert lines[0].startswith(f"V1: magkf's calibration improves on {flies} by {median:.0f} nT")
    assert lines[0].endswith("median over 2 log(s)")
    assert lines[1] == f"V2: no calibrated log gives {flies}"


@pytest.mark.slow
def test_fleet_command_prints_the_improvement_per_vehicle(fleet, tmp_path):
    proc = run_cli("fleet", fleet, "-o", tmp_path / "out", "--workers", "0", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "  V1: magkf's calibration improves on the calibration the vehicle flies by" in proc.stdout
    assert "  V2: no calibrated log gives the calibration the vehicle flies" in proc.stdout


def test_the_report_s_field_as_read_is_the_comparison_s_identity_or_compared_alone():
    """The report draws the field as read from the comparison's identity (raw); a log read calibrated whose vehicle's
    calibration is unknown has none there, and the field as read is compared alone, at the same epochs drawn."""
    from magkf.diagnostics.baseline import MAGKF
    from magkf.diagnostics.report import Comparison, _as_read, _sample
    from magkf.io.drivelog import from_table

    sim = simulate_drive(DriveConfig(duration_s=120.0, rate_hz=10, seed=2, disturbances=0))
    log = from_table(sim.table.reset_index(), "sim2")
    drawn = _sample(len(log.table))
    with_raw = compare_calibrations(log, {RAW: None, MAGKF: sim.calibration}, sample=drawn)
    base, name = _as_read(log, Comparison(with_raw, None, "", False))
    assert base is with_raw and name == RAW
    magkf_only = compare_calibrations(log, {MAGKF: sim.calibration}, sample=drawn)
    before, name = _as_read(log, Comparison(magkf_only, None, "", True))
    assert name not in magkf_only.names
    assert np.array_equal(before.magnitude_error_nt[name], with_raw.magnitude_error_nt[RAW], equal_nan=True)
    assert np.array_equal(before.heading_error_deg[name], with_raw.heading_error_deg[RAW], equal_nan=True)
    assert np.array_equal(before.fields[name], log.mag[drawn])
    as_read = Calibration(np.eye(3), np.zeros(3), method="logged-as-read")  # a log read calibrated: the identity
    with_vehicle = compare_calibrations(log, {VEHICLE: as_read, MAGKF: sim.calibration}, sample=drawn)
    base, name = _as_read(log, Comparison(with_vehicle, as_read, "", True))
    assert base is with_vehicle and name == VEHICLE
