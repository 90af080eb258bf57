"""``bias_drift``: the offset wanders in time (a random walk on ``b``, or steps)."""

import numpy as np

from .base import at_rows
from .linear import LinearEffect

__all__ = ["DRIFT_SEGMENTS", "BiasDrift"]

#: Straight segments in time of the drift the diagnostics fit for a held-out residual (knots evenly spaced
#: over the log); the constant is ``b``'s.
DRIFT_SEGMENTS = 12


class BiasDrift(LinearEffect):
    """Three parameters: the offset's departure from ``b`` (nT), following a random walk of ``walk``
    nT per sqrt(s) in the filter. A constant departure is ``b`` itself, so the diagnostics test whether
    ``b`` wanders (Nyblom's constancy test) and fit the wander as a continuous piecewise-linear offset on
    each axis (``DRIFT_SEGMENTS`` segments) for the residual it would leave."""

    name = "bias_drift"
    parameter_names = ("d_x", "d_y", "d_z")
    units = ("nT",) * 3
    prior_std = 1.0
    simulation_sizes = (1, 3)  # one walk for every axis, or one each
    wanders = True
    #: the random walk, nT per sqrt(s) (the range of ``calibrate --b-walk``)
    settings_schema = {"walk": {"type": "number", "minimum": 0, "maximum": 1e5}}

    def __init__(self, walk: float = 2.0):
        self.walk = walk

    def design(self, data):
        G = np.zeros((len(data), 3, 3))
        G[:, [0, 1, 2], [0, 1, 2]] = 1.0
        return G

    def regressors(self, data, rows=None):
        """Hat functions in time (N, 3, 3 (DRIFT_SEGMENTS + 1)) at the epochs ``rows`` of ``data`` (None: all),
        the knots spread evenly over all of ``data``'s time: knot ``k`` on axis ``i`` is column ``3 k + i``;
        they sum to the constant offset."""
        span = data.time
        t = at_rows(span, rows)
        u = DRIFT_SEGMENTS * (t - span[0]) / max(span[-1] - span[0], 1e-9)
        hats = np.clip(1.0 - np.abs(u[:, None] - np.arange(DRIFT_SEGMENTS + 1)), 0.0, None)  # (N, knots)
        G = np.zeros((len(t), 3, 3 * (DRIFT_SEGMENTS + 1)))
        for i in range(3):
            G[:, i, i::3] = hats
        return G

    def increments(self):
        """First differences (3 DRIFT_SEGMENTS, 3 (DRIFT_SEGMENTS + 1)) of the knot values, axis by axis."""
        q = 3 * (DRIFT_SEGMENTS + 1)
        return np.eye(q)[3:] - np.eye(q)[:-3]

    def simulate(self, theta, data, rng):
        """A random walk of ``theta[0]`` nT per sqrt(s) on each axis (``theta`` (1,) or (3,))."""
        t = data.time
        dt = np.diff(t, prepend=t[0])
        walk = np.broadcast_to(np.asarray(theta, float)[:3], (3,)) if np.size(theta) >= 3 else np.full(3, theta[0])
        return np.cumsum(rng.normal(size=(len(t), 3)) * walk * np.sqrt(dt)[:, None], axis=0)
