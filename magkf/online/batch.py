"""Batch calibration of a whole log: the patent's objective with a robust loss.

For every usable epoch, with ``c = R^-1 (m - b - e)`` the calibrated field:

* the **total-field residual** ``|c| - |B_ref|``;
* the **inter-axis residuals**: the NED residual ``C_nb c - B_ref`` (``measure="vector"``: all three
  components), or for ``measure="both"`` its two components across the reference field (the component
  along it is the total-field residual already, to first order, and is not counted twice).

Each residual is divided by its standard deviation from the same noise settings as the filter
(sensor noise, attitude, reference). A robust loss (``soft_l1``, scale 3 sigma) is minimised from the
linear least-squares solution in the sensor frame; epochs with a residual beyond ``OUTLIER_SIGMA`` after
that robust pass are dropped (reported as ``gated_innovation``) and the rest fitted by plain least
squares, whose Jacobian gives the covariance. Epochs gated by DOP, missing values or the magnitude gate
(with the starting estimate) are left out. The prior ``(x - x0) / prior_std`` (the initial calibration's,
or the bootstrap's weak one) counts as ``n`` more residuals, under the same loss.

**How it is solved.** The objective has ``n`` parameters (12 core plus the effects') but up to three
residuals for every epoch of the log. ``scipy.optimize.least_squares`` is not used for it: it holds the
whole log's Jacobian as a dense array (rows = epochs x residuals, ``n`` columns: 288 bytes per epoch for
12 parameters) and several copies of it and of the whole-log residuals; with it, ``calibrate --batch``
peaked at 1.4 GB (3.3 kB per epoch above the read log) on an hour at 100 Hz. Here the log is gone through
``CHUNK_EPOCHS`` epochs at a time (``BatchProblem``), and each chunk's residuals ``r`` and Jacobian ``J``
are folded into the ``n x n`` normal equations ``J^T W J`` and ``J^T W r`` and dropped: besides the
prepared log, the solver holds the usable epochs' indices and flags (about ten bytes per epoch) whatever
the length of the log.

* Each model gives its residuals and their Jacobian (``MeasurementModel.batch_residuals``). The built-in
  ones give the residuals above as a function of each epoch's calibrated field (``measurements.
  field_residuals``): their Jacobian is analytic in the state, ``dc/dx = -R^-1 dm/dx`` evaluated at ``c``
  (``core_jacobian(c)`` for ``R`` and ``b``, the effects' own ``jacobian`` for theirs), times the residual
  functions' derivative in ``c``, three central differences of that function per epoch. Any other model's
  are its rows whitened by its noise at the start, ``W (predict - measure)``, with ``W jacobian``.
* The robust pass is iteratively reweighted Gauss-Newton with a backtracking line search. The
  ``soft_l1`` cost of a residual ``r`` with scale ``s`` is ``s^2 (sqrt(1 + (r/s)^2) - 1)``; its derivative
  is ``r / sqrt(1 + (r/s)^2)``, which is the derivative of ``w r^2 / 2`` with the weight
  ``w = (1 + (r/s)^2)^(-1/2)`` held fixed. So the weighted normal equations ``(J^T W J) dx = -J^T W r`` at
  the current weights give a descent direction of the robust cost (their right side is its gradient).
  The plain fit is Gauss-Newton with ``W`` the 0/1 mask of the kept epochs. A step is taken whole when it
  lowers the cost (to within ``COST_RTOL`` of it: the rounding of a sum over the log), else halved until
  it does (down to ``2^-MAX_HALVINGS``): the cost never rises.
* **Converged** when every parameter's Gauss-Newton step is below ``STEP_TOL`` of its standard deviation
  (``sqrt(diag((J^T W J)^-1))``), or when no fraction of a step below ``FLAT_STEP_TOL`` of them lowers the
  cost (the cost is then at its minimum to rounding, and the step within what a finite-difference
  Jacobian, as an effect's may be, can resolve). A pass that reaches ``MAX_ITERATIONS`` iterations, or
  whose step of ``FLAT_STEP_TOL`` or more no fraction of lowers the cost, stops and says so in a warning
  naming the log and the size of its last step.
* The covariance is ``(J^T J)^-1`` at the solution (prior rows included); the outlying epochs are found
  again at the solution.

A log with a nonlinear effect (``time_lag``, whose model interpolates between epochs) is gone through in
one chunk, the magnitude gate included, so that its model sees the same neighbours in every pass (the
usable epochs of each model's group). The linear start in the sensor frame is fitted to at most
``prepare.FIT_EPOCHS`` attitude epochs spread evenly over the log (every one of a shorter log).
"""

from __future__ import annotations

import time as _time
import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..blas import one_thread
from ..calibration import Calibration
from ..config import FilterConfig
from ..effects.base import EpochData
from ..errors import InputError, names_the_log
from ..io.drivelog import DriveLog
from ..status import Status
from .bootstrap import vector_least_squares
from .measurements import Block, MeasurementModel
from .prepare import PreparedLog, fit_positions, prepare, prepare_run
from .results import RunTrace, build_run
from .state import StateLayout

__all__ = [
    "solve_batch",
    "batch_problem",
    "BatchProblem",
    "NormalEquations",
    "Solution",
    "OUTLIER_SIGMA",
    "LOSS_SCALE",
    "CHUNK_EPOCHS",
    "STEP_TOL",
    "FLAT_STEP_TOL",
    "MAX_ITERATIONS",
]

OUTLIER_SIGMA = 5.0
LOSS_SCALE = 3.0
#: Epochs evaluated at once (their Jacobian is about 1 kB per epoch while it lives).
CHUNK_EPOCHS = 8192
#: Converged when every parameter's step is below this many of its standard deviations.
STEP_TOL = 1e-6
#: Also converged when no fraction of a step below this many standard deviations lowers the cost.
FLAT_STEP_TOL = 1e-3
#: At most this many Gauss-Newton iterations per pass. The robust pass's reweighting converges linearly: a
#: parameter the log determines to a small fraction of its prior (a 0.05 s time lag to 1.2e-4 s over 150 s)
#: took 50 to 100 iterations to step below ``STEP_TOL`` of its standard deviation.
MAX_ITERATIONS = 100
#: A step may raise the cost by this fraction of it (the rounding of a sum over the whole log) and be taken.
COST_RTOL = 1e-12
#: A step is halved at most this many times before the pass stops.
MAX_HALVINGS = 10


@dataclass(frozen=True)
class NormalEquations:
    """``J^T W J`` (n, n) and ``J^T W r`` (n,) of the whole objective at one state, and its ``cost`` (the loss's
    sum: ``sum w r^2 / 2`` for plain least squares, ``s^2 sum (sqrt(1 + (r/s)^2) - 1)`` for ``soft_l1``)."""

    A: np.ndarray
    g: np.ndarray
    cost: float

    def _factor(self):
        """Cholesky factor of ``A`` scaled to a unit diagonal, and the scale ``D`` (n,)."""
        D = 1.0 / np.sqrt(np.diag(self.A))
        return cho_factor(self.A * D[:, None] * D[None, :]), D

    def step(self) -> tuple[np.ndarray, np.ndarray]:
        """The Gauss-Newton step ``-A^-1 g`` (n,) and the parameters' standard deviations ``sqrt(diag(A^-1))`` (n,)."""
        factor, D = self._factor()
        dx = -D * cho_solve(factor, D * self.g)
        return dx, D * np.sqrt(np.diag(cho_solve(factor, np.eye(len(D)))))

    def covariance(self) -> np.ndarray:
        """``A^-1`` (n, n), symmetric."""
        factor, D = self._factor()
        P = cho_solve(factor, np.eye(len(D))) * D[:, None] * D[None, :]
        return 0.5 * (P + P.T)


@dataclass(frozen=True)
class Solution:
    """Where a pass ended: the state ``x`` (n,), the normal equations there, the iterations taken, whether it
    ``converged`` and its last step's largest ratio to a standard deviation (``largest_step``)."""

    x: np.ndarray
    normal: NormalEquations
    iterations: int
    converged: bool
    largest_step: float


@dataclass
class BatchProblem:
    """The batch objective of one log, evaluated ``chunk`` epochs at a time.

    ``prep`` the prepared log (without the heading axis, and without the field's rates when no effect is
    added: only the start and the effects use them); ``layout`` the state layout; ``x0`` (n,) and ``P0``
    (n, n) the start and its covariance, ``how`` how it was found; ``status`` (N,) the statuses before the
    solve (the magnitude gate included); ``x_start`` (n,) the state the robust pass starts from; ``groups``
    the usable epochs, as ``(model, epochs)`` pairs: the measurement model that takes them and their
    indices (k,) into the log; ``prior_std`` (n,) the prior's standard deviations.
    """

    prep: PreparedLog
    layout: StateLayout
    x0: np.ndarray
    P0: np.ndarray
    how: str
    status: np.ndarray
    x_start: np.ndarray
    groups: list
    prior_std: np.ndarray
    chunk: int = CHUNK_EPOCHS

    def chunks(self):
        """``(model, epochs)`` of every chunk of usable epochs (epochs (k,) indices into the log)."""
        for model, epochs in self.groups:
            for i in range(0, len(epochs), self.chunk):
                yield model, epochs[i : i + self.chunk]

    def calibrated(self, x, epochs) -> tuple[np.ndarray, object]:
        """The calibrated field ``c`` (k, 3) nT at state ``x`` of the log's ``epochs`` (k,), and their
        ``EpochData`` (None without effects, which then need none)."""
        layout = self.layout
        data = self.prep.data.take(epochs) if layout.has_extra else None
        terms = 0.0 if data is None else layout.effect_terms(x, data)
        return layout.calibrated(x, self.prep.m[epochs], terms), data

    def residuals(self, x, model: MeasurementModel, epochs, jacobian: bool = False):
        """Normalised residuals ``r`` (k, q) of ``epochs`` (k,) at state ``x`` (n,) for ``model``
        (``MeasurementModel.batch_residuals``, with its noise at the start ``x0``); with ``jacobian``, ``(r, J)``
        with ``J = dr/dx`` (k, q, n)."""
        return model.batch_residuals(x, self.block(epochs), jacobian, noise_at=self.x0)

    def block(self, epochs) -> Block:
        """The log's ``epochs`` (k,) as the models see them (``Block``): the readings, the reference magnitude,
        the body field, the start's ``R`` (the noise's), and the epochs' ``EpochData`` (without effects, only
        the time, the fields and the attitude); without the linear Jacobian (``Block.H`` None), which a model
        that needs it makes."""
        prep = self.prep
        if self.layout.has_extra:
            data = prep.data.take(epochs)
        else:
            d = prep.data
            data = EpochData(d.time[epochs], d.field_body[epochs], prep.ref[epochs], c_nb=prep.c_nb[epochs])
        return Block(prep.m[epochs], prep.ref_mag[epochs], None, data.field_body, self.layout.R(self.x0), data=data)

    def normal_equations(self, x, scale: float | None = None, keep=None) -> NormalEquations:
        """The normal equations at state ``x`` (n,): under the ``soft_l1`` loss of ``scale`` (IRLS weights), or
        plain least squares (None); ``keep`` (N,) bool: only those epochs count (None: all usable ones)."""
        x = np.asarray(x, float)
        n = len(x)
        A, g = np.zeros((n, n)), np.zeros(n)
        cost = 0.0

        def add(r, J, mask):
            nonlocal A, g, cost
            mask = np.broadcast_to(mask, r.shape)
            if scale is None:
                w = mask
                cost += 0.5 * float(np.sum(w * r * r))
            else:
                root = np.sqrt(1.0 + (r / scale) ** 2)
                w = mask / root
                cost += scale**2 * float(np.sum(mask * (root - 1.0)))
            A += J.T @ (J * w[:, None])
            g += J.T @ (w * r)

        add((x - self.x0) / self.prior_std, np.diag(1.0 / self.prior_std), 1.0)
        for model, epochs in self.chunks():
            r, J = self.residuals(x, model, epochs, jacobian=True)
            mask = 1.0 if keep is None else np.repeat(keep[epochs], r.shape[1]).astype(float)
            add(r.ravel(), J.reshape(-1, n), mask)
        return NormalEquations(A, g, cost)

    def outliers(self, x) -> np.ndarray:
        """Epochs (N,) bool with any residual beyond ``OUTLIER_SIGMA`` at state ``x``."""
        bad = np.zeros(len(self.status), bool)
        for model, epochs in self.chunks():
            bad[epochs] = np.abs(self.residuals(x, model, epochs)).max(axis=1) > OUTLIER_SIGMA
        return bad

    def minimise(self, x, scale: float | None = None, keep=None) -> Solution:
        """Minimise the cost (``normal_equations``' arguments) from ``x`` (n,) by Gauss-Newton steps, halved
        until they lower it (see the module's docstring for the convergence test)."""
        x = np.asarray(x, float)
        normal = self.normal_equations(x, scale, keep)
        largest = np.inf
        for iteration in range(MAX_ITERATIONS):
            dx, sigma = normal.step()
            largest = float(np.max(np.abs(dx) / sigma))
            if largest < STEP_TOL:
                return Solution(x, normal, iteration, True, largest)
            fraction = 1.0
            for _ in range(MAX_HALVINGS + 1):
                trial = self.normal_equations(x + fraction * dx, scale, keep)
                if trial.cost <= normal.cost + COST_RTOL * abs(normal.cost):
                    break
                fraction /= 2
            else:  # no fraction of the step lowers the cost
                return Solution(x, normal, iteration, largest < FLAT_STEP_TOL, largest)
            x, normal = x + fraction * dx, trial
        dx, sigma = normal.step()
        largest = float(np.max(np.abs(dx) / sigma))
        return Solution(x, normal, MAX_ITERATIONS, largest < STEP_TOL, largest)


def batch_problem(
    log: DriveLog,
    config: FilterConfig = FilterConfig(),
    init: Calibration | None = None,
    effects=(),
    prepared: PreparedLog | None = None,
) -> BatchProblem:
    """The batch objective of ``log``: its start (``prepare.prepare_run``, as the filter's, with the model
    ``config.measure`` names), the epochs it uses and the models that take them. ``prepared`` is ``prepare(log,
    config)`` when the caller has it already (None: made here)."""
    prep = prepare(log, config) if prepared is None else prepared
    setup = prepare_run(prep, config, init, effects, log.source, batch=True)
    prep, layout, model, status = setup.prep, setup.layout, setup.model, setup.base.copy()
    if setup.noise is not None:  # the noise of the log, as the filter starts from it
        model.set_noise(setup.noise)
    # Each epoch goes to the model that can use it: the model itself, or its fallback without attitude.
    takes = {Status.USED: model, Status.MISSING_ATTITUDE: model.fallback if model.needs_attitude else model}
    takes = {code: taker for code, taker in takes.items() if taker is not None}
    cand = np.zeros(len(status), bool)
    for code in takes:
        cand |= status == code
    if cand.sum() < 3 * layout.size:
        raise InputError(f"too few usable epochs ({int(cand.sum())}) for a batch calibration", log.source)
    prior_std = np.sqrt(np.diag(setup.P0))
    x_start = setup.x0.copy()
    att = np.flatnonzero(cand & prep.has_attitude)
    if init is None and len(att) >= 3 * 12 and not effects:
        x_start[layout.CORE] = _linear_start(prep, att, config, setup.x0, prior_std)
    prep = replace(prep, heading=None)  # the noise's structure is the start's alone
    idx = np.flatnonzero(cand)
    # one chunk for a nonlinear model (it may look at its neighbours), the magnitude gate's included
    chunk = max(len(idx), 1) if layout.nonlinear else CHUNK_EPOCHS
    problem = BatchProblem(prep, layout, setup.x0, setup.P0, setup.how, status, x_start, [], prior_std, chunk)
    off = _magnitude_gated(problem, idx, max(config.gate_nt, config.gate_sigma * np.sqrt(model.noise.along_var)))
    status[off] = Status.GATED_MAGNITUDE
    idx = idx[~off[idx]]
    for code, taker in takes.items():
        epochs = idx[setup.base[idx] == code]
        if len(epochs):
            problem.groups.append((taker, epochs))
    return problem


def _linear_start(prep: PreparedLog, att, config: FilterConfig, x0, prior_std) -> np.ndarray:
    """The core (12,) of the robust pass's start: a linear least-squares fit in the sensor frame
    (``bootstrap.vector_least_squares``) to at most ``prepare.FIT_EPOCHS`` of the usable epochs with attitude
    ``att`` (k,), spread evenly over the log (a start needs no more), under the prior ``x0``, ``prior_std`` (n,)."""
    core = StateLayout.CORE
    fit = att[fit_positions(len(att))]
    x, _, _ = vector_least_squares(
        prep.m[fit], prep.data.field_body[fit], config.sensor_noise_nt, x0[core], prior_std[core]
    )
    return x


def _magnitude_gated(problem: BatchProblem, idx, gate: float) -> np.ndarray:
    """Epochs (N,) bool among ``idx`` (k,) whose calibrated field at the robust pass's start is more than ``gate``
    nT off the reference magnitude (the magnitude gate with the starting estimate), in ``problem``'s chunks."""
    off = np.zeros(len(problem.status), bool)
    for i in range(0, len(idx), problem.chunk):
        epochs = idx[i : i + problem.chunk]
        c, _ = problem.calibrated(problem.x_start, epochs)
        off[epochs] = np.abs(np.linalg.norm(c, axis=1) - problem.prep.ref_mag[epochs]) > gate
    return off


@one_thread
@names_the_log
def solve_batch(
    log: DriveLog,
    config: FilterConfig = FilterConfig(),
    init: Calibration | None = None,
    effects=(),
    prepared: PreparedLog | None = None,
):
    """Batch calibration of ``log``: the online calibration's model solved by robust least squares.

    A robust pass (soft L1) finds the outlying epochs, then a least-squares fit without them gives the
    estimate; the outlying epochs get the status ``gated_innovation``.

    Parameters
    ----------
    log : DriveLog
        The drive or flight log.
    config : FilterConfig, optional
        The settings (noise, gates, measurement model).
    init : Calibration or None, optional
        An offline calibration to start from; else a bootstrap from the log.
    effects : sequence of Effect, optional
        Extra ``Effect`` blocks, estimated with ``R, b``.
    prepared : PreparedLog or None, optional
        ``prepare(log, config)`` when the caller has it already (a command that also compares the result with
        the vehicle's calibration): the log's reference field and attitude are then held once, not twice.

    Returns
    -------
    CalibrationRun
        The result, its states constant over the log.

    Raises
    ------
    InputError
        The log cannot be calibrated (as ``calibrate_log``); it names the log.

    Warns
    -----
    UserWarning
        A pass of the solver that does not converge says so, with the size of its last step.
    """
    started = _time.perf_counter()
    problem = batch_problem(log, config, init, effects, prepared)
    # Robust pass (soft L1) to find the outlying epochs, then least squares without them.
    robust = problem.minimise(problem.x_start, scale=LOSS_SCALE)
    fit = problem.minimise(robust.x, keep=~problem.outliers(robust.x))
    for name, solution in (("robust pass", robust), ("least-squares fit", fit)):
        if not solution.converged:
            warnings.warn(
                f"{log.source}: the batch solver's {name} did not converge: its last step after "
                f"{solution.iterations} iterations was {solution.largest_step:.2g} standard deviations "
                f"(converged below {STEP_TOL:g}); the estimate may be off by about that much",
                stacklevel=3,
            )
    outlier = problem.outliers(fit.x)
    status = problem.status
    status[outlier] = Status.GATED_INNOVATION
    P = fit.normal.covariance()
    used = np.zeros(len(status), bool)
    for _, epochs in problem.groups:
        used[epochs] = True
    used &= ~outlier
    information = fit.normal.A - np.linalg.inv(problem.P0)
    n = len(status)
    trace = RunTrace(
        fit.x[None],
        np.sqrt(np.diag(P))[None],
        status,
        used,
        np.full(n, np.nan, np.float32),
        fit.x,
        P,
        information,
        problem.how,
        _time.perf_counter() - started,
        method="batch",
        stops=np.array([n]),
    )
    prep, layout, x0, P0 = problem.prep, problem.layout, problem.x0, problem.P0
    del problem  # the solver's epoch indices are not kept while the per-epoch table is built
    return build_run(log, prep, config, layout, x0, P0, trace)
