"""Batch calibration of a whole log: the patent's objective with a robust loss.

For every usable epoch, with ``c = R^-1 (m - b - e)`` the calibrated field:

* the **total-field residual** ``|c| - |B_ref|``;
* the **inter-axis residuals**: the NED residual ``C_nb c - B_ref`` (``measure="vector"``: all three
  components), or for ``measure="both"`` its two components across the reference field (the component
  along it is the total-field residual already, to first order, and is not counted twice).

Each residual is divided by its standard deviation from the same noise settings as the filter
(sensor noise, attitude, reference). A robust loss (``soft_l1``, scale 3 sigma) is
minimised with ``scipy.optimize.least_squares`` from the linear least-squares solution in the sensor
frame; epochs with a residual beyond ``OUTLIER_SIGMA`` after that robust pass are dropped (reported as
``gated_innovation``) and the rest fitted by plain least squares, whose Jacobian gives the covariance.
Epochs gated by DOP, missing values or the magnitude gate (with the starting estimate) are left out.
"""

from __future__ import annotations

import time as _time

import numpy as np
from scipy.optimize import least_squares

from ..config import FilterConfig
from ..conventions import body_to_ned
from ..errors import InputError
from ..io.calibration import Calibration
from ..io.drivelog import DriveLog
from .bootstrap import vector_least_squares
from .estimator import GATED_INNOVATION, GATED_MAGNITUDE, MISSING_ATTITUDE, USED
from .results import build_run
from .run import initial_state, prepare

OUTLIER_SIGMA = 5.0
LOSS_SCALE = 3.0


def _cross_basis(ref: np.ndarray) -> np.ndarray:
    """Two unit vectors (N, 2, 3) spanning the plane across each reference field (N, 3)."""
    u = ref / np.linalg.norm(ref, axis=1)[:, None]
    helper = np.where(np.abs(u[:, [0]]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    return np.stack([e1, np.cross(u, e1)], axis=1)


def solve_batch(log: DriveLog, config: FilterConfig = FilterConfig(), init: Calibration | None = None,
                effects=()):
    """Batch calibration of ``log``; returns a ``CalibrationRun`` (states constant over the log)."""
    started = _time.perf_counter()
    prep = prepare(log, config)
    prep, layout, x0, P0, how = initial_state(prep, config, init, effects)
    status = prep.base.copy()
    use_vector = config.measure != "magnitude"
    cand = (status == USED) if use_vector else ((status == USED) | (status == MISSING_ATTITUDE))
    if config.measure == "both":
        cand |= status == MISSING_ATTITUDE
    if cand.sum() < 3 * layout.size:
        raise InputError(f"too few usable epochs ({int(cand.sum())}) for a batch calibration", log.source)
    data = prep.data

    def calibrated(x, d, m):
        """Calibrated field (N, 3) of the epochs in ``d`` (EpochData) with raw readings ``m``."""
        e = np.zeros((len(m), 3))
        for effect, sl in list(zip(layout.effects, layout.slices.values()))[1:]:
            e += effect.contribution(x[sl], d)
        R, b = x[:9].reshape(3, 3), x[9:12]
        return np.linalg.solve(R, (m - b - e).T).T

    # Linear start in the sensor frame where attitude exists, then the magnitude gate with it.
    att = np.flatnonzero(cand & prep.has_attitude)
    x_start = x0.copy()
    if init is None and len(att) >= 3 * 12 and not effects:
        x_start[:12], _, _ = vector_least_squares(prep.m[att], data.field_body[att], config.sensor_noise_nt,
                                                  x0[:12], np.sqrt(np.diag(P0)[:12]))
    idx = np.flatnonzero(cand)
    c0 = calibrated(x_start, data.take(idx), prep.m[idx])
    off = np.abs(np.linalg.norm(c0, axis=1) - prep.ref_mag[idx]) > config.gate_nt
    status[idx[off]] = GATED_MAGNITUDE
    idx = idx[~off]
    has_att = prep.has_attitude[idx]
    ref = prep.ref[idx]
    s2 = config.sensor_noise_nt**2 + config.reference_nt**2
    sigma_total = np.sqrt(s2)
    sigma_cross = np.sqrt(s2 + (np.radians(config.attitude_deg) * prep.ref_mag[idx]) ** 2)
    basis = _cross_basis(ref)
    att_idx = np.flatnonzero(has_att) if use_vector else np.zeros(0, int)
    prior_std = np.sqrt(np.diag(P0))
    data_used, m_used = data.take(idx), prep.m[idx]  # taken once, not at every evaluation

    def residuals(x, keep=None):
        c = calibrated(x, data_used, m_used)
        parts = []
        if config.measure != "vector":
            parts.append((np.linalg.norm(c, axis=1) - prep.ref_mag[idx]) / sigma_total)
        if use_vector:
            ned = body_to_ned(prep.c_nb[idx[att_idx]], c[att_idx]) - ref[att_idx]
            if config.measure == "both":
                parts.append((np.einsum("nki,ni->nk", basis[att_idx], ned) / sigma_cross[att_idx, None]).ravel())
            else:
                parts.append((ned / sigma_cross[att_idx, None]).ravel())
        r = np.concatenate(parts)
        if keep is not None:
            r = r * keep
        return np.concatenate([r, (x - x0) / prior_std])  # the prior: initial calibration or weak bootstrap

    def epoch_outliers(r):
        """Epochs (len(idx),) with any residual beyond OUTLIER_SIGMA, and the row mask of the rest."""
        per_epoch = np.zeros(len(idx))
        offset = 0
        if config.measure != "vector":
            per_epoch = np.abs(r[:len(idx)])
            offset = len(idx)
        if use_vector:
            width = 2 if config.measure == "both" else 3
            cross = np.abs(r[offset:offset + width * len(att_idx)]).reshape(-1, width).max(axis=1)
            per_epoch[att_idx] = np.maximum(per_epoch[att_idx], cross)
        bad = per_epoch > OUTLIER_SIGMA
        rows = [~bad] if config.measure != "vector" else []
        if use_vector:
            rows.append(np.repeat(~bad[att_idx], width))
        return bad, np.concatenate(rows).astype(float)

    scale = np.maximum(np.abs(prior_std), 1e-9)
    # Robust pass (soft L1) to find the outlying epochs, then least squares without them.
    robust = least_squares(residuals, x_start, loss="soft_l1", f_scale=LOSS_SCALE, x_scale=scale, method="trf")
    outlier, keep = epoch_outliers(robust.fun[:-layout.size])
    fit = least_squares(residuals, robust.x, x_scale=scale, method="trf", kwargs={"keep": keep})
    outlier, keep = epoch_outliers(residuals(fit.x)[:-layout.size])
    status[idx[outlier]] = GATED_INNOVATION
    J = fit.jac
    P = np.linalg.inv(J.T @ J)
    P = 0.5 * (P + P.T)
    used = np.zeros(len(status), bool)
    used[idx[~outlier]] = True
    information = np.linalg.inv(P) - np.linalg.inv(P0)
    n = len(status)
    xs = np.tile(fit.x, (n, 1))
    stds = np.tile(np.sqrt(np.diag(P)), (n, 1))
    return build_run(log=log, prep=prep, config=config.replace(), layout=layout, x0=x0, P0=P0, xs=xs, stds=stds,
                     status=status, updated=used, nis=np.full(n, np.nan), x_final=fit.x, P_final=P,
                     information=information, init_how=how, smoothed=False, reacquisitions=0,
                     elapsed_s=_time.perf_counter() - started, method="batch")
