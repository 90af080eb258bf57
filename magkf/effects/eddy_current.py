"""``eddy_current``: a field proportional to the rate of change of the body-frame field, the eddy term
of the Tolles-Lawson model: ``m += E dB_b/dt`` with ``E`` (3x3, s) in sensor axes."""

import numpy as np

from .linear import LinearEffect

__all__ = ["EddyCurrent"]


class EddyCurrent(LinearEffect):
    """Nine parameters ``E_ij`` (seconds: nT of field per nT/s of change), row-major."""

    name = "eddy_current"
    parameter_names = tuple(f"E{i}{j}" for i in range(1, 4) for j in range(1, 4))
    units = ("s",) * 9
    prior_std = 0.05

    def design(self, data):
        rate = data.field_body_rate
        G = np.zeros((len(rate), 3, 9))
        for i in range(3):
            G[:, i, 3 * i : 3 * i + 3] = rate
        return G
