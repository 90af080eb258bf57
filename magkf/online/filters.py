"""FilterPy's EKF and UKF, specialised for random-walk parameter states.

The parameters follow a random walk (``F = I``), so the prediction is exact and cheap: ``x``
unchanged, ``P += Q dt``. FilterPy's generic steps pay for ``F`` products, a ``deepcopy`` of the
measurement and (UKF) one Python call of ``hx`` per sigma point; these subclasses keep FilterPy's
attributes (``x, P, Q, K, y, S``) and replace the hot steps:

* ``RandomWalkEKF.correct_stacked(y, H, R)``: Joseph-form update (expanded, exactly symmetric),
  positive-definiteness checked, for a measurement stacked from several epochs.
* ``RandomWalkUKF.correct_sigmas(sigmas, h, y, R)``: the update from sigma points drawn fresh from the
  current ``(x, P)`` for this update (never stale ones from an earlier prediction), whose measurements
  ``h`` the caller computed in one vectorised call.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import (
    ExtendedKalmanFilter,
    MerweScaledSigmaPoints,
    UnscentedKalmanFilter,
)


def inv_small(A: np.ndarray) -> np.ndarray:
    """Inverse of a matrix (or a stack of them); a single 3x3 by cofactors, which for one small
    matrix is several times cheaper than numpy's general call."""
    if A.shape == (3, 3):
        return _inv3(A)
    if A.shape == (1, 3, 3):
        return _inv3(A[0])[None]
    return np.linalg.inv(A)


def _inv3(A: np.ndarray) -> np.ndarray:
    (a, b, c), (d, e, f), (g, h, i) = A.tolist()
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + b * c01 + c * c02
    return np.array([[c00, c * h - b * i, b * f - c * e],
                     [c01, a * i - c * g, c * d - a * f],
                     [c02, b * g - a * h, a * e - b * d]]) / det


def _guard(P: np.ndarray) -> np.ndarray:
    """``P`` (symmetric) with its eigenvalues clipped if a diagonal element is not positive."""
    if P.ravel()[:: P.shape[0] + 1].min() <= 0:
        w, v = np.linalg.eigh(P)
        P = (v * np.maximum(w, 1e-18 * max(w.max(), 1e-300))) @ v.T
    return P


class RandomWalkEKF(ExtendedKalmanFilter):
    """Extended Kalman filter over a random-walk state (FilterPy ``ExtendedKalmanFilter``).

    ``x0`` (n,), ``P0`` (n, n), ``q_rate`` (n,) random-walk variance per second.
    """

    def __init__(self, x0, P0, q_rate):
        super().__init__(dim_x=len(x0), dim_z=3)
        self.x = np.array(x0, float)
        self.P = np.array(P0, float)
        self.q_rate = np.asarray(q_rate, float)
        self.Q = np.diag(self.q_rate)
        self._stride = len(x0) + 1

    def predict_dt(self, dt: float) -> None:
        """Random-walk prediction over ``dt`` seconds: ``P += Q dt`` (``x`` unchanged)."""
        self.P.ravel()[:: self._stride] += self.q_rate * dt

    def correct_stacked(self, y, H, R=None) -> None:
        """Update with innovation ``y`` (r,), Jacobian ``H`` (r, n) and noise ``R`` (r, r; default the
        identity, for whitened rows).

        Joseph form ``(I - K H) P (I - K H)^T + K R K^T``, expanded as ``P + M + M^T`` with
        ``M = K S K^T / 2 - K (P H^T)^T``: the same expression, valid for any gain, in two products
        instead of four and exactly symmetric by construction.
        """
        PHt = self.P @ H.T
        S = H @ PHt
        if R is None:
            S.ravel()[:: len(S) + 1] += 1.0
        else:
            S += R
        K = PHt @ inv_small(S) if S.shape == (3, 3) else np.linalg.solve(S, PHt.T).T
        self.x = self.x + K @ y
        M = (0.5 * (K @ S)) @ K.T - K @ PHt.T
        self.P = _guard(self.P + (M + M.T))
        self.K, self.y, self.S = K, y, S


class RandomWalkUKF(UnscentedKalmanFilter):
    """Unscented Kalman filter over a random-walk state (FilterPy ``UnscentedKalmanFilter``).

    Van der Merwe's scaled sigma points (``alpha=1, beta=2, kappa=0``: all mean weights equal and
    positive). The prediction of a random walk is exact without sigma points.
    """

    def __init__(self, x0, P0, q_rate, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        n = len(x0)
        points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
        super().__init__(dim_x=n, dim_z=3, dt=1.0, hx=None, fx=lambda x, dt: x, points=points)
        self.x = np.array(x0, float)
        self.P = np.array(P0, float)
        self.q_rate = np.asarray(q_rate, float)
        self.Q = np.diag(self.q_rate)
        self._stride = n + 1

    def predict_dt(self, dt: float) -> None:
        """Random-walk prediction over ``dt`` seconds: ``P += Q dt`` (``x`` unchanged, exact)."""
        self.P.ravel()[:: self._stride] += self.q_rate * dt

    def correct_sigmas(self, sigmas, h, y, R=None) -> None:
        """Update from ``sigmas`` (2n+1, n) drawn from the current ``(x, P)``, their measurements ``h``
        (2n+1, r), the innovation ``y = z - zp`` (r,) and the noise ``R`` (r, r; default the identity,
        for whitened rows)."""
        zp = self.Wm @ h
        dz = h - zp
        S = (dz.T * self.Wc) @ dz
        S = S + (np.eye(len(S)) if R is None else R)
        Pxz = ((sigmas - self.x).T * self.Wc) @ dz
        K = np.linalg.solve(S, Pxz.T).T
        self.x = self.x + K @ y
        P = self.P - (K @ S) @ K.T
        self.P = _guard(0.5 * (P + P.T))
        self.K, self.y, self.S = K, y, S
