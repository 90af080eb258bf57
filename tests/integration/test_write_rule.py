"""The write rule through the command line: on the shipped ArduPilot logs and a straight level flight no
calibration is written whose determinant is not positive or whose offsets' standard deviations exceed 10 % of
the field, and the refusals say what the data lack; apply, export and ellipsoid refuse what no one should load."""

import json
import re

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.io.drivelog import read_drive_log
from magkf.plausibility import log_field_nt
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA, run_cli

REAL = DATA / "real"
#: The acceptance: no file written whose offsets' standard deviations exceed this share of the field.
ACCEPTED_SHARE = 0.10


def _judge_written(path, field_nt: float) -> None:
    """A written calibration: determinant positive, offsets' standard deviations within the acceptance."""
    cal = Calibration.load(path)
    assert np.linalg.det(cal.R) > 0
    b_std = np.sqrt(np.diag(cal.covariance)[9:12])
    assert b_std.max() <= ACCEPTED_SHARE * field_nt, b_std / field_nt


#: The shipped ArduPilot logs, with the place and date a log without GNSS needs.
ARDUPILOT = {
    "ardupilot_box_center_0003.bin": [],
    "ardupilot_box_pilot_0004.bin": [],
    "ardusub_small.bin": ["--site", "47.4,8.5,400", "--date", "2022-01-01"],
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(ARDUPILOT))
@pytest.mark.parametrize("batch", [[], ["--batch"]])
def test_the_shipped_ardupilot_logs_write_nothing_absurd(tmp, name, batch):
    """Each shipped ArduPilot log, filter and batch: refused in one line that does not suggest --mag-unit (refused
    for .bin logs), or written with a positive determinant and offsets known within the acceptance."""
    out = tmp / "cal.json"
    proc = run_cli("calibrate", REAL / name, *ARDUPILOT[name], *batch, "--quiet", "-o", out)
    if proc.returncode == 0:
        _judge_written(out, 49_000.0 * 1.1)  # the logs' field is 48 000 to 49 100 nT (IGRF at the site)
    else:
        assert proc.returncode == 2 and not out.exists()
        assert proc.stderr.splitlines()[-1].startswith(f"magkf: error: {REAL / name}: ")
        assert "--mag-unit" not in proc.stderr


@pytest.mark.slow
def test_the_weakly_turning_log_is_refused_by_the_batch_solver_with_what_it_lacks(tmp):
    """``ardupilot_box_pilot_0004.bin`` turns through 1 degree of heading over the epochs used: the batch solver,
    which solves all 12 parameters, is refused saying so and what would determine them."""
    out = tmp / "cal.json"
    proc = run_cli("calibrate", REAL / "ardupilot_box_pilot_0004.bin", "--batch", "-o", out)
    assert proc.returncode == 2 and not out.exists()
    assert "epochs used turn through 1 deg of heading" in proc.stderr
    assert "turns through every heading (a full circle) with some pitch and roll determines R and b" in proc.stderr
    assert "drop --batch" in proc.stderr


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """A 10-minute straight, level flight (heading within 5 deg, roll and pitch within 3 deg) at 10 Hz."""
    path = tmp_path_factory.mktemp("straight") / "straight.csv"
    sim = simulate_drive(DriveConfig(seed=0, duration_s=600.0, rate_hz=10.0, motion="straight"))
    sim.write(path)
    return path, sim


@pytest.mark.slow
def test_a_straight_flight_writes_offsets_with_r_held_and_says_how_little_they_are_known(tmp, straight):
    """The filter writes the offsets with R held at the identity; their standard deviation, R's prior (0.02 per
    element) times the field, about 2 %, is warned with how far the flight turns; the file is within the rule."""
    path, _ = straight
    out = tmp / "cal.json"
    proc = run_cli("calibrate", path, "--quiet", "--json", "-o", out)
    assert proc.returncode == 0, proc.stderr
    field = log_field_nt(read_drive_log(path))
    _judge_written(out, field)
    warnings = json.loads(proc.stdout)["warnings"]
    assert any("the offsets' standard deviations reach" in w and "deg of heading" in w for w in warnings), warnings


@pytest.mark.slow
def test_a_straight_flight_is_refused_by_the_batch_solver(tmp, straight):
    """The batch solver solves all 12 parameters; over a flight turning through 6 degrees of heading its offsets
    were 12 of their standard deviations (3 200 nT) off the truth at 50 Hz: refused, saying how far (under 10
    degrees: the simulated heading stays within 5 degrees of its mean) the epochs turn."""
    path, _ = straight
    out = tmp / "cal.json"
    proc = run_cli("calibrate", path, "--batch", "--quiet", "-o", out)
    assert proc.returncode == 2 and not out.exists()
    assert "turn through fewer than 90 deg of heading, which do not determine R" in proc.stderr
    assert re.search(r"epochs used turn through [0-9] deg of heading", proc.stderr) and "drop --batch" in proc.stderr


def test_a_mirrored_start_is_refused_before_the_run(tmp, straight):
    path, _ = straight
    start = tmp / "mirror.json"
    Calibration(R=np.diag([1.0, 1.0, -1.0]), b=np.zeros(3), covariance=np.eye(12) * 1e-12).save(start)
    out = tmp / "cal.json"
    proc = run_cli("calibrate", path, "--init", start, "-o", out)
    assert proc.returncode == 2 and not out.exists()
    assert proc.stderr.startswith(f"magkf: error: {start}: the start calibration itself is mirrored")


def test_apply_and_export_refuse_an_absurd_calibration(tmp):
    """R = 1e-3 I and b = 1e7 nT: apply and export refuse it in one line naming the calibration file; nothing
    is written."""
    cal = tmp / "absurd.json"
    Calibration(R=np.eye(3) * 1e-3, b=np.full(3, 1e7)).save(cal)
    out = tmp / "out.csv"
    proc = run_cli("apply", DATA / "example_drive.csv", "--cal", cal, "-o", out)
    assert proc.returncode == 2 and not out.exists()
    assert proc.stderr.startswith(f"magkf: error: {cal}: the calibration is not used: sensitivities 0.001")
    assert proc.stderr.count("\n") == 1
    params = tmp / "out.param"
    proc = run_cli("export", cal, "--to", "ardupilot", "-o", params)
    assert proc.returncode == 2 and not params.exists()
    assert proc.stderr.startswith(f"magkf: error: {cal}: the calibration is not used")


def test_ellipsoid_with_a_unit_but_no_field_writes_nothing(tmp):
    """--mag-unit without --field: R would be scaled to determinant 1, not to the field; refused with -o, saying
    to give --field."""
    out = tmp / "cal.json"
    proc = run_cli("ellipsoid", DATA / "example_drive.csv", "--mag-unit", "nT", "-o", out)
    assert proc.returncode == 2 and not out.exists()
    assert "give --field with the field's magnitude in nT, or --field igrf" in proc.stderr


@pytest.mark.parametrize("command", ["validate", "diagnose", "report"])
def test_every_command_that_uses_a_calibration_refuses_a_mirrored_one(tmp, capsys, command):
    """A calibration with one axis flipped (det R = -1), given to validate, diagnose and report --cal: refused in
    one line naming the calibration file (not the log), before any work, and no report written."""
    from magkf.cli import main

    cal = tmp / "mirrored.json"
    Calibration(R=np.diag([-1.0, 1.0, 1.0]), b=np.zeros(3)).save(cal)
    out = tmp / "report.html"
    status = main(
        [command, str(DATA / "example_drive.csv"), "--cal", str(cal), *(["-o", str(out)] * (command == "report"))]
    )
    err = capsys.readouterr().err
    assert status == 2 and err.startswith(f"magkf: error: {cal}: the calibration is not used: R is mirrored")
    assert err.count("\n") == 1 and not out.exists()
