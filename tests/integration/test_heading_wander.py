"""A time lag on a car looks like a heading error within each stretch of the heading's wander: the diagnosis
still takes it, and says how much it explains with the logged heading taken as exact (what the wander, fitted
with it, takes up).

A 0.12 s lag on a car turning at tens of degrees per second moves the body field by hundreds of nT; the heading's
wander (0.2 deg, Gauss-Markov over a minute) by about 70 nT across a horizontal field of 20 000 nT. With the
heading taken as exact, adding the lag must bring the held-out residual down by at least half the lag's own RMS
contribution (the core can take up part of it, its projection on R and b: 1.5 % here), to less than half of what
it was; with the wander taken out, the fall is a fraction of that (it took up most of the lag).
"""

import numpy as np
import pytest

from magkf.diagnostics.diagnose import diagnose
from magkf.effects import BUILTIN
from magkf.io.drivelog import DriveLog
from magkf.sim import DriveConfig, simulate_drive


@pytest.mark.slow
def test_a_time_lag_on_a_car_is_taken_and_its_size_said_with_the_heading_taken_as_exact():
    config = DriveConfig(
        duration_s=600, rate_hz=20, motion="planar", noise_nt=30.0, seed=40, noise_correlation_s=2.0,
        attitude_wander_deg=(0.0, 0.0, 0.2),
    )  # fmt: skip
    sim = simulate_drive(config, effects=[(BUILTIN["time_lag"](), [0.12])])
    d, _ = diagnose(DriveLog(sim.table))
    assert d.recommended and d.recommended[0].effect == "time_lag"
    before, after = d.residual_rms_held_out_exact_heading_nt
    lag_rms = float(np.sqrt(np.mean(np.sum(sim.contributions[0] ** 2, axis=1))))
    assert before - after >= 0.5 * lag_rms and after < 0.5 * before, (before, lag_rms, after)
    assert d.residual_rms_held_out_nt - d.recommended[0].residual_rms_after_nt < 0.5 * (before - after)
    assert f"falls from {before:.1f} to {after:.1f} nT" in d.text
