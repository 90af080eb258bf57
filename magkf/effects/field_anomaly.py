"""``field_anomaly``: a constant NED offset of the true field from the reference (crustal anomaly,
model error): ``m += R C_nb^T d`` with ``d`` in nT (north, east, down)."""

import numpy as np

from .linear import LinearEffect

__all__ = ["FieldAnomaly"]


class FieldAnomaly(LinearEffect):
    """Three parameters, the anomaly's north, east and down components (nT). On a level drive the down
    component cannot be told from the offset ``b``."""

    name = "field_anomaly"
    parameter_names = ("d_n", "d_e", "d_d")
    units = ("nT",) * 3
    prior_std = 2000.0

    def design(self, data):
        # d(R C_nb^T d)/dd = R C_nb^T
        return data.R0 @ np.swapaxes(data.c_nb, -1, -2)
