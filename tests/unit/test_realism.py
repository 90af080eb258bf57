"""The simulator's realism: coloured noise, attitude wander and interference with the stated statistics,
and logs without them unchanged draw for draw (seeded)."""

import numpy as np
import pytest
from scipy import stats

from magkf.sim import DriveConfig, simulate_drive
from magkf.sim.realism import gauss_markov


@pytest.mark.parametrize("tau", [0.5, 2.0])
def test_gauss_markov_has_the_stated_spread_and_correlation(tau):
    rate, n = 50.0, 400_000
    x = gauss_markov(n, rate, 30.0, tau, np.random.default_rng(3), dims=1)[:, 0]
    # n / (2 tau rate) independent samples: the standard error of the variance is about sqrt(2 / n_eff).
    n_eff = n / (2 * tau * rate)
    assert abs(x.var() / 900.0 - 1) < 4 * np.sqrt(2 / n_eff)
    lag = int(tau * rate)
    rho = np.corrcoef(x[:-lag], x[lag:])[0, 1]
    assert abs(rho - np.exp(-1.0)) < 4 * np.sqrt(2 / n_eff)


def test_a_log_without_realism_is_unchanged_draw_for_draw():
    plain = simulate_drive(DriveConfig(duration_s=60, rate_hz=20, seed=4))
    again = simulate_drive(DriveConfig(duration_s=60, rate_hz=20, seed=4, attitude_wander_s=10.0, interference_s=5.0))
    assert np.array_equal(plain.table.to_numpy(), again.table.to_numpy())
    assert not plain.attitude_error.any() and not plain.interference.any()
    white = plain.sensor_noise
    assert stats.normaltest(white[:, 0]).pvalue > 1e-3


def test_realism_is_recorded_and_in_the_log():
    cfg = DriveConfig(
        duration_s=600,
        rate_hz=20,
        seed=5,
        noise_correlation_s=2.0,
        attitude_wander_deg=(0.0, 0.0, 0.3),
        interference_nt=40.0,
    )
    sim = simulate_drive(cfg)
    plain = simulate_drive(DriveConfig(duration_s=600, rate_hz=20, seed=5))
    logged_minus_true = ((sim.table["yaw"] - plain.table["yaw"] + 180.0) % 360.0) - 180.0
    assert np.allclose(logged_minus_true, sim.attitude_error[:, 2], atol=1e-9)
    assert 0.05 < sim.attitude_error[:, 2].std() < 0.6 and not sim.attitude_error[:, :2].any()
    assert 10.0 < sim.interference.std() < 80.0
    lag = 40  # 2 s at 20 Hz: the sensor noise's correlation there is exp(-1)
    rho = np.corrcoef(sim.sensor_noise[:-lag, 0], sim.sensor_noise[lag:, 0])[0, 1]
    assert 0.2 < rho < 0.55
