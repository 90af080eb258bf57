"""The core effect: soft and hard iron, ``m = R B_b + b`` (12 parameters)."""

from __future__ import annotations

import numpy as np

from ..calibration import PARAMETER_NAMES
from .base import Effect, EpochData, at_rows

__all__ = ["DEFAULT_R_WALK", "DEFAULT_B_WALK", "SoftHardIron", "core_jacobian"]

#: Default random walks: R per sqrt(s) (dimensionless) and b in nT per sqrt(s).
DEFAULT_R_WALK = 1e-7
DEFAULT_B_WALK = 0.01


class SoftHardIron(Effect):
    """``R B_b + b``: the 3x3 matrix ``R`` (row-major, dimensionless) and offset ``b`` (nT).

    ``prior_mean`` (12,) and ``prior_std`` (12,) come from an offline calibration or the bootstrap;
    ``r_walk`` and ``b_walk`` are the random walks of ``R`` (per sqrt(s)) and ``b`` (nT per sqrt(s)).
    """

    name = "core"
    parameter_names = PARAMETER_NAMES
    units = ("",) * 9 + ("nT",) * 3
    linear = True

    def __init__(self, prior_mean=None, prior_std=None, r_walk: float = DEFAULT_R_WALK, b_walk: float = DEFAULT_B_WALK):
        self.prior_mean = (
            np.concatenate([np.eye(3).ravel(), np.zeros(3)]) if prior_mean is None else np.asarray(prior_mean, float)
        )
        self.prior_std = (
            np.concatenate([np.full(9, 0.1), np.full(3, 1000.0)]) if prior_std is None else np.asarray(prior_std, float)
        )
        self.r_walk, self.b_walk = float(r_walk), float(b_walk)

    def prior(self):
        return self.prior_mean.copy(), self.prior_std.copy()

    def random_walk(self):
        return np.concatenate([np.full(9, self.r_walk), np.full(3, self.b_walk)])

    def contribution(self, theta, data: EpochData, rows=None) -> np.ndarray:
        theta = np.asarray(theta, float)
        R = theta[..., :9].reshape(theta.shape[:-1] + (3, 3))
        b = theta[..., 9:]
        B = at_rows(data.field_body, rows)
        if theta.ndim == 1:
            return B @ R.T + b
        return np.einsum("sij,nj->sni", R, B) + b[:, None, :]

    def jacobian(self, theta, data: EpochData, rows=None) -> np.ndarray:
        return core_jacobian(at_rows(data.field_body, rows))


def core_jacobian(field_body) -> np.ndarray:
    """(N, 3, 12): d(R B + b)/d(R row-major, b) = [I3 kron B^T, I3]."""
    B = np.asarray(field_body, float)
    n = len(B)
    J = np.zeros((n, 3, 12))
    for i in range(3):
        J[:, i, 3 * i : 3 * i + 3] = B
        J[:, i, 9 + i] = 1.0
    return J
