"""The whole-log estimate of a layout with a wandering offset (``bias_drift``): ``b`` as the offset's mean over the
log, the drift's smoothed path and its learned rate.

A drifting offset is ``b + d(t)``, its departure ``d`` a random walk of ``walk`` nT/sqrt(s) on each sensor axis.
No constant describes it, and the filter's last value of ``d`` is the departure at the end of the log only: a
calibration file that stored it shifted every epoch by it. Here the departure is a zero-mean path, and

1. the core and the other effects are the whole-log estimate (``whole_log.fit_whole_log``, its family choice and
   covariance) of the readings less the path (at first none), so ``b`` is the offset's mean over the epochs used;
2. the residual ``r = m - R B_body - b - e`` of those epochs (sensor axes, nT) is averaged in bins of ``BIN_S``
   seconds, at least ``MIN_BIN_EPOCHS`` epochs and ``CORRELATIONS_PER_BIN`` correlation times of the noise
   (``noise_correlation_s``, measured across the heading axis). Each bin's mean is taken as
   ``y_k = d_k + h_k a_k + dR B_k + e_k``: the departure ``d`` a random walk of variance ``q dt`` per axis; the
   logged heading's error ``a`` (rad) a random walk of its own, ``h`` the heading axis in the sensor frame (what a
   heading error adds to the reading); ``dR`` the error of the fitted ``R`` (constant, ``B`` the bin's mean body
   field: a first fit that took part of the drift for ``R`` leaves a residual that follows the attitude, which
   the rate must not take for drift; for the path, only the elements the model family lets the fit change,
   ``Binned.r_free``); ``e_k`` white with variance ``s c_k`` (``c_k`` each axis's variance within
   the bins over the bin's epochs; ``s`` one scale, learned, which takes up a correlation shorter than a bin).
   The filter's learned correlation time is not used: the filter's residuals hold the part of the drift its
   random walk did not follow (on a 10-minute drive with a drift of 2 nT/sqrt(s) and white noise it learned
   17 s);
3. ``q = walk^2`` is learned by maximising the exact marginal likelihood of the bins (Kalman filter with a
   diffuse start, ``s`` concentrated out, the heading's walk maximised with it on a grid) over a grid in
   ``log q``, refined about its maximum; its 95 % interval is where twice the profile log-likelihood is within
   ``CHI2_95`` (one degree of freedom) of its maximum;
4. the path is the Rauch-Tung-Striebel smoothed departure at the learned rates
   (``magkf.online.smoother.rts_smooth``), made zero-mean over the epochs used (its mean is ``b``'s); the next
   round's fit takes the readings less the path and less the heading error's wander about its mean (``ROUNDS``).

The path is kept at knots (``KNOTS_PER_SCALE`` per smoothing time ``sqrt(noise per s / q)``, at most ``MAX_KNOTS``)
with its standard deviation, the log's time span and a fingerprint (first and last time, epoch count, and the
raw readings of ``FINGERPRINT_EPOCHS`` epochs): ``magkf apply`` subtracts it on the log it was learned on and
predicts the mean (zero departure) with a growing uncertainty elsewhere (``path_terms``). The whole-log machinery
is reused as it is; nothing here solves for ``R`` or ``b``.

The bins' noise model is exact for white residuals; a residual correlated over about a bin is partly taken
for wander (with noise correlated over 3 s the rates learned were 2.1 to 3.3 nT/sqrt(s) for a true 2). The walk
within a bin (``q BIN_S / 12`` of variance) is left out of the bin's noise: under 1 % of it for rates below
3 nT/sqrt(s) at 30 nT of noise and 10 Hz.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..calibration import PARAMETER_NAMES
from .measurements import heading_axis
from .state import CORE_SIZE, StateLayout
from .whole_log import WholeLogFit, filter_estimate, fit_whole_log

__all__ = [
    "Binned",
    "WalkRate",
    "DriftPath",
    "bin_residuals",
    "profile_log_likelihood",
    "learn_walk",
    "smooth_level",
    "fit_with_drift",
    "path_terms",
    "BIN_S",
    "ROUNDS",
]

#: Bin length of the residuals (s), at least ``MIN_BIN_EPOCHS`` epochs and ``CORRELATIONS_PER_BIN`` of the noise's
#: correlation times (``noise_correlation_s``); at most ``MAX_BINS`` bins over the log.
BIN_S = 2.0
MIN_BIN_EPOCHS = 4
CORRELATIONS_PER_BIN = 3.0
MAX_BINS = 1000
#: The noise's correlation is measured against its variance within windows of this length (s), and a correlation
#: of consecutive epochs below ``WHITE_CORRELATION`` is taken as white noise.
VARIANCE_WINDOW_S = 30.0
WHITE_CORRELATION = 0.2
#: Bins needed to learn a rate (fewer: the effect's own ``walk`` is kept, said not learned).
MIN_BINS = 20
#: The grid of ``q`` (nT^2/s): ``log10 q`` from ``Q_DECADES[0]`` to ``Q_DECADES[1]``, ``COARSE`` points a decade,
#: then ``FINE`` points a decade over ``REFINE_DECADES`` either side of the coarse maximum.
Q_DECADES = (-6.0, 6.0)
COARSE = 2
FINE = 30
REFINE_DECADES = 0.75
#: Twice the log-likelihood's drop at the edge of a 95 % interval (chi-square, one degree of freedom).
CHI2_95 = 3.841
#: Rounds of whole-log fit and path.
ROUNDS = 2
#: Epochs whose raw readings the fingerprint keeps, and how close (nT) a reading must be to be the same.
FINGERPRINT_EPOCHS = 8
SAME_READING_NT = 1e-3
#: Knots of the stored path: per smoothing time, and at most.
KNOTS_PER_SCALE = 2.0
MAX_KNOTS = 1000


@dataclass(frozen=True)
class Binned:
    """Residuals averaged in bins: ``time`` (K,) UNIX s (the epochs' mean), ``y`` (K, 3) nT, ``c`` (K, 3) nT^2
    the variance of each bin's mean up to one scale, ``counts`` (K,) epochs, and ``h`` (K, 3) nT/rad the
    heading axis in the sensor frame (what a heading error of one radian adds to the reading; None: zero)."""

    time: np.ndarray
    y: np.ndarray
    c: np.ndarray
    counts: np.ndarray
    h: np.ndarray | None = None
    field: np.ndarray | None = None
    r_free: np.ndarray | None = None

    def heading(self) -> np.ndarray:
        """``h`` (K, 3), zeros where none was given."""
        return np.zeros_like(self.y) if self.h is None else self.h

    def regressors(self) -> np.ndarray:
        """(K, 3, STATE) of each bin's mean: ``y = d + h a + dR B + e``, ``B`` the bin's mean body field (``field``,
        nT; zero where none was given) and ``dR`` (row-major) the error of the fitted ``R`` in the elements the fit
        is free to change (``r_free`` (9,) bool, None: all): one the calibration holds stays in the residual, and
        the path may take it."""
        H = np.zeros((len(self.y), 3, STATE))
        H[:, :, :3] = np.eye(3)
        H[:, :, 3] = self.heading()
        if self.field is not None:
            free = np.ones(9, bool) if self.r_free is None else np.asarray(self.r_free, bool)
            for i in range(3):
                H[:, i, 4 + 3 * i : 7 + 3 * i] = self.field * free[3 * i : 3 * i + 3]
        return H

    def __len__(self) -> int:
        return len(self.time)


@dataclass(frozen=True)
class WalkRate:
    """The learned random walk: ``value`` nT/sqrt(s), its standard deviation (from the width of the 95 %
    interval of ``log q``), the 95 % interval ``(low, high)`` (``low`` 0 where the likelihood does not fall
    below the grid), ``scale`` the bins' noise scale ``s`` (1 when the within-bin variance is the bins' noise),
    ``learned`` False where the log had too few bins, and ``heading_q`` (rad^2/s) the random walk of the logged
    heading's error learned with it (0: none)."""

    value: float
    std: float
    interval: tuple
    scale: float
    learned: bool = True
    heading_q: float = 0.0


@dataclass(frozen=True)
class DriftPath:
    """A wandering offset's departure from ``b`` over the log: ``time`` (K,) UNIX s knots, ``values`` (K, 3) nT,
    ``std`` (K, 3) nT, the log's ``span`` ``(first, last)`` UNIX s and epoch count ``n_epochs``, its ``rate``, and
    ``sample``: the times (S,) UNIX s and raw readings (S, 3) nT of ``FINGERPRINT_EPOCHS`` of the log's epochs, by
    which another log of the same times is told from it (``same_log``)."""

    time: np.ndarray
    values: np.ndarray
    std: np.ndarray
    span: tuple
    n_epochs: int
    rate: WalkRate
    sample: tuple = (np.zeros(0), np.zeros((0, 3)))

    def departure_rms(self) -> np.ndarray:
        """(3,) nT the path's RMS per axis (its mean is zero): how far the offset departs from ``b``."""
        return np.sqrt(np.mean(self.values**2, axis=0))

    def record(self, label: str) -> dict:
        """The JSON-ready record a calibration file keeps with the effect ``label`` (see docs/data-contract.md)."""
        r = self.rate
        return {
            "effect": label,
            "walk": {
                "value": r.value,
                "std": r.std,
                "interval_95": [r.interval[0], r.interval[1]],
                "unit": "nT/sqrt(s)",
                "learned": r.learned,
            },
            "departure": {"mean": [0.0, 0.0, 0.0], "rms": self.departure_rms().tolist(), "unit": "nT"},
            "span": [float(self.span[0]), float(self.span[1])],
            "fingerprint": {
                "first": float(self.span[0]),
                "last": float(self.span[1]),
                "n_epochs": self.n_epochs,
                "time": np.asarray(self.sample[0], float).tolist(),
                "mag": np.asarray(self.sample[1], float).tolist(),
            },
            "path": {"time": self.time.tolist(), "values": self.values.tolist(), "std": self.std.tolist()},
        }


# ------------------------------------------------------------------ the bins


def bin_length(time: np.ndarray, correlation_s: float = 0.0) -> float:
    """The bins' length (s) for epochs at ``time`` (N,) UNIX s whose noise is correlated over ``correlation_s``."""
    step = float(np.median(np.diff(time))) if len(time) > 1 else 1.0
    span = float(time[-1] - time[0]) if len(time) > 1 else 1.0
    return max(BIN_S, MIN_BIN_EPOCHS * step, CORRELATIONS_PER_BIN * correlation_s, span / MAX_BINS)


def noise_correlation_s(time, r) -> float:
    """The correlation time (s) of the noise in residuals ``r`` (N, 3) nT at ``time`` (N,) UNIX s, as a first-order
    Gauss-Markov process: from the correlation ``rho = 1 - var(step difference) / (2 var)`` of consecutive epochs,
    ``var`` each axis's variance within ``VARIANCE_WINDOW_S`` windows (short against the offset's wander), both
    pooled over the axes; ``tau = -step / ln rho``, 0 where ``rho`` is below ``WHITE_CORRELATION``."""
    time = np.asarray(time, float)
    if len(time) < 3:
        return 0.0
    window = np.floor((time - time[0]) / VARIANCE_WINDOW_S).astype(np.int64)
    _, start, counts = np.unique(window, return_index=True, return_counts=True)
    means = np.repeat(np.add.reduceat(r, start, axis=0) / counts[:, None], counts, axis=0)
    variance = float(np.sum((r - means) ** 2) / max(r.size - 3 * len(counts), 1))
    same = np.diff(window) == 0
    steps = np.diff(r, axis=0)[same]
    if not len(steps) or variance <= 0:
        return 0.0
    rho = 1.0 - float(np.mean(steps**2)) / (2.0 * variance)
    if rho < WHITE_CORRELATION:
        return 0.0
    step = float(np.median(np.diff(time)[same]))
    return -step / np.log(min(rho, 0.999))


def bin_residuals(time, r, length_s: float, heading=None, field=None) -> Binned:
    """Residuals ``r`` (N, 3) nT at ``time`` (N,) UNIX s averaged in bins of ``length_s``: each bin's mean, and the
    variance of that mean up to one scale, each axis's pooled within-bin variance over the bin's epochs; the
    sensor-frame ``heading`` axis (N, 3) nT/rad and the body ``field`` (N, 3) nT averaged alike (None: none). Bins
    of one epoch are dropped."""
    time = np.asarray(time, float)
    index = np.floor((time - time[0]) / length_s).astype(np.int64)
    _, start, counts = np.unique(index, return_index=True, return_counts=True)
    keep = counts >= 2
    sums = np.add.reduceat(r, start, axis=0)
    means = sums / counts[:, None]
    deviation = r - np.repeat(means, counts, axis=0)
    own = np.repeat(keep, counts)
    dof = max(int(counts[keep].sum() - keep.sum()), 1)
    within = (deviation[own] ** 2).sum(axis=0) / dof  # (3,)
    t_mean = np.add.reduceat(time, start) / counts
    n = counts[keep].astype(float)
    c = within[None, :] / n[:, None]
    h, f = (
        (None if a is None else (np.add.reduceat(a, start, axis=0) / counts[:, None])[keep]) for a in (heading, field)
    )
    return Binned(t_mean[keep], means[keep], c, counts[keep], h, f)


# ------------------------------------------------------------------ the rate


def profile_log_likelihood(binned: Binned, rho, rho_heading=None) -> tuple[np.ndarray, np.ndarray]:
    """``(W, logdet)`` (G,) of the bins under a walk of ``rho`` (G,) per s of the offset and ``rho_heading`` (G,)
    rad^2 per s of the logged heading's error (None: zeros), both in units of the bins' noise scale: ``sum nu^T
    S^-1 nu`` and ``sum log det S`` over the bins after the first ``SKIP_BINS`` of the Kalman filter of the
    state (departure (3,), heading error, the fitted R's error (9,), ``Binned.regressors``) with noise ``c``. With
    the scale ``s``, the marginal log-likelihood of ``q = rho s`` is ``-(m log s + logdet + W / s) / 2`` up to a
    constant, ``m = 3 (K - SKIP_BINS)``."""
    rho = np.asarray(rho, float)
    rho_heading = np.zeros(len(rho)) if rho_heading is None else np.asarray(rho_heading, float)
    walk = np.column_stack([rho, rho, rho, rho_heading, np.zeros((len(rho), STATE - 4))])  # (G, STATE)
    x, P = _diffuse(len(rho))
    weighted, logdet = np.zeros(len(rho)), np.zeros(len(rho))
    dt = np.diff(binned.time, prepend=binned.time[0])
    y, c, H = binned.y, binned.c, binned.regressors()
    for k in range(len(y)):
        P[:, _DIAG, _DIAG] += walk * dt[k]
        nu, (w, d), gain, PHt = _update_terms(x, P, y[k], c[k], H[k])
        if k >= SKIP_BINS:
            weighted += w
            logdet += d
        x += np.einsum("gij,gj->gi", gain, nu)
        P -= gain @ np.swapaxes(PHt, 1, 2)
    return weighted, logdet


#: The state: the departure (3), the logged heading's error (rad) and the error of the fitted R (9, constant:
#: the residual of a fit that took part of the drift for R, which the path must not take for drift). Its
#: start: a departure of 1e4 nT, a heading error of 1 rad and R's error of ``R_ERROR`` (standard deviations),
#: the first ``SKIP_BINS`` bins left out of the likelihood (they settle the start).
STATE = 13
_DIAG = np.arange(STATE)
DIFFUSE_NT = 1e4
DIFFUSE_RAD = 1.0
R_ERROR = 0.01
SKIP_BINS = 5


def _diffuse(G: int) -> tuple[np.ndarray, np.ndarray]:
    """The start of ``G`` filters: state (G, STATE) zero, covariance (G, STATE, STATE) diffuse."""
    P = np.zeros((G, STATE, STATE))
    P[:, _DIAG, _DIAG] = [DIFFUSE_NT**2] * 3 + [DIFFUSE_RAD**2] + [R_ERROR**2] * 9
    return np.zeros((G, STATE)), P


def _update_terms(x, P, y, c, H) -> tuple:
    """The innovation ``nu`` (G, 3), ``nu^T S^-1 nu`` and ``log det S`` (G,) of its covariance ``S``, the gain
    (G, STATE, 3) and ``P H^T`` (G, STATE, 3) of a bin ``y`` (3,) with noise ``c`` (3,) and regressors ``H``
    (3, STATE) (``Binned.regressors``)."""
    PHt = P @ H.T
    S = H @ PHt + np.diag(c)
    nu = y - x @ H.T
    solved = np.linalg.solve(S, np.concatenate([np.swapaxes(PHt, 1, 2), nu[:, :, None]], axis=2))  # S^-1 [H P, nu]
    weighted = np.einsum("gi,gi->g", nu, solved[:, :, -1])
    return nu, (weighted, np.linalg.slogdet(S)[1]), np.swapaxes(solved[:, :, :-1], 1, 2), PHt


#: The heading error's walk (rad^2/s, in units of the noise scale) tried beside none: 10^-10 to 10^-4.
HEADING_DECADES = (-10.0, -4.0)
HEADING_PER_DECADE = 1


def learn_walk(binned: Binned, default_walk: float) -> WalkRate:
    """The walk (nT/sqrt(s)) that maximises the bins' marginal likelihood, the logged heading's wander maximised
    with it (none, or a walk on ``HEADING_DECADES``), with its 95 % interval from the profile likelihood of ``q``
    (the scale and the heading's walk maximised at each ``q``); the effect's ``default_walk`` (not learned) when
    there are fewer than ``MIN_BINS`` bins."""
    if len(binned) < MIN_BINS:
        return WalkRate(float(default_walk), float("nan"), (float("nan"), float("nan")), 1.0, learned=False)
    m = 3 * (len(binned) - SKIP_BINS)
    lo, hi = Q_DECADES
    coarse = np.linspace(lo, hi, int((hi - lo) * COARSE) + 1)  # log10 rho
    heading = _heading_grid(binned)
    grid, gh = (a.ravel() for a in np.meshgrid(coarse, heading, indexing="ij"))
    W, logdet = profile_log_likelihood(binned, 10.0**grid, gh)
    best = int(np.argmax(-(m * np.log(W / m) + logdet)))
    fine = np.linspace(grid[best] - REFINE_DECADES, grid[best] + REFINE_DECADES, int(2 * REFINE_DECADES * FINE) + 1)
    near = np.unique(gh[best] * np.array([10.0**-0.5, 1.0, 10.0**0.5]))  # the heading's walk about its best
    fine, near = (a.ravel() for a in np.meshgrid(fine, near, indexing="ij"))
    W_f, logdet_f = profile_log_likelihood(binned, 10.0**fine, near)
    grid, gh = np.concatenate([grid, fine]), np.concatenate([gh, near])
    W, logdet = np.concatenate([W, W_f]), np.concatenate([logdet, logdet_f])
    best = int(np.argmax(-(m * np.log(W / m) + logdet)))
    scale = float(W[best] / m)
    # the profile of q on the points evaluated, the scale and the heading's walk maximised at each
    log_q = np.unique(np.round(grid, 9)) + np.log10(scale)
    s = 10.0 ** (log_q[:, None] - grid[None, :])  # (q, evaluated): the scale that makes rho s = q
    ll = np.max(-0.5 * (m * np.log(s) + logdet[None, :] + W[None, :] / s), axis=1)
    top = int(np.argmax(ll))
    drop = 2.0 * (ll[top] - ll)
    low, high = _crossing(log_q, drop, top, -1), _crossing(log_q, drop, top, +1)
    walk = float(np.sqrt(10.0 ** log_q[top]))
    if np.isfinite(low):
        std_log_q = (high - low) * np.log(10.0) / (2.0 * 1.96)
    else:  # one-sided: the upper half-width stands for both
        std_log_q = (high - log_q[top]) * np.log(10.0) / 1.96
    interval = (float(np.sqrt(10.0**low)) if np.isfinite(low) else 0.0, float(np.sqrt(10.0**high)))
    return WalkRate(walk, walk * std_log_q / 2.0, interval, scale, heading_q=float(gh[best] * scale))


def _heading_grid(binned: Binned) -> np.ndarray:
    """The heading error's walks tried (rad^2/s): none, and ``HEADING_DECADES`` where the bins have a heading
    axis."""
    if binned.h is None or not np.any(binned.h):
        return np.zeros(1)
    lo, hi = HEADING_DECADES
    return np.concatenate([[0.0], 10.0 ** np.linspace(lo, hi, int((hi - lo) * HEADING_PER_DECADE) + 1)])


def _crossing(grid, drop, top: int, direction: int) -> float:
    """``log10 q`` where ``drop`` (twice the log-likelihood's fall from its maximum at ``grid[top]``) first reaches
    ``CHI2_95`` going ``direction`` from ``top``, linearly interpolated; -inf (below) or the grid's end (above)
    where it never does."""
    order = np.arange(top, -1 if direction < 0 else len(grid), direction)
    over = order[drop[order] >= CHI2_95]
    if not len(over):
        return float("-inf") if direction < 0 else float(grid[-1])
    j = int(over[0])
    i = j - direction
    return float(grid[i] + (grid[j] - grid[i]) * (CHI2_95 - drop[i]) / (drop[j] - drop[i]))


# ------------------------------------------------------------------ the path


def smooth_level(binned: Binned, rate: WalkRate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Rauch-Tung-Striebel smoothed departure (K, 3) nT, its variance (K, 3) nT^2 and the smoothed heading
    error (K,) rad of the bins under the walks of ``rate`` (the offset's ``value^2``, the heading error's
    ``heading_q``) and the bins' noise ``rate.scale * c`` (``magkf.online.smoother.rts_smooth``)."""
    from .smoother import rts_smooth

    walk = np.array([rate.value**2] * 3 + [rate.heading_q] + [0.0] * (STATE - 4))
    x, P = _diffuse(1)
    dt = np.diff(binned.time, prepend=binned.time[0])
    y, c, H = binned.y, binned.c * rate.scale, binned.regressors()
    xs, Ps = np.empty((len(y), STATE)), np.empty((len(y), STATE, STATE))
    for k in range(len(y)):
        P[:, _DIAG, _DIAG] += walk * dt[k]
        nu, _, gain, PHt = _update_terms(x, P, y[k], c[k], H[k])
        x = x + np.einsum("gij,gj->gi", gain, nu)
        P = P - gain @ np.swapaxes(PHt, 1, 2)
        xs[k], Ps[k] = x[0], 0.5 * (P[0] + P[0].T)
    xs, Ps = rts_smooth(xs, Ps, dt, walk)
    return xs[:, :3], np.einsum("kii->ki", Ps[:, :3, :3]), xs[:, 3]


def _knots(binned: Binned, q: float, scale: float) -> np.ndarray:
    """Indices (k,) of the bins kept as the stored path's knots: ``KNOTS_PER_SCALE`` per smoothing time
    ``sqrt(noise per s / q)`` (s), at most ``MAX_KNOTS``, the first and last always."""
    K = len(binned)
    span = float(binned.time[-1] - binned.time[0]) if K > 1 else 1.0
    length = span / max(K - 1, 1)
    noise_per_s = float(np.median(binned.c.mean(axis=1))) * scale * length
    smoothing_s = np.sqrt(noise_per_s / max(q, 1e-12))
    wanted = min(max(span / (smoothing_s / KNOTS_PER_SCALE), 1.0), MAX_KNOTS - 1, K - 1)
    return np.unique(np.round(np.linspace(0, K - 1, int(wanted) + 1)).astype(np.int64))


def _drift_path(binned: Binned, rate: WalkRate, time, span, n_epochs) -> tuple[DriftPath, np.ndarray]:
    """The path at the rate learned, zero-mean over the epochs at ``time`` (N,) (the epochs used), and the logged
    heading's error (N,) rad at those epochs less its mean."""
    level, var, heading = smooth_level(binned, rate)
    at_epochs = np.column_stack([np.interp(time, binned.time, level[:, i]) for i in range(3)])
    mean = at_epochs.mean(axis=0)
    knots = _knots(binned, rate.value**2, rate.scale)
    path = DriftPath(binned.time[knots], level[knots] - mean, np.sqrt(var[knots]), span, n_epochs, rate)
    error = np.interp(time, binned.time, heading)
    return path, error - error.mean()


# ------------------------------------------------------------------ the whole-log estimate


def fit_with_drift(prep, layout: StateLayout, x_filter, P_filter, used, labels, **options) -> WholeLogFit:
    """The whole-log estimate of ``layout`` whose effects ``labels`` wander (see the module), over the ``used``
    epochs (N,) of ``prep``, from the filter's last state ``x_filter`` (n,), ``P_filter`` (n, n), with the
    options of ``whole_log.fit_whole_log``: ``x`` (n,) with the
    core and the other effects at the whole-log fit and the wandering block at zero (the mean departure), ``P``
    (n, n) with the block's variance the path's mean square (the spread a start from the file allows), and
    the ``model`` record with ``wandering`` (label -> ``DriftPath.record``). Falls back to the filter's state
    (``whole_log.filter_estimate``) for what it does not model: a wandering effect that is not an offset on
    each axis, two of them, the magnitude alone, or fewer than ``MIN_BINS`` bins' epochs with attitude."""
    drift = _offset_block(layout, labels)
    if drift is None or not options.get("vector", True):
        return filter_estimate(x_filter, P_filter, labels)
    effect, block = drift
    still = StateLayout(tuple(e for e in layout.effects if e is not effect))
    keep = np.ones(layout.size, bool)
    keep[block] = False
    x_still = np.asarray(x_filter, float)[keep]
    if options.get("held_effects") is not None:
        options = dict(options, held_effects=_without_rows(options["held_effects"], keep[CORE_SIZE:], effect.label))
    used = np.asarray(used, bool) & prep.has_attitude
    idx = np.flatnonzero(used)
    if len(idx) < MIN_BINS * MIN_BIN_EPOCHS:  # too few epochs with attitude to follow a path
        return filter_estimate(x_filter, P_filter, labels)
    departure = np.zeros((len(prep), 3))
    span = (float(prep.time[0]), float(prep.time[-1]))
    for _ in range(ROUNDS):
        fit = fit_whole_log(replace(prep, m=prep.m - departure), still, x_still, used, **options)
        x_still = fit.x
        r = _residuals(prep, still, fit.x, idx)
        heading = np.nan_to_num(heading_axis(prep.c_nb, prep.ref)) @ still.R(fit.x).T  # (N, 3) nT/rad, sensor axes
        length = bin_length(prep.time[idx], noise_correlation_s(prep.time[idx], _across(r, heading[idx])))
        binned = bin_residuals(prep.time[idx], r, length, heading[idx], prep.data.field_body[idx])
        rate = learn_walk(binned, float(np.sqrt(effect.random_walk()[0] ** 2)))
        # the rate with every element of R's error in the state (what a held R leaves is not drift); the path on
        # this log with the free ones only (what the calibration holds stays in the residual: the path may take it)
        binned = replace(binned, r_free=_free_R(fit.model))
        path, error = _drift_path(binned, rate, prep.time[idx], span, len(prep))
        # the next fit takes the readings less the departure and the heading error's wander about its mean (the
        # logged attitude's error, not the sensor's): neither is R's or b's
        wander = np.interp(prep.time, prep.time[idx], error)[:, None] * heading
        departure = np.column_stack([np.interp(prep.time, path.time, path.values[:, i]) for i in range(3)]) + wander
    return _with_block(fit, layout, keep, block, replace(path, sample=_sample(prep)), effect.label)


def _without_rows(held, rows, label: str):
    """The run's held directions of the effects' parameters (``determined.HeldDirections``) over the
    parameters ``rows`` (q,) bool only, the wandering effect ``label``'s (which is left free) dropped; None when
    nothing is held then."""
    free = held.free[rows]
    free = free[:, np.abs(free).sum(axis=0) > 1e-12]
    basis = held.held_basis[rows]
    basis = basis[:, np.abs(basis).sum(axis=0) > 1e-12]
    counts = {k: v for k, v in held.held.items() if k != label}
    if not sum(counts.values()):
        return None
    return replace(held, free=free, projector=held.projector[np.ix_(rows, rows)], held_basis=basis, held=counts)


def _free_R(model: dict) -> np.ndarray:
    """(9,) bool: the elements of ``R`` the whole-log fit of ``model`` (its record) was free to change: all in the
    ``full`` family, else those with a ``std_given_held``."""
    given = model.get("std_given_held")
    if given is None:
        return np.full(9, model.get("family") == "full")
    return np.array([name in given for name in PARAMETER_NAMES[:9]])


def _across(r, heading) -> np.ndarray:
    """The residuals ``r`` (k, 3) nT less their component along the ``heading`` axis (k, 3): what a wandering
    logged heading leaves alone (its correlation is not the sensor noise's)."""
    unit = heading / np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
    return r - np.sum(r * unit, axis=1, keepdims=True) * unit


def _sample(prep) -> tuple[np.ndarray, np.ndarray]:
    """The times (S,) and raw readings (S, 3) nT of ``FINGERPRINT_EPOCHS`` epochs spread over ``prep``'s epochs with
    a reading."""
    has = np.flatnonzero(np.all(np.isfinite(prep.m), axis=1))
    pick = (
        has[np.unique(np.round(np.linspace(0, len(has) - 1, FINGERPRINT_EPOCHS)).astype(np.int64))] if len(has) else has
    )
    return prep.time[pick].copy(), prep.m[pick].copy()


def _offset_block(layout: StateLayout, labels):
    """``(effect, slice)`` of the one wandering effect of ``labels`` that adds an offset on each sensor axis
    (three linear parameters, Jacobian the identity), or None."""
    found = [(e, sl) for e, sl in layout.blocks() if e.label in labels]
    if len(found) != 1 or len(labels) != 1:
        return None
    effect, sl = found[0]
    if effect.size != 3 or not effect.linear or not hasattr(effect, "design"):
        return None
    probe = effect.design(_probe_data())
    return (effect, sl) if np.allclose(probe, np.eye(3)) else None


def _probe_data():
    """Two epochs of plausible data to check an effect's regressors on."""
    from ..effects.base import EpochData

    field = np.array([[20000.0, 1000.0, 43000.0], [-5000.0, 19000.0, 43000.0]])
    return EpochData(np.array([0.0, 1.0]), field, field)


def _residuals(prep, layout: StateLayout, x, idx) -> np.ndarray:
    """``m - R B_body - b - e`` (k, 3) nT at the epochs ``idx`` (k,), sensor axes: the offset's departure and
    the noise."""
    data = prep.data.take(idx)
    terms = layout.effect_terms(x, data) if layout.has_extra else 0.0
    R, b = layout.R_b(x)
    return prep.m[idx] - data.field_body @ R.T - b - terms


def _with_block(fit: WholeLogFit, layout: StateLayout, keep, block, path: DriftPath, label: str) -> WholeLogFit:
    """``fit`` of the layout without the wandering block made one of ``layout``: the block at zero, its variance
    the path's mean square plus its mean variance, no covariance with the rest; the path in the record."""
    n = layout.size
    x = np.zeros(n)
    x[keep] = fit.x
    P = np.zeros((n, n))
    P[np.ix_(keep, keep)] = fit.P
    spread = np.mean(path.values**2 + path.std**2, axis=0)
    P[block, block] = np.diag(np.maximum(spread, 1e-12))
    rate = path.rate
    words = (
        f"{label} wanders: b is the offset's mean over the log, the departure's smoothed path is kept for this log "
        f"({len(path.time)} knots); rate {rate.value:.3g} nT/sqrt(s)"
        + (" learned" if rate.learned else " as set (too short a log to learn it)")
    )
    record = dict(fit.model, text=f"{fit.model['text']}; {words}", wandering={label: path.record(label)})
    return replace(fit, x=x, P=P, model=record)


# ------------------------------------------------------------------ applying a stored path


def same_log(wander: dict, time, mag) -> bool:
    """Whether the log of epochs at ``time`` (N,) UNIX s with raw readings ``mag`` (N, 3) nT (None: not compared) is
    the one a stored path was learned on (or a part of it): every fingerprint epoch within its times is there,
    with its reading within ``SAME_READING_NT``, and at least one is; without a fingerprint sample, or without
    ``mag``, a log within the path's span is taken as its own."""
    time = np.asarray(time, float)
    sample = wander.get("fingerprint", {})
    s_time, s_mag = np.asarray(sample.get("time", []), float), np.asarray(sample.get("mag", []), float)
    if mag is None or not len(s_time) or not len(time):
        return True
    within = s_time[(s_time >= time[0]) & (s_time <= time[-1])]
    at = np.clip(np.searchsorted(time, within), 0, len(time) - 1)
    found = np.abs(time[at] - within) <= 1e-6 * np.maximum(np.abs(within), 1.0)
    readings = np.asarray(mag, float)[at]
    close = np.all(np.abs(readings - s_mag[np.isin(s_time, within)]) <= SAME_READING_NT, axis=1)
    return bool(len(within)) and bool(np.all(found & close))


def path_terms(wander: dict | None, time, mag=None) -> tuple[np.ndarray, np.ndarray]:
    """The departure (N, 3) nT a stored wandering effect adds at ``time`` (N,) UNIX s, and its standard deviation
    (N,) nT (RMS over the axes): on the log it was learned on (``same_log`` with the raw readings ``mag`` (N, 3)
    nT, None: by time alone) and within its span, the path interpolated and its own standard deviation;
    elsewhere zero (the offset's mean, ``b``) with the uncertainty of that prediction,
    ``sqrt(rms^2 + walk^2 |t - nearest end of the span|)`` (``rms`` the path's spread about ``b``; within the span
    of another log, ``walk^2`` times the span's half length stands for the time). ``wander`` None (a file without
    a path): zero departure, NaN standard deviation."""
    time = np.asarray(time, float)
    if wander is None:
        return np.zeros((len(time), 3)), np.full(len(time), np.nan)
    path = wander["path"]
    knots = np.asarray(path["time"], float)
    values, std = np.asarray(path["values"], float), np.asarray(path["std"], float)
    first, last = (float(v) for v in wander["span"])
    inside = (time >= first) & (time <= last)
    if not same_log(wander, time, mag):
        inside[:] = False
    out = np.zeros((len(time), 3))
    sd = np.empty(len(time))
    for i in range(3):
        out[inside, i] = np.interp(time[inside], knots, values[:, i])
    sd[inside] = np.sqrt(np.mean([np.interp(time[inside], knots, std[:, i] ** 2) for i in range(3)], axis=0))
    away = np.maximum(np.maximum(first - time, time - last), 0.5 * (last - first))[~inside]
    spread = float(np.mean(np.asarray(wander["departure"]["rms"], float) ** 2))
    sd[~inside] = np.sqrt(spread + float(wander["walk"]["value"]) ** 2 * away)
    return out, sd
