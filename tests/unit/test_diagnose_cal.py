"""``diagnose --cal``: a calibration diagnosed as it is is gated and weighed as ``calibrate`` gates and weighs.

A simulated log with twelve disturbances (1 000 to 5 000 nT, 2 to 8 s each), white noise of ``NOISE_NT`` per axis,
the exact attitude and reference field, is diagnosed with its true calibration. The disturbances left among
the diagnosed epochs must add at most ``SHARE`` of the noise's variance per epoch (``3 NOISE_NT^2``): before the
filter's magnitude gate was applied to this path, they added 6 % (the outlier screening alone keeps a
bump's shoulders up to 400 nT). And with the disturbances out, the residual's mean square is the noise's through
``R^-1`` plus what is left of them, within ``SIGMAS`` standard errors.
"""

import numpy as np

from magkf.diagnostics.diagnose import diagnose
from magkf.io.drivelog import DriveLog
from magkf.sim import DriveConfig, simulate_drive

NOISE_NT = 30.0
SHARE = 0.05
#: Two-sided normal tail 7e-6: a mean of squares over thousands of independent epochs.
SIGMAS = 4.5


def test_a_calibration_diagnosed_as_it_is_leaves_the_disturbances_out():
    config = DriveConfig(duration_s=600, rate_hz=10, noise_nt=NOISE_NT, seed=300, disturbances=12, write_reference=True)
    sim = simulate_drive(config)
    d, run = diagnose(DriveLog(sim.table), cal=sim.calibration, wander_s=None, candidates=[])
    assert run is None  # the calibration itself is the model
    on = np.isin(sim.table.index.to_numpy(), d.residuals["time"])
    left = np.sum(sim.disturbance[on] ** 2, axis=1)
    assert left.mean() < SHARE * 3 * NOISE_NT**2, f"disturbances left: {left.mean():.0f} nT^2 per epoch"
    # NED residual = C (noise through R^-1 + disturbance): mean square noise^2 trace(R^-T R^-1) + |d|^2
    Rinv = np.linalg.inv(sim.R)
    eig = np.linalg.eigvalsh(Rinv.T @ Rinv) * NOISE_NT**2
    n = int(on.sum())
    expected = eig.sum() + left.mean()
    sd = np.sqrt(2 * np.sum(eig**2) + 4 * np.mean(left) * eig.max()) / np.sqrt(n)
    found = d.residual_rms_nt**2
    assert abs(found - expected) < SIGMAS * sd, f"mean square {found:.0f}, expected {expected:.0f} +- {sd:.0f}"
