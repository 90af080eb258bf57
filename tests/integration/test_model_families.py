"""The calibration a post-processing run writes: the whole-log estimate in the model family the log determines
(``magkf.online.whole_log``), judged against the simulator's truth and against the exact least-squares optimum.

Tolerances: a parameter within 3 of its standard deviations (fixed seeds; the chance of a larger deviation of
one Gaussian parameter is 0.27 %); the exact optimum is the linear least-squares fit of the body-frame
reference ``B`` on the reading, ``B ~ M m - c``, computed here with numpy, independently of magkf's solver.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.config import FilterConfig
from magkf.io.dataflash import write_dataflash
from magkf.io.drivelog import DriveLog
from magkf.online.prepare import prepare
from magkf.online.run import calibrate_log
from magkf.plausibility import check_run, log_field_nt
from magkf.sim import DriveConfig, simulate_drive

#: A straight, level flight: heading within 5 deg, roll and pitch within 3 deg (``magkf.sim.motion``).
STRAIGHT = dict(duration_s=600.0, rate_hz=10.0, motion="straight")
#: Coloured sensor noise and a slowly varying field nobody modelled (the offsets drift by about 60 nT).
COLOURED = dict(duration_s=600.0, rate_hz=10.0, motion="3d", noise_correlation_s=3.0, interference_nt=60.0)


def _b_std(run) -> np.ndarray:
    return np.array([run.summary.std[k] for k in ("b_x", "b_y", "b_z")])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_straight_level_flight_determines_the_offsets_with_r_at_the_prior_given(seed):
    sim = simulate_drive(DriveConfig(seed=seed, **STRAIGHT))
    prior = Calibration(R=sim.R, b=np.zeros(3), method="sinefit")
    run = calibrate_log(DriveLog(sim.table, "straight"), FilterConfig(), init=prior)
    model = run.summary.model
    assert model["family"] == "offsets", model["text"]
    np.testing.assert_array_equal(run.calibration.R, sim.R)  # held at the prior given, exactly
    b = run.calibration.b
    given = np.array([model["std_given_held"][k] for k in ("b_x", "b_y", "b_z")])
    assert np.all(np.abs(b - sim.b) < 3 * given), (b - sim.b) / given
    # the stated standard deviation counts R's uncertainty (init_r_std per element) on top: never smaller
    assert np.all(_b_std(run) >= given)


def test_a_straight_flight_without_a_prior_is_written_not_refused():
    """No calibration of the vehicle and none given: the offsets at R = I, said in words, and the plausibility rule
    (which refused this flight when R was estimated) writes it, with the one warning that the offsets' standard
    deviations (R's prior spread 0.02 times the field, 2 %) lie between the warned 1 % and the refused 3 %."""
    sim = simulate_drive(DriveConfig(seed=5, **STRAIGHT))
    log = DriveLog(sim.table, "straight")
    run = calibrate_log(log, FilterConfig())
    assert run.summary.model["family"] == "offsets"
    assert "identity" in run.summary.model["text"]
    np.testing.assert_array_equal(run.calibration.R, np.eye(3))
    (warning,) = check_run(run, log.source, log_field_nt(log))
    assert warning.startswith("the offsets' standard deviations reach") and "(2 % of the field" in warning


def _optimum(m, B):
    """The exact least-squares fit of ``B`` (k, 3) on ``[m, 1]`` (k, 4): coefficients (4, 3) and RMS (nT)."""
    X = np.column_stack([m, np.ones(len(m))])
    beta, *_ = np.linalg.lstsq(X, B, rcond=None)
    return beta, float(np.sqrt(np.mean(np.sum((X @ beta - B) ** 2, axis=1))))


def _rms(cal, m, B) -> float:
    return float(np.sqrt(np.mean(np.sum((cal.correct(m) - B) ** 2, axis=1))))


@pytest.mark.parametrize("seed", [40, 41])
def test_the_written_calibration_is_the_whole_log_optimum_and_holds_on_the_next_flight(seed):
    """Coloured noise and drifting offsets: over the epochs the run used, the written calibration's residual is
    within 1.02 times the exact optimum's; on a second flight of the same vehicle it is no worse than the optimum's.
    The two estimates are a small fraction of a standard deviation apart (measured: 1.00001 and at most 1.0003
    times), so 0.1 % bounds the held-out difference."""
    sim = simulate_drive(DriveConfig(seed=seed, **COLOURED))
    log = DriveLog(sim.table, "coloured")
    run = calibrate_log(log, FilterConfig())
    assert run.summary.model["family"] == "full"
    prep = prepare(log, FilterConfig())
    used = ((run.states["status"] == "used") & run.states["updated"]).to_numpy()
    m, B = prep.m[used], prep.data.field_body[used]
    beta, best = _optimum(m, B)
    ours = _rms(run.calibration, m, B)
    assert best <= ours <= 1.02 * best
    assert run.summary.residual_rms_nt == pytest.approx(ours, rel=1e-9)  # the NED norm the summary reports
    second = simulate_drive(DriveConfig(seed=seed + 100, **COLOURED), truth=(sim.R, sim.b))
    prep2 = prepare(DriveLog(second.table, "second"), FilterConfig())
    quiet = (np.linalg.norm(second.disturbance, axis=1) == 0) & ~second.dop_bad & prep2.has_attitude
    m2, B2 = prep2.m[quiet], prep2.data.field_body[quiet]
    X2 = np.column_stack([m2, np.ones(len(m2))])
    held_out_best = float(np.sqrt(np.mean(np.sum((X2 @ beta - B2) ** 2, axis=1))))
    assert _rms(run.calibration, m2, B2) <= 1.001 * held_out_best


def test_a_three_d_drive_determines_all_twelve_parameters():
    sim = simulate_drive(DriveConfig(duration_s=600.0, rate_hz=10.0, motion="3d", seed=21))
    run = calibrate_log(DriveLog(sim.table, "3d"), FilterConfig())
    assert run.summary.model["family"] == "full"
    truth = np.concatenate([sim.R.ravel(), sim.b])
    z = (run.x[:12] - truth) / run.std[:12]
    assert np.all(np.abs(z) < 3), z
    assert run.filter_x is not None and run.summary.filter_state["b"] == pytest.approx(list(run.filter_x[9:12]))


def test_a_level_drive_holds_the_elements_on_the_vertical():
    """A car: the vertical body field hardly varies, so R's third column is held at the reference (the identity
    here), and b_z's standard deviation carries that (at least PRIOR R std times the vertical field)."""
    sim = simulate_drive(DriveConfig(duration_s=600.0, rate_hz=10.0, motion="planar", seed=22))
    run = calibrate_log(DriveLog(sim.table, "car"), FilterConfig())
    model = run.summary.model
    assert "z component" in model["text"], model["text"]
    np.testing.assert_array_equal(run.calibration.R[:, 2], [0.0, 0.0, 1.0])
    assert run.summary.std["b_z"] > 0.01 * 40_000.0


def test_the_model_option_forces_a_family():
    sim = simulate_drive(DriveConfig(duration_s=300.0, rate_hz=10.0, motion="3d", seed=23))
    prior = Calibration(R=np.eye(3) * 1.01, b=np.zeros(3))
    run = calibrate_log(DriveLog(sim.table, "3d"), FilterConfig(model="scale"), init=prior)
    assert run.summary.model["family"] == "scale" and run.summary.model["asked"] == "scale"
    R = run.calibration.R
    np.testing.assert_array_equal(R - np.diag(np.diag(R)), np.zeros((3, 3)))  # off-diagonals held at the prior


def test_the_magnitude_alone_never_claims_the_rotation():
    sim = simulate_drive(DriveConfig(duration_s=600.0, rate_hz=10.0, motion="3d", seed=24))
    run = calibrate_log(DriveLog(sim.table, "3d"), FilterConfig(measure="magnitude"))
    assert run.summary.model["family"] == "soft-iron"
    R = run.calibration.R
    np.testing.assert_allclose(R, R.T, atol=1e-12)


#: The vehicle's calibration in the DataFlash log: ArduPilot's symmetric matrix and offsets 300 nT off the truth.
DIA, ODI = (0.96, 1.03, 0.99), (0.01, -0.02, 0.015)


def _vehicle(b_true):
    M = np.diag(DIA) + np.array([[0, ODI[0], ODI[1]], [ODI[0], 0, ODI[2]], [ODI[1], ODI[2], 0]])
    ofs = -(np.asarray(b_true) + np.array([300.0, -300.0, 300.0])) / 100.0  # mG, added by the firmware
    params = {f"COMPASS_OFS_{a}": v for a, v in zip("XYZ", ofs)}
    params |= {f"COMPASS_DIA_{a}": v for a, v in zip("XYZ", DIA)}
    params |= {f"COMPASS_ODI_{a}": v for a, v in zip("XYZ", ODI)}
    return np.linalg.inv(M), params


@pytest.mark.slow
def test_an_autopilot_log_holds_r_at_the_vehicles_calibration(tmp_path):
    """A straight flight logged by ArduPilot with its COMPASS_* calibration: ``calibrate`` (defaults) estimates the
    offsets with R held at the vehicle's matrix, and ``--init logged`` starts from it; both say so."""
    b_true = np.array([350.0, -220.0, 480.0])
    R_vehicle, params = _vehicle(b_true)
    sim = simulate_drive(DriveConfig(seed=7, **STRAIGHT), truth=(R_vehicle, b_true))
    path = tmp_path / "straight.bin"
    write_dataflash(sim.table.assign(hdop=sim.table["dop"]), path, parameters=params)
    for extra in ([], ["--init", "logged"]):
        out = subprocess.run(
            [sys.executable, "-m", "magkf", "calibrate", str(path), "--json", "--quiet", *extra],
            capture_output=True,
            text=True,
        )
        assert out.returncode == 0, out.stderr
        summary = json.loads(out.stdout)
        model = summary["model"]
        assert model["family"] == "offsets", model["text"]
        # the parameters are stored as float32: R to their rounding
        np.testing.assert_allclose(summary["R"], R_vehicle, rtol=1e-6)
        given = np.array([model["std_given_held"][k] for k in ("b_x", "b_y", "b_z")])
        # the log stores the field in whole mG (100 nT): its quantisation adds 100 / sqrt(12) nT per epoch
        assert np.all(np.abs(np.array(summary["b"]) - b_true) < 3 * given), (np.array(summary["b"]) - b_true) / given
        assert "vehicle" in model["text"] or "logged" in model["text"]
