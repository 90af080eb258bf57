"""A helper base for effects that are a linear map of per-epoch regressors: ``contribution = G theta``."""

from __future__ import annotations

import numpy as np

from .base import Effect, EpochData

__all__ = ["LinearEffect", "per_axis"]


class LinearEffect(Effect):
    """An effect ``m += G(data) theta`` with regressors ``G`` (N, 3, k); subclasses implement ``design``,
    epoch by epoch (row ``i`` of ``G`` from epoch ``i`` of ``data`` alone), so that the epochs ``rows`` of
    ``contribution`` and ``jacobian`` are ``design(data.take(rows))``.

    ``prior_std`` and ``walk`` (per sqrt(s)) set the prior and random walk of every parameter.
    """

    prior_std: float = 1.0
    walk: float = 0.0

    def design(self, data: EpochData) -> np.ndarray:
        """The regressors ``G`` (N, 3, k)."""
        raise NotImplementedError

    def prior(self):
        return np.zeros(self.size), np.full(self.size, float(self.prior_std))

    def random_walk(self):
        return np.full(self.size, float(self.walk))

    def contribution(self, theta, data: EpochData, rows=None) -> np.ndarray:
        G = self.jacobian(theta, data, rows=rows)
        theta = np.asarray(theta, float)
        if theta.ndim == 1:
            return G @ theta
        return np.einsum("nik,sk->sni", G, theta)

    def jacobian(self, theta, data: EpochData, rows=None) -> np.ndarray:
        return self.design(data.take(rows))


def per_axis(values: np.ndarray) -> np.ndarray:
    """(N, 3, 3) regressors putting ``values`` (N,) or (N, 3) on each sensor axis with its own parameter."""
    v = np.asarray(values, float)
    if v.ndim == 1:
        v = np.repeat(v[:, None], 3, axis=1)
    G = np.zeros(v.shape[:1] + (3, 3))
    for i in range(3):
        G[:, i, i] = v[:, i]
    return G
