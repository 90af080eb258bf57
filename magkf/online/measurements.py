"""Measurement models of the online calibration: the NED vector and the field magnitude.

**Vector.** The NED components of the calibrated field, ``C_nb R^-1 (m - b - e)``, against the reference
``B_ref``. The same equation, multiplied through by ``R C_nb^T``, reads ``m = R C_nb^T B_ref + b + e``:
in the sensor frame it is *linear* in ``R``, ``b`` and every linear effect, so magkf processes it there
(the Kalman update is then exact, and its Jacobian is the effects' Jacobians evaluated once per log).
Residuals are reported in NED. Noise covariance in the sensor frame:

    sensor_noise^2 I + R (reference^2 I + A) R^T

with the attitude term ``A = att^2 (|B|^2 I - B B^T)`` for ``both``: an attitude error turns the field
but does not change its length, so the along-field (total-field) component keeps sensor-level noise and
only the two cross-field (inter-axis) components carry the attitude noise; this is the patent's
total-field plus inter-axis residual pair without counting the magnitude twice. For ``vector``,
``A = att^2 |B|^2 I`` on every component.

**Magnitude.** ``|R^-1 (m - b - e)|`` against ``|B_ref|``; needs no attitude. Variance
``sensor_noise^2 u^T R^-1 R^-T u + reference^2`` with ``u`` the unit calibrated field.
"""

from __future__ import annotations

import numpy as np

from ..config import FilterConfig

_EYE = np.eye(3)


def vector_noise(field_body: np.ndarray, R: np.ndarray, config: FilterConfig, measure: str) -> np.ndarray:
    """Sensor-frame noise covariance (N, 3, 3) of the vector measurement at N epochs (body field in nT)."""
    B = np.asarray(field_body, float)
    att2 = np.radians(config.attitude_deg) ** 2
    b2 = np.einsum("ni,ni->n", B, B)
    diagonal = att2 * b2 + config.reference_nt**2  # (N,)
    A = _EYE * diagonal[:, None, None]
    if measure == "both":
        A = A - att2 * B[:, :, None] * B[:, None, :]
    return config.sensor_noise_nt**2 * _EYE + R @ A @ R.T


def whitening(noise: np.ndarray) -> np.ndarray:
    """``W = L^-1`` (N, 3, 3) with ``noise = L L^T``: ``W y`` has unit, uncorrelated noise."""
    if len(noise) == 1:  # one epoch (real time): the 3x3 algebra written out beats numpy's call overhead
        return _whitening3(noise[0])[None]
    return np.linalg.inv(np.linalg.cholesky(noise))


def _whitening3(N: np.ndarray) -> np.ndarray:
    """Inverse Cholesky factor of one symmetric positive-definite 3x3 matrix."""
    (a, b, c), (_, d, e), (_, _, f) = N.tolist()
    l11 = a**0.5
    l21, l31 = b / l11, c / l11
    l22 = (d - l21 * l21) ** 0.5
    l32 = (e - l31 * l21) / l22
    l33 = (f - l31 * l31 - l32 * l32) ** 0.5
    i11, i22, i33 = 1 / l11, 1 / l22, 1 / l33
    i21 = -l21 * i11 * i22
    i32 = -l32 * i22 * i33
    i31 = -(l31 * i11 + l32 * i21) * i33
    return np.array([[i11, 0.0, 0.0], [i21, i22, 0.0], [i31, i32, i33]])


def magnitude_jacobian(x_core: np.ndarray, m_minus_e: np.ndarray):
    """Magnitude model at k epochs: ``h`` (k,), ``H`` (k, 12) and ``w = u^T R^-1`` (k, 3).

    ``x_core`` (12,) is ``R`` row-major and ``b``; ``m_minus_e`` (k, 3) the raw readings less the other
    effects. ``h = |c|`` with ``c = R^-1 (m - e - b)``; ``dh/db = -w`` and ``dh/dR_ij = -w_i c_j``.
    """
    R = x_core[:9].reshape(3, 3)
    Rinv = np.linalg.inv(R)
    c = (m_minus_e - x_core[9:12]) @ Rinv.T
    h = np.linalg.norm(c, axis=1)
    w = (c / h[:, None]) @ Rinv
    H = np.concatenate([-(w[:, :, None] * c[:, None, :]).reshape(-1, 9), -w], axis=1)
    return h, H, w


def magnitude_noise(w: np.ndarray, config: FilterConfig) -> np.ndarray:
    """Variance (k,) of the magnitude measurement: ``sensor^2 |w|^2 + reference^2``, nT^2."""
    return config.sensor_noise_nt**2 * np.einsum("ki,ki->k", w, w) + config.reference_nt**2
