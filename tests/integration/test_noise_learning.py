"""Real-flight conditions on simulated logs: a noise set 30 times too small or too large, coloured noise and
a wandering logged attitude, a log without attitude (seeded)."""

import numpy as np
import pytest
from scipy import stats

from magkf import DriveLog, FilterConfig, calibrate_log
from magkf.online.prepare import prepare
from magkf.online.results import residuals
from magkf.online.state import StateLayout
from magkf.sim import DriveConfig, simulate_drive

NOISE = 30.0


def whole_log_rms(log, R, b) -> float:
    """RMS of the NED residual norm (nT) of ``R``, ``b`` over every epoch with attitude and a reference."""
    ned, _ = residuals(prepare(log, FilterConfig()), StateLayout.with_core(), np.concatenate([np.ravel(R), b]))
    ok = np.all(np.isfinite(ned), axis=1)
    return float(np.sqrt(np.mean(np.sum(ned[ok] ** 2, axis=1))))


@pytest.fixture(scope="module")
def drives():
    return [simulate_drive(DriveConfig(duration_s=1200, rate_hz=50, noise_nt=NOISE, seed=400 + s)) for s in range(2)]


#: Largest |z| of 24 parameter estimates at a 1 % family-wise false-alarm rate: Phi^-1(1 - 0.01 / 48).
Z_MAX = 3.53


@pytest.mark.slow
@pytest.mark.parametrize("configured", [NOISE / 30, NOISE * 30])
def test_a_noise_set_30_times_wrong_is_learned(drives, configured):
    """The noise configured 30 times too small or too large is learned, and the estimate is as right as with it:
    each of the 24 parameters of the two drives within ``Z_MAX`` of its standard deviation (Bonferroni: the chance
    that any of 24 Gaussian z reaches 3.53 is 1 %; 3.0 would be reached by chance 6 % of the time)."""
    for sim in drives:
        log = DriveLog(sim.table)
        run = calibrate_log(log, FilterConfig(sensor_noise_nt=configured))
        assert whole_log_rms(log, run.calibration.R, run.calibration.b) <= 1.05 * whole_log_rms(log, sim.R, sim.b)
        z = np.abs(run.x[:12] - np.concatenate([sim.R.ravel(), sim.b])) / run.std[:12]
        assert z.max() < Z_MAX, z
        status = run.states["status"].to_numpy()
        disturbed = np.linalg.norm(sim.disturbance, axis=1)
        quiet = (disturbed == 0) & (status != "gated_dop")
        assert np.mean(status[quiet] == "used") >= 0.95
        assert np.mean(status[disturbed > 5 * NOISE] != "used") >= 0.95
        learned = run.summary.noise["learned"]["sensor_median_nt"]
        assert learned == pytest.approx(np.sqrt(NOISE**2 - 10.0**2), rel=0.1)  # the reference's 10 nT apart


@pytest.fixture(scope="module")
def wandering():
    """20 seeded 20-minute 25 Hz drives whose sensor noise is correlated over 2 s and whose logged yaw
    wanders from the truth by 0.3 deg (a Gauss-Markov process of 60 s), calibrated with the defaults."""
    out = []
    for seed in range(20):
        config = DriveConfig(
            duration_s=1200,
            rate_hz=25,
            noise_nt=NOISE,
            seed=700 + seed,
            noise_correlation_s=2.0,
            attitude_wander_deg=(0.0, 0.0, 0.3),
        )
        sim = simulate_drive(config)
        out.append((sim, calibrate_log(DriveLog(sim.table), FilterConfig())))
    return out


@pytest.mark.slow
def test_coloured_noise_and_a_wandering_yaw_keep_nees_in_its_band(wandering):
    """The residuals' correlation is measured (each epoch counts as 1/k of an independent one, k near
    the 100 epochs of a 2 s process at 25 Hz along the field and 3 000 of the 60 s heading error across it),
    so the covariance of the estimate is honest: the mean NEES of 20 runs lies in its 95 % chi-square band."""
    nees = []
    for sim, run in wandering:
        e = run.x[:12] - np.concatenate([sim.R.ravel(), sim.b])
        nees.append(float(e @ np.linalg.solve(run.P[:12, :12], e)))
    lo, hi = stats.chi2.ppf([0.025, 0.975], 12 * len(nees)) / len(nees)
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


@pytest.mark.slow
def test_coloured_noise_and_a_wandering_yaw_fit_as_well_as_the_truth(wandering):
    for sim, run in wandering[:5]:
        log = DriveLog(sim.table)
        assert whole_log_rms(log, run.calibration.R, run.calibration.b) <= 1.05 * whole_log_rms(log, sim.R, sim.b)
        assert "correlated over" in run.summary.verdict.lower() and "magkf diagnose" in run.summary.verdict


@pytest.mark.slow
def test_a_heading_error_is_learned_apart_from_the_tilt(wandering):
    """The learned heading noise (median over each log) against the realised RMS of the logged yaw's error:
    their ratio scatters from log to log (a 60 s window holds about one correlation time of the error), so
    the median ratio over the 20 logs is checked, and the tilt, which has no error here, is near zero."""
    ratios, tilts = [], []
    for sim, run in wandering:
        learned = run.summary.noise["learned"]
        ratios.append(learned["heading_median_deg"] / float(np.sqrt(np.mean(sim.attitude_error[:, 2] ** 2))))
        tilts.append(learned["attitude_median_deg"])
    assert 0.7 < np.median(ratios) < 1.3, ratios
    assert np.median(tilts) < 0.1 * 0.3, tilts


def test_a_log_without_attitude_reports_its_magnitude_residual_and_the_unseen_rotation():
    sim = simulate_drive(DriveConfig(duration_s=300, rate_hz=20, noise_nt=NOISE, seed=41))
    log = DriveLog(sim.table.drop(columns=["roll", "pitch", "yaw"]))
    run = calibrate_log(log, FilterConfig())
    s = run.summary
    assert np.isfinite(s.residual_rms_magnitude_nt) and np.isfinite(s.residual_rms_magnitude_all_nt)
    assert s.residual_rms_magnitude_nt < 1.2 * NOISE
    assert "the orientation of R" in s.observability["text"]
