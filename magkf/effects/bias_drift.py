"""``bias_drift``: the offset wanders in time (a random walk on ``b``, or steps)."""

import numpy as np

from .linear import LinearEffect

__all__ = ["DRIFT_DEGREE", "BiasDrift"]

#: Degree of the Legendre polynomials in time that the diagnostics test for a drift.
DRIFT_DEGREE = 1


class BiasDrift(LinearEffect):
    """Three parameters: the offset's departure from ``b`` (nT), following a random walk of ``walk``
    nT per sqrt(s) in the filter. A constant departure is ``b`` itself, so the diagnostics look for
    what a drift leaves in the residual instead: a slow trend in time (Legendre polynomials of degree
    1 to ``DRIFT_DEGREE`` on each axis)."""

    name = "bias_drift"
    parameter_names = ("d_x", "d_y", "d_z")
    units = ("nT",) * 3
    prior_std = 1.0
    simulation_sizes = (1, 3)  # one walk for every axis, or one each

    def __init__(self, walk: float = 2.0):
        self.walk = walk

    def design(self, data):
        G = np.zeros((len(data), 3, 3))
        G[:, [0, 1, 2], [0, 1, 2]] = 1.0
        return G

    def regressors(self, data):
        t = data.time
        u = 2 * (t - t[0]) / max(t[-1] - t[0], 1e-9) - 1
        basis = [np.polynomial.legendre.Legendre.basis(d)(u) for d in range(1, DRIFT_DEGREE + 1)]
        G = np.zeros((len(t), 3, 3 * DRIFT_DEGREE))
        for i in range(3):
            for d, values in enumerate(basis):
                G[:, i, 3 * d + i] = values
        return G

    def simulate(self, theta, data, rng):
        """A random walk of ``theta[0]`` nT per sqrt(s) on each axis (``theta`` (1,) or (3,))."""
        t = data.time
        dt = np.diff(t, prepend=t[0])
        walk = np.broadcast_to(np.asarray(theta, float)[:3], (3,)) if np.size(theta) >= 3 else np.full(3, theta[0])
        return np.cumsum(rng.normal(size=(len(t), 3)) * walk * np.sqrt(dt)[:, None], axis=0)
