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

from ..config import FilterConfig
from ..errors import InputError, names_the_log
from ..io.calibration import Calibration
from ..io.drivelog import DriveLog
from ..status import Status
from .bootstrap import vector_least_squares
from .measurements import measurement_model
from .prepare import deflate_bootstrap, initial_state, prepare, start_noise
from .results import RunTrace, build_run

__all__ = ["solve_batch", "OUTLIER_SIGMA", "LOSS_SCALE"]

OUTLIER_SIGMA = 5.0
LOSS_SCALE = 3.0


@names_the_log
def solve_batch(log: DriveLog, config: FilterConfig = FilterConfig(), init: Calibration | None = None, effects=()):
    """Batch calibration of ``log``; returns a ``CalibrationRun`` (states constant over the log)."""
    from scipy.optimize import least_squares

    started = _time.perf_counter()
    prep = prepare(log, config)
    try:
        prep, layout, x0, P0, how = initial_state(prep, config, init, effects)
    except InputError as exc:
        raise exc.located(log.source) from None
    model = measurement_model(config, layout, x0)
    if init is None:  # the noise of the log, as the filter starts from it
        noise = start_noise(prep, config, x0, layout, model.needs_attitude, prep.base)
        P0 = deflate_bootstrap(P0, layout, noise.inflation)
        if config.adapt_noise:
            model.set_noise(noise)
    status = prep.base.copy()
    # Each epoch goes to the model that can use it: the model itself, or its fallback without attitude.
    takes = {Status.USED: model, Status.MISSING_ATTITUDE: model.fallback if model.needs_attitude else model}
    cand = np.zeros(len(status), bool)
    for code, taker in takes.items():
        if taker is not None:
            cand |= status == code
    if cand.sum() < 3 * layout.size:
        raise InputError(f"too few usable epochs ({int(cand.sum())}) for a batch calibration", log.source)
    data = prep.data

    def calibrated(x, d, m):
        """Calibrated field (N, 3) of the epochs in ``d`` (EpochData) with raw readings ``m``."""
        return layout.calibrated(x, m, layout.effect_terms(x, d))

    # Linear start in the sensor frame where attitude exists, then the magnitude gate with it.
    att = np.flatnonzero(cand & prep.has_attitude)
    x_start = x0.copy()
    core = layout.CORE
    if init is None and len(att) >= 3 * 12 and not effects:
        x_start[core], _, _ = vector_least_squares(
            prep.m[att], data.field_body[att], config.sensor_noise_nt, x0[core], np.sqrt(np.diag(P0)[core])
        )
    idx = np.flatnonzero(cand)
    c0 = calibrated(x_start, data.take(idx), prep.m[idx])
    gate = max(config.gate_nt, config.gate_sigma * np.sqrt(model.noise.along_var))
    off = np.abs(np.linalg.norm(c0, axis=1) - prep.ref_mag[idx]) > gate
    status[idx[off]] = Status.GATED_MAGNITUDE
    idx = idx[~off]
    # The residual functions of each model over its epochs, built once.
    groups = []
    for code, taker in takes.items():
        if taker is None:
            continue
        sel = np.flatnonzero(prep.base[idx] == code)
        if len(sel):
            e = idx[sel]
            groups.append((sel, taker.batch_residuals(prep.ref[e], prep.c_nb[e], prep.ref_mag[e])))
    prior_std = np.sqrt(np.diag(P0))
    data_used, m_used = data.take(idx), prep.m[idx]  # taken once, not at every evaluation

    def epoch_residuals(x) -> list:
        """Each group's normalised residuals (k, q)."""
        c = calibrated(x, data_used, m_used)
        return [f(c[sel]) for sel, f in groups]

    def residuals(x, keep=None):
        parts = epoch_residuals(x)
        r = np.concatenate([p.ravel() for p in parts])
        if keep is not None:
            r = r * keep
        return np.concatenate([r, (x - x0) / prior_std])  # the prior: initial calibration or weak bootstrap

    def epoch_outliers(x):
        """Epochs (len(idx),) with any residual beyond OUTLIER_SIGMA, and the row mask of the rest."""
        bad = np.zeros(len(idx), bool)
        parts = epoch_residuals(x)
        for (sel, _), p in zip(groups, parts):
            bad[sel] = np.abs(p).max(axis=1) > OUTLIER_SIGMA
        rows = [np.repeat(~bad[sel], p.shape[1]) for (sel, _), p in zip(groups, parts)]
        return bad, np.concatenate(rows).astype(float)

    scale = np.maximum(np.abs(prior_std), 1e-9)
    # Robust pass (soft L1) to find the outlying epochs, then least squares without them.
    robust = least_squares(residuals, x_start, loss="soft_l1", f_scale=LOSS_SCALE, x_scale=scale, method="trf")
    outlier, keep = epoch_outliers(robust.x)
    fit = least_squares(residuals, robust.x, x_scale=scale, method="trf", kwargs={"keep": keep})
    outlier, keep = epoch_outliers(fit.x)
    status[idx[outlier]] = Status.GATED_INNOVATION
    J = fit.jac
    P = np.linalg.inv(J.T @ J)
    P = 0.5 * (P + P.T)
    used = np.zeros(len(status), bool)
    used[idx[~outlier]] = True
    information = np.linalg.inv(P) - np.linalg.inv(P0)
    n = len(status)
    trace = RunTrace(
        fit.x[None],
        np.sqrt(np.diag(P))[None],
        status,
        used,
        np.full(n, np.nan),
        fit.x,
        P,
        information,
        how,
        _time.perf_counter() - started,
        method="batch",
        stops=np.array([n]),
    )
    return build_run(log, prep, config, layout, x0, P0, trace)
