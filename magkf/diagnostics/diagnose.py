"""Compare the model with the measurements, and find which physical effect is missing.

For a log and a model (the filter's run, or a calibration file with the effects it stores), on the epochs
the model used:

* **Residuals** in NED and magnitude (nT), and against every candidate explanatory signal (heading,
  roll, pitch, time, each auxiliary channel, yaw rate, rate of change of the body field): binned means
  with 95 % bands and a one-way analysis of variance per signal whose F statistic is divided by the
  residual's integrated autocorrelation time (the epochs are not independent); the stretches where the
  residual is largest.
* **Which effect is missing.** The vector measurement is linear in the parameters in the sensor frame, so
  adding an effect is a regression of the whitened residual on the effect's regressors (``regressors``),
  with the model refitted jointly. The model is first refitted to the whole log (iterated: the
  whitening and the effects' linearisation follow the estimate), so that candidates are not judged
  around an estimate that the missing effect has pulled off. Each candidate is then tested by a
  correlation-robust F test (``magkf.diagnostics.inference``), and the residual it would leave is
  measured on held-out blocks of the log. The leading candidates are refitted jointly with the model at
  their own best fit before they are compared.
* **The heading's slow error.** An INS heading wanders by tenths of a degree over minutes, and its error
  moves the body-frame field by tens of nT: left in, it dominates the residual and its correlation leaves
  too few independent stretches to test anything. By default it is a nuisance, a straight line in time
  over each ``WANDER_BLOCK_S`` seconds, taken out of the residual and of every regressor before anything
  is fitted (``fitting.HeadingWander``). An effect whose parameters wander (``bias_drift``) is tested for
  constancy against a random walk instead of for a value (``inference.constancy_test``).

  **One decision rule.** A candidate is significant when its p-value is below ``alpha / m`` (``m`` the
  candidates tested; Bonferroni). Among the significant ones that also lower the held-out residual, the
  one with the lowest held-out residual is taken into the model, unless a simpler candidate it contains
  (a time lag inside the eddy-current terms) does as well: the larger one wins only when it is
  significant given the smaller one and better on held-out data. The rest are tested again given it,
  until none is significant. The stars, the order, the stop and the advice are all this rule.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np

from ..allocator import release_free_memory
from ..blas import one_thread
from ..calibration import Calibration
from ..config import FilterConfig
from ..conventions import body_to_ned
from ..effects import Effect, LinearEffect, check_columns, restore_effects
from ..effects import candidates as default_candidates
from ..effects.base import _gradient
from ..errors import InputError, names_the_log
from ..files import temporary_folder
from ..io.drivelog import DriveLog
from ..online.chunked import Spill
from ..online.determined import ChunkCache
from ..online.noise import NoiseLevels
from ..online.prepare import attitude_known, prepare, reference_track
from ..online.results import CalibrationRun
from ..online.run import calibrate_log
from ..online.state import StateLayout
from ..status import Status
from .fitting import (
    CHUNK,
    OUTLIER_SIGMA,
    WANDER_BLOCK_S,
    EpochSet,
    Linearised,
    determined,
    finite_regressors,
    gram_svd,
    inliers,
    span_coefficients,
)
from .inference import (
    HeldOut,
    RobustTest,
    constancy_test,
    f_sf,
    fold_edges,
    held_out_residuals,
    high_passed,
    integrated_time,
    score_test,
)

__all__ = [
    "BINS",
    "WINDOW_S",
    "OUTLIER_SIGMA",
    "LEADING",
    "Candidate",
    "Diagnosis",
    "diagnose",
    "signal_values",
    "compare_runs",
]

#: Bins of the binned residual means; stretch length of the "largest residual" search, s.
BINS = 12
WINDOW_S = 10.0
#: How many of the significant candidates are refitted at their own best fit before they are compared.
LEADING = 3
#: The tests a candidate's ``statistic`` comes from.
TESTS = {
    "F": "correlation-robust F (equal-weighted cosine long-run variance, Sun 2013)",
    "L": "constancy against a random walk, correlation-robust (Nyblom 1989, Hansen 1992)",
}
#: Singular values of a candidate's (column-normalised) regressors below this, once the model's span is
#: removed, are directions the model already has: a candidate with none left is contained in it.
RANK_TOLERANCE = 1e-4


@dataclass(frozen=True)
class Candidate:
    """One candidate effect's test. ``effect`` is the name as ``--effect`` accepts it.

    ``statistic`` the correlation-robust F with ``dof`` and ``dof_denominator`` degrees of freedom, or for
    an effect whose parameters wander Nyblom's constancy statistic ``L`` (``test`` says which; ``terms``
    cosine terms; ``correlation_s`` the scores' integrated autocorrelation time, s);
    ``residual_rms_after_nt`` the NED residual RMS on held-out blocks with the effect added (its expected
    residual), ``residual_rms_fit_nt`` the same in-sample; ``estimate`` the parameters with their
    correlation-robust standard deviations; ``note`` why a candidate was not tested or not taken."""

    effect: str
    statistic: float
    dof: int
    dof_denominator: int
    p_value: float
    terms: int
    correlation_s: float
    residual_rms_after_nt: float
    residual_rms_fit_nt: float
    significant: bool
    estimate: dict = field(default_factory=dict)
    note: str = ""
    test: str = "F"

    @property
    def option(self) -> str:
        """The command-line option that adds this effect."""
        return f"--effect {self.effect}"

    def as_dict(self) -> dict:
        return {
            "effect": self.effect,
            "option": self.option,
            "statistic": self.statistic,
            "test": TESTS[self.test],
            "dof": self.dof,
            "dof_denominator": self.dof_denominator,
            "p_value": self.p_value,
            "terms": self.terms,
            "correlation_s": self.correlation_s,
            "residual_rms_after_nt": self.residual_rms_after_nt,
            "residual_rms_fit_nt": self.residual_rms_fit_nt,
            "significant": self.significant,
            "estimate": self.estimate,
            "note": self.note,
        }


@dataclass(frozen=True)
class Diagnosis:
    """Outcome of ``diagnose``: residual figures, ranked candidates, signals the residual follows.

    ``residual_rms_axis_nt`` holds the RMS per NED axis, per body axis (``body_x`` ...), of the
    magnitude, and the filter's mean normalised innovation squared (``nis_mean``) when a run was made.
    ``residual_rms_held_out_nt`` is the model's own residual on held-out blocks (refitted on the others),
    the baseline of the candidates' ``residual_rms_after_nt``; ``level`` the p-value below which a
    candidate is significant (``alpha / n_tested``); ``correlation_s`` the residual's integrated
    autocorrelation time; ``untried`` the auxiliary channels no candidate could use (unknown kind);
    ``heading_wander_s`` the stretches over which the heading's error was taken out (None: it was not);
    ``residual_rms_held_out_exact_heading_nt`` ``[before, after]`` the held-out residual of the model and of the model
    with the candidates taken, both with the logged heading taken as exact (None: the wander was not taken out, or
    nothing was taken): what the candidates explain that the heading's wander, fitted with them, takes up.
    """

    residual_rms_nt: float
    residual_rms_axis_nt: dict
    n_epochs_used: int
    alpha: float
    candidates: list
    signals: list
    largest: list
    text: str
    binned: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    residual_rms_held_out_nt: float = float("nan")
    n_tested: int = 0
    level: float = float("nan")
    correlation_s: float = float("nan")
    untried: list = field(default_factory=list)
    model_effects: list = field(default_factory=list)
    heading_wander_s: float | None = None
    residual_rms_held_out_exact_heading_nt: list | None = None

    @property
    def recommended(self) -> list:
        """The candidates the decision rule took into the model, in order."""
        return [c for c in self.candidates if c.significant]

    def candidates_frame(self):
        """The candidates as a DataFrame indexed by effect (``--effect`` name), in ranking order."""
        import pandas as pd

        return pd.DataFrame([c.as_dict() for c in self.candidates]).set_index("effect")

    def summary(self) -> dict:
        return {
            "residual_rms_nt": self.residual_rms_nt,
            "residual_rms_axis_nt": self.residual_rms_axis_nt,
            "residual_rms_held_out_nt": self.residual_rms_held_out_nt,
            "n_epochs_used": self.n_epochs_used,
            "alpha": self.alpha,
            "n_tested": self.n_tested,
            "level": self.level,
            "correlation_s": self.correlation_s,
            "heading_wander_s": self.heading_wander_s,
            "residual_rms_held_out_exact_heading_nt": self.residual_rms_held_out_exact_heading_nt,
            "model_effects": self.model_effects,
            "candidates": [c.as_dict() for c in self.candidates],
            "recommended": [c.option for c in self.recommended],
            "untried_channels": self.untried,
            "signals": self.signals,
            "largest_residuals": self.largest,
            "text": self.text,
        }


def _learned_noise(run, config: FilterConfig) -> NoiseLevels | None:
    """The noise a run learned (medians over the log), to weigh the residuals as the filter did."""
    learned = run.summary.noise.get("learned") if run is not None else None
    if not learned:
        return None
    return NoiseLevels(
        learned["sensor_median_nt"],
        np.radians(learned["attitude_median_deg"]),
        config.reference_nt,
        1.0,
        1.0,
        np.radians(learned["heading_median_deg"]),
    )


@one_thread
@names_the_log
def diagnose(
    log: DriveLog,
    config: FilterConfig = FilterConfig(),
    cal: Calibration | None = None,
    effects=(),
    candidates=None,
    alpha: float = 0.01,
    run: CalibrationRun | None = None,
    wander_s: float | None = WANDER_BLOCK_S,
    progress=None,
):
    """Diagnose ``log``: compare the model with the measurements and test which effect is missing.

    The model is the calibration ``cal`` with the effects it stores (used as it is when ``effects`` adds
    nothing to them), or the online filter's estimate with ``effects`` added (started from ``cal`` if
    given), or an existing ``run``. Gross outliers (disturbances) are left out before the candidates are
    tested (docs/diagnosis.md says how it decides).

    Parameters
    ----------
    log : DriveLog
        The drive or flight log.
    config : FilterConfig, optional
        The filter's settings, for the run the model comes from.
    cal : Calibration or None, optional
        A calibration: the model itself, or the filter's start when ``effects`` adds to its effects.
    effects : sequence of Effect, optional
        Effects added to the model.
    candidates : sequence of Effect or None, optional
        The effects to test (default: every registered effect, ``magkf.plugins.EFFECTS``, that the log's
        channels allow); those already in the model are skipped.
    alpha : float, optional
        The significance level over all candidates, in (0, 1).
    run : CalibrationRun or None, optional
        An existing run to take as the model.
    wander_s : float or None, optional
        The logged heading's error is let wander, a straight line over each stretch of that many seconds,
        and taken out of the residuals and regressors before anything is fitted or tested
        (``fitting.HeadingWander``); None: the logged heading is taken as exact.
    progress : callable or None, optional
        Called with a few words at each stage.

    Returns
    -------
    diagnosis : Diagnosis
        The residuals, every candidate's test and the decision (``candidates_frame()``: one row a
        candidate).
    run : CalibrationRun
        The run the model comes from (``run`` itself when given).

    Raises
    ------
    InputError
        ``alpha`` outside (0, 1), fewer than ten epochs left once the outliers are out, or a log that cannot
        be calibrated; it names the log.
    """
    say = progress or (lambda text: None)
    if not 0.0 < alpha < 1.0:
        raise InputError(f"alpha must lie strictly between 0 and 1, got {alpha:g}")
    # Between the stages, what each left free in the heap is given back (``release_free_memory``): the run's and
    # the tests' chunks would otherwise stay resident under the next stage's peak.
    run, layout, x, problem, channels = _diagnosed(log, config, cal, list(effects), run, wander_s, say)
    release_free_memory()
    present = {e.label for e in layout.extra()}
    pool = _pool(candidates, problem, present)
    problem = _without_outliers(problem, layout, x, pool, log)
    release_free_memory()
    tests = _tested(problem, layout, x, pool, alpha, say)
    release_free_memory()
    residuals = _model_residuals(problem, layout, x, run)  # made after the tests: not held while they run
    release_free_memory()
    from ..effects import untried_columns

    untried = untried_columns(channels) if candidates is None else []
    return _diagnosis(problem, residuals, tests, untried, sorted(present), wander_s), run


def _diagnosed(log: DriveLog, config: FilterConfig, cal, effects: list, run, wander_s, say):
    """The model and the epochs it is judged on: ``(run, layout, x, problem, channels)``, ``problem`` the
    ``EpochSet`` of the model's epochs, ``channels`` the names of the log's auxiliary channels. The run is made
    first (its prepared arrays let go at its end). The epochs judged are a run's (``_run_model``: its statuses and
    the log's columns, no epoch prepared), or a calibration's as it is (``_calibration_model``: the log prepared
    again, and let go once the ``EpochSet`` holds what it needs); the ``EpochSet`` prepares them again a chunk at a
    time when read."""
    stored = list(restore_effects(cal)) if cal is not None else []
    check_columns(stored + list(effects), log.auxiliary, log.source)  # naming the calibration file
    run = _run(log, config, cal, effects, stored, run, say)  # the run's own prepared arrays let go at its end
    if run is not None:
        layout, x, used, noise = _run_model(run, effects or stored, log, config)
        ref = reference_track(log, config)
    else:
        layout, x, used, noise, ref = _calibration_model(cal, stored, log, config)
    problem = EpochSet.of(log, ref, used, config, noise, wander_s)
    if len(problem) < 10:
        raise InputError(
            f"too few usable epochs ({len(problem)}) to diagnose; the log needs attitude and a reference", log.source
        )
    return run, layout, x, problem, list(log.auxiliary)


def _run(log: DriveLog, config: FilterConfig, cal, effects: list, stored: list, run, say):
    """The run the model comes from: ``run`` when given, else the filter's over ``log`` (started from ``cal``)
    unless ``cal`` with its ``stored`` effects is the model as it is (None then)."""
    adds = [e for e in effects if e.label not in {s.label for s in stored}]
    if run is None and (cal is None or adds):
        say("calibrating")
        run = calibrate_log(log, config, init=cal, effects=effects or stored, fit_residuals=False)  # not read here
    return run


def _run_model(run, effects: list, log: DriveLog, config: FilterConfig):
    """The model of ``run`` (with ``effects``), ``(layout, x, used, noise)``: the state layout, the run's state
    (n,), the epochs judged (mask (N,) of ``log``: those the run used or its innovation gate refused, with attitude
    and every column the effects read) and the noise the run learned (None: the configured noise)."""
    x = run.x
    layout = StateLayout.with_core(effects)
    if len(x) != layout.size:
        raise ValueError(
            f"the run's state has {len(x)} parameters; the model with {layout.names[12:]} has {layout.size}"
        )
    # The epochs the innovation gate refused are kept: where an effect is missing, the gate refuses
    # the epochs where it is largest, and leaving them out would bias the diagnosis.
    used = attitude_known(log.attitude_columns)
    used &= run.states["status"].isin(["used", "gated_innovation"]).to_numpy()
    return layout, x, _with_columns(used, layout, log.column), _learned_noise(run, config)


def _calibration_model(cal, stored: list, log: DriveLog, config: FilterConfig):
    """The calibration ``cal`` with its ``stored`` effects as it is, ``(layout, x, used, noise, ref)``: the state
    layout, ``cal``'s state (n,), the epochs it can use (mask (N,) of ``log``, with every column its effects read)
    less those the filter's magnitude gate refuses, the noise learned from the log at it (``_gated_as_calibrate``)
    and the reference field (``reference_track``). The log is prepared whole for these (the field's rates, 48
    bytes an epoch, only where the effects may read them), and let go."""
    prep = prepare(log, config, rates=bool(stored))
    layout = StateLayout.with_core(stored)
    x = cal.full_state
    used = _with_columns(prep.base == Status.USED, layout, lambda column: prep.data.columns[column])
    noise, used = _gated_as_calibrate(prep, config, layout, x, used)
    return layout, x, used, noise, reference_track(log, config, prep)


def _with_columns(used: np.ndarray, layout: StateLayout, column) -> np.ndarray:
    """``used`` (N,) bool, in place, less the epochs where a column the effects of ``layout`` read (``column(name)``
    (N,)) is not finite."""
    for effect in layout.extra():
        for name in effect.columns:
            used &= np.isfinite(column(name))
    return used


def _gated_as_calibrate(prep, config: FilterConfig, layout: StateLayout, x, used) -> tuple[NoiseLevels, np.ndarray]:
    """``(noise, used)``: for a calibration diagnosed as it is (state ``x`` (n,) of ``layout``), the noise learned
    from the log at it as ``calibrate`` learns its starting noise (``prepare.start_noise``: a robust scale of the
    residuals), which weighs the residuals, and the epochs ``used`` (N,) bool less those the filter's magnitude
    gate refuses (``| |calibrated m| - |B_ref| |`` beyond ``gate_sigma`` of that noise along the field, or
    ``gate_nt``): the disturbances, which ``calibrate`` refuses the same way. The calibration is held fixed, so no
    uncertainty of its own widens the gate."""
    import math

    from ..online.prepare import start_noise

    noise, _ = start_noise(prep, config, x, layout, True, np.where(used, Status.USED, Status.GATED_DOP))
    width = max(config.gate_nt, config.gate_sigma * math.sqrt(noise.along_var))
    rows = np.flatnonzero(used)
    data = replace(prep.data, R0=layout.R(x))
    distance = np.empty(len(rows))
    for i in range(0, len(rows), CHUNK):
        at = rows[i : i + CHUNK]
        terms = np.nan_to_num(layout.extra_terms(x, layout.linear_jacobian(data, rows=at), data, rows=at))
        c = layout.calibrated(x, prep.m[at], terms)
        distance[i : i + CHUNK] = np.abs(np.linalg.norm(c, axis=1) - prep.ref_mag[at])
    kept = used.copy()
    kept[rows[distance > width]] = False
    return noise, kept


def _pool(candidates, problem: EpochSet, present: set) -> list:
    """The candidate effects to test: ``candidates`` (default: every registered effect that the diagnosed epochs'
    channels allow) less those already in the model (labels ``present``) and those
    reading a column the epochs do not have."""
    offered = candidates if candidates is not None else default_candidates(list(problem.data.columns))
    return [e for e in offered if e.label not in present and all(col in problem.data.columns for col in e.columns)]


def _without_outliers(problem: EpochSet, layout: StateLayout, x, pool: list, log: DriveLog) -> EpochSet:
    """``problem`` with its gross outliers (disturbances) left out, judged at the model ``layout``, ``x`` with the
    candidates of ``pool`` added; raises ``InputError`` when fewer than ten epochs are left."""
    # Gross outliers (disturbances) out: beyond OUTLIER_SIGMA times the robust scale of the residual of the
    # model with every candidate added, so that a missing effect does not hide them by inflating the scale;
    # judged before the heading wander is taken out, which would spread a burst over its stretch.
    # A wandering effect's flexible basis would absorb the bursts, so it is left out of the screening.
    keep = inliers(_screening_residual(problem.with_wander(None).at(layout, x), [e for e in pool if not e.wanders]))
    if not keep.all():
        problem = problem.keep_only(keep)
    n = len(problem)
    if n < 10:
        raise InputError(f"too few usable epochs ({n}) to diagnose once outliers are left out", log.source)
    return problem


@dataclass(frozen=True)
class _Residuals:
    """The model's residuals as it is, on the diagnosed epochs: NED ``ned`` (n, 3), sensor-frame ``body`` (n, 3)
    and magnitude ``mag`` (n,), nT; the RMS of the NED norm ``rms`` (nT) and the figures of
    ``Diagnosis.residual_rms_axis_nt`` (``axis_rms``)."""

    ned: np.ndarray
    body: np.ndarray
    mag: np.ndarray
    rms: float
    axis_rms: dict


def _model_residuals(problem: EpochSet, layout: StateLayout, x, run) -> _Residuals:
    """The residuals in nT (NED, sensor frame and magnitude) of the model ``layout``, ``x`` as it is, and with
    ``run`` the mean NIS of the epochs the filter updated with."""
    n = len(problem)
    data = replace(problem.data, R0=layout.R(x))  # the model as it is
    # the NED residual's components side by side in memory (column-major): each is binned against the signals
    # as a contiguous array, not copied from every third value
    ned, body, mag = np.empty((n, 3), order="F"), np.empty((n, 3)), np.empty(n)
    for a in range(0, n, CHUNK):  # the epochs read a chunk at a time; the effects see the whole set (``rows``)
        s = slice(a, min(a + CHUNK, n))
        c = layout.calibrated(
            x, problem.m[s], layout.extra_terms(x, layout.linear_jacobian(data, rows=s), data, rows=s)
        )
        ned[s] = body_to_ned(data.c_nb[s], c) - data.field_ned[s]
        body[s] = c - data.field_body[s]
        mag[s] = np.linalg.norm(c, axis=1) - np.linalg.norm(data.field_ned[s], axis=1)
    rms = float(np.sqrt(np.mean(_squared_norms(ned))))
    axis_rms = {a: float(np.sqrt(np.mean(ned[:, k] ** 2))) for k, a in enumerate(("north", "east", "down"))}
    axis_rms |= {f"body_{a}": float(np.sqrt(np.mean(body[:, k] ** 2))) for k, a in enumerate("xyz")}
    axis_rms["magnitude"] = float(np.sqrt(np.mean(mag**2)))
    if run is not None:  # normalised innovations of the filter, on the epochs it updated with
        nis = run.states["nis"].to_numpy(dtype=float)[(run.states["status"] == "used").to_numpy()]  # a file's float32
        axis_rms["nis_mean"] = float(np.nanmean(nis)) if np.isfinite(nis).any() else float("nan")
    return _Residuals(ned, body, mag, rms, axis_rms)


@dataclass(frozen=True)
class _Tests:
    """The candidates tested by the decision rule: the ``selection`` (its level and the count tested), the
    ``results`` (``Candidate``s, taken ones first), the residual's integrated autocorrelation time ``tau``
    (epochs), the median epoch interval ``dt`` (s) and the model's own held-out residual ``baseline`` (nT);
    ``unwandered`` the held-out residual (nT) before and after the candidates taken with the logged heading taken as
    exact (``_without_wander``; None where the wander was not taken out or nothing was taken)."""

    selection: _Selection
    results: list
    tau: float
    dt: float
    baseline: float
    unwandered: tuple | None = None


def _tested(problem: EpochSet, layout: StateLayout, x, pool: list, alpha: float, say) -> _Tests:
    """The model refitted to the whole log (its own best fit), then the candidates of ``pool`` tested against it
    and taken or not by the decision rule at level ``alpha``."""
    n = len(problem)
    dt = float(np.median(np.diff(problem.data.time))) if n > 1 else 1.0
    say(f"fitting the model to {n} epochs")
    null = problem.fit(layout, x)  # the model at its own best fit over the log
    with _epoch_rows(n, 3) as r:  # its residual, written a chunk at a time
        for a, b in null.chunks:
            _put(r, a, null.r_of(a, b).reshape(b - a, 3))
        tau = integrated_time(r)
        edges = fold_edges(n, integrated_time(high_passed(r, held=False)))
    baseline = _held_out_nt(null, edges)
    start = (null.layout, null.x_fit)  # refitted with the logged heading taken as exact, below
    selection = _Selection(problem, pool, edges, dt, alpha, say)
    selection.final, null = null, None  # moved on by the selection, and let go once a candidate is taken
    results = selection.run(baseline)
    final, selection.final = selection.final, None  # its whitening and reading are not held beyond the tests
    unwandered = None
    if problem.wander_s and any(c.significant for c in results):
        final = (final.layout, final.x_fit)  # the model itself let go before the refits
        unwandered = _without_wander(problem, start, final, edges)
    return _Tests(selection, results, tau, dt, baseline, unwandered)


def _without_wander(problem: EpochSet, null: tuple, final: tuple, edges) -> tuple[float, float]:
    """The held-out residual RMS (nT) of the model ``null`` and of the model with the candidates taken (``final``),
    each ``(layout, x)`` refitted with the logged heading taken as exact (one at a time): how much the candidates
    explain when the heading's wander, a nuisance fitted jointly with them, does not take up part of it (a time lag
    on a car looks like a heading error within each stretch)."""
    exact = problem.with_wander(None)
    return _held_out_nt(exact.fit(*null), edges), _held_out_nt(exact.fit(*final), edges)


def _diagnosis(problem: EpochSet, res: _Residuals, tests: _Tests, untried: list, model_effects: list, wander_s):
    """The ``Diagnosis`` of the tested candidates: the residual figures, the signals the residual follows, its
    largest stretches and the advice in words."""
    selection, alpha = tests.selection, tests.selection.alpha
    signals, binned = _signals(problem.data, res.ned, res.mag, alpha, tests.tau)
    return Diagnosis(
        res.rms,
        res.axis_rms,
        len(problem),
        alpha,
        tests.results,
        signals,
        _largest(problem.data.time, res.ned),
        _describe(tests.results, signals, selection, tests.baseline, tests.unwandered),
        binned,
        {"time": problem.data.time, "ned": res.ned, "body": res.body, "magnitude": res.mag},
        residual_rms_held_out_nt=tests.baseline,
        n_tested=selection.m,
        level=selection.level,
        correlation_s=tests.tau * tests.dt,
        untried=untried,
        model_effects=model_effects,
        heading_wander_s=wander_s,
        residual_rms_held_out_exact_heading_nt=None if tests.unwandered is None else list(tests.unwandered),
    )


def _screening_residual(fit: Linearised, pool) -> np.ndarray:
    """Whitened residual (n, 3) of ``fit``'s model with every candidate of ``pool`` added (screening
    regressors, one least-squares fit of the columns scaled to unit norm, directions below ``1e-9`` of the
    largest singular value left out, as LAPACK's ``lstsq`` with that ``rcond``), the regressors made and
    reduced a chunk at a time (``gram_svd``: nested candidates, a time lag in the eddy-current terms, make the
    columns dependent). The rows are the model's and each candidate's blocks of columns, reduced block by
    block (``HeldOut`` over a single block of the whole log) without being copied side by side, except for
    the pass that ``gram_svd`` may make."""

    cache = ChunkCache(len(fit.y) // 3)  # the candidates' whitened regressors, made once if the budget allows

    def whitened(j, effect, a, b):
        return cache.get((j, a, b), lambda: fit.whitened(finite_regressors(effect, fit.data, slice(a, b)), a, b))

    def rows(a, b):
        return (fit.rows(a, b), *(whitened(j, effect, a, b) for j, effect in enumerate(pool)))

    whole = HeldOut(fit.y, np.array([0, len(fit.y) // 3]))
    for a, b in fit.chunks:
        whole.add(rows(a, b), a, b)
    gram, moment = whole.N[0], whole.c[0]
    norms = np.maximum(np.sqrt(np.diag(gram)), 1e-300)
    s, vt = gram_svd(
        gram / np.outer(norms, norms), lambda: (np.hstack(rows(a, b)) / norms for a, b in fit.chunks), len(fit.y)
    )
    keep = s > 1e-9 * s[0]
    # X = U S V^T: the least-squares coefficients V S^-2 V^T X^T y over the directions kept
    beta = (vt[keep].T @ ((vt[keep] @ (moment / norms)) / s[keep] ** 2)) / norms
    out = np.empty_like(fit.y)
    for a, b in fit.chunks:
        out[3 * a : 3 * b] = whole.residual(rows(a, b), a, b, [beta])
    return out.reshape(-1, 3)


def _held_out_nt(fit: Linearised, edges) -> float:
    """The NED residual RMS (nT) of ``fit``'s model on held-out blocks between ``edges``."""
    nT = _InNanotesla(fit)  # each chunk's residual reduced to its squares as it is made, none held for the log
    total = sum(nT.squares(r, a, b) for a, b, r in held_out_residuals(fit.rows, fit.y, edges, fit.chunks))
    return float(np.sqrt(total / (len(fit.y) // 3)))


class _InNanotesla:
    """Whitened residuals (3n,) of the diagnosed epochs as NED residual RMS in nT, at the model ``fit``: un-whitened
    by ``fit``'s own whitening, which follows its estimate (a residual whitened at one model and un-whitened at
    another is in neither's nanotesla)."""

    def __init__(self, fit: Linearised):
        self.fit = fit
        self.Rinv = np.linalg.inv(fit.layout.R(fit.x_fit))

    def squares(self, residual_w: np.ndarray, a: int, b: int) -> float:
        """The sum of squares (nT^2) of the NED residual of epochs ``a`` to ``b`` whose whitened residual is
        ``residual_w`` (3 (b - a),) (the rotation to NED keeps the norm)."""
        raw = self.fit.unwhitened(residual_w.reshape(b - a, 3), a, b)
        return float(np.sum((raw @ self.Rinv.T) ** 2))


@dataclass
class _Trial:
    """One candidate evaluated in a model: its test (None: contained, or not testable), held-out and
    in-sample residual RMS (nT), the parameter estimate, and its whitened regressors' directions."""

    effect: object
    test: object
    held_out_nt: float
    fit_nt: float
    estimate: dict
    rank: int
    note: str = ""

    def candidate(self, significant: bool, dt: float, note: str | None = None) -> Candidate:
        t = self.test
        return Candidate(
            effect=self.effect.label,
            statistic=t.F if t else float("nan"),
            dof=t.dof if t else self.rank,
            dof_denominator=t.dof_denominator if t else 0,
            p_value=t.p_value if t else 1.0,
            terms=t.terms if t else 0,
            correlation_s=t.tau * dt if t else float("nan"),
            residual_rms_after_nt=self.held_out_nt,
            residual_rms_fit_nt=self.fit_nt,
            significant=significant,
            estimate=self.estimate,
            note=self.note if note is None else note,
            test="L" if self.effect.wanders else "F",
        )


def _determined_part(effect, gram, rows, n_rows, value, cov):
    """The estimate ``value`` (q,) and its covariance (q, q) of an effect whose whitened regressors are its
    Jacobian, projected onto the directions the data determine beside the model (``fitting.determined``, in
    units of the effect's prior spread): the others, which the model or the heading's wander mimics, are held
    at zero. ``gram`` (q, q) is the Gram matrix of the regressors' part outside the model's span, ``rows()``
    yields that part's rows (``n_rows`` in all, q) a block at a time (``gram_svd``). Returns ``(value, cov,
    directions held)``."""
    mean, spread = effect.prior()
    if gram.shape[0] != len(spread):
        return value, cov, 0
    sv, vt = gram_svd(gram * np.outer(spread, spread), lambda: (X * spread for X in rows()), n_rows)
    k = determined(sv)
    if k == len(spread):
        return value, cov, 0
    keep = (vt[:k].T @ vt[:k]) * spread[None, :] / spread[:, None]  # projector in the parameters' units
    return mean + keep @ (value - mean), keep @ cov @ keep.T, len(spread) - k


@dataclass(frozen=True)
class _Split:
    """A candidate's whitened regressors ``G`` against a model's whitened Jacobian ``A``, from a first pass over
    the rows ``rows(a, b) -> (A, G)`` that sums their normal equations per held-out block (``held``): the model's
    least-squares coefficients ``fitted`` (p,) (its residual ``r = y - A fitted``), the regressors' products
    ``moment`` (q,) with ``r``, their column norms ``norms`` (q,), the Gram matrix ``outside`` (q, q) of the
    normalised regressors' part outside the model's span, and ``proj`` (p, q), the coefficients of their part
    inside it."""

    rows: object
    held: HeldOut
    p: int
    fitted: np.ndarray
    moment: np.ndarray
    norms: np.ndarray
    outside: np.ndarray
    proj: np.ndarray

    @classmethod
    def of(cls, rows, p: int, span, edges, model: Linearised) -> _Split:
        """The first pass over ``model``'s chunks; ``span`` (p, k) the orthonormal basis coefficients of the
        model's span (None: found here, once more over the rows)."""
        chunks, y = model.chunks, model.y
        held = HeldOut(y, edges)
        for a, b in chunks:
            held.add(rows(a, b), a, b)
        normal, c = held.normal, sum(held.c)
        if span is None:
            span = span_coefficients(normal[:p, :p], lambda: (rows(a, b)[0] for a, b in chunks), len(y))
        fitted = span @ (span.T @ c[:p])  # the model's least-squares coefficients: r = y - A fitted
        moment = c[p:] - normal[p:, :p] @ fitted  # the regressors' products with r
        gram, cross = normal[p:, p:], normal[:p, p:]
        norms = np.sqrt(np.diag(gram))
        norms[norms == 0] = 1.0
        along = span.T @ (cross / norms)  # the basis's components of the normalised regressors
        outside = np.asarray(gram / np.outer(norms, norms) - along.T @ along)  # Gram of their part outside it
        return cls(rows, held, p, fitted, moment, norms, outside, span @ along)

    def part(self, a, b, X=None):
        """Normalised regressors of epochs ``a`` to ``b`` less their part in the model's span (3 (b - a), q)."""
        A, G = self.rows(a, b) if X is None else X
        return G / self.norms - A @ self.proj

    def residuals(self, effect, to_u, theta, model: Linearised, scores=None):
        """The second pass over the rows, with the regressors' orthonormal directions ``part @ to_u`` (q, rank) at
        coefficients ``theta`` (rank,): the NED residual RMS (nT) in sample and on held-out blocks (each chunk's
        residual reduced to its sum of squares as it is made); the per-epoch scores (n, rank) of the test written
        to ``scores`` (``_epoch_rows``; None: not made, as for a wandering effect, tested on scores of its own)."""
        y, rank = model.y, to_u.shape[1]
        D = effect.increments()  # a wander's steps, given a prior so held-out blocks are interpolated
        beta = self.held.coefficients(None if D is None else np.hstack([np.zeros((len(D), self.p)), D]))
        nT, in_sample, held_out = _InNanotesla(model), 0.0, 0.0
        for a, b in model.chunks:
            X = self.rows(a, b)
            U = self.part(a, b, X) @ to_u
            e = y[3 * a : 3 * b] - X[0] @ self.fitted - U @ theta
            in_sample += nT.squares(e, a, b)
            if scores is not None:
                _put(scores, a, np.einsum("nik,ni->nk", U.reshape(b - a, 3, rank), e.reshape(b - a, 3)))
            held_out += nT.squares(self.held.residual(X, a, b, beta), a, b)
        n = len(y) // 3
        return float(np.sqrt(in_sample / n)), float(np.sqrt(held_out / n))


#: Per-epoch rows beyond this many bytes (a test's scores, 8 bytes a score: 72 bytes an epoch for nine parameters,
#: some 600 MB on a day at 100 Hz; the tests' residual, 24 bytes an epoch) are kept in a file while the statistics
#: read them a block at a time, not in memory.
ROWS_IN_MEMORY_BYTES = 8 << 20


@contextmanager
def _epoch_rows(n: int, q: int):
    """Where per-epoch rows (n, q) are written in order, a chunk at a time (``_put``), for the statistics of
    ``inference`` to read (``integrated_time``, ``score_test``, ``constancy_test``): an array, or beyond
    ``ROWS_IN_MEMORY_BYTES`` a ``Spill`` of (q,) rows in a temporary folder, removed with it when the block ends."""
    if 8 * n * q <= ROWS_IN_MEMORY_BYTES:
        yield np.empty((n, q))
        return
    with temporary_folder() as folder:
        yield Spill(folder, "rows", float, (q,))


def _put(out, a: int, rows: np.ndarray) -> None:
    """Write the ``rows`` (k, q) of epochs ``a`` on into ``out`` (``_epoch_rows``), after those before."""
    if isinstance(out, np.ndarray):
        out[a : a + len(rows)] = rows
    else:
        out.append(rows)


def _constancy_test(effect, null: Linearised) -> RobustTest | None:
    """A wandering effect's constancy test (``inference.constancy_test``) on its scores (n, q): its whitened
    Jacobian at its prior mean against the whitened residual of the model ``null`` without it, epoch by epoch,
    written a chunk at a time (``_epoch_rows``)."""
    prior = effect.prior()[0]
    q = effect.jacobian(prior, null.data, rows=slice(0, 1)).shape[2]
    with _epoch_rows(len(null.y) // 3, q) as scores:
        for a, b in null.chunks:
            G = null.whitened(effect.jacobian(prior, null.data, rows=slice(a, b)), a, b)
            _put(scores, a, np.einsum("nik,ni->nk", G.reshape(b - a, 3, q), null.r_of(a, b).reshape(b - a, 3)))
        return constancy_test(scores)


def _estimate(effect, test, split: _Split, to_u, names, model: Linearised) -> tuple[dict, str]:
    """A candidate's parameters ``{name: {"value", "std"}}`` from its ``test`` over the directions the data
    determine beside the model (``_determined_part``), and the note on it: why it was not testable, or how many
    directions of its parameters were held. A wandering effect's test has no estimate."""
    if test is None:
        return {}, "not testable: the residual's correlation leaves too few independent stretches"
    if effect.wanders:
        return {}, ""
    # coefficients of G (Frisch-Waugh): theta_G = V S^-1 theta_U / norms, with the robust covariance
    norms = split.norms
    back = to_u / norms[:, None]
    value, cov = back @ test.theta, back @ test.cov @ back.T
    value, cov, undetermined = _determined_part(
        effect,
        split.outside * np.outer(norms, norms),
        lambda: (split.part(a, b) * norms for a, b in model.chunks),
        len(model.y),
        value,
        cov,
    )
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    estimate = {nm: {"value": float(v), "std": float(sd)} for nm, v, sd in zip(names, value, std)}
    if not undetermined:
        return estimate, ""
    plural = "s" if undetermined > 1 else ""
    return estimate, f"{undetermined} direction{plural} of its parameters not determined (held at the prior mean)"


class _AsTested(LinearEffect):
    """An effect whose diagnostic regressors are not its Jacobian (a slow drift, whose Jacobian is the
    offset itself) as the linear block of those regressors, so that it can be refitted and kept in the model
    while the other candidates are tested."""

    def __init__(self, effect, size: int):
        self.effect, self.name, self.columns = effect, effect.name, effect.columns
        self.parameter_names = tuple(f"g{j + 1}" for j in range(size))

    def jacobian(self, theta, data, rows=None):
        return finite_regressors(self.effect, data, rows)


class _Selection:
    """Forward selection by the one decision rule (see the module's docstring)."""

    def __init__(self, problem, pool, edges, dt, alpha, say=lambda text: None):
        self.problem, self.pool, self.edges, self.dt, self.say = problem, pool, edges, dt, say
        self.alpha = alpha
        self.m = 0
        self.level = float("nan")
        self.final = None  # the model ``run`` starts from, then the one with the candidates taken

    def trial(self, effect, fit: Linearised) -> _Trial:
        """Screen ``effect`` added to the model ``fit``: its regressors at ``fit``'s linearisation."""
        q = finite_regressors(effect, fit.data, slice(0, 1)).shape[2]
        names = effect.parameter_names if q == effect.size else [f"g{j + 1}" for j in range(q)]

        cache = ChunkCache(len(fit.y) // 3)  # kept for the trial's passes on a short set, made again beyond

        def whitened(a, b):
            return cache.get((a, b), lambda: fit.whitened(finite_regressors(effect, fit.data, slice(a, b)), a, b))

        def rows(a, b):
            return fit.rows(a, b), whitened(a, b)

        return self._evaluate(effect, rows, fit.layout.size, fit.span, names, fit, fit)

    def refit(self, effect, fit: Linearised) -> tuple[_Trial, Linearised]:
        """``effect`` at its own best fit: the model refitted with it (iterated; a nonlinear effect such as the
        exact time lag linearised at its estimate), and its test there. Returns the trial and that model, whose
        whitened Jacobian is made again a chunk at a time when it is read."""
        block = effect
        if type(effect).regressors is not Effect.regressors:
            block = _AsTested(effect, effect.regressors(fit.data, rows=slice(0, 1)).shape[2])
        layout = StateLayout((*fit.layout.effects, block))
        p = fit.layout.size
        with_it = self.problem.fit(layout, np.concatenate([fit.x_fit, block.prior()[0]]))

        # a wandering effect's test is made at the model without it (a score test): it is fitted here only
        # for its held-out residual
        def rows(a, b):
            X = with_it.rows(a, b)
            return X[:, :p], X[:, p:]

        trial = self._evaluate(effect, rows, p, None, block.parameter_names, fit, with_it)
        return trial, with_it

    def _evaluate(self, effect, rows, p, span, names, null: Linearised, model: Linearised) -> _Trial:
        """The test of whitened regressors added to a model, from ``rows(a, b)``, the rows of epochs ``a`` to
        ``b`` (one chunk of ``model.chunks``) of the model's whitened Jacobian ``A`` (3 (b - a), p), with
        orthonormal basis ``A @ span`` of its span (None: found here), and of the regressors (3 (b - a), q);
        all whitened at ``model``, for ``model``'s reading ``y``; a wandering effect's constancy test at the
        model ``null`` without it.

        The rows are made a chunk at a time, twice: once for their normal equations per held-out block, from
        which the model's span, what it leaves of ``y``, the regressors' part outside it and its SVD follow
        (``_Split``), and once for the per-epoch scores of the test, the residual it leaves and the held-out
        residual (``_Split.residuals``); where the normal equations are ill-conditioned, once more
        (``gram_svd``)."""
        chunks, y = model.chunks, model.y
        split = _Split.of(rows, p, span, self.edges, model)
        s, vt = gram_svd(split.outside, lambda: (split.part(a, b) for a, b in chunks), len(y))
        rank = int(np.sum(s > RANK_TOLERANCE))
        if rank == 0:
            return _Trial(effect, None, float("nan"), float("nan"), {}, 0, "contained in the model")
        to_u = vt[:rank].T / s[:rank]  # U = part @ to_u: orthonormal
        theta = to_u.T @ (split.moment / split.norms)  # U^T r (the span's basis is orthogonal to r)
        if effect.wanders:
            in_sample, held_out = split.residuals(effect, to_u, theta, model)
            test = _constancy_test(effect, null)
        else:
            with _epoch_rows(len(y) // 3, rank) as scores:
                in_sample, held_out = split.residuals(effect, to_u, theta, model, scores)
                test = score_test(scores, theta)
        estimate, note = _estimate(effect, test, split, to_u, names, model)
        return _Trial(effect, test, held_out, in_sample, estimate, rank, note)

    def significant(self, trial: _Trial) -> bool:
        return trial.test is not None and trial.test.p_value < self.level

    def run(self, held_out_nt: float) -> list[Candidate]:
        """The candidates, taken ones first, starting from the model ``final`` (a ``Linearised``) whose held-out
        residual (nT) is ``held_out_nt``; ``final`` is then the model with the candidates taken (the one it started
        from not held once a candidate is taken: three rows an epoch)."""
        fit, current, self.final = self.final, held_out_nt, None
        remaining = list(self.pool)
        self.say(f"testing {len(remaining)} candidates")
        trials = {e.label: self.trial(e, fit) for e in remaining}
        self.m = max(sum(t.test is not None for t in trials.values()), 1)
        self.level = self.alpha / self.m
        taken, refused = [], set()
        while remaining:
            hits = self._hits(trials, remaining, refused)
            if not hits:
                break
            leading = self._leading(hits, fit, current, trials, refused)
            if leading is None:
                continue
            best, best_fit = self._simpler(*leading, hits, fit)
            leading = None
            taken.append(best.candidate(True, self.dt))
            remaining = [e for e in remaining if e.label != best.effect.label]
            fit, refused = best_fit, set()
            current = _held_out_nt(fit, self.edges)
            trials = self._retried(best, remaining, fit)
        rest = sorted(
            (trials[e.label] for e in remaining), key=lambda t: (t.test is None, t.test.p_value if t.test else 1.0)
        )
        self.final = fit
        return taken + [t.candidate(False, self.dt) for t in rest]

    def _hits(self, trials: dict, remaining: list, refused: set) -> list[_Trial]:
        """The significant trials of the ``remaining`` candidates not ``refused``, lowest held-out residual first."""
        hits = [trials[e.label] for e in remaining if e.label not in refused and self.significant(trials[e.label])]
        hits.sort(key=lambda t: t.held_out_nt)
        return hits

    def _leading(self, hits: list, fit: Linearised, current: float, trials: dict, refused: set):
        """The first ``LEADING`` of ``hits`` refitted at their own best fit (their trials in ``trials`` replaced):
        ``(trial, model)`` of the one significant there and lowest on held-out data below ``current`` (nT), or
        None. A candidate significant there but no better than the model on held-out blocks joins ``refused``."""
        # taken only if significant at its own best fit and better than the model on held-out data; of
        # those, the lowest held-out residual (only its refitted model is kept)
        leading = None
        for t in hits[:LEADING]:
            self.say(f"refitting the model with {t.effect.label}")
            trial, with_it = self.refit(t.effect, fit)
            trials[t.effect.label] = trial
            if self.significant(trial) and trial.held_out_nt < current:
                if leading is None or trial.held_out_nt < leading[0].held_out_nt:
                    leading = (trial, with_it)
            elif self.significant(trial):
                trial.note = f"significant, but no better than the model on held-out blocks ({current:.1f} nT)"
                refused.add(t.effect.label)
            del with_it
        return leading

    def _retried(self, best: _Trial, remaining: list, fit: Linearised) -> dict:
        """The trials of the ``remaining`` candidates in the model ``fit`` that has just taken ``best``; those it
        contains are noted so."""
        trials = {e.label: self.trial(e, fit) for e in remaining}
        for e in remaining:
            if trials[e.label].rank == 0:
                trials[e.label].note = f"contained in {best.effect.label}"
        return trials

    def _simpler(self, best: _Trial, best_fit: Linearised, hits, fit: Linearised):
        """Among significant candidates contained in ``best`` (fewer parameters, nothing left once ``best`` is
        in the model), the simplest that ``best`` does not beat on held-out data beyond chance."""
        smaller = sorted((t for t in hits if t.rank < best.rank), key=lambda t: t.rank)
        for small in smaller:
            if self.trial(small.effect, best_fit).rank != 0:
                continue  # not nested in best
            small_trial, small_fit = self.refit(small.effect, fit)
            beyond = self.trial(best.effect, small_fit)  # best given the smaller one
            if not self.significant(beyond) or beyond.held_out_nt >= small_trial.held_out_nt:
                small_trial.note = f"preferred to {best.effect.label}, which it is nested in"
                return small_trial, small_fit
        return best, best_fit


# ---------------------------------------------------------------- residual against signals
def signal_values(data):
    """Candidate explanatory signals (N,) at the used epochs, ``(name, values)`` made one after another rather than
    all held at once: each of the attitude's angles and the field's rate from a pass of its own over the epochs a
    chunk at a time (the heading held until its rate is made), then the log's own columns (a column named as one of
    these signals takes its place, as a dict's key would)."""
    t = data.time
    n = len(t)
    columns = data.columns

    def signal(name: str, make):
        return name, np.asarray(columns[name]) if name in columns else make()

    def angle(of):  # an angle (deg) of the attitude matrices, in a pass of its own
        return _chunkwise(data.c_nb, n, lambda c: np.degrees(of(c)))

    yaw = angle(lambda c: np.arctan2(c[:, 1, 0], c[:, 0, 0]))
    yaw %= 360.0
    yield signal("heading_deg", lambda: yaw)
    yield signal("roll_deg", lambda: angle(lambda c: np.arctan2(c[:, 2, 1], c[:, 2, 2])))
    yield signal("pitch_deg", lambda: angle(lambda c: np.arcsin(np.clip(-c[:, 2, 0], -1, 1))))
    yield signal("time_s", lambda: t - t[0])
    if n > 2 or "yaw_rate_dps" in columns:  # a rate needs three epochs; a column of that name is taken as it is
        yield signal("yaw_rate_dps", lambda: yaw_rate(yaw, t))
    yaw = None  # not held beyond its rate
    yield signal("field_rate_nt_s", lambda: _chunkwise(data.field_body_rate, n, lambda r: np.linalg.norm(r, axis=1)))
    for name, values in columns.items():
        if name not in MADE_SIGNALS:
            yield name, np.asarray(values)


#: The signals ``signal_values`` makes from the epochs (a log's column of the same name is taken instead).
MADE_SIGNALS = ("heading_deg", "roll_deg", "pitch_deg", "time_s", "yaw_rate_dps", "field_rate_nt_s")


def _chunkwise(array, n: int, value) -> np.ndarray:
    """``value(rows)`` (k,) of each ``CHUNK`` rows of the first ``n`` of ``array`` (an array, or one read a chunk at
    a time such as an ``EpochData``'s), side by side (n,): a chunk's working arrays, not the whole array's."""
    out = np.empty(n)
    for a in range(0, n, CHUNK):
        out[a : a + CHUNK] = value(array[a : a + CHUNK])
    return out


def yaw_rate(yaw: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The heading's rate (N,) deg/s of ``yaw`` (N,) deg at ``t`` (N,) s (N >= 2), to the last bit
    ``np.gradient(np.unwrap(np.radians(yaw)), t) * 180 / np.pi``, made ``CHUNK`` epochs at a time: the whole-array
    expression holds some ten working arrays of the log's length (28 MB on the hour's log, the peak of the signals'
    stage). The unwrapping's running sum of corrections is carried from chunk to chunk as one ``cumsum`` adds it up,
    and the rate takes numpy's formula for even steps (``np.gradient`` at one step) where every step of ``t`` is
    equal, else its formula for uneven steps (``effects.base._gradient``), whatever a chunk's own steps."""
    n = len(yaw)
    unwrapped = np.empty(n)
    carried = 0.0  # the sum of the corrections up to the chunk's first epoch
    unwrapped[0] = np.radians(yaw[0])
    for a in range(1, n, CHUNK):
        p = np.radians(yaw[a - 1 : a + CHUNK])
        dd = np.diff(p)
        wrapped = np.mod(dd + np.pi, 2 * np.pi) - np.pi  # np.unwrap's steps into [-pi, pi)
        np.copyto(wrapped, np.pi, where=(wrapped == -np.pi) & (dd > 0))
        correction = wrapped - dd
        np.copyto(correction, 0, where=np.abs(dd) < np.pi)
        sums = np.cumsum(np.concatenate([[carried], correction]))[1:]
        unwrapped[a : a + CHUNK] = p[1:] + sums
        carried = sums[-1]
    even = all(np.all(np.diff(t[a : a + CHUNK + 1]) == t[1] - t[0]) for a in range(0, n - 1, CHUNK))
    out = np.empty(n)
    for a in range(0, n, CHUNK):
        lo, hi = max(a - 1, 0), min(a + CHUNK + 1, n)  # the chunk and a neighbour either side
        f = unwrapped[lo:hi]
        rate = np.gradient(f, t[1] - t[0]) if even else _gradient(t[lo:hi], f[:, None])[:, 0]
        first = a - lo
        out[a : a + CHUNK] = rate[first : first + min(CHUNK, n - a)] * 180 / np.pi
    return out


def _bins(name: str, v: np.ndarray) -> np.ndarray:
    """The bin (N,) int of each value of the signal ``name`` (``v`` (N,), finite): ``BINS`` equal sectors of
    the heading, else ``BINS`` bins between the signal's quantiles (fewer where they coincide); made in place."""
    if name == "heading_deg":
        sectors = v / (360.0 / BINS)
        out = np.floor(sectors, out=sectors).astype(int)
        return np.remainder(out, BINS, out=out)
    edges = np.unique(np.nanquantile(v, np.linspace(0, 1, BINS + 1)))
    if len(edges) < 3:
        return np.zeros(len(v), int)
    out = np.searchsorted(edges, v, side="right")
    out -= 1
    return np.clip(out, 0, len(edges) - 2, out=out)


def _signals(data, ned, mag, alpha, tau: float = 1.0):
    """One-way ANOVA of each residual component over bins of each signal; binned means for plots.

    The residual is correlated over ``tau`` epochs (its integrated autocorrelation time), so each bin's
    mean varies about ``tau`` times more than independent epochs would make it: the F statistic is divided
    by ``tau`` and the denominator's degrees of freedom are those of ``n / tau`` independent epochs, and the
    95 % band of each binned mean is widened by ``sqrt(tau)``. The signals are made one at a time, and the
    epochs a signal bins are picked from the residuals only where some are left out (not finite, or alone in
    their bin)."""
    components = {"north": ned[:, 0], "east": ned[:, 1], "down": ned[:, 2], "magnitude": mag}
    out, binned, tests = [], {}, 0
    for name, v in signal_values(data):
        tests += len(components)
        ok = np.isfinite(v)
        if ok.sum() < 2 * BINS:
            continue
        picked = None if ok.all() else np.flatnonzero(ok)
        v = v if picked is None else v[picked]
        b = _bins(name, v)
        best = None
        binned[name] = {}
        counts = np.bincount(b)
        keys = np.flatnonzero(counts > 1)  # bins of more than one epoch
        if len(keys) < len(counts):  # some epochs alone in their bin (or bins empty): those epochs left out
            inside = counts[b] > 1
            if not inside.all():
                picked = np.flatnonzero(inside) if picked is None else picked[inside]
                v, b = v[inside], b[inside]
            del inside
        group = b if len(keys) == len(counts) else np.searchsorted(keys, b)  # every bin kept: its index
        sizes, k = counts[keys], len(keys)
        centres = np.bincount(group, v, minlength=k) / sizes
        for comp, r in components.items():
            if k < 2:
                continue
            x = np.ascontiguousarray(r) if picked is None else r[picked]
            # one-way analysis of variance from the bins' sums (as scipy.stats.f_oneway)
            means = np.bincount(group, x, minlength=k) / sizes
            within = _within_squares(group, x, means)
            total = len(x)
            between = float(np.sum(sizes * (means - x.mean()) ** 2))
            with np.errstate(divide="ignore", invalid="ignore"):
                f = (between / (k - 1)) / (float(np.sum(within)) / (total - k))
            p = float(f_sf(f / max(tau, 1.0), k - 1, max((total - k) / max(tau, 1.0), 1.0)))
            # a bin's mean varies tau times more than that of independent epochs
            half = 1.96 * np.sqrt(within / (sizes - 1)) * np.sqrt(max(tau, 1.0) / sizes)
            binned[name][comp] = {"centre": centres.tolist(), "mean": means.tolist(), "ci95": half.tolist()}
            if best is None or p < best[1]:
                best = (comp, float(p), float(np.ptp(means)))
        if best is not None:
            out.append(
                {
                    "signal": name,
                    "component": best[0],
                    "p_value": best[1],
                    "binned_range_nt": best[2],
                    "significant": None,  # once every signal's tests are counted
                }
            )
    for entry in out:
        entry["significant"] = entry["p_value"] < alpha / tests
    out.sort(key=lambda s: s["p_value"])
    return out, binned


def _squared_norms(v: np.ndarray) -> np.ndarray:
    """The squared norm (n,) of each row of ``v`` (n, 3), ``np.sum(v**2, axis=1)`` to the bit, made ``CHUNK`` rows at
    a time (the squares of a chunk, not of the whole array, are held beside it)."""
    return _chunkwise(v, len(v), lambda rows: np.sum(rows**2, axis=1))


def _within_squares(group: np.ndarray, x: np.ndarray, means: np.ndarray) -> np.ndarray:
    """Each bin's sum of squares (k,) about its mean ``means`` (k,) of the values ``x`` (n,) in bins ``group`` (n,),
    ``np.bincount(group, (x - means[group]) ** 2)`` to the bit (``np.add.at`` adds each value to its bin in the same
    order), made ``CHUNK`` values at a time: the squares of a chunk, not of every value, are held."""
    out = np.zeros(len(means))
    for a in range(0, len(x), CHUNK):
        g = group[a : a + CHUNK]
        d = x[a : a + CHUNK] - means[g]
        d *= d
        np.add.at(out, g, d)
    return out


def _largest(t: np.ndarray, ned: np.ndarray, count: int = 3) -> list:
    """The ``count`` stretches of ``WINDOW_S`` seconds with the largest RMS residual norm."""
    window = np.floor((t - t[0]) / WINDOW_S).astype(int)
    norm2 = _squared_norms(ned)
    sums = np.bincount(window, norm2)
    counts = np.bincount(window)
    rms = np.sqrt(sums / np.maximum(counts, 1))
    out = []
    for w in np.argsort(-rms)[:count]:
        idx = np.flatnonzero(window == w)
        if idx.size == 0:
            continue
        worst = idx[np.argmax(norm2[idx])]
        out.append(
            {
                "start": float(t[idx[0]]),
                "stop": float(t[idx[-1]]),
                "rms_nt": float(rms[w]),
                "max_nt": float(np.sqrt(norm2[worst])),
                "max_time": float(t[worst]),
            }
        )
    return out


def _describe(results, signals, selection, baseline: float, unwandered=None) -> str:
    """The advice: what the decision rule took (and, ``unwandered`` the held-out residual before and after with the
    logged heading taken as exact, how much the heading's wander took up of it), or what the residual still
    follows."""
    taken = [r for r in results if r.significant]
    following = [s for s in signals if s["significant"]]
    if taken:
        best = taken[0]
        text = (
            f"{best.effect} explains the residual beyond chance (F = {best.statistic:.1f} on {best.dof} and "
            f"{best.dof_denominator} dof, p = {best.p_value:.2g}, robust to the residual's correlation); on "
            f"held-out data it brings the residual RMS from {baseline:.1f} to {best.residual_rms_after_nt:.1f} nT: "
            f"add {best.option}"
        )
        if len(taken) > 1:
            text += "; then also " + ", ".join(r.option for r in taken[1:])
        if unwandered is not None and unwandered[0] - unwandered[1] > baseline - taken[-1].residual_rms_after_nt:
            text += (
                f" (with the logged heading taken as exact, the held-out residual falls from {unwandered[0]:.1f} to "
                f"{unwandered[1]:.1f} nT: the heading's wander, fitted with the candidates, takes up part of what "
                "they explain)"
            )
        return text
    text = (
        f"no candidate explains the residual beyond chance ({selection.m} tested, each at p < "
        f"{selection.level:.2g}, alpha {selection.alpha:g})"
    )
    if following:
        text += "; it still follows " + ", ".join(
            f"{s['signal']} ({s['component']}, p = {s['p_value']:.2g})" for s in following[:4]
        )
    return text


def _nis_per_dof(run: CalibrationRun, epochs) -> float:
    """Mean NIS per degree of freedom over ``epochs`` (mask) of ``run``'s states: the rows its measurement gives
    an epoch with a vector residual (one with attitude) and one without (``measurements.nis_rows``; 3 and 1
    for a measurement that is not registered)."""
    from ..online.measurements import MEASUREMENTS, nis_rows

    model = MEASUREMENTS.get(run.summary.measure)
    rows = (3, 1) if model is None else nis_rows(model)
    nis = run.states["nis"].to_numpy()[epochs]
    dof = np.where(np.isfinite(run.states["residual_n"].to_numpy()[epochs]), *map(float, rows))
    ok = np.isfinite(nis)
    return float(np.sum(nis[ok]) / np.sum(dof[ok])) if ok.any() else float("nan")


def compare_runs(before: CalibrationRun, after: CalibrationRun) -> dict:
    """Before and after adding effects, on the epochs both used: residual RMS (nT), mean NIS per degree of
    freedom (each run with its own learned noise), AIC, BIC."""
    both = ((before.states["status"] == "used") & (after.states["status"] == "used")).to_numpy()
    out = {}
    for label, run in (("before", before), ("after", after)):
        ned = run.states[["residual_n", "residual_e", "residual_d"]].to_numpy()[both]
        ned = ned[np.all(np.isfinite(ned), axis=1)]
        k = len(run.x)
        nrows = ned.size
        rss = float(np.sum(ned**2))
        out[label] = {
            "residual_rms_nt": float(np.sqrt(rss / max(len(ned), 1))),
            "nis_mean": _nis_per_dof(run, both),
            "aic": float(nrows * np.log(rss / nrows) + 2 * k),
            "bic": float(nrows * np.log(rss / nrows) + k * np.log(nrows)),
            "n_parameters": k,
        }
    out["n_epochs"] = int(both.sum())
    return out
