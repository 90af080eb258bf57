"""Online calibration of a whole log: ``calibrate_log(log, config) -> CalibrationRun``.

Per-log work is done once and vectorised: the reference field (IGRF or ``ref_*``), the attitude
matrices, the body-frame reference, the Jacobians of the linear effects, the measurement noise, and the
statuses known before filtering (missing values, DOP). The per-epoch loop then only gates and updates.
"""

from __future__ import annotations

import sys
import time as _time
from dataclasses import dataclass, replace

import numpy as np

from ..config import FilterConfig
from ..conventions import euler_to_dcm, ned_to_body
from ..effects.base import EpochData, rate_of_change
from ..effects.core import SoftHardIron
from ..errors import InputError
from ..io.calibration import Calibration
from ..io.drivelog import DriveLog
from .bootstrap import bootstrap_magnitude, bootstrap_vector
from .estimator import (
    GATED_DOP,
    MISSING_ATTITUDE,
    MISSING_COLUMN,
    MISSING_MAG,
    MISSING_POSITION,
    USED,
    Estimator,
)
from .measurements import vector_noise, whitening
from .results import CalibrationRun, build_run
from .state import StateLayout


@dataclass(frozen=True)
class PreparedLog:
    """Per-epoch arrays of a log, computed once: ``m`` (N, 3) nT, ``ref`` (N, 3) NED nT, ``ref_mag`` (N,), ``c_nb``
    (N, 3, 3), ``has_attitude`` (N,), ``dop`` (N,), ``dt`` (N,) s since the previous epoch, ``base`` (N,)
    status before filtering, and ``data`` (EpochData for the effects)."""

    m: np.ndarray
    ref: np.ndarray
    ref_mag: np.ndarray
    c_nb: np.ndarray
    has_attitude: np.ndarray
    dop: np.ndarray
    dt: np.ndarray
    base: np.ndarray
    data: EpochData


def prepare(log: DriveLog, config: FilterConfig) -> PreparedLog:
    """Reference field, attitude and the statuses known before filtering, for every epoch."""
    t = log.time
    m = log.mag
    ref = log.reference_ned(knot_spacing_m=config.reference_refresh_m)
    att = log.attitude
    has_att = np.all(np.isfinite(att), axis=1)
    c_nb = euler_to_dcm(att[:, 2], att[:, 1], att[:, 0])
    field_body = ned_to_body(c_nb, ref)
    dop = log.dop
    base = base_status(m, ref, has_att, dop, config.dop_max)
    dt = np.concatenate([[0.0], np.diff(t)])
    columns = {c: log.column(c) for c in log.auxiliary}
    ref_mag = np.linalg.norm(ref, axis=1)
    data = EpochData(t, field_body, ref, columns, mag=m, c_nb=c_nb, field_body_rate=rate_of_change(t, field_body))
    return PreparedLog(m, ref, ref_mag, c_nb, has_att, dop, dt, base, data)


def with_initial_R(prep: PreparedLog, x_core) -> PreparedLog:
    """``prep`` whose effect data carry the initial calibration's ``R`` (see ``EpochData.R0``)."""
    return replace(prep, data=replace(prep.data, R0=np.asarray(x_core[:9], float).reshape(3, 3)))


def base_status(m, ref, has_attitude, dop, dop_max: float) -> np.ndarray:
    """Statuses (N,) known before filtering: missing values and the DOP gate, in order of precedence."""
    base = np.full(len(m), USED, dtype=np.int8)
    base[~has_attitude] = MISSING_ATTITUDE
    base[dop > dop_max] = GATED_DOP
    base[~np.all(np.isfinite(ref), axis=1)] = MISSING_POSITION
    base[~np.all(np.isfinite(m), axis=1)] = MISSING_MAG
    return base


def sample_status(m, ref, has_attitude: bool, dop: float, dop_max: float) -> int:
    """``base_status`` of one epoch (``m``, ``ref`` (3,)), for the real-time path."""
    if not np.isfinite(m).all():
        return MISSING_MAG
    if not np.isfinite(ref).all():
        return MISSING_POSITION
    if dop > dop_max:
        return GATED_DOP
    return USED if has_attitude else MISSING_ATTITUDE


def initial_core(prep: PreparedLog, config: FilterConfig, init: Calibration | None, effects=()):
    """Initial ``(x, P, how)`` of the core block (and of ``effects``, when the bootstrap fitted them with
    it: then ``x`` and ``P`` cover 12 + their parameters): from ``init`` or bootstrapped."""
    if init is not None:
        x = init.state
        if init.covariance is not None:
            P = np.array(init.covariance)
        else:
            P = np.diag(np.concatenate([np.full(9, config.init_r_std**2), np.full(3, config.init_b_std**2)]))
        return x, P, f"file ({init.method})"
    good = prep.base == USED
    linear = [e for e in effects if e.linear]
    if linear:
        good &= np.all([np.isfinite(prep.data.columns[c]) for e in linear for c in e.columns] or [True], axis=0)
    if good.sum() >= 50 and config.measure != "magnitude":
        extra = extra_prior = None
        if linear and len(linear) == len(effects):
            d = prep.data.take(good)
            d = replace(d, R0=bootstrap_vector(prep.m[good], d.field_body, d.time, config.sensor_noise_nt,
                                               config.bootstrap_s).x[:9].reshape(3, 3))
            extra = np.concatenate([e.jacobian(e.prior()[0], d) for e in effects], axis=2)
            extra_prior = tuple(np.concatenate(v) for v in zip(*(e.prior() for e in effects)))
        boot = bootstrap_vector(prep.m[good], prep.data.field_body[good], prep.data.time[good],
                                config.sensor_noise_nt, config.bootstrap_s, extra, extra_prior)
    else:
        cand = (prep.base == USED) | (prep.base == MISSING_ATTITUDE)
        if cand.sum() < 200:
            raise InputError(f"too few usable epochs ({int(cand.sum())}) to bootstrap a calibration; give --init")
        boot = bootstrap_magnitude(prep.m[cand], np.linalg.norm(prep.ref[cand], axis=1), prep.data.time[cand],
                                   config.bootstrap_s)
    return boot.x, boot.P, f"{boot.method} ({boot.n_epochs} epochs, {boot.span_s:.0f} s)"


def initial_state(prep: PreparedLog, config: FilterConfig, init: Calibration | None, effects=()):
    """The start of a run: ``(prep, layout, x0, P0, how)``.

    The core block (and the effects, when the bootstrap fitted them jointly) from ``initial_core``;
    the other effects from their priors; ``prep`` with the initial ``R`` for the effects that use it.
    """
    x_init, P_init, how = initial_core(prep, config, init, effects)
    core = SoftHardIron(x_init[:12], np.sqrt(np.diag(P_init)[:12]), config.r_walk, config.b_walk)
    layout = StateLayout((core, *effects))
    x0, P0 = layout.prior()
    x0[:len(x_init)] = x_init
    P0[:len(x_init), :len(x_init)] = P_init
    return with_initial_R(prep, x_init), layout, x0, P0, how


def linear_jacobian(layout: StateLayout, data: EpochData) -> np.ndarray:
    """(N, 3, n) Jacobian of the linear blocks (zero columns for nonlinear ones), computed once per log."""
    n_ep = len(data)
    H = np.zeros((n_ep, 3, layout.size))
    x0, _ = layout.prior()
    for effect, sl in zip(layout.effects, layout.slices.values()):
        if effect.linear:
            H[:, :, sl] = effect.jacobian(x0[sl], data)
    return H


def calibrate_log(log: DriveLog, config: FilterConfig = FilterConfig(), init: Calibration | None = None,
                  effects=(), smooth: bool = False, progress=None) -> CalibrationRun:
    """Run the online calibration over a log.

    ``init`` is an offline calibration (else a bootstrap from the log); ``effects`` are extra
    ``Effect`` blocks; ``smooth`` adds a Rauch-Tung-Striebel pass; ``progress(fraction)`` is called now
    and then. Epochs are processed in blocks of ``config.block_s`` seconds (see ``magkf.estimator``);
    the per-epoch estimates are those after each epoch's block. Returns an immutable ``CalibrationRun``.
    """
    started = _time.perf_counter()
    prep = prepare(log, config)
    for effect in effects:
        missing = [c for c in effect.columns if c not in prep.data.columns]
        if missing:
            raise InputError(f"effect {effect.name!r} needs column {missing[0]!r}, which the log lacks "
                             f"(auxiliary columns: {', '.join(prep.data.columns) or 'none'})", log.source)
    prep, layout, x0, P0, how = initial_state(prep, config, init, effects)
    est = Estimator(layout, config, x0, P0)
    H_all = linear_jacobian(layout, prep.data)
    R_hat = x0[:9].reshape(3, 3)
    W = whitening(vector_noise(np.nan_to_num(prep.data.field_body), R_hat, config, config.measure))
    n_ep, n = len(prep.m), layout.size
    base = prep.base.copy()
    for effect in effects:
        for c in effect.columns:
            base[(base == USED) & ~np.isfinite(prep.data.columns[c])] = MISSING_COLUMN
    t = prep.data.time
    starts, stops = blocks(t, config.block_s)
    block_dt = np.diff(np.concatenate([[t[0]], t[stops - 1]]))
    xs_b = np.empty((len(starts), n))
    Ps_b = np.empty((len(starts), n, n))
    status = np.empty(n_ep, np.int8)
    updated = np.zeros(n_ep, bool)
    nis = np.full(n_ep, np.nan)
    nonlinear = any(not e.linear for e in effects)
    every = max(len(starts) // 100, 1)
    loop_started = _time.perf_counter()
    for j, (i0, i1) in enumerate(zip(starts.tolist(), stops.tolist())):
        data = prep.data.take(slice(i0, i1)) if nonlinear else None
        status[i0:i1], updated[i0:i1], nis[i0:i1] = est.process_block(
            t[i0:i1], block_dt[j], prep.m[i0:i1], prep.ref_mag[i0:i1], H_all[i0:i1], W[i0:i1], base[i0:i1], data)
        xs_b[j] = est.kf.x
        Ps_b[j] = est.kf.P
        if progress is not None and j % every == 0:
            progress(j / len(starts))
    loop_s = _time.perf_counter() - loop_started
    if progress is not None:
        progress(1.0)
    if smooth:
        xs_b, Ps_b = rts_smooth(xs_b, Ps_b, block_dt, layout.q_rate())
    # The calibration at the end of the log (smoothing leaves the last estimate as it is).
    x_final, P_final = est.kf.x, est.kf.P
    block_of = np.repeat(np.arange(len(starts)), stops - starts)
    xs = xs_b[block_of]
    stds = np.sqrt(np.einsum("bii->bi", Ps_b))[block_of]
    return build_run(log=log, prep=prep, config=config, layout=layout, x0=x0, P0=P0, xs=xs, stds=stds,
                     status=status, updated=updated, nis=nis, x_final=x_final, P_final=P_final,
                     information=est.information, init_how=how, smoothed=smooth, reacquisitions=est.reacquisitions,
                     elapsed_s=_time.perf_counter() - started, loop_s=loop_s)


def blocks(time_s: np.ndarray, block_s: float) -> tuple[np.ndarray, np.ndarray]:
    """First and one-past-last epoch (each (K,)) of consecutive blocks of at most ``block_s`` seconds."""
    n = len(time_s)
    if block_s <= 0 or n == 0:
        starts = np.arange(n)
    else:
        block_id = np.floor((time_s - time_s[0]) / block_s).astype(np.int64)
        starts = np.flatnonzero(np.diff(np.concatenate([[-1], block_id])))
    return starts, np.append(starts[1:], n)


def rts_smooth(xs, Ps, dt, q_rate):
    """Rauch-Tung-Striebel smoother for a random walk (``F = I``) over filter steps (blocks).

    ``xs`` (K, n), ``Ps`` (K, n, n) are the filtered estimates after each step, ``dt`` (K,) the time
    each step's prediction covered. The prediction from step k to k+1 is ``x`` unchanged and
    ``P + Q dt_{k+1}``; the gain is ``C_k = P_k (P_k + Q dt_{k+1})^-1``.
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


def terminal_progress(stream=sys.stderr):
    """A progress callback drawing a bar on ``stream``, or None when ``stream`` is not a terminal."""
    if not stream.isatty():
        return None

    def show(fraction: float) -> None:
        width = 40
        filled = int(fraction * width)
        stream.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {100 * fraction:5.1f}%")
        if fraction >= 1.0:
            stream.write("\n")
        stream.flush()

    return show
