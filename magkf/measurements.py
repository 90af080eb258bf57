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

from .config import FilterConfig


def vector_noise(field_body: np.ndarray, R: np.ndarray, config: FilterConfig, measure: str) -> np.ndarray:
    """Sensor-frame noise covariance (N, 3, 3) of the vector measurement at N epochs (body field in nT)."""
    B = np.asarray(field_body, float)
    att = np.radians(config.attitude_deg)
    b2 = np.einsum("ni,ni->n", B, B)
    eye = np.eye(3)
    if measure == "both":
        A = att**2 * (b2[:, None, None] * eye - np.einsum("ni,nj->nij", B, B))
    else:
        A = (att**2 * b2)[:, None, None] * eye
    A = A + config.reference_nt**2 * eye
    return config.sensor_noise_nt**2 * eye + R @ A @ R.T


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
