"""The whole-log estimate a post-processing run writes, in the model family the log determines.

A filter's last state is the estimate *at the end* of the log, shaped by its random walk, its gating history
and the weights of its learned noise. A post-processing run writes instead the constant parameters that fit
the epochs the filter used best, the exact least-squares optimum of the residual magkf reports:

* an epoch with attitude: the NED residual ``C_nb c - B_ref`` of the calibrated field
  ``c = R^-1 (m - b - e)``, all three components at one weight. Its norm equals that of ``c - B_body``, and is
  computed as ``W (m - R B_body - b - e)`` with ``W`` the inverse of the filter's final ``R``, held: the same to
  first order in ``R``'s change from it (a few standard deviations), and a residual in the reading's own units,
  so that a larger ``R`` cannot shrink the noise of ``c`` (with a field anomaly that trades with ``R``'s scale, a
  fit of ``c`` itself ran off to ``R`` seven times too large, its residuals seven times smaller than the noise);
* an epoch without attitude (or the magnitude model): the total-field residual ``|c| - |B_ref|``.

It is solved by Gauss-Newton in the family's free directions ``theta`` (``magkf.families``:
``x = anchor + T theta``) with the analytic Jacobian ``dc/dx = -R^-1 dm/dx`` (the core's ``[I kron c^T, I]``
at ``c``, the effects' own), steps halved until the cost falls, under the run's prior (the filter's start and its
covariance), weighed as one of the data's epochs (``_Problem.weigh_prior``): the data outweigh it wherever they
determine a direction, and where they do not (an effect that trades with the core, a constant field anomaly
against R's scale) it holds the estimate near the start.
The log is gone through ``CHUNK`` epochs at a time (one chunk with a nonlinear effect, which looks at
its neighbours); each pass also folds the sums of ``FOLDS`` contiguous stretches of the used epochs and of
batches of ``batch_s`` seconds.

**Which family** (``model="auto"``): from the poorest up, a family is taken over the one chosen so far when

1. the log *determines* it: the standard deviation of each of its core parameters, from the data's
   information alone and the residuals' variance inflated by their correlation, leaves a field error below
   ``DETERMINED_FRACTION`` of the log's field (``R`` entries times the field, ``b`` as it is;
   ``OFFSETS_FRACTION`` for the offsets alone, below which the log is refused); and
2. it predicts *held-out stretches* of the same log at least as well: fitted to all stretches but one, its
   residual on the one left out, summed over the ``FOLDS`` stretches, is no larger (the quadratic model of the
   objective at the full fit gives every such fit in one pass).

**Standard deviations** account for the residuals' correlation in time: the covariance is the sandwich
``H^-1 M H^-1`` with ``M`` the covariance of the gradient in the noise the filter learned (each of its
components a Gauss-Markov process of the correlation time the filter measured; ``_Problem.model_meat``), or,
without a learned noise, the scatter of the gradient's contributions of batches of ``batch_s`` seconds (batch
means), so a residual correlated over seconds is not counted as independent epochs. Held parameters keep the
prior's standard deviation, and what it does to the free ones is added (a consider covariance).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..calibration import PARAMETER_NAMES
from ..conventions import inverse3
from ..effects.core import core_jacobian
from ..errors import InputError
from ..families import FAMILIES, ModelFamily, family
from ..plausibility import RESIDUAL_REFUSED
from .results import FILTER_STATE
from .state import CORE_SIZE, StateLayout

__all__ = [
    "WholeLogFit",
    "fit_whole_log",
    "fit_whole_log_parts",
    "wandering",
    "filter_estimate",
    "FOLDS",
    "DETERMINED_FRACTION",
    "PRIOR_R_STD",
    "PRIOR_B_STD",
]

#: The weak prior of the whole-log fit: standard deviation of each element of R and each offset (nT).
PRIOR_R_STD = 0.1
PRIOR_B_STD = 5000.0
#: Contiguous stretches of the used epochs for the held-out check.
FOLDS = 5
#: A family is determined when its parameters' standard deviations leave less than this share of the field
#: (250 nT at 50 000 nT, about 0.3 deg of heading) ...
DETERMINED_FRACTION = 0.005
#: ... except the offsets, the least a calibration gives, which are taken up to this share (1 000 nT at 50 000 nT,
#: about 1.1 deg of heading: still far better than a vehicle's offsets that are off by thousands of nT).
OFFSETS_FRACTION = 0.02
#: An R column is estimated only where its body field component's standard deviation over the used epochs is at
#: least this share of the field (about 6 degrees of rotation): the regression of a reading on a component that
#: hardly varies cannot tell its scale from the offset, and a few tens of nT of unmodelled field or attitude
#: error then move it (on a straight, level flight with the body field varying by 1 to 2 % of the field, the
#: scale family's R was 5 to 6 of its standard deviations off the truth).
EXCITATION_FRACTION = 0.1
#: Epochs evaluated at once.
CHUNK = 16384
#: Batches of the covariance last this many correlation times, and there are at least this many per parameter.
BATCH_CORRELATIONS = 5.0
BATCHES_PER_PARAMETER = 4
#: Gauss-Newton stops when every step is below this many standard deviations, or after MAX_ITERATIONS.
STEP_TOL = 1e-6
MAX_ITERATIONS = 30
MAX_HALVINGS = 12


@dataclass(frozen=True)
class WholeLogFit:
    """The whole-log estimate: state ``x`` (n,) and covariance ``P`` (n, n), the ``family`` chosen, the
    ``model`` record a calibration file keeps (``family``, ``estimated``, ``held``, ``held_at``, ``text``,
    ``candidates`` and, where something is held, ``std_given_held``: the free parameters' standard deviations
    were the held values exact), the residual RMS (nT) of the used epochs with attitude (NED norm) and without
    (magnitude), the number of epochs and the batch length ``batch_s`` of the covariance."""

    x: np.ndarray
    P: np.ndarray
    family: str
    model: dict
    residual_rms_nt: float
    magnitude_rms_nt: float
    n_epochs: int
    batch_s: float


@dataclass
class _Sums:
    """The normal equations of the data at one state: ``A`` (n, n), ``g`` (n,), the sum of squares ``ss``, and
    the same per fold (``A_k`` (F, n, n), ``g_k`` (F, n), ``ss_k`` (F,)), each batch's gradient ``scores``
    (K, n; None where not summed: ``_Problem.with_scores``), and the vector and magnitude sums of squares and
    counts."""

    A: np.ndarray
    g: np.ndarray
    ss: float
    A_k: np.ndarray
    g_k: np.ndarray
    ss_k: np.ndarray
    scores: np.ndarray | None
    vec: list
    mag: list

    @property
    def count(self) -> int:
        """The residual components summed: three per vector epoch, one per magnitude epoch."""
        return self.vec[0] * 3 + self.mag[0]

    @classmethod
    def empty(cls, n: int, batches: int | None) -> _Sums:
        """Zero sums over ``n`` parameters and ``batches`` batches (None: no batch scores)."""
        return cls(
            np.zeros((n, n)),
            np.zeros(n),
            0.0,
            np.zeros((FOLDS, n, n)),
            np.zeros((FOLDS, n)),
            np.zeros(FOLDS),
            None if batches is None else np.zeros((batches, n)),
            [0, 0.0],
            [0, 0.0],
        )

    def add(self, r, J, fold, batch) -> None:
        """Add epochs' residuals ``r`` (k, q) nT with their Jacobian ``J`` (k, q, n), folds and batches (k,), both
        non-decreasing (the epochs in time order): each fold's and batch's sums over its run of epochs."""
        n = J.shape[2]
        g_e = np.einsum("kqi,kq->ki", J, r)
        ss_e = np.einsum("kq,kq->k", r, r)
        for f in np.unique(fold):
            own = fold == f
            Jf = J[own].reshape(-1, n)
            A_f = Jf.T @ Jf
            self.A_k[f] += A_f
            self.A += A_f
            self.g_k[f] += g_e[own].sum(axis=0)
            self.ss_k[f] += float(ss_e[own].sum())
        self.g += g_e.sum(axis=0)
        self.ss += float(ss_e.sum())
        if self.scores is not None:
            starts = np.flatnonzero(np.diff(batch, prepend=-1))
            self.scores[batch[starts]] += np.add.reduceat(g_e, starts, axis=0)
        acc = self.vec if r.shape[1] == 3 else self.mag
        acc[0] += len(r)
        acc[1] += float(ss_e.sum())


class _Problem:
    """The whole-log objective of the used epochs of a log given in parts: ``parts()`` yields ``(prep, used)``, a
    ``PreparedLog`` and its epochs used (k,) bool, in time order (a whole log is one part). A first pass over
    the parts counts the used epochs and measures the field, the motion and the time span."""

    def __init__(self, parts, layout: StateLayout, vector: bool, correlation_s: float, prior_x, prior_std):
        self.parts, self.layout, self.vector = parts, layout, vector
        self.W = np.eye(3)  # the whitening of the vector residuals: the inverse of the fitted R (``_fit_family``)
        self.prior_x = np.asarray(prior_x, float)
        cov = np.asarray(prior_std, float)
        # the prior's information (n, n): a covariance's inverse, or the reciprocal variances of standard deviations
        self.information = np.linalg.inv(cov) if cov.ndim == 2 else np.diag(1.0 / cov**2)
        self.omega = self.information
        n_used, times, field, moments, n_moments, step = 0, [], 0.0, np.zeros((2, 3)), 0, None
        for prep, used in parts():
            idx = np.flatnonzero(used)
            if not len(idx):
                continue
            n_used += len(idx)
            times += [prep.time[idx[0]], prep.time[idx[-1]]]
            if step is None and len(idx) > 1:
                step = float(np.median(np.diff(prep.time[idx])))
            for a in range(0, len(idx), CHUNK):  # summed a chunk at a time: no copy of the used epochs' fields
                piece = idx[a : a + CHUNK]
                field += float(prep.ref_mag[piece].sum())
                values = prep.data.field_body[piece[prep.has_attitude[piece]]] if vector else prep.m[piece]
                moments += [values.sum(axis=0), (values**2).sum(axis=0)]
                n_moments += len(values)
        self.n_used = n_used
        self.t0 = times[0] if times else 0.0
        span = (times[-1] - times[0]) if times else 1.0
        self.field_nt = field / max(n_used, 1)
        count = max(n_moments, 1)
        # the standard deviation of each component over the used epochs: how much the motion turned it
        self.spread = np.sqrt(np.maximum(moments[1] / count - (moments[0] / count) ** 2, 0.0))
        self.span_s, self.step_s = span, step or 1.0
        self.batch_s = _batch_length(span, self.step_s, correlation_s, layout.size)
        self.n_batches = int(np.floor(span / self.batch_s)) + 1

    def chunks(self):
        """``(prep, vector, epochs, fold, batch)`` of every chunk of used epochs: their part, whether they give the
        vector residual, their indices (k,) into the part, and their folds and batches (k,)."""
        seen = 0
        for prep, used in self.parts():
            idx = np.flatnonzero(used)
            with_att = prep.has_attitude[idx] if self.vector else np.zeros(len(idx), bool)
            chunk = max(len(idx), 1) if self.layout.nonlinear else CHUNK
            for vector in (True, False):
                pick = np.flatnonzero(with_att == vector)
                for i in range(0, len(pick), chunk):
                    k = pick[i : i + chunk]  # the folds and batches of a chunk's epochs, not of the part's
                    fold = (FOLDS * (seen + k)) // max(self.n_used, 1)
                    batch = np.floor((prep.time[idx[k]] - self.t0) / self.batch_s).astype(np.int64)
                    yield prep, vector, idx[k], fold, np.minimum(batch, self.n_batches - 1)
            seen += len(idx)

    def residuals(self, x, prep, vector: bool, epochs) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (k, q) nT and Jacobian (k, q, n) of the ``epochs`` (k,) of ``prep`` at ``x`` (n,): vector
        residuals ``W (m - R B_body - b - e)`` (q = 3) or magnitude residuals ``|c| - |B_ref|`` (q = 1)."""
        layout = self.layout
        data = prep.data.take(epochs) if layout.has_extra else None
        terms = 0.0 if data is None else layout.effect_terms(x, data)
        if vector:
            B = prep.data.field_body[epochs]
            R, b = layout.R_b(x)
            r = (prep.m[epochs] - B @ R.T - b - terms) @ self.W.T
            return r, -(self.W @ self._model_jacobian(x, data, B))
        c = layout.calibrated(x, prep.m[epochs], terms)
        dcdx = -(inverse3(layout.R(x)) @ self._model_jacobian(x, data, c))
        norm = np.linalg.norm(c, axis=1)
        r = (norm - prep.ref_mag[epochs])[:, None]
        return r, np.einsum("ki,kin->kn", c / norm[:, None], dcdx)[:, None, :]

    def _model_jacobian(self, x, data, field) -> np.ndarray:
        """``dm/dx`` (k, 3, n) of the reading ``R field + b + e`` at ``x``: the core's at the body ``field`` (k, 3)
        nT, the effects' own at their ``data`` (None: no effects; missing inputs count as 0)."""
        if data is None:
            return core_jacobian(field)
        dmdx = np.nan_to_num(self.layout.jacobian(x, data))
        dmdx[:, :, self.layout.CORE] = core_jacobian(field)
        return dmdx

    def sums(self, x, scores: bool = False) -> _Sums:
        """The data's normal equations and sums (``_Sums``) at ``x`` (n,), one pass over the parts; with ``scores``,
        each batch's gradient too (12 parameters' worth, 8 bytes each, a batch of a few epochs: about 19 bytes an
        epoch at 100 Hz, twice while a step is tried, which the fit's own passes do without)."""
        s = _Sums.empty(len(x), self.n_batches if scores else None)
        for prep, vector, epochs, fold, batch in self.chunks():
            r, J = self.residuals(x, prep, vector, epochs)
            s.add(r, J, fold, batch)
        return s

    def with_scores(self, x, s: _Sums) -> _Sums:
        """``s``, the sums at ``x``, with its batch scores: made again with them by one more pass where it has none
        (the same chunks in the same order; seen equal to the bit but for one figure's 1.8e-16 with a fixed noise)."""
        return s if s.scores is not None else self.sums(x, scores=True)

    def model_meat(self, x, noise, field_aligned: bool) -> np.ndarray:
        """The covariance (n, n) of the gradient ``sum J^T r`` at ``x`` were the residuals' noise the filter's
        learned one, ``noise`` (``NoiseLevels``), each of its three components in the field's frame (along the
        field, along the heading axis, across both) a Gauss-Markov process of the correlation time its
        inflation implies (``tau = inflation * step_s / 2``: the sum of an exponential correlation over epochs
        ``step_s`` apart, the log's median time step, is ``2 tau / step_s``). Each component's gradient
        contributions are summed over short batches (``tau / 8``) and the batches' cross products weighted by
        ``exp(-lag / tau)`` out to ``5 tau``; a component correlated over less than two epochs counts as
        independent epochs, each inflated by its inflation."""
        from .measurements import sensor_frame, vector_noise

        R, step_s = self.layout.R(x), self.step_s
        n = len(x)
        taus = [0.5 * max(f, 1.0) * step_s for f in noise.inflations]
        widths = [max(tau / 8.0, step_s) for tau in taus]
        counts = [int(np.floor((self.span_s) / w)) + 1 for w in widths]
        # a batch sum a width, for the components kernel-summed only (a log's length of them each)
        batches = [np.zeros((k, n)) if tau >= 2.0 * step_s else None for k, tau in zip(counts, taus)]
        white = np.zeros((n, n))
        for prep, vector, epochs, _, _ in self.chunks():
            _, J = self.residuals(x, prep, vector, epochs)
            t = prep.time[epochs] - self.t0
            if vector:
                B = prep.data.field_body[epochs]
                heading = None if prep.heading is None else prep.heading[epochs]
                F = sensor_frame(B, heading, R)  # (k, 3, 3): rows along, h, v
                cov = vector_noise(B, R, noise, field_aligned, heading)
                sd = np.sqrt(np.abs(np.sum((F @ cov) * F, axis=2)))  # (k, 3): each component's standard deviation
                # (k, 3, n): the gradient's contribution per unit noise in each component, J^T W F^T
                G = np.swapaxes(np.swapaxes(J, 1, 2) @ (self.W @ np.swapaxes(F, 1, 2)), 1, 2) * sd[:, :, None]
            else:
                sd = np.sqrt(noise.sensor_nt**2 + noise.reference_nt**2)
                G = np.zeros((len(epochs), 3, n))
                G[:, 0] = J[:, 0] * sd
            for c in range(3):
                if taus[c] < 2.0 * step_s:  # correlated over less than two epochs: inflated, not kernel-summed
                    white += max(noise.inflations[c], 1.0) * (G[:, c].T @ G[:, c])
                else:
                    index = np.minimum((t / widths[c]).astype(np.int64), counts[c] - 1)  # non-decreasing in time
                    starts = np.flatnonzero(np.diff(index, prepend=-1))
                    batches[c][index[starts]] += np.add.reduceat(G[:, c], starts, axis=0)
        meat = white
        for c in range(3):
            if taus[c] < 2.0 * step_s:
                continue
            Gc = batches[c]
            meat = meat + Gc.T @ Gc
            for lag in range(1, min(int(np.ceil(5.0 * taus[c] / widths[c])), len(Gc) - 1) + 1):
                cross = Gc[:-lag].T @ Gc[lag:]
                meat = meat + np.exp(-lag * widths[c] / taus[c]) * (cross + cross.T)
        return meat

    def cost(self, x, s: _Sums) -> float:
        d = x - self.prior_x
        return 0.5 * (s.ss + float(d @ self.omega @ d))

    def weigh_prior(self, variance_nt2: float) -> None:
        """Put the prior in the residuals' units: its information (per parameter unit squared) times the variance of
        a residual component ``variance_nt2`` (nT^2), so that the cost ``(ss + sigma^2 d^T Omega d) / 2`` weighs
        the prior as one of the data's independent epochs would. Weighed first by the filter's noise, then by
        the mean square residual of the first fit. (Weighed also by the residuals' correlation, as
        the filter weighs it, it pulled a coloured-noise log's estimate away from the optimum by 0.1 % of its
        held-out residual; measured at the filter's last state instead of taken from its learned noise, a
        wandered last state made the prior outweigh the data.)"""
        self.omega = self.information * float(variance_nt2)

    def minimise(self, x, T) -> tuple[np.ndarray, _Sums]:
        """Gauss-Newton from ``x`` (n,) in the directions ``T`` (n, k), steps halved until the cost falls."""
        s = self.sums(x)
        for _ in range(MAX_ITERATIONS):
            H, grad = self.normal(x, s, T)
            step, sigma = _solve(H, grad)
            if np.max(np.abs(step) / sigma) < STEP_TOL:
                break
            cost, fraction = self.cost(x, s), 1.0
            for _ in range(MAX_HALVINGS):
                trial = x + fraction * (T @ step)
                s_trial = self.sums(trial)
                if self.cost(trial, s_trial) <= cost * (1.0 + 1e-12):
                    break
                fraction /= 2.0
            else:
                break
            x, s = trial, s_trial
        return x, s

    def normal(self, x, s: _Sums, T) -> tuple[np.ndarray, np.ndarray]:
        """The normal equations ``H`` (k, k) and gradient (k,) in the directions ``T`` (n, k), prior included."""
        H = T.T @ (s.A + self.omega) @ T
        grad = T.T @ (s.g + self.omega @ (x - self.prior_x))
        return H, grad


def _solve(H, grad) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton step ``-H^-1 grad`` (k,) and ``sqrt(diag(H^-1))`` (k,), scaled for conditioning."""
    D = 1.0 / np.sqrt(np.diag(H))
    Hi = np.linalg.inv(H * D[:, None] * D[None, :]) * D[:, None] * D[None, :]
    return -Hi @ grad, np.sqrt(np.abs(np.diag(Hi)))


def fit_whole_log(prep, layout: StateLayout, x_start, used, **options) -> WholeLogFit:
    """The whole-log estimate over the ``used`` epochs (N,) bool of the prepared log ``prep`` (its effects' data at
    the run's initial ``R``), from ``x_start`` (n,), the filter's last state: ``fit_whole_log_parts`` of the log
    as one part, with its ``options``."""
    used = np.asarray(used, bool)
    return fit_whole_log_parts(lambda: iter([(prep, used)]), layout, x_start, **options)


def fit_whole_log_parts(
    parts,
    layout: StateLayout,
    x_start,
    *,
    vector: bool = True,
    model: str = "auto",
    held_at=None,
    held_how: str = "the identity (no calibration of the vehicle, none given)",
    correlation_s: float = 0.0,
    held_std=(0.02, 300.0),
    prior=None,
    noise=None,
    prior_noise=None,
    source: str | None = None,
    held_effects=None,
) -> WholeLogFit:
    """The whole-log estimate in the family ``model`` (see the module) of a log given in parts.

    Parameters
    ----------
    parts : callable
        ``parts()`` yields ``(prep, used)`` pairs in time order, each a ``PreparedLog`` (its effects' data at the
        run's initial ``R``) and its used epochs (k,) bool; it is called once per pass (a chunked log is read
        again).
    layout : StateLayout
        The state's blocks.
    x_start : array_like
        (n,) where to start (the filter's last state).
    vector : bool
        Whether epochs with attitude give the vector residual (False: the magnitude model).
    model : str
        ``auto`` or one of ``magkf.families.FAMILIES``.
    held_at : array_like or None
        (12,) the core the held directions take (None: the identity and zero offsets).
    held_how : str
        Where ``held_at`` comes from, in words.
    correlation_s : float
        The residuals' correlation time learned by the filter, s (the batch length of the covariance).
    held_std : tuple of float or array_like
        Standard deviations of the held values: ``(R element, offset nT)``, or (12,) one per core parameter (the
        held calibration's own): not estimated here, they widen the free parameters' (consider covariance).
    prior : tuple of array_like or None
        ``(mean (n,), covariance (n, n) or standard deviations (n,))`` of the prior (the run's start); None: a
        weak prior (``PRIOR_R_STD``, ``PRIOR_B_STD`` about ``held_at``, the effects' own).
    noise : tuple or None
        ``(NoiseLevels, field_aligned)`` the filter's learned noise and whether its vector noise is aligned with
        the field, which the covariance is computed with (see ``_covariance``; None: batch means).
    prior_noise : NoiseLevels or None
        The noise the filter ran with, which the prior is weighed by when ``noise`` is None
        (``_Problem.weigh_prior``).
    source : str or None
        The log's name, for errors.
    held_effects : magkf.online.determined.HeldDirections or None
        The directions of the effects' parameters the log does not determine (the run's start found them), held
        at the prior mean with the prior's variance (None: every effect parameter free).

    Returns
    -------
    WholeLogFit

    Raises
    ------
    InputError
        Too few used epochs, or (``auto``) a log that does not determine even the offsets.
    """
    n = layout.size
    core_ref = np.concatenate([np.eye(3).ravel(), np.zeros(3)]) if held_at is None else np.asarray(held_at, float)
    x_start = np.asarray(x_start, float).reshape(n)
    prior_x, prior_std = _prior(layout, core_ref) if prior is None else (np.asarray(p, float) for p in prior)
    problem = _Problem(parts, layout, vector, correlation_s, prior_x, prior_std)
    if problem.n_used < 3 * n:
        raise InputError(f"too few used epochs ({problem.n_used}) for a whole-log estimate of {n} parameters", source)
    problem.weigh_prior(_component_variance(prior_noise, problem.field_nt, config_noise=noise))
    field_nt = problem.field_nt
    excited = problem.spread >= EXCITATION_FRACTION * field_nt
    families, x_start = _families(vector, excited, held_effects, x_start, prior_x)
    if model != "auto" and model not in families:
        raise InputError(
            f"--model {model}: the magnitude alone cannot see the rotation between sensor and body; measure the "
            "vector too (--measure both, with attitude) or take soft-iron",
            source,
        )
    # The richest family the log's motion allows first (from the filter's state): the others are judged at its fit.
    first = list(families)[-1] if model == "auto" else model
    x, s = _fit_family(problem, families[first], x_start, core_ref)
    # the prior weighed again by the residuals of this fit (the filter's last noise may be a passing disturbance's)
    # and its core centred at the fit: it then holds only what the data leave free, where this fit put it
    problem.weigh_prior(s.ss / max(s.count, 1))
    problem.prior_x[:CORE_SIZE] = x[:CORE_SIZE]
    x, s = problem.minimise(x, families[first].state_basis(n))
    s = problem.with_scores(x, s)  # the residuals' correlation by batch means (``_correlation_factor``)
    candidates = _candidates(problem, x, s, core_ref, field_nt, families)
    chosen = first
    if model == "auto":
        if not candidates[FAMILIES[0]]["determined"]:
            raise InputError(_undetermined(candidates[FAMILIES[0]], s, field_nt), source)
        chosen = _choose(candidates, FAMILIES[0], families)
        if chosen != first:
            x, s = _fit_family(problem, families[chosen], x, core_ref)
    fam = families[chosen]
    if noise is None:  # the batch-means sandwich
        s = problem.with_scores(x, s)
    P, given = _covariance(problem, x, s, fam.state_basis(n), fam, held_std, noise, held_effects)
    record = _record(fam, model, held_how, core_ref, candidates, chosen)
    record |= _notes(fam, given, float(np.sqrt(s.ss / max(s.count, 1))), field_nt, held_effects)
    return WholeLogFit(
        x=x,
        P=P,
        family=fam.name,
        model=record,
        residual_rms_nt=float(np.sqrt(s.vec[1] / s.vec[0])) if s.vec[0] else float("nan"),
        magnitude_rms_nt=float(np.sqrt(s.mag[1] / s.mag[0])) if s.mag[0] else float("nan"),
        n_epochs=problem.n_used,
        batch_s=problem.batch_s,
    )


def _families(vector: bool, excited, held_effects, x_start, prior_x) -> tuple[dict, np.ndarray]:
    """``(families, x_start)``: the families the fit may take (name -> ``ModelFamily``, restricted to the body
    field's ``excited`` (3,) components), with the effects' undetermined directions (``held_effects``) held at the
    prior mean ``prior_x`` (n,) in every family and in the start ``x_start`` (n,)."""
    families = {name: family(name).restricted(excited) for name in _possible(vector)}
    if held_effects is None:
        return families, x_start
    x_start = x_start.copy()
    x_start[CORE_SIZE:] = held_effects.hold(x_start[CORE_SIZE:], prior_x[CORE_SIZE:])
    return {name: replace(f, effects=held_effects.free) for name, f in families.items()}, x_start


def _notes(fam: ModelFamily, given, rms: float, field_nt: float, held_effects) -> dict:
    """What the ``model`` record adds about the estimate: ``misfit`` where its residual RMS ``rms`` (nT per
    component) exceeds ``MISFIT_FRACTION`` of the field (the plausibility rule refuses it before anything is
    written), ``effects_held``, and ``std_given_held`` (the free core parameters' standard deviations ``given``
    (12,) were the held values exact) for a family that holds some."""
    notes = {}
    if rms > MISFIT_FRACTION * field_nt:
        notes["misfit"] = f"no calibration fits: {_misfit_words(rms, field_nt)}"
    if held_effects is not None:
        notes["effects_held"] = held_effects.text()
    if fam.name != "full" or fam.size < CORE_SIZE:
        free = np.abs(fam.basis).sum(axis=1) > 0
        notes["std_given_held"] = {n: float(v) for n, v, f in zip(PARAMETER_NAMES, given, free) if f}
    return notes


def wandering(layout: StateLayout) -> list[str]:
    """The labels of the effects after the core whose parameters follow a random walk (``bias_drift``): a constant
    whole-log estimate does not describe them."""
    return [effect.label for effect, _ in layout.blocks() if np.any(effect.random_walk() > 0)]


def filter_estimate(x, P, labels) -> WholeLogFit:
    """The record of a run whose calibration is the filter's state ``x`` (n,), ``P`` (n, n) at the end of the log,
    because the effects ``labels`` wander."""
    text = (
        f"{', '.join(labels)} wanders in time: the calibration is the filter's estimate at the end of the log (its "
        "path is in the per-epoch states), not a constant whole-log estimate"
    )
    record = {"family": "full", "asked": "auto", "estimated": FILTER_STATE, "held": "nothing", "text": text}
    nan = float("nan")
    return WholeLogFit(np.asarray(x, float), np.asarray(P, float), "full", record, nan, nan, 0, nan)


def _prior(layout: StateLayout, core_ref) -> tuple[np.ndarray, np.ndarray]:
    """The weak prior ``(mean (n,), std (n,))``: the core at ``core_ref`` (12,) with ``PRIOR_R_STD``/``PRIOR_B_STD``,
    the effects at their own priors."""
    x, P = layout.prior()
    std = np.sqrt(np.diag(P))
    x[:CORE_SIZE] = core_ref
    std[:CORE_SIZE] = np.concatenate([np.full(9, PRIOR_R_STD), np.full(3, PRIOR_B_STD)])
    return x, std


def _batch_length(span: float, step: float, correlation_s: float, n: int) -> float:
    """Batches of ``BATCH_CORRELATIONS`` correlation times, at least two time steps ``step`` s, and short enough
    for ``BATCHES_PER_PARAMETER`` batches per parameter over the used epochs' ``span`` s."""
    wanted = max(BATCH_CORRELATIONS * correlation_s, 2.0 * step)
    return max(min(wanted, span / (BATCHES_PER_PARAMETER * n)), step)


#: Residuals beyond this share of the field mean the readings do not follow the reference through the attitude:
#: the rule the offline fits follow (``magkf.plausibility.RESIDUAL_REFUSED``).
MISFIT_FRACTION = RESIDUAL_REFUSED


def _undetermined(offsets: dict, s: _Sums, field_nt: float) -> str:
    """Why not even the offsets are determined (``offsets`` the family's candidate record), in words."""
    rms = float(np.sqrt(s.ss / max(s.count, 1)))
    text = (
        f"the log does not determine even the offsets (their standard deviation is {offsets['worst_std_nt']:.3g} nT, "
        f"over {100 * OFFSETS_FRACTION:g} % of the field)"
    )
    if rms > MISFIT_FRACTION * field_nt:
        return f"{text}: {_misfit_words(rms, field_nt)}"
    return f"{text}: the data do not determine R or b; record a longer flight, or give a calibration (--init)"


def _misfit_words(rms: float, field_nt: float) -> str:
    """That residuals of ``rms`` nT against a field of ``field_nt`` nT are no calibration, and what may cause them."""
    return (
        f"the readings do not follow the reference field through the logged attitude (residuals of {rms:.3g} nT, "
        f"{100 * rms / field_nt:.0f} % of the field): a wrong attitude or magnetometer unit (--mag-unit), a heading "
        "that is not the compass's, a disturbing field (motors, currents), a sensor that does not follow the field, "
        "or data that do not determine R (the magnitude alone, --measure magnitude, needs no attitude)"
    )


def _possible(vector: bool) -> tuple:
    """The families a log can determine at all: the magnitude alone cannot see a rotation (no ``full``)."""
    return FAMILIES if vector else FAMILIES[:-1]


#: Fits of a family, each whitened with the ``R`` of the one before (``_fit_family``).
WHITENINGS = 3


def _fit_family(problem: _Problem, fam: ModelFamily, x, core_ref) -> tuple[np.ndarray, _Sums]:
    """The least-squares fit in family ``fam``, from ``x`` (n,) brought into it (``ModelFamily.project``), the
    vector residuals whitened with the inverse of the ``R`` fitted (``_Problem.W``): first at the start's, then
    again at each fit's, ``WHITENINGS`` times (a start from a filter whose ``R`` wandered is far from the fit's;
    the whitening's error is of second order in the change, so a few rounds reach the calibrated field's own
    optimum)."""
    x = np.array(x, float)
    x[:CORE_SIZE] = fam.project(x[:CORE_SIZE], core_ref)
    T = fam.state_basis(len(x))
    for _ in range(WHITENINGS):
        problem.W = inverse3(problem.layout.R(x))
        x, s = problem.minimise(x, T)
    return x, s


def _candidates(problem: _Problem, x_full, s: _Sums, core_ref, field_nt: float, families: dict) -> dict:
    """For each of ``families`` (name -> ``ModelFamily``): its worst standard deviation as a field error (nT),
    whether that is determined, its held-out residual RMS (nT), all from the quadratic model of the objective at
    ``x_full`` (n,) (the fit so far, whose sums are ``s``), and the number of core parameters it frees."""
    n = len(x_full)
    dof = max(s.count - n, 1)
    variance = s.ss / dof * _correlation_factor(problem, x_full, s)
    scale = np.concatenate([np.full(9, field_nt), np.ones(3)])
    out = {}
    for name, fam in families.items():
        T = fam.state_basis(n)
        anchor = x_full.copy()
        anchor[:CORE_SIZE] = fam.anchor(core_ref)
        worst = _worst_std(fam.basis, s.A[:CORE_SIZE, :CORE_SIZE], variance, scale)
        out[name] = {
            "worst_std_nt": worst,
            "determined": bool(worst <= (OFFSETS_FRACTION if name == FAMILIES[0] else DETERMINED_FRACTION) * field_nt),
            "held_out_rms_nt": _held_out(problem, x_full, s, T, anchor),
            "free": fam.size,
        }
    return out


def _worst_std(basis, A_core, variance: float, scale) -> float:
    """The largest standard deviation (nT of field error: ``R`` elements times ``scale``, offsets as they are) of
    the core parameters free in ``basis`` (12, k), from the information ``A_core`` (12, 12) of the core with the
    effects held at their fit, and the residuals' ``variance`` (nT^2): what the data tell of R and b themselves.
    An effect that trades with the core (a constant field anomaly with R's scale) is bounded by its prior in
    the fit; it does not make the family undetermined. Infinite where a direction received no information."""
    info = basis.T @ A_core @ basis
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    normal = info / np.outer(d, d)
    if np.linalg.eigvalsh(normal).min() < 1e-12:
        return float("inf")
    cov = variance * np.linalg.inv(normal) / np.outer(d, d)
    core_var = np.einsum("ik,kl,il->i", basis, cov, basis)
    free = np.abs(basis).sum(axis=1) > 0
    return float(np.sqrt(np.max(np.abs(core_var[free]) * scale[free] ** 2)))


def _correlation_factor(problem: _Problem, x, s: _Sums) -> float:
    """How many times the variance of the gradient's batch contributions exceeds that of independent epochs
    (at least 1): the residuals' correlation, by batch means, at the full fit ``x``."""
    n = len(x)
    Hi = np.linalg.pinv(s.A + problem.omega)
    white = Hi * (s.ss / max(s.count - n, 1))
    scores = s.scores - s.scores.mean(axis=0)
    hac = Hi @ (scores.T @ scores) @ Hi
    ratio = np.diag(hac) / np.maximum(np.diag(white), 1e-300)
    ratio = ratio[np.isfinite(ratio) & (np.diag(white) > 0)]
    return float(max(np.median(ratio), 1.0)) if len(ratio) else 1.0


def _held_out(problem: _Problem, x_full, s: _Sums, T, anchor) -> float:
    """RMS residual (nT per component) of each fold predicted by the family (directions ``T``, held parts at
    ``anchor``) fitted to the other folds, summed over the folds, in the quadratic model at ``x_full``."""
    d = anchor - x_full
    d[problem.layout.CORE] = d[problem.layout.CORE] - T[:CORE_SIZE] @ (T[:CORE_SIZE].T @ d[problem.layout.CORE])
    omega = problem.omega
    prior_grad = omega @ (x_full - problem.prior_x)
    total, count = 0.0, 0
    for k in range(FOLDS):
        A, g = s.A - s.A_k[k], s.g - s.g_k[k]
        H = T.T @ (A + omega) @ T
        rhs = -T.T @ (g + prior_grad + (A + omega) @ d)
        try:
            theta = np.linalg.solve(H, rhs)
        except np.linalg.LinAlgError:
            return float("inf")
        delta = d + T @ theta
        total += s.ss_k[k] + 2.0 * s.g_k[k] @ delta + delta @ s.A_k[k] @ delta
    count = s.count
    return float(np.sqrt(max(total, 0.0) / max(count, 1)))


def _choose(candidates: dict, chosen: str, families: dict) -> str:
    """The richest family above ``chosen`` that frees more parameters, is determined and predicts the held-out
    stretches no worse than the family chosen so far, or ``chosen``."""
    for name in list(families)[list(families).index(chosen) + 1 :]:
        c = candidates[name]
        adds = c["free"] > candidates[chosen]["free"]
        if adds and c["determined"] and c["held_out_rms_nt"] <= candidates[chosen]["held_out_rms_nt"]:
            chosen = name
    return chosen


def _covariance(
    problem: _Problem, x, s: _Sums, T, fam: ModelFamily, held_std, noise=None, held_effects=None
) -> tuple[np.ndarray, np.ndarray]:
    """The covariance (n, n): the batch-means sandwich in the free directions, the prior's standard deviations
    ``held_std`` (R element, offset nT) along the held ones (and the effects' own prior along their held directions,
    ``held_effects``: a field anomaly along the field, held, widens R's scale as much as it trades with it), and
    what the held values' uncertainty does to the
    free estimates (a consider covariance: the free estimate moves by ``S dh`` when the held values move by
    ``dh``, ``S = -H_ff^-1 H_fh``, so ``P_f + S P_h S^T``). A level drive's ``b_z`` is then as uncertain as
    ``R_33`` held makes it (``std(R_33) B_z``), not as the data alone would say. Also returns the core's
    standard deviations (12,) given the held values (zero for the held ones).

    With ``noise``, ``(NoiseLevels, field_aligned)`` the noise the filter learned, the free directions' covariance
    is the sandwich ``H^-1 (T^T M T) H^-1`` of the residuals' covariance in that noise model (``M`` from
    ``_Problem.model_meat``: each component of the noise a Gauss-Markov process of the correlation time the
    filter measured), never below independent epochs'. Batches of a few seconds cannot see an error correlated
    over a minute (a wandering heading): on 20 drives with one, their covariance gave a mean NEES of 24 for 12
    parameters, the noise model's 10 to 12. Without a learned noise (``--fixed-noise``, a plug-in model), the
    batch-means sandwich."""
    H = T.T @ (s.A + problem.omega) @ T
    Hi = np.linalg.inv(H)
    dof = max(s.count - T.shape[1], 1)
    white = Hi * (s.ss / dof)
    # never below independent epochs' covariance: a correlation cannot make the estimate better than white noise
    if noise is not None:  # the learned noise model's correlation, in place of the batches (see the docstring)
        P_theta = _at_least(white, Hi @ (T.T @ problem.model_meat(x, *noise) @ T) @ Hi)
    else:
        used_batches = np.any(s.scores != 0, axis=1)
        k = int(used_batches.sum())
        scores = s.scores[used_batches] @ T  # two batches' lengths of scores at a time, not four
        scores -= scores.mean(axis=0)
        meat = scores.T @ scores * (k / max(k - 1, 1))
        del scores
        P_theta = _at_least(white, Hi @ meat @ Hi)
    core_held = fam.held()
    effect_held = np.zeros((len(x) - CORE_SIZE, 0)) if held_effects is None else held_effects.held_basis
    N = np.zeros((len(x), core_held.shape[1] + effect_held.shape[1]))
    N[:CORE_SIZE, : core_held.shape[1]] = core_held
    N[CORE_SIZE:, core_held.shape[1] :] = effect_held
    given = np.sqrt(np.abs(np.einsum("ik,kl,il->i", T, P_theta, T)))[:CORE_SIZE]
    if not N.shape[1]:
        P = T @ P_theta @ T.T
        return 0.5 * (P + P.T), given
    held_var = _held_variances(held_std)
    P_h = np.eye(N.shape[1])  # the effects' held directions: one prior standard deviation each
    h = core_held.shape[1]
    P_h[:h, :h] = core_held.T @ (held_var[:, None] * core_held)
    S = -Hi @ (T.T @ (s.A + problem.omega) @ N)
    basis = np.hstack([T, N])
    joint = np.block([[P_theta + S @ P_h @ S.T, S @ P_h], [P_h @ S.T, P_h]])
    P = basis @ joint @ basis.T
    return 0.5 * (P + P.T), given


def _component_variance(levels, field_nt: float, config_noise=None) -> float:
    """The variance (nT^2) of one residual component in the noise ``levels`` (``NoiseLevels``: the sensor's, the
    reference's, and the attitude error's across the field, two components of three, at ``field_nt``); the learned
    noise of ``config_noise`` when given; 1 nT^2 without either."""
    levels = config_noise[0] if config_noise is not None else levels
    if levels is None:
        return 1.0
    attitude = (levels.attitude_rad * field_nt) ** 2 * 2.0 / 3.0
    return levels.sensor_nt**2 + levels.reference_nt**2 + attitude


def _held_variances(held_std) -> np.ndarray:
    """The variances (12,) of the held core: ``held_std`` as ``(R element, offset nT)`` or one per parameter (12,)."""
    std = np.asarray(held_std, float)
    if std.shape == (CORE_SIZE,):
        return std**2
    return np.concatenate([np.full(9, std[0] ** 2), np.full(3, std[1] ** 2)])


def _at_least(P, Q) -> np.ndarray:
    """The smallest-looking covariance no smaller than either ``P`` or ``Q`` (k, k): ``P`` plus the positive part of
    ``Q - P``."""
    w, V = np.linalg.eigh(0.5 * ((Q - P) + (Q - P).T))
    return P + (V * np.maximum(w, 0.0)) @ V.T


def _record(fam: ModelFamily, asked: str, held_how: str, core_ref, candidates: dict, key: str) -> dict:
    """The ``model`` record of a calibration file: the family, what it estimated and held, in words (``key`` the
    family's name among ``candidates``; ``fam.name`` may be poorer, as the motion allowed)."""
    if fam.size == CORE_SIZE:
        text = "this log determines all 12 parameters of R and b"
    else:
        text = f"this log determines {fam.estimates}; {fam.holds} held at {held_how}"
    if asked != "auto":
        text = f"{asked} asked for (--model {asked}): {text}"
        if not candidates[key]["determined"]:
            text += f"; the log does not determine it (worst std {candidates[key]['worst_std_nt']:.3g} nT)"
    return {
        "family": fam.name,
        "asked": asked,
        "estimated": fam.estimates,
        "held": fam.holds,
        "held_at": held_how,
        "held_core": np.asarray(core_ref, float).tolist(),
        "text": text,
        "candidates": candidates,
    }
