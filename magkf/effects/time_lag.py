"""``time_lag``: the magnetometer's time stamps lag (or lead) the attitude by a constant delay."""

import numpy as np

from .linear import LinearEffect

__all__ = ["TimeLag"]


class TimeLag(LinearEffect):
    """One parameter ``tau`` (s, positive when the magnetometer lags): the reading at ``t`` is the field
    at ``t - tau``, ``m(t) = R B(t - tau) + b``, so ``m += -tau R dB/dt`` to first order (with the
    initial ``R``, which keeps the effect linear; the difference is second order)."""

    name = "time_lag"
    parameter_names = ("tau",)
    units = ("s",)
    prior_std = 0.5

    def design(self, data):
        return -(data.field_body_rate @ data.R0.T)[:, :, None]

    def simulate(self, theta, data, rng):
        """The exact delay: the body field interpolated ``tau`` earlier, less the field now."""
        t = data.time
        lagged = np.column_stack([np.interp(t - theta[0], t, data.field_body[:, i]) for i in range(3)])
        return (lagged - data.field_body) @ data.R0.T
