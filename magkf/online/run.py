"""Online calibration of a whole log: ``calibrate_log(log, config) -> CalibrationRun``.

Per-log work is done once and vectorised (``magkf.online.prepare``): the reference field, the attitude
matrices, the body-frame reference, the starting noise and the statuses known before filtering. The loop
then gates and updates a block of ``config.block_s`` seconds at a time (see ``magkf.online.estimator``);
the Jacobians of the linear effects and the whitening are computed for a span of blocks at once (the
learned noise changes every few seconds).
"""

from __future__ import annotations

import sys
import time as _time
from dataclasses import replace

import numpy as np

from ..blas import one_thread
from ..calibration import Calibration
from ..config import FilterConfig
from ..errors import names_the_log
from ..io.drivelog import DriveLog
from ..timing import NO_PHASES
from .estimator import Estimator
from .measurements import nis_rows
from .noise import ESTIMATE_EVERY_S
from .prepare import PreparedLog, RunSetup, prepare, prepare_run
from .results import CalibrationRun, RunTrace, build_run
from .smoother import rts_smooth
from .whole_log import WholeLogFit, fit_whole_log, wandering

__all__ = ["calibrate_log", "filter_trace", "ForwardPass", "blocks", "terminal_progress"]


@one_thread
@names_the_log
def calibrate_log(
    log: DriveLog,
    config: FilterConfig = FilterConfig(),
    init: Calibration | None = None,
    effects=(),
    smooth: bool = False,
    progress=None,
    phases=NO_PHASES,
    prepared: PreparedLog | None = None,
    reference: Calibration | None = None,
    fit_residuals: bool = True,
) -> CalibrationRun:
    """Run the online calibration over a log.

    Epochs are processed in blocks of ``config.block_s`` seconds; the per-epoch estimates are those after
    each epoch's block. The calibration is the whole-log estimate over the epochs the filter used, in the
    model family ``config.model`` (``magkf.online.whole_log``); the filter's state at the end of the log, for
    real-time use, is the summary's ``filter_state``.

    Parameters
    ----------
    log : DriveLog
        The drive or flight log.
    config : FilterConfig, optional
        The filter's settings.
    init : Calibration or None, optional
        An offline calibration to start from; else a bootstrap from the log.
    effects : sequence of Effect, optional
        Extra ``Effect`` blocks, estimated with ``R, b``.
    smooth : bool, optional
        Add a Rauch-Tung-Striebel pass.
    progress : callable or None, optional
        ``progress(fraction)`` is called now and then.
    phases : magkf.timing.Phases, optional
        Told the time of each phase.
    prepared : PreparedLog or None, optional
        ``prepare(log, config)`` when the caller has made it already (it is not changed).
    reference : Calibration or None, optional
        The calibration whose values the parameters the log does not determine are held at (the vehicle's
        own, ``magkf.io.vehicle_calibration``); None: ``init``, else the vehicle's calibration the log
        records, else the identity.
    fit_residuals : bool, optional
        Keep the per-epoch residuals with the final estimate (``CalibrationRun.fit``, 16 bytes an epoch); False:
        ``fit`` is None, the run's figures the same.

    Returns
    -------
    CalibrationRun
        The immutable result: calibration, per-epoch states, summary.

    Raises
    ------
    InputError
        The log cannot be calibrated (too few usable epochs, magnitudes that determine no starting
        calibration, a column an effect needs missing, an effect too wide for the magnitude alone); it names
        the log.
    """
    started = _time.perf_counter()
    with phases("reference field and attitude"):
        prep = prepare(log, config, rates=bool(effects)) if prepared is None else prepared
    with phases("start (bootstrap, noise)"):
        setup = prepare_run(prep, config, init, effects, log.source)
        est = setup.estimator(config)
    prep, t = setup.prep, setup.prep.time
    forward = ForwardPass(est, setup.model, setup.R0, config, t[0] if len(t) else 0.0)
    loop_started = _time.perf_counter()
    # without smoothing only each block's standard deviations are kept, not its n x n covariance
    status, updated, nis, xs_b, Ps_b, noise_b, stops, block_dt = forward.run(
        prep, setup.base, progress, covariances=smooth
    )
    loop_s = _time.perf_counter() - loop_started
    phases.add("filter loop", loop_s)
    if progress is not None:
        progress(1.0)
    if smooth:
        with phases("smoother"):
            xs_b, Ps_b = rts_smooth(xs_b, Ps_b, block_dt, setup.layout.q_rate())
    stds_b = np.sqrt(np.einsum("bii->bi", Ps_b)) if smooth else Ps_b
    del Ps_b
    step_s = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    with phases("whole-log estimate"):
        whole = whole_log_estimate(log, prep, setup, est, status, updated, config, init, reference, step_s)
    trace = filter_trace(
        est,
        setup,
        step_s,
        whole=whole,
        xs=xs_b,
        stds=stds_b,
        status=status,
        updated=updated,
        nis=nis,
        elapsed_s=_time.perf_counter() - started,
        smoothed=smooth,
        loop_s=loop_s,
        noise=noise_b,
        stops=stops,
    )
    prep = replace(prep, heading=None)  # the heading axis is the filter's alone: not kept for the table
    with phases("per-epoch table and summary"):
        return build_run(log, prep, config, setup.layout, setup.x0, setup.P0, trace, fit_residuals)


def filter_trace(
    est: Estimator, setup: RunSetup, step_s: float, whole: WholeLogFit | None = None, **per_epoch
) -> RunTrace:
    """The ``RunTrace`` of a filter run started from ``setup`` (``prepare.prepare_run``) and ended with ``est``: the
    estimate (the whole-log estimate ``whole``, else the filter's final state), information, reacquisitions and
    learned correlation time (``step_s`` the log's median time step, s), and the start's description;
    ``per_epoch`` the trace's other fields (``RunTrace``: the per-block states, the per-epoch statuses, the
    times)."""
    return RunTrace(
        x=est.x if whole is None else whole.x,
        P=est.P if whole is None else whole.P,
        model=None if whole is None else whole.model,
        filter_x=est.x,
        filter_P=est.P,
        information=est.information,
        init_how=setup.how,
        reacquisitions=est.reacquisitions,
        correlation_s=est.learner.inflation() * step_s,
        nis_rows=nis_rows(setup.model),
        **per_epoch,
    )


def whole_log_estimate(log, prep, setup: RunSetup, est: Estimator, status, updated, config, init, reference, step_s):
    """The whole-log estimate (``whole_log.fit_whole_log``) over the epochs the filter updated with (``status``,
    ``updated`` (N,)), with ``whole_log_options``; where an effect wanders, with its departure a zero-mean
    path (``drift_path.fit_with_drift``: ``b`` the offset's mean, the path and its learned rate)."""
    from ..status import Status

    used = updated & ((status == Status.USED) | (status == Status.MISSING_ATTITUDE))
    options = whole_log_options(setup, est, config, held_reference(log, init, reference), step_s, log.source)
    moving = wandering(setup.layout)
    if moving:
        from .drift_path import fit_with_drift

        return fit_with_drift(prep, setup.layout, est.x, est.P, used, moving, **options)
    return fit_whole_log(prep, setup.layout, est.x, used, **options)


def whole_log_options(setup: RunSetup, est: Estimator, config: FilterConfig, held: tuple, step_s: float, source):
    """The options of ``whole_log.fit_whole_log`` for a run from ``setup`` ended with ``est``: the family
    ``config.model``, the held parameters at ``held`` (``held_reference``), the run's prior, the noise and
    correlation time the filter learned (``step_s`` the log's median time step, s), the effects' directions the
    run's start held (``RunSetup.held``)."""
    calibration, how = held
    return {
        "vector": setup.model.needs_attitude,
        "model": config.model,
        "held_at": None if calibration is None else calibration.state,
        "held_how": how,
        "correlation_s": est.learner.inflation() * step_s,
        "held_std": (config.init_r_std, config.init_b_std)
        if calibration is None or calibration.covariance is None
        else np.sqrt(np.diag(calibration.covariance)),
        "prior": None,
        "noise": learned_noise(setup.model, est, config),
        "prior_noise": est.noise,
        "source": source,
        "held_effects": setup.held,
    }


def learned_noise(model, est: Estimator, config: FilterConfig):
    """``(NoiseLevels, field_aligned)``: the noise the filter learned and the alignment of its vector model, for the
    covariance of the whole-log estimate; None when the noise was not learned (``config.adapt_noise`` False) or
    the model has no vector noise of that form (a plug-in, the magnitude alone)."""
    aligned = getattr(model, "field_aligned", None)
    if not config.adapt_noise or aligned is None or not model.needs_attitude:
        return None
    return est.noise, bool(aligned)


def held_reference(log, init: Calibration | None, reference: Calibration | None) -> tuple:
    """``(calibration or None, where it comes from in words)``: what the parameters a log does not determine
    are held at (``log`` None: a log that records no calibration of its own)."""
    if reference is not None:
        return reference, f"the calibration given ({reference.method})"
    if init is not None:
        return init, f"the starting calibration (--init, {init.method})"
    if log is None:
        return None, "the identity (no calibration of the vehicle in the log, none given)"
    from ..io.vehicle_calibration import logged_calibration

    logged = logged_calibration(log)
    if logged is not None and logged.method != "logged-as-read":
        return logged, "the vehicle's calibration recorded in the log"
    return None, "the identity (no calibration of the vehicle in the log, none given)"


class ForwardPass:
    """The filter's forward pass over a log given in consecutive pieces, each made of whole blocks (a whole log
    is one piece): ``run`` filters a piece and keeps what the next one needs (the time of the last block's end).

    ``est`` the ``Estimator``, ``model`` its measurement model, ``R0`` (3, 3) the calibration the Jacobians and
    the noise structure are computed at, ``origin`` (UNIX s) the log's first time, from which blocks are
    counted (``blocks``).
    """

    def __init__(self, est: Estimator, model, R0, config: FilterConfig, origin: float):
        self.est, self.model, self.R0, self.config = est, model, R0, config
        self.origin = self.last_end = float(origin)
        self.with_data = bool(est.layout.nonlinear) or model.needs_data

    def run(self, prep, base, progress=None, covariances: bool = True) -> tuple:
        """Filter the epochs of ``prep`` (a ``PreparedLog``) with statuses before filtering ``base`` (k,).

        Returns ``(status (k,) int8, updated (k,) bool, nis (k,), xs (K, n) and Ps (K, n, n) after each of its
        K blocks, noise (K, 4) the learned sensor nT, tilt and heading deg and inflation after each block,
        stops (K,) one past each block's last epoch, dt (K,) s each block's prediction covered)``; with
        ``covariances`` False, each block's standard deviations (K, n) in place of ``Ps``.
        ``progress(fraction)`` is told the share done now and then."""
        est, config = self.est, self.config
        n_ep, n = len(prep), est.layout.size
        t = prep.time
        starts, stops = blocks(t, config.block_s, self.origin)
        block_dt = np.diff(np.concatenate([[self.last_end], t[stops - 1]]))
        xs_b = np.empty((len(starts), n))
        Ps_b = np.empty((len(starts), n, n) if covariances else (len(starts), n))
        status = np.empty(n_ep, np.int8)
        updated = np.zeros(n_ep, bool)
        nis = np.full(n_ep, np.nan)
        noise_b = np.empty((len(starts), 4))
        every = max(len(starts) // 100, 1)
        # Blocks are cut from spans whitened at once, cut anew where the learned noise changed (it changes at
        # most every ESTIMATE_EVERY_S, after the block that crosses a tick).
        span_s = ESTIMATE_EVERY_S + config.block_s
        span_ends = stops[np.maximum(np.searchsorted(t[starts], t[starts] + span_s) - 1, np.arange(len(starts)))]
        span, s0, s1 = None, 0, 0
        for j, (i0, i1) in enumerate(zip(starts.tolist(), stops.tolist())):
            epochs = slice(i0, i1)
            if i1 > s1 or span.whitened_with is not est.noise:
                s0, s1 = i0, int(span_ends[j])
                span = prep.block(slice(s0, s1), est.layout, self.model, self.R0, self.with_data)
                est.whiten(span)
            status[epochs], updated[epochs], nis[epochs] = est.process_block(
                t[epochs], block_dt[j], span.take(slice(i0 - s0, i1 - s0)), base[epochs]
            )
            xs_b[j] = est.x
            Ps_b[j] = est.P if covariances else np.sqrt(np.diagonal(est.P))
            noise_b[j] = est.noise.sensor_nt, est.noise.attitude_deg, est.noise.heading_deg, est.noise.inflation
            if progress is not None and j % every == 0:
                progress(j / len(starts))
        if n_ep:
            self.last_end = float(t[-1])
        return status, updated, nis, xs_b, Ps_b, noise_b, stops, block_dt


def blocks(time_s: np.ndarray, block_s: float, origin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First and one-past-last epoch (each (K,)) of consecutive blocks of at most ``block_s`` seconds, counted
    from ``origin`` (UNIX s; default the first time)."""
    n = len(time_s)
    if block_s <= 0 or n == 0:
        starts = np.arange(n)
    else:
        origin = time_s[0] if origin is None else origin
        block_id = np.floor((time_s - origin) / block_s).astype(np.int64)
        starts = np.flatnonzero(np.diff(np.concatenate([[-1], block_id])))
    return starts, np.append(starts[1:], n)


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
