"""A measurement model is one class of four methods (``measure``, ``predict``, ``jacobian``, ``covariance``):
defined here, registered, and run through the EKF, the UKF, the batch solver and the real-time step without a
change anywhere else (seeded)."""

import numpy as np
import pytest
from scipy import stats

from magkf import Calibration, DriveLog, FilterConfig, OnlineCalibrator, calibrate_log, solve_batch
from magkf.online.measurements import MEASUREMENTS, MeasurementModel, register_measurement
from magkf.sim import DriveConfig, simulate_drive

NOISE = 30.0
#: Largest |error| / std allowed over 12 parameters and 4 paths: the two-sided normal quantile at 1e-3
#: shared out over the 48 checks (Bonferroni), so a correct model fails by chance with probability 1e-3.
Z_MAX = stats.norm.ppf(1 - 1e-3 / 2 / 48)


class IsotropicVector(MeasurementModel):
    """The field vector in the sensor frame with the same noise on every component:
    ``sigma^2 = sensor^2 + reference^2 + (attitude |B|)^2``. Linear in the state, like ``vector``. It
    implements only the four methods of the interface; the EKF's, the UKF's, the batch solver's and the
    noise learner's rows are the base class's."""

    name = "isotropic_vector"
    rows = 3
    needs_attitude = True

    def measure(self, blk):
        return blk.m

    def predict(self, x, blk):
        x = np.asarray(x, float)
        return blk.H @ x if x.ndim == 1 else np.einsum("kin,sn->ski", blk.H, x)

    def jacobian(self, x, blk):
        return blk.H

    def covariance(self, x, blk):
        n = self.noise
        var = n.sensor_nt**2 + n.reference_nt**2 + (n.attitude_rad * np.linalg.norm(blk.B, axis=-1)) ** 2
        return var[:, None, None] * np.eye(3)


@pytest.fixture(scope="module")
def registered():
    register_measurement(IsotropicVector)
    yield FilterConfig(
        measure="isotropic_vector", sensor_noise_nt=NOISE, attitude_deg=0.0, reference_nt=0.0, r_walk=0.0, b_walk=0.0
    )
    del MEASUREMENTS[IsotropicVector.name]


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(
        DriveConfig(duration_s=600, rate_hz=10, noise_nt=NOISE, seed=77, disturbances=0, dop_bad_stretches=0)
    )


def _z(x, std, sim):
    truth = np.concatenate([sim.R.ravel(), sim.b])
    return np.abs(x[:12] - truth) / std[:12]


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_added_model_runs_through_the_filters(registered, drive, name):
    run = calibrate_log(DriveLog(drive.table), registered.replace(filter=name))
    assert run.summary.measure == "isotropic_vector"
    assert (run.states["status"] == "used").mean() > 0.99
    assert _z(run.x, run.std, drive).max() < Z_MAX


def test_added_model_runs_through_the_batch_solver(registered, drive):
    run = solve_batch(DriveLog(drive.table), registered)
    assert _z(run.x, run.std, drive).max() < Z_MAX


@pytest.mark.slow
def test_added_model_runs_through_the_realtime_step(registered, drive):
    rng = np.random.default_rng(5)
    start = Calibration(
        R=drive.R + rng.normal(scale=0.01, size=(3, 3)),
        b=drive.b + rng.normal(scale=200, size=3),
        covariance=np.diag([0.02**2] * 9 + [300.0**2] * 3),
    )
    online = OnlineCalibrator(start, registered)
    statuses = [online.step(row).status for _, row in drive.table.iterrows()]  # rows named by their time
    assert statuses.count("used") > 0.99 * len(statuses)
    std = np.sqrt(np.diag(online.calibration.covariance))
    assert _z(online.calibration.state, std, drive).max() < Z_MAX


class LinearIsotropicVector(IsotropicVector):
    """The same rows declared linear in the state: the UKF takes them at the estimate through ``linearise``
    and never asks for sigma-point predictions."""

    name = "isotropic_vector_linear"
    linear = True

    def sigma_predict(self, sigmas, x, blk):
        raise AssertionError("a linear model's rows are taken at the estimate")


def test_linear_model_under_the_ukf_is_taken_at_the_estimate(registered, drive):
    """A model declared linear runs through the UKF without sigma points, and the UKF's estimate is then the
    EKF's: the unscented transform of a linear function is exact (the same update to rounding)."""
    register_measurement(LinearIsotropicVector)
    try:
        config = registered.replace(measure=LinearIsotropicVector.name)
        ukf = calibrate_log(DriveLog(drive.table), config.replace(filter="ukf"))
        ekf = calibrate_log(DriveLog(drive.table), config.replace(filter="ekf"))
        online = OnlineCalibrator(Calibration(R=drive.R, b=drive.b), config.replace(filter="ukf"))
    finally:
        del MEASUREMENTS[LinearIsotropicVector.name]
    assert online.estimator.filter._points is None  # no sigma points made for a model that never needs them
    assert list(ukf.states["status"]) == list(ekf.states["status"])
    assert np.allclose(ukf.x, ekf.x, rtol=0, atol=1e-9 * ekf.std.max())
    assert _z(ukf.x, ukf.std, drive).max() < Z_MAX
