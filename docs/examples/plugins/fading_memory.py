"""A filter: the EKF with a fading memory, which forgets old epochs by widening its covariance by a factor at
every prediction (Sorenson and Sacks' fading-memory filter; FilterPy's ``KalmanFilter.alpha``). Useful
when the calibration changes faster than the random walk allows (a payload swapped in flight).

    FilterConfig(filter="ekf_fading")           in Python, once this module is imported
    magkf calibrate LOG.csv --filter ekf_fading  once a package installs it (entry point group magkf.filters)
"""

import numpy as np

from magkf.online.filters import EKF
from magkf.plugins import FILTERS


@FILTERS.register
class FadingMemoryEKF(EKF):
    """EKF whose covariance grows by ``fading ** (2 dt / 1 s)`` at each prediction over ``dt`` seconds (on
    top of the random walk), so that an epoch's weight halves about every ``ln 2 / (2 ln fading)`` seconds."""

    name = "ekf_fading"
    #: Factor on the standard deviations per second (1: the plain EKF).
    fading = 1.0005

    def predict(self, dt: float) -> None:
        super().predict(dt)
        self.P = self.P * np.float64(self.fading) ** (2.0 * dt)
