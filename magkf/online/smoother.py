"""Rauch-Tung-Striebel smoothing of a random-walk state over the filter's steps."""

from __future__ import annotations

import numpy as np

__all__ = ["rts_smooth"]


def rts_smooth(xs, Ps, dt, q_rate):
    """Rauch-Tung-Striebel smoother for a random walk (``F = I``) over filter steps (blocks).

    ``xs`` (K, n), ``Ps`` (K, n, n) are the filtered estimates after each step, ``dt`` (K,) the time
    each step's prediction covered, ``q_rate`` (n,) the random walk's variance per second. The prediction
    from step k to k+1 is ``x`` unchanged and ``P + Q dt_{k+1}``; the gain is
    ``C_k = P_k (P_k + Q dt_{k+1})^-1``. Returns the smoothed ``(xs, Ps)`` (new arrays).
    """
    xs, Ps = xs.copy(), Ps.copy()
    for k in range(len(xs) - 2, -1, -1):
        P_pred = Ps[k].copy()
        P_pred[np.diag_indices_from(P_pred)] += q_rate * dt[k + 1]
        C = np.linalg.solve(P_pred.T, Ps[k].T).T
        xs[k] = xs[k] + C @ (xs[k + 1] - xs[k])
        Ps[k] = Ps[k] + C @ (Ps[k + 1] - P_pred) @ C.T
        Ps[k] = 0.5 * (Ps[k] + Ps[k].T)
    return xs, Ps
