"""A nonlinear effect: an offset that settles after power-on, ``a exp(-t / tau)`` on each axis, with ``t`` the
time since the sensor was powered (a logged ``uptime_s`` channel), ``a`` the settling offset (nT) and ``tau``
its time constant (s). It is nonlinear in ``tau``, so it subclasses ``Effect`` with ``linear = False``: the
filters take its Jacobian at the estimate (finite differences by default) and the UKF its sigma points.

    magkf calibrate LOG.csv --effect-file docs/examples/plugins/warm_up.py --effect warm_up
"""

import numpy as np

from magkf.effects import Effect


class WarmUp(Effect):
    """Offset settling after power-on: ``a exp(-t / tau)`` (nT) on each axis, ``t`` the logged uptime (s)."""

    name = "warm_up"
    parameter_names = ("a_x", "a_y", "a_z", "tau")
    units = ("nT", "nT", "nT", "s")
    linear = False

    def __init__(self, column: str = "uptime_s"):
        self.columns = (column,)

    def prior(self):
        """A settling of up to a few hundred nT, over about five minutes."""
        return np.array([0.0, 0.0, 0.0, 300.0]), np.array([500.0, 500.0, 500.0, 200.0])

    def contribution(self, theta, data):
        """(N, 3) nT for ``theta`` (4,); (S, N, 3) for the UKF's sigma points (S, 4)."""
        theta = np.asarray(theta, float)
        t = np.asarray(data.columns[self.columns[0]], float)
        tau = np.maximum(theta[..., 3:4], 1.0)  # (1,) or (S, 1): a time constant under a second is none
        decay = np.exp(-t / tau)  # (N,) or (S, N)
        return decay[..., None] * theta[..., None, :3]
