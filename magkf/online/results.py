"""The result of a calibration run: final calibration, per-epoch states, residuals and a summary."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np
import pandas as pd

from ..calibration import Calibration
from ..conventions import body_to_ned
from ..effects import stored_effect
from ..errors import InputError
from ..status import STATUS_NAMES, Status
from . import observability
from .prepare import CHUNK
from .state import StateLayout
from .states_table import NOISE_COLUMNS, StatesTable, states_frame
from .verdict import verdict

__all__ = [
    "CalibrationRun",
    "RunSummary",
    "RunTrace",
    "residuals",
    "build_run",
    "noise_summary",
    "FitSums",
    "nis_summary",
    "repeated_median",
    "epoch_columns",
    "epoch_residuals",
    "states_frame",
    "StatesTable",
    "NOISE_COLUMNS",
    "summarise",
]


@dataclass(frozen=True)
class RunSummary:
    """The figures of a run, each with its unit.

    Residuals are all computed with the final estimate (the smoothed per-epoch estimate when smoothed).
    Plain Python values (lists, dicts, floats), so that ``as_dict`` is ready for JSON.

    Parameters
    ----------
    R : list
        (3, 3) the final estimate of ``R``.
    b : list
        (3,) the final estimate of the offsets, nT.
    std : dict
        The standard deviation of every state, by name.
    residual_rms_nt : float
        The RMS of the NED residual norm, nT, over the epochs *used* with attitude.
    residual_rms_axis_nt : dict
        The same per NED axis (``north``, ``east``, ``down``), nT.
    residual_rms_magnitude_nt : float
        The RMS magnitude residual, nT, over the epochs used (with or without attitude).
    residual_rms_all_nt : float
        ``residual_rms_nt`` over the *whole log* (every epoch with a magnetometer reading, a reference and
        attitude), gated epochs included, nT.
    residual_rms_magnitude_all_nt : float
        ``residual_rms_magnitude_nt`` over the *whole log* (every epoch with a magnetometer reading and a
        reference), gated epochs included, nT.
    innovation_rms_nt : float
        The RMS NED residual norm with the estimate before each epoch, nT.
    nis_mean : float
        The mean normalised innovation squared per degree of freedom of the epochs used.
    nis_band : list
        Its 95 % band ``[low, high]`` for the effective number of independent epochs.
    used_share : float
        The share of epochs used.
    noise : dict
        The configured and the learned noise (sensor nT, attitude deg), the residuals' correlation time (s)
        and the inflation of each epoch's noise it implies.
    verdict : str
        What these figures say, in words.
    n_epochs : int
        The epochs of the log.
    n_updates : int
        The epochs that updated the estimate.
    status_counts : dict
        The epochs of each status, by name.
    run_time_s : float
        The run's duration, s.
    epochs_per_second : float
        ``n_epochs / run_time_s``.
    filter_loop_s : float
        The time spent in the filter loop, part of ``run_time_s``, s (NaN where there is none).
    filter : str
        The filter (``ekf``, ``ukf``, ...) or the method (``batch``).
    measure : str
        The measurement model.
    smoothed : bool
        Whether the estimates were smoothed (Rauch-Tung-Striebel).
    init : str
        How the run started (the calibration given, or the bootstrap), in words.
    reacquisitions : int
        How often the covariance was inflated after ``max_gated_s`` of innovation gating.
    observability : dict
        The directions the data did not determine (``text`` says it in words).
    effects : dict
        Every effect's parameters by name: ``{"value", "std", "unit"}``.
    config : dict
        The settings of the run (``FilterConfig.as_dict``).
    model : dict or None
        The model family of the estimate (``whole_log.WholeLogFit.model``: ``family``, ``text`` in words, the
        families weighed), or None for an estimate that is the filter's last state.
    filter_state : dict or None
        The filter's estimate at the end of the log (``R``, ``b``, ``std`` by name), for real-time use, when the
        estimate written is the whole-log one; else None.
    """

    R: list
    b: list
    std: dict
    residual_rms_nt: float
    residual_rms_axis_nt: dict
    residual_rms_magnitude_nt: float
    residual_rms_all_nt: float
    residual_rms_magnitude_all_nt: float
    innovation_rms_nt: float
    nis_mean: float
    nis_band: list
    used_share: float
    noise: dict
    verdict: str
    n_epochs: int
    n_updates: int
    status_counts: dict
    run_time_s: float
    epochs_per_second: float
    filter_loop_s: float
    filter: str
    measure: str
    smoothed: bool
    init: str
    reacquisitions: int
    observability: dict
    effects: dict
    config: dict
    model: dict | None = None
    filter_state: dict | None = None

    def as_dict(self) -> dict:
        """JSON-ready mapping of every field.

        Returns
        -------
        dict
            Field name -> value.
        """
        return asdict(self)


@dataclass(frozen=True)
class CalibrationRun:
    """Outcome of ``calibrate_log`` or ``solve_batch``.

    An immutable value: the final calibration and state, the per-epoch table and the run's figures.

    Parameters
    ----------
    calibration : Calibration
        The final ``R``, ``b`` with their 12x12 covariance.
    x : numpy.ndarray
        (n,) the final state.
    P : numpy.ndarray
        (n, n) its covariance.
    names : list of str
        State names.
    states : StatesTable or None
        The per-epoch table, indexed by time, with ``status``, ``updated``, ``nis``, every state and its ``std_``
        column, and the residuals ``residual_n, residual_e, residual_d`` (NED, nT) and ``residual_mag`` (nT)
        computed with the estimate before each epoch (and the learned noise, when learned). A column or a stretch
        of rows is built when read (``states["status"]``, ``states.iloc[a:b]``), the whole DataFrame by
        ``states.frame()``: the states are kept once a filter block (``magkf.online.states_table``).
    summary : RunSummary
        The run's figures.
    effects : dict, optional
        Every effect's parameters by name, as in ``RunSummary.effects``.
    fit : pandas.DataFrame or None, optional
        Indexed by time, the residuals with the final estimate (with the smoothed per-epoch estimate when
        smoothed): ``fit_n, fit_e, fit_d`` (NED, nT) and ``fit_mag`` (nT); None where the run was made without
        them (``calibrate_log(fit_residuals=False)``, as the diagnosis makes its run).
    filter_x, filter_P : numpy.ndarray or None, optional
        (n,) and (n, n): the filter's state at the end of the log and its covariance, where ``x`` is the
        whole-log estimate (None: ``x`` is the filter's, or a batch solution).
    start : Calibration or None, optional
        The calibration the run started from (the one given, or the bootstrap's), with its effects at their
        starting values: what the calibration written is judged against (``magkf.diagnostics.baseline``).
    """

    calibration: Calibration
    x: np.ndarray
    P: np.ndarray
    names: list
    states: StatesTable | None
    summary: RunSummary
    effects: dict = field(default_factory=dict)
    fit: pd.DataFrame | None = None
    filter_x: np.ndarray | None = None
    filter_P: np.ndarray | None = None
    start: Calibration | None = None

    @property
    def std(self) -> np.ndarray:
        """(n,) the final state's standard deviations, in the order of ``names``."""
        return np.sqrt(np.diag(self.P))


def residuals(prep, layout: StateLayout, x, last=None) -> tuple[np.ndarray, np.ndarray]:
    """NED residual (N, 3) and magnitude residual (N,) in nT of state ``x`` (n,) or per-epoch (N, n) (``last``:
    see ``StateLayout.effect_terms``)."""
    c = layout.calibrated(x, prep.m, layout.effect_terms(x, prep.data, last))
    ned = body_to_ned(prep.c_nb, c) - prep.ref
    mag = np.linalg.norm(c, axis=1) - prep.ref_mag
    return ned, mag


def noise_summary(config, trace: RunTrace, counts=None) -> dict:
    """The configured and learned noise of a run, and the residuals' correlation (JSON-ready); the medians are
    over epochs, block ``k``'s learned noise counting ``counts[k]`` times (default: the trace's blocks)."""
    learned = trace.noise
    if learned is not None and counts is None:
        counts = np.diff(trace.stops, prepend=0) if trace.stops is not None else np.ones(len(learned), np.int64)
    out = {
        "adapted": bool(config.adapt_noise) and learned is not None,
        "configured": {"sensor_nt": config.sensor_noise_nt, "attitude_deg": config.attitude_deg},
        "correlation_s": float(trace.correlation_s),
        "inflation": 1.0,
    }
    if learned is not None and len(learned) and np.sum(counts):
        medians = repeated_median(learned[:, :3], counts)
        out["learned"] = {
            "sensor_nt": float(learned[-1, 0]),
            "attitude_deg": float(learned[-1, 1]),
            "heading_deg": float(learned[-1, 2]),
            "sensor_median_nt": float(medians[0]),
            "attitude_median_deg": float(medians[1]),
            "heading_median_deg": float(medians[2]),
        }
        out["inflation"] = float(learned[-1, 3])
    return out


@dataclass(frozen=True)
class RunTrace:
    """What a run went through: the states ``xs`` (K, n) and their standard deviations ``stds`` (K, n) after
    each of K blocks of epochs, block ``j`` ending before epoch ``stops[j]`` (K,) (None: one block per
    epoch); statuses (N,), update flags (N,) and NIS (N,); the final state ``x`` (n,) and ``P`` (n, n); the
    whitened information of the updates (n, n); how it started, how long it took (s), and the run's
    options; ``noise`` (K, 4) the noise the filter had learned after each block (sensor nT, tilt and heading
    deg, inflation) and ``correlation_s`` the residuals' integrated correlation time at the end, s;
    ``nis_rows`` the measurement's rows (the NIS's degrees of freedom) at an epoch with attitude and at one
    without (``measurements.nis_rows``)."""

    xs: np.ndarray
    stds: np.ndarray
    status: np.ndarray
    updated: np.ndarray
    nis: np.ndarray
    x: np.ndarray
    P: np.ndarray
    information: np.ndarray
    init_how: str
    elapsed_s: float
    smoothed: bool = False
    reacquisitions: int = 0
    loop_s: float = float("nan")
    method: str | None = None
    noise: np.ndarray | None = None
    correlation_s: float = 0.0
    stops: np.ndarray | None = None
    nis_rows: tuple = (3, 1)
    model: dict | None = None
    filter_x: np.ndarray | None = None
    filter_P: np.ndarray | None = None

    def block_of(self, epochs: slice | None = None) -> np.ndarray:
        """The block (N,) of every epoch, or (k,) of the epochs ``epochs`` (a slice) only."""
        n = len(self.status)
        if epochs is not None:
            positions = np.arange(*epochs.indices(n))
            return positions if self.stops is None else np.searchsorted(self.stops, positions, side="right")
        if self.stops is None:
            return np.arange(n)
        return np.repeat(np.arange(len(self.stops)), np.diff(self.stops, prepend=0))


def repeated_median(values, counts) -> np.ndarray:
    """The median of every column of ``values`` (K, c) with row ``k`` repeated ``counts[k]`` times (K,), exactly
    as ``np.median`` of the repeated rows, without repeating them."""
    values = np.asarray(values, float)
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    out = np.empty(values.shape[1])
    for j in range(values.shape[1]):
        order = np.argsort(values[:, j], kind="stable")
        ends = np.cumsum(counts[order])  # one past the last repeated position of each sorted value
        lo, hi = (total - 1) // 2, total // 2
        v = values[order, j]
        out[j] = 0.5 * (v[np.searchsorted(ends, lo, side="right")] + v[np.searchsorted(ends, hi, side="right")])
    return out


@dataclass
class FitSums:
    """Running sums of the residual figures of a run, added chunk by chunk (``add``), so that the summary of a log
    of any length is computed without holding its residuals. ``rows``: the NIS's degrees of freedom at an epoch
    with attitude and at one without (``RunTrace.nis_rows``)."""

    rows: tuple = (3, 1)
    n_epochs: int = 0
    n_updates: int = 0
    n_updated_any: int = 0
    counts: np.ndarray = field(default_factory=lambda: np.zeros(len(Status), np.int64))
    vec: list = field(default_factory=lambda: [0, 0.0, np.zeros(3)])  # epochs, sum of |e|^2, per axis
    mag_used: list = field(default_factory=lambda: [0, 0.0])
    vec_all: list = field(default_factory=lambda: [0, 0.0])
    mag_all: list = field(default_factory=lambda: [0, 0.0])
    innovation: list = field(default_factory=lambda: [0, 0.0])
    nis: list = field(default_factory=lambda: [0.0, 0.0])  # sum of NIS, sum of degrees of freedom

    def add(self, status, updated, nis, has_attitude, ned_f, mag_f, ned_i) -> None:
        """Add the epochs of a chunk: statuses, update flags, NIS and attitude flags (k,), the residuals with the
        final estimate ``ned_f`` (k, 3), ``mag_f`` (k,) and before each epoch ``ned_i`` (k, 3), nT."""
        used = (status == Status.USED) & updated
        vec_used = used & has_attitude
        updated_any = updated & ((status == Status.USED) | (status == Status.MISSING_ATTITUDE))
        self.n_epochs += len(status)
        self.n_updates += int(np.count_nonzero(updated))
        self.n_updated_any += int(np.count_nonzero(updated_any))
        self.counts += np.bincount(np.asarray(status, np.int64), minlength=len(Status))
        squares = np.asarray(ned_f[vec_used], float) ** 2
        self.vec[0] += len(squares)
        self.vec[1] += float(np.sum(squares))
        self.vec[2] = self.vec[2] + squares.sum(axis=0)
        _add_squares(self.mag_used, mag_f[updated_any])
        _add_squares(self.vec_all, ned_f[np.all(np.isfinite(ned_f), axis=1)])
        _add_squares(self.mag_all, mag_f[np.isfinite(mag_f)])
        _add_squares(self.innovation, ned_i[vec_used])
        ok = updated_any & np.isfinite(nis)
        self.nis[0] += float(np.sum(nis[ok]))
        self.nis[1] += float(np.sum(np.where(has_attitude[ok], *map(float, self.rows))))

    def nis_summary(self, inflation: float) -> dict:
        """Mean NIS per degree of freedom of the updated epochs and its two-sided 95 % chi-square band for the
        effective number of independent epochs (``n / inflation``; ``nis_summary``)."""
        return nis_summary(*self.nis, inflation)

    @property
    def used_share(self) -> float:
        return self.n_updated_any / self.n_epochs if self.n_epochs else 0.0


def nis_summary(total: float, dof: int, inflation: float = 1.0) -> dict:
    """``{"mean", "band"}``: the mean NIS per degree of freedom of a sum ``total`` over ``dof`` degrees of freedom,
    and its two-sided 95 % chi-square band for ``dof / inflation`` independent ones (NaN for none)."""
    from scipy.special import gammaincinv  # the chi-square quantile as scipy.stats computes it, without its import

    if dof == 0:
        return {"mean": float("nan"), "band": [float("nan"), float("nan")]}
    total_dof = max(dof / max(inflation, 1.0), 1.0)
    band = [float(2.0 * gammaincinv(total_dof / 2.0, q) / total_dof) for q in (0.025, 0.975)]
    return {"mean": total / dof, "band": band}


def _add_squares(acc: list, values) -> None:
    """Add the count and the sum of squares (of the row norms, for (k, 3)) of ``values`` to ``acc``."""
    a = np.asarray(values, float)
    acc[0] += len(a)
    acc[1] += float(np.sum(a**2))


def _root_mean(acc: list) -> float:
    return float(np.sqrt(acc[1] / acc[0])) if acc[0] else float("nan")


def epoch_columns(part, block, layout: StateLayout, trace: RunTrace, x0, own: bool, last=(None, None)) -> tuple:
    """The per-epoch columns of the epochs ``part`` (a ``PreparedLog``) of blocks ``block`` (k,): states (k, n)
    and standard deviations (k, n) after each epoch's block, and the residuals of ``epoch_residuals``."""
    return trace.xs[block], trace.stds[block], *epoch_residuals(part, block, layout, trace, x0, own, last)


def epoch_residuals(part, block, layout: StateLayout, trace: RunTrace, x0, own: bool, last=(None, None)) -> tuple:
    """The residuals of the epochs ``part`` (a ``PreparedLog``) of blocks ``block`` (k,): before each epoch (NED
    (k, 3), magnitude (k,), nT) with the estimate before its block (``own``: its own, when smoothed or a batch
    solution), and with the final estimate (with the per-epoch estimate when smoothed). ``last``: the states (n,)
    at which nonlinear effects are evaluated for the residuals before each epoch and for the per-epoch estimate
    (``StateLayout.effect_terms``; None: the part's last)."""
    xs = trace.xs[block]
    prior = xs if own else np.where((block == 0)[:, None], x0, trace.xs[np.maximum(block - 1, 0)])
    ned_i, mag_i = residuals(part, layout, prior, last[0])
    ned_f, mag_f = residuals(part, layout, xs if trace.smoothed else trace.x, last[1])
    return ned_i, mag_i, ned_f, mag_f


def build_run(
    log, prep, config, layout: StateLayout, x0, P0, trace: RunTrace, fit_residuals: bool = True
) -> CalibrationRun:
    """Assemble a ``CalibrationRun`` from the start ``x0`` (n,), ``P0`` (n, n) and what the run went through.

    The residuals are computed ``CHUNK`` epochs at a time, so that nothing of the size of a long log is held
    twice. The per-epoch table (``StatesTable``) keeps the states and standard deviations once a block and is
    built when read. The states, their standard deviations, the residuals, the NIS and the learned noise are
    float32: 7 significant digits, 0.01 nT of a 100 000 nT residual, and a rounding of a state below a
    hundredth of its standard deviation unless the standard deviation is below 6e-6 of the value. The
    calibration, ``x`` and ``P`` keep float64. Without ``fit_residuals`` the run's ``fit`` is None: the residuals
    with the final estimate are summed a chunk at a time and not kept (16 bytes an epoch)."""
    status, updated, nis = trace.status, trace.updated, trace.nis
    n_ep = len(status)
    # The residuals before each epoch use the estimate before its block (the start's for the first block),
    # which its reading has not updated; with smoothing or a batch solution, the epoch's own. With smoothing
    # the per-epoch states are the estimate at every epoch (a drift is followed); otherwise the final
    # estimate is the best for every epoch. Nonlinear effects (a time lag interpolates between epochs) take
    # the whole log at once.
    own = trace.smoothed or (trace.method or config.filter) == "batch"
    chunk = max(n_ep, 1) if layout.nonlinear else CHUNK
    # residuals before each epoch and with the final estimate: north, east, down, magnitude
    before = np.empty((n_ep, 4), np.float32)
    final = np.empty((n_ep, 4), np.float32) if fit_residuals else None
    sums = FitSums(rows=trace.nis_rows)
    for start in range(0, n_ep, chunk):
        epochs = slice(start, min(start + chunk, n_ep))
        with_final = final[epochs] if final is not None else np.empty((epochs.stop - epochs.start, 4), np.float32)
        before[epochs, :3], before[epochs, 3], with_final[:, :3], with_final[:, 3] = epoch_residuals(
            prep.take(epochs), trace.block_of(epochs), layout, trace, x0, own
        )
        sums.add(
            status[epochs],
            updated[epochs],
            nis[epochs],
            prep.has_attitude[epochs],
            with_final[:, :3],
            with_final[:, 3],
            before[epochs, :3],
        )
    index = log.table.index
    states = StatesTable(
        index, layout.names, status, updated, nis, trace.xs, trace.stds, trace.stops, before, trace.noise
    )
    counts = np.diff(trace.stops, prepend=0) if trace.stops is not None else np.ones(n_ep, np.int64)
    summary, cal, effects = summarise(log.source, config, layout, P0, trace, sums, counts)
    cal = replace(cal, magnetometer=log.magnetometer, site=log.site)
    columns = ["fit_n", "fit_e", "fit_d", "fit_mag"]
    fit = None if final is None else pd.DataFrame(final, columns=columns, index=index, copy=False)
    return CalibrationRun(
        calibration=cal,
        x=trace.x,
        P=trace.P,
        names=layout.names,
        states=states,
        summary=summary,
        effects=effects,
        fit=fit,
        filter_x=trace.filter_x if summary.filter_state is not None else None,
        filter_P=trace.filter_P if summary.filter_state is not None else None,
        start=start_calibration(cal, layout, x0, P0),
    )


def start_calibration(cal: Calibration, layout: StateLayout, x0, P0) -> Calibration | None:
    """The calibration a run started from: its state ``x0`` (n,) with covariance ``P0`` (n, n) of ``layout``, with
    ``cal``'s (the run's calibration's) magnetometer, site and source; None when the start is degenerate (``R``
    singular: a start that cannot be applied)."""
    std = np.sqrt(np.clip(np.diag(P0), 0.0, None))
    R, b = layout.R_b(x0)
    try:
        return replace(
            cal,
            R=R,
            b=b,
            method="start",
            covariance=P0[layout.CORE, layout.CORE],
            effects=tuple(stored_effect(e, x0[sl], std[sl]) for e, sl in layout.blocks()),
            state_covariance=P0 if layout.has_extra else None,
            standard_errors=dict(zip(layout.names[layout.CORE], std[layout.CORE].tolist())),
            quality={},
            model=None,
        )
    except ValueError:
        return None


def summarise(source, config, layout: StateLayout, P0, trace: RunTrace, sums: FitSums, counts) -> tuple:
    """``(RunSummary, Calibration, effects)`` of a run from its trace (only its final state, information,
    learned noise and figures are used, never its per-epoch arrays), the residual sums of every epoch and the
    epochs of each block ``counts`` (K,)."""
    x_final, P_final = trace.x, trace.P
    names = layout.names
    method = trace.method or config.filter
    std = np.sqrt(np.diag(P_final))
    R, b = layout.R_b(x_final)
    obs = observability.analyse(P0, trace.information, names, R)
    effects = _effect_values(layout, x_final, std)
    noise = noise_summary(config, trace, counts)
    nis_stats = sums.nis_summary(noise["inflation"])
    summary = RunSummary(
        R=R.tolist(),
        b=b.tolist(),
        std=dict(zip(names, std.tolist())),
        **_residual_figures(sums),
        nis_mean=nis_stats["mean"],
        nis_band=nis_stats["band"],
        used_share=sums.used_share,
        noise=noise,
        verdict=verdict(noise, nis_stats, sums.used_share, obs),
        n_epochs=int(sums.n_epochs),
        n_updates=int(sums.n_updates),
        status_counts={name: int(k) for name, k in zip(STATUS_NAMES, sums.counts)},
        run_time_s=float(trace.elapsed_s),
        epochs_per_second=float(sums.n_epochs / trace.elapsed_s),
        filter_loop_s=float(trace.loop_s),
        filter=method,
        measure=config.measure,
        smoothed=bool(trace.smoothed),
        init=trace.init_how,
        reacquisitions=int(trace.reacquisitions),
        observability=obs,
        effects=effects,
        config=config.as_dict(),
        model=trace.model,
        filter_state=_filter_state(layout, trace),
    )
    cal = _run_calibration(source, f"{method}-{config.measure}", layout, trace, R, b, std, summary)
    return summary, replace(cal, model=trace.model), effects


#: What ``whole_log.filter_estimate`` records as estimated: the calibration is the filter's state itself.
FILTER_STATE = "the filter's state"


def _filter_state(layout: StateLayout, trace: RunTrace) -> dict | None:
    """The filter's last state as the summary gives it (``RunSummary.filter_state``), or None."""
    if trace.model is None or trace.filter_x is None or trace.model.get("estimated") == FILTER_STATE:
        return None
    R, b = layout.R_b(trace.filter_x)
    std = np.sqrt(np.diag(trace.filter_P))
    return {
        "R": R.tolist(),
        "b": b.tolist(),
        "std": dict(zip(layout.names, std.tolist())),
        "meaning": "the filter's estimate at the end of the log (for real-time use); the calibration written is "
        "the whole-log estimate",
    }


def _effect_values(layout: StateLayout, x_final, std) -> dict:
    """Each effect's parameters ``{effect: {parameter: {value, std, unit}}}`` from the final state (n,)."""
    effects = {}
    for key, (effect, sl) in zip(layout.keys[1:], layout.blocks()):
        effects[key] = {
            p: {
                "value": float(x_final[sl][j]),
                "std": float(std[sl][j]),
                "unit": (effect.units[j] if j < len(effect.units) else ""),
            }
            for j, p in enumerate(effect.parameter_names)
        }
    return effects


def _residual_figures(sums: FitSums) -> dict:
    """The run's residual and innovation RMS figures (nT) from its residual sums, by RunSummary field."""
    vec_n, vec_ss, vec_axis = sums.vec
    return {
        "residual_rms_nt": float(np.sqrt(vec_ss / vec_n)) if vec_n else float("nan"),
        "residual_rms_axis_nt": {
            a: (float(np.sqrt(vec_axis[k] / vec_n)) if vec_n else float("nan"))
            for k, a in enumerate(("north", "east", "down"))
        },
        "residual_rms_magnitude_nt": _root_mean(sums.mag_used),
        "residual_rms_all_nt": _root_mean(sums.vec_all),
        "residual_rms_magnitude_all_nt": _root_mean(sums.mag_all),
        "innovation_rms_nt": _root_mean(sums.innovation),
    }


#: The RunSummary figures a run's Calibration keeps as its ``quality``, in this order.
_QUALITY = (
    "residual_rms_all_nt",
    "used_share",
    "verdict",
    "residual_rms_nt",
    "residual_rms_axis_nt",
    "residual_rms_magnitude_nt",
    "nis_mean",
    "n_epochs",
    "status_counts",
)


def _run_calibration(source, method: str, layout: StateLayout, trace: RunTrace, R, b, std, summary: RunSummary):
    """The run's Calibration of ``R`` (3, 3) and ``b`` (3,) nT with the final covariance (``std`` (n,) the
    standard deviations of the states) and the summary's quality figures; InputError if it is degenerate."""
    x_final, P_final = trace.x, trace.P
    core = layout.CORE
    quality = {k: getattr(summary, k) for k in _QUALITY}
    try:
        return Calibration(
            R=R,
            b=b,
            method=method,
            covariance=P_final[core, core],
            effects=tuple(stored_effect(e, x_final[sl], std[sl]) for e, sl in layout.blocks()),
            state_covariance=P_final if layout.has_extra else None,
            standard_errors=dict(zip(layout.names[core], std[core].tolist())),
            quality=quality | {"undetermined": summary.observability["text"]},
            source=source,
        )
    except ValueError as exc:  # a degenerate estimate (R singular): the data, not the code
        raise InputError(
            f"the estimate is degenerate ({exc}): the data do not determine R, or the magnetometer unit is wrong "
            "(--mag-unit)",
            source,
        ) from None
