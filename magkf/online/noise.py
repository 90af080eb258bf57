"""Measurement noise learned from the log as it goes, in constant memory.

Real logs are far noisier than a magnetometer's data sheet (motor and wiring fields, attitude errors,
local anomalies), and their residuals are correlated over seconds. ``NoiseLearner`` estimates, from the
innovations of the epochs the filter could use (before its gates, so that a noise set too low cannot
starve it):

* the **sensor part** ``s`` (nT): the spread of the innovation *along* the reference field, where an
  attitude error does not act (the total-field residual);
* the **attitude part**, apart for the two kinds of attitude error an INS makes: a *tilt* ``a_t`` (rad,
  about the horizontal axes) and a *heading* error ``a_h`` (rad, about the vertical; an INS's heading is
  usually its worst-determined angle). A heading error turns the field about the vertical, so it shows
  only along ``h``, the horizontal direction across the field; ``v``, the third direction (across both),
  sees the tilt alone. With ``B`` the field and ``B_h`` its horizontal part: ``var_v = s^2 + a_t^2 |B|^2``
  and ``var_h = s^2 + a_t^2 (|B|^2 - B_h^2) + a_h^2 B_h^2``, solved for ``a_t`` and then ``a_h``;
* the **correlation** of the innovations in time, as the integrated autocorrelation time ``k`` (in
  epochs): ``k = 2 integral rho(L) dL - 1`` over lags of 1, 2, 4, ... epochs (trapezoid rule, up to the
  lag where ``rho`` falls below 0.05), along the field, along ``h`` and along ``v`` apart (a wandering
  heading is correlated over minutes, sensor noise over seconds). ``n`` epochs carry the information of
  ``n / k`` independent ones, so the filter's update counts each epoch ``1 / k`` (its noise variance is
  inflated by ``k``); without this, the covariance of the estimate, and NEES, would be ``k`` times too
  optimistic on real data.

The spreads are robust scales (1.4826 times the median absolute innovation) over the last ``window_s``
seconds: the disturbances of thousands of nT that the gates refuse are a minority and do not move them,
and a noise set 30 times too small or too large is corrected within one window. This is innovation-based
covariance matching (Mohamed and Schwarz, "Adaptive Kalman filtering for INS/GPS", Journal of Geodesy 73,
1999: the measurement covariance from the windowed innovation covariance less the part the state's
uncertainty explains) with a robust scale in place of the sample covariance, per component of the
field-aligned noise model of ``magkf.online.measurements``. ``method="variational"`` adds the state's
uncertainty instead of subtracting it, as the variational-Bayes filter does (Sarkka and Nummenmaa,
"Recursive noise adaptive Kalman filtering by variational Bayesian approximations", IEEE TAC 54, 2009,
where the residual after the update and its covariance enter the inverse-gamma update); ``scripts/
noise_study.py`` compares the two. ``floor_nt`` keeps the learned sensor noise from collapsing (a quiet
stretch, a quantised sensor); the configured noise only starts the estimate when no robust scale of the
bootstrap stretch is given (the real-time path).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import NOISE_METHODS

__all__ = ["NoiseLevels", "NoiseLearner", "estimate_levels", "robust_start", "CLIP_SIGMA", "METHODS"]

#: Squared innovations are winsorised at this many standard deviations of the current estimate.
CLIP_SIGMA = 5.0
#: The robust scales and the correlation are re-estimated this often, s of data.
ESTIMATE_EVERY_S = 5.0
#: The robust scales need at least this many innovations in the window (else the start is kept).
MIN_SAMPLES = 200
#: Innovations kept for the robust scale (the latest within the window are used).
BUFFER = 8192
#: Lags (epochs) of the autocorrelation: 1, 2, 4, ... 8192 (164 s at 50 Hz: an attitude error wanders slowly).
LAGS = 2 ** np.arange(14)
_LAG_LIST = LAGS.tolist()
#: The autocorrelation is averaged over this many noise windows: a short average underestimates it (an
#: estimate from N samples is biased low by about the integrated time over N).
CORRELATION_WINDOWS = 10.0
#: The correlation is measured once the state's part of the total-field variance is below this share.
CONVERGED = 0.1
#: The autocorrelation sum stops where it falls below this.
RHO_STOP = 0.05
METHODS = NOISE_METHODS
#: Columns of the learner's ring of innovations.
_COLUMNS = 8
#: Innovations whose lagged products are taken at once (bounds the memory of a whole log's start).
_CHUNK = 16384
#: The heading error is learned where the horizontal field is at least this share of the field (squared).
HORIZONTAL_SHARE = 0.05


@dataclass(frozen=True)
class NoiseLevels:
    """Noise of the measurement models.

    ``sensor_nt`` per axis (nT); ``attitude_rad`` the tilt error (1 sigma, about each horizontal axis);
    ``reference_nt`` per component (nT); ``heading_rad`` the heading error (1 sigma, about the vertical;
    None: the same as the tilt). ``inflation_along``, ``inflation_heading``, ``inflation_across``: along
    the field, along ``h`` (horizontal, across the field) and along ``v`` (across both), each epoch counts
    ``1 / inflation`` of an independent one in the update (1 for white residuals; ``inflation_heading``
    None: ``inflation_across``)."""

    sensor_nt: float
    attitude_rad: float
    reference_nt: float
    inflation_along: float = 1.0
    inflation_across: float = 1.0
    heading_rad: float | None = None
    inflation_heading: float | None = None

    @property
    def heading(self) -> float:
        """The heading error, rad (1 sigma)."""
        return self.attitude_rad if self.heading_rad is None else self.heading_rad

    @property
    def inflations(self) -> tuple[float, float, float]:
        """Along the field, along ``h``, along ``v``."""
        heading = self.inflation_across if self.inflation_heading is None else self.inflation_heading
        return self.inflation_along, heading, self.inflation_across

    @property
    def inflation(self) -> float:
        """The largest inflation (for reports)."""
        return max(self.inflations)

    @property
    def attitude_deg(self) -> float:
        return math.degrees(self.attitude_rad)

    @property
    def heading_deg(self) -> float:
        return math.degrees(self.heading)

    @property
    def along_var(self) -> float:
        """Variance (nT^2) of a residual along the field: sensor and reference."""
        return self.sensor_nt**2 + self.reference_nt**2

    def across_vars(self, field2, horizontal2) -> tuple[np.ndarray, np.ndarray]:
        """Variances (nT^2) of a residual along ``h`` and along ``v`` for fields of squared magnitude ``field2``
        with squared horizontal part ``horizontal2`` (nT^2, arrays or scalars)."""
        tilt2, heading2 = self.attitude_rad**2, self.heading**2
        var_h = self.along_var + tilt2 * (field2 - horizontal2) + heading2 * horizontal2
        return var_h, self.along_var + tilt2 * field2

    def with_inflations(self, along: float, heading: float, across: float) -> NoiseLevels:
        return NoiseLevels(
            self.sensor_nt, self.attitude_rad, self.reference_nt, along, across, self.heading_rad, heading
        )


class NoiseLearner:
    """Learns ``NoiseLevels`` from innovations, block after block (constant memory).

    ``start`` the initial levels (configured, or a robust scale from the bootstrap); ``floor_nt`` the
    least sensor noise; ``window_s`` the time over which the noise is estimated, s; ``attitude`` whether
    the attitude part is learned (False for magnitude-only models); ``adapt`` False keeps ``start`` fixed
    (the learner then only measures the correlation); ``method`` ``matching`` (subtract what the state's
    uncertainty explains) or ``variational`` (add it). The start's inflations hold until the correlation
    has been measured over one window.
    """

    def __init__(
        self,
        start: NoiseLevels,
        floor_nt: float = 1.0,
        window_s: float = 60.0,
        attitude: bool = True,
        adapt: bool = True,
        method: str = "variational",
    ):
        if method not in METHODS:
            raise ValueError(f"unknown noise method {method!r}; use one of {', '.join(METHODS)}")
        self.levels = start
        self._start_inflations = start.inflations
        self.floor_nt, self.window_s, self.attitude, self.adapt, self.method = (
            floor_nt,
            window_s,
            attitude,
            adapt,
            method,
        )
        # The latest innovations: time (s), along (nT), along h and v (nT), the field and its horizontal
        # part squared (nT^2), whether the state had converged (1 or 0) and whether h and v were given.
        self._buffer = np.full((BUFFER, _COLUMNS), np.nan)
        self._next = 0
        self._unflushed = 0  # the latest rows of the ring not yet standardised (``_flush``)
        self._predicted = 0.0
        self._ring = np.zeros((LAGS[-1], 3))  # the latest standardised innovations (along, h, v)
        self._count = 0  # innovations whose lagged products were taken
        self._pending = []  # (times, standardised innovations) not yet in the lagged products
        self._prod = np.zeros((3, len(LAGS)))
        self._sq = np.zeros(3)
        self._t = None
        self._t_products = None  # time of the latest innovation in the lagged products, s
        self._t0 = None
        self._estimated = None
        self._measured_s = 0.0  # seconds of innovations whose correlation was measured

    def observe(self, t, along, cross, field2, predicted: float = 0.0, horizontal2=None) -> None:
        """Take the innovations of k epochs at times ``t`` (k,) s: ``along`` (k,) nT along the field,
        ``cross`` (k, 2) nT along ``h`` and ``v`` (None for magnitude-only), ``field2`` (k,) the field's squared
        magnitude and ``horizontal2`` (k,) its horizontal part's (default ``field2``), nT^2; ``predicted`` the
        variance (nT^2) the state's uncertainty explains along the field."""
        along = np.asarray(along, float)
        k = len(along)
        if k == 0:
            return
        t = np.asarray(t, float)
        field2 = np.asarray(field2, float)
        horizontal2 = field2 if horizontal2 is None else np.asarray(horizontal2, float)
        t_end = float(t[-1])
        dt = 0.0 if self._t is None else max(t_end - self._t, 0.0)
        self._t = t_end
        self._predicted = float(predicted)
        # While the state is still far less certain than the noise, its own error makes the innovations look
        # correlated: the correlation is measured only once it explains a small part of them.
        converged = predicted <= CONVERGED * self.levels.along_var
        if converged:
            self._measured_s += dt
        with_cross = cross is not None and self.attitude
        if k > BUFFER - self._unflushed:  # what the ring still holds unflushed would be overwritten
            self._flush()
        rows = np.empty((k, _COLUMNS))
        rows.fill(np.nan)
        rows[:, 0], rows[:, 1], rows[:, 4], rows[:, 5], rows[:, 6] = t, along, field2, horizontal2, converged
        rows[:, 7] = with_cross
        if with_cross:
            rows[:, 2:4] = cross
        if k > BUFFER:  # more than the ring holds at once (a whole log's residuals at the start)
            self._standardise(rows)
        else:
            self._unflushed += k
        self._store(rows)
        # Re-estimated on a fixed grid of times (the same epochs whether they come in blocks or one by one):
        # the levels, and the correlation of the innovations seen since the last tick, all at once.
        if self._t0 is None:
            self._t0 = float(t[0])
        tick = math.floor((float(t[0]) - self._t0) / ESTIMATE_EVERY_S)
        if tick != self._estimated:
            self._estimated = tick
            self._flush()
            lv = self._estimate() if self.adapt else self.levels
            self.levels = lv.with_inflations(*self.inflations())

    def _flush(self) -> None:
        """Standardise the innovations stored since the last flush (``_standardise``): the levels that
        standardise them change only at ticks, so this is done once per tick rather than per call."""
        if self._unflushed:
            idx = (self._next - self._unflushed + np.arange(self._unflushed)) % BUFFER
            self._unflushed = 0
            self._standardise(self._buffer[idx])

    def _standardise(self, rows: np.ndarray) -> None:
        """Queue for the correlation the standardised innovations of ``rows`` (k, ``_COLUMNS``) observed at
        the current levels, of the epochs observed once the state had converged; epochs beyond
        ``CLIP_SIGMA`` (disturbances) count as gaps."""
        lv = self.levels
        z = np.zeros((len(rows), 3))
        z[:, 0] = rows[:, 1] / math.sqrt(lv.along_var)
        with_cross = rows[:, 7] == 1.0
        if with_cross.any():
            var_h, var_v = lv.across_vars(rows[with_cross, 4], rows[with_cross, 5])
            z[with_cross, 1:] = rows[with_cross, 2:4] / np.sqrt(np.column_stack([var_h, var_v]))
        z[np.abs(z).max(axis=1) > CLIP_SIGMA] = 0.0
        converged = rows[:, 6] == 1.0
        if converged.all():
            self._pending.append((rows[:, 0].copy(), z))  # not a view: the rows (64 bytes an epoch) are let go
        elif converged.any():
            self._pending.append((rows[converged, 0], z[converged]))

    def _store(self, rows: np.ndarray) -> None:
        k = min(len(rows), BUFFER)
        start = self._next
        stop = start + k
        if stop <= BUFFER:
            self._buffer[start:stop] = rows[-k:]
        else:  # wrapping around the ring's end
            self._buffer[start:] = rows[len(rows) - k : len(rows) - k + BUFFER - start]
            self._buffer[: stop - BUFFER] = rows[len(rows) - (stop - BUFFER) :]
        self._next = stop % BUFFER

    def _estimate(self) -> NoiseLevels:
        """The levels from the innovations within the window (``estimate_levels``)."""
        self._flush()
        # np.compress copies the selected rows at a third of the cost of boolean indexing
        recent = np.compress(self._buffer[:, 0] >= self._t - self.window_s, self._buffer, axis=0)
        if len(recent) < MIN_SAMPLES:  # too few to say more than the start did
            return self.levels
        cross = recent[:, 2:4] if self.attitude and np.isfinite(recent[:, 2:4]).all() else None
        return estimate_levels(
            recent[:, 1], cross, recent[:, 4], recent[:, 5], self.levels, self.floor_nt, self._predicted, self.method
        )

    def _autocorrelate(self) -> None:
        """Accumulate, with forgetting, the lagged products of the pending standardised innovations (k, 3)
        against the latest ``LAGS[-1]`` ones before them (kept in chronological order). Each epoch's products
        are weighted by ``exp(-age / memory)``, its age counted from the latest pending epoch, and what was
        accumulated before decays by the time since it."""
        if not self._pending:
            return
        pending, self._pending = self._pending, []
        memory = CORRELATION_WINDOWS * self.window_s
        end = float(pending[-1][0][-1])
        decay = 1.0 if self._t_products is None else math.exp(-max(end - self._t_products, 0.0) / memory)
        self._t_products = end
        self._prod *= decay
        self._sq *= decay
        # In pieces, each let go once counted: a whole log's products (and its pending innovations joined) would
        # not fit.
        while pending:
            times, z = pending.pop(0)
            for start in range(0, len(z), _CHUNK):
                piece = z[start : start + _CHUNK]
                weight = np.exp(-(end - times[start : start + _CHUNK]) / memory)
                self._sq += np.einsum("kc,k->c", piece**2, weight)
                # The ring starts as zeros, so a partner from before the first innovation adds nothing.
                history = np.concatenate([self._ring, piece])
                k, n = len(piece), len(history)
                weighted = piece * weight[:, None]
                for j, lag in enumerate(_LAG_LIST):  # each lag's partners are one slice of the history
                    self._prod[:, j] += np.einsum("kc,kc->c", weighted, history[n - k - lag : n - lag])
                self._count += k
                self._ring[...] = history[-len(self._ring) :]  # in place: constant memory

    def correlation(self) -> np.ndarray:
        """The autocorrelation (3, len(LAGS)) of the standardised innovations along the field, along ``h`` and
        along ``v`` at ``LAGS`` epochs, of every innovation observed so far."""
        self._flush()
        self._autocorrelate()
        return np.where(self._sq[:, None] > 0, self._prod / np.maximum(self._sq[:, None], 1e-300), 0.0)

    def inflations(self) -> tuple[float, float, float]:
        """The integrated autocorrelation times along the field, along ``h`` and along ``v``, epochs (1 for
        white innovations); the start's until the correlation has been measured over one window."""
        if self._measured_s < self.window_s:
            return self._start_inflations
        return self.measured_inflations()

    def measured_inflations(self) -> tuple[float, float, float]:
        """The integrated autocorrelation times of what has been observed so far, epochs (``inflations``
        without the start's)."""
        along, heading, across = (_integrated_time(rho) for rho in self.correlation())
        return (along, heading, across) if self.attitude else (along, along, along)

    def inflation(self) -> float:
        """The largest of ``inflations``."""
        return max(self.inflations())


def _integrated_time(rho) -> float:
    """``2 integral rho(L) dL - 1`` (epochs) of an autocorrelation sampled at ``LAGS``, by the trapezoid rule up
    to the lag where it falls below ``RHO_STOP``; at least 1."""
    total, prev_lag, prev_rho = 1.0, 0, 1.0
    for lag, r in zip(LAGS, rho):
        r = max(float(r), 0.0)
        total += (lag - prev_lag) * (prev_rho + r)  # 2 x the trapezoid over [prev_lag, lag]
        if r < RHO_STOP:  # the segment that crosses the threshold is the last one counted
            break
        prev_lag, prev_rho = lag, r
    return max(total - 2.0, 1.0)


def _robust_scale(values) -> float:
    """Standard deviation of zero-mean normal values among outliers: 1.4826 times the median absolute value,
    then again over the values within ``CLIP_SIGMA`` of that first scale (the first pass is moved by the
    share of outliers, the second is not)."""
    a = np.abs(np.asarray(values, float))  # a new array, its own to reorder (``_median(in_place=True)``)
    finite = np.isfinite(a)
    if not finite.all():
        a = a[finite]
    del finite
    if not a.size:
        return 0.0
    first = 1.4826 * _median(a, in_place=True)
    inside = a[a <= CLIP_SIGMA * first]
    del a
    return 1.4826 * _median(inside, in_place=True) if inside.size else first


def _median(a: np.ndarray, in_place: bool = False) -> float:
    """The median of a non-empty 1-D array (``np.partition`` directly: ``np.median``'s own handling costs
    more than the partition on the learner's few thousand values); ``in_place``: ``a`` reordered by the
    partition rather than copied (the same values, so the same median)."""
    n = len(a)
    hi = n // 2
    p = a if in_place else a.copy()
    p.partition(hi)
    # the lower middle value of an even count is the largest below the upper one: one selection, not two
    lo = float(p[:hi].max()) if n % 2 == 0 else float(p[hi])
    return 0.5 * (lo + float(p[hi]))


def estimate_levels(
    along, cross, field2, horizontal2, prior: NoiseLevels, floor_nt: float, predicted: float = 0.0, method="variational"
) -> NoiseLevels:
    """Noise levels from innovations: ``along`` (N,) nT along the field, ``cross`` (N, 2) nT along ``h`` and
    ``v`` (None: the attitude part of ``prior`` is kept), ``field2`` and ``horizontal2`` (N,) the field and
    its horizontal part squared, nT^2. Robust scales (1.4826 times the median absolute value, which a
    minority of disturbed epochs does not move), less (``matching``) or plus (``variational``) the
    variance ``predicted`` (nT^2) that the state's uncertainty explains along the field. The reference
    noise and the inflations are the prior's."""
    var_along = _robust_scale(along) ** 2
    # The state's part may not remove more than half of what was seen (a covariance-matching estimate can
    # otherwise go negative while the state is still uncertain).
    var_along += -min(predicted, 0.5 * var_along) if method == "matching" else predicted
    sensor2 = max(var_along - prior.reference_nt**2, floor_nt**2)
    tilt, heading = prior.attitude_rad, prior.heading_rad
    if cross is not None and len(cross):
        f2, h2 = float(np.mean(field2)), float(np.mean(horizontal2))  # smooth: the reference field's
        var_h, var_v = _robust_scale(cross[:, 0]) ** 2, _robust_scale(cross[:, 1]) ** 2
        tilt2 = max(var_v - var_along, 0.0) / f2
        tilt = math.sqrt(tilt2)
        heading = None  # a field nearly vertical shows no heading error: the tilt stands for it
        if h2 > HORIZONTAL_SHARE * f2:
            heading = math.sqrt(max(var_h - var_along - tilt2 * (f2 - h2), 0.0) / h2)
    along_i, heading_i, across_i = prior.inflations
    return NoiseLevels(math.sqrt(sensor2), tilt, prior.reference_nt, along_i, across_i, heading, heading_i)


#: Residuals given to the learner at once by ``robust_start``.
START_PIECE = 16_384


def robust_start(
    along, cross, field2, reference_nt: float, floor_nt: float, attitude_rad: float, horizontal2=None
) -> NoiseLevels:
    """Starting levels from the residuals of a first fit: ``along`` (N,) nT along the field, ``cross`` (N, 2)
    nT along ``h`` and ``v`` (None: keep ``attitude_rad``), ``field2`` (N,) and ``horizontal2`` (N,, default
    ``field2``) the field and its horizontal part squared, nT^2 (``estimate_levels`` of the residuals less
    their medians); their correlation measured the way the learner measures it. ``along`` and ``cross`` are
    the caller's working arrays (float64), centred in place: a long log's residuals are not copied."""
    along = np.asarray(along, float)
    along -= np.median(along)
    if cross is not None:
        cross = np.asarray(cross, float)
        for j in range(cross.shape[1]):  # a column's median at a time: one column's working copy
            cross[:, j] -= np.median(cross[:, j])
    horizontal2 = field2 if horizontal2 is None else horizontal2
    prior = NoiseLevels(floor_nt, attitude_rad, reference_nt)
    levels = estimate_levels(along, cross, field2, horizontal2, prior, floor_nt)
    learner = NoiseLearner(levels, floor_nt, attitude=cross is not None, adapt=False)
    # All at one instant, so that every epoch's lagged products weigh the same (no forgetting); in pieces, so
    # that the learner's working copies stay small for a long log (the ring carries the lags across them).
    for i in range(0, len(along), START_PIECE):
        piece = slice(i, i + START_PIECE)
        learner.observe(
            np.zeros(len(along[piece])),
            along[piece],
            None if cross is None else cross[piece],
            field2[piece],
            horizontal2=horizontal2[piece],
        )
    return levels.with_inflations(*learner.measured_inflations())
