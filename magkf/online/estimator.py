"""Gates and Kalman updates for blocks of epochs. Shared by logs (blocks of several epochs) and real
time (blocks of one).

``Estimator.process_block`` takes k consecutive epochs. The random walk's process noise for the block
is added first; then every epoch is gated on its own against the estimate before the block (magnitude
gate, then normalised innovation squared), and all accepted epochs update the state together as one
stacked measurement. For the linear vector measurement this is exactly the same as updating epoch by
epoch (the process noise is merely added at the block's start instead of spread over it); it lets the
per-log loop pay numpy's per-call cost once per block instead of once per epoch.

The noise the block's gates and update use is the one learned from the blocks before it; the block's own
innovations go to the learner at its end. The learned noise changes only every few seconds of data
(``noise.ESTIMATE_EVERY_S``), so a caller may whiten a span of many blocks at once (``Estimator.whiten``;
``Block.take`` cuts the span, and a block whitened at another noise is whitened again).

Which epochs a measurement model takes: those with status ``used`` (and, for a model that needs no
attitude, those with ``missing_attitude`` too); its ``fallback`` takes the ``missing_attitude`` ones.
The statuses are defined in ``magkf.status``.

The estimator knows a model only through ``MeasurementModel``'s methods: its whitening (``whiten``), its
rows (through the filter), their count (``rows``: the NIS's degrees of freedom) and its innovations for the
noise learner (``innovation``, split along the field by ``along_across``); never its name or its number of
rows otherwise.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import FilterConfig
from ..status import GATED_INNOVATION, GATED_MAGNITUDE, MISSING_ATTITUDE, USED
from . import kernel
from .filters import EKF, UKF, make_filter
from .measurements import Block, Magnitude, MeasurementModel, magnitude_jacobian, measurement_model
from .noise import NoiseLearner, NoiseLevels
from .state import StateLayout

__all__ = ["Estimator", "run_model"]

#: The kernel's stand-in for a block without whitened noise (``Block.N`` None: the identity), never read.
_NO_NOISE = np.zeros((1, 1, 1))


def _scale_rows(rows, factor) -> None:
    """Multiply each epoch's whitened rows (innovation, Jacobian, sigma-point predictions) by ``factor`` (k,):
    the epoch's noise variance divided by ``factor^2``."""
    rows.y = rows.y * factor[:, None]
    rows.H = rows.H * factor[:, None, None]
    if rows.h is not None:
        rows.h = rows.h * factor[None, :, None]


def _any_of(parts) -> np.ndarray:
    """The epochs (k,) that any of the ``(model, mask)`` parts takes (the one mask itself for one part)."""
    out = parts[0][1]
    for _, mask in parts[1:]:
        out = out | mask
    return out


def _huber(q: float, nis: np.ndarray) -> np.ndarray:
    """Huber weights (k,) of epochs of normalised innovation squared ``nis`` (k,): 1 up to the quantile ``q``,
    ``sqrt(q / nis)`` beyond it."""
    return np.minimum(1.0, np.sqrt(q / np.maximum(nis, 1e-300)))


def run_model(config: FilterConfig, layout: StateLayout, x0, magnitude_only: bool = False) -> MeasurementModel:
    """The measurement model of a run: the one ``config.measure`` names, or the magnitude alone
    (``magnitude_only``: a log without attitude)."""
    return Magnitude(config, layout, x0) if magnitude_only else measurement_model(config, layout, x0)


def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile of ``probability`` with ``dof`` degrees of freedom."""
    from scipy.special import chdtri

    return float(chdtri(dof, 1.0 - probability))


class Estimator:
    """The filter, the measurement model and the gates of one calibration run.

    ``layout`` gives the state blocks; ``x0`` (n,), ``P0`` (n, n) the initial estimate; the filter and the
    measurement model are the ones ``config`` names. ``noise`` the starting ``NoiseLevels`` (default: the
    configured noise); the learner (``magkf.online.noise``) refines it from the innovations unless
    ``config.adapt_noise`` is False. ``information`` accumulates the whitened ``H^T H`` of every update
    (for the observability report). ``model`` the measurement model (default: the one ``config.measure``
    names; ``run_model`` chooses it for a log).
    """

    def __init__(
        self,
        layout: StateLayout,
        config: FilterConfig,
        x0,
        P0,
        noise: NoiseLevels | None = None,
        model: MeasurementModel | None = None,
    ):
        self.layout, self.config = layout, config
        self.filter = make_filter(config.filter, x0, P0, layout.q_rate())
        self.model = model or measurement_model(config, layout, x0)
        start = noise or self.model.noise
        self.learner = NoiseLearner(
            start,
            config.noise_floor_nt,
            config.noise_window_s,
            attitude=self.model.needs_attitude,
            adapt=config.adapt_noise,
            method=config.noise_method,
        )
        self.model.set_noise(start)
        self.P0 = np.array(P0, float)
        self.information = np.zeros((layout.size, layout.size))
        self.reacquisitions = 0
        self._gated_since = None
        self._chi2 = {}
        # The compiled kernel (``magkf.online.kernel``): None until the run has filtered enough epochs in blocks
        # to pay for loading it (``kernel.WORTH_AFTER_EPOCHS``), False where it is not to be used.
        self._kernel = None if kernel.available() else False
        self._blocked_epochs = 0

    @property
    def noise(self) -> NoiseLevels:
        """The noise the models use now."""
        return self.model.noise

    @property
    def x(self) -> np.ndarray:
        return self.filter.x

    @property
    def P(self) -> np.ndarray:
        return self.filter.P

    def structure(self, field_body, R, heading=None):
        """What the model's noise at epochs with body field ``field_body`` (N, 3) and heading axis ``heading``
        (N, 3) is made of (see ``MeasurementModel.structure``), at calibration ``R``; None for a model that
        needs no attitude."""
        return self.model.structure(field_body, R, heading)

    def _bound(self, probability: float, rows: int) -> float:
        key = (probability, rows)
        if key not in self._chi2:
            self._chi2[key] = chi2_quantile(probability, rows)
        return self._chi2[key]

    def _parts(self, status) -> list:
        """``(model, mask)`` of the epochs each model takes."""
        model = self.model
        if not model.needs_attitude:
            return [(model, (status == USED) | (status == MISSING_ATTITUDE))]
        parts = [(model, status == USED)]
        if model.fallback is not None:
            parts.append((model.fallback, status == MISSING_ATTITUDE))
        return parts

    def process_block(self, t, dt_total: float, blk: Block, base):
        """Process k epochs; returns ``(status (k,) int8, updated (k,) bool, nis (k,) float)``.

        ``t`` (k,) s; ``dt_total`` seconds since the previous block's last epoch; ``blk`` the epochs'
        ``Block`` (its ``e`` is filled in here); ``base`` (k,) status known before filtering.
        """
        kf, layout = self.filter, self.layout
        if dt_total > 0:
            kf.predict(dt_total)
        status = np.array(base, dtype=np.int8)
        k = len(status)
        updated = np.zeros(k, bool)
        nis = np.empty(k)
        nis.fill(np.nan)  # cheaper than np.full for the one epoch of real time
        parts = self._parts(status)
        cand = _any_of(parts)
        if not np.count_nonzero(cand):
            return status, updated, nis
        x = kf.x
        if layout.has_extra:
            # a missing input counts as 0, as in the per-epoch table: an epoch that lacks a channel is not a
            # candidate, and a magnitude update without attitude does without a time lag's term (which needs it)
            blk.e = np.nan_to_num(layout.extra_terms(x, blk.H, blk.data))
        # The variance of the calibrated magnitude that the estimate's covariance implies, at the block's
        # first candidate (it changes little within a block), every block of the state included; and the
        # calibrated magnitude ``h`` (k,) of every epoch (for one epoch, the magnitude model's own), which the
        # block keeps for the models (``Block.magnitude``).
        i0 = int(cand.argmax())
        e0 = blk.e[i0 : i0 + 1] if isinstance(blk.e, np.ndarray) else blk.e
        h0, H0, w0 = magnitude_jacobian(layout.core_of(x), blk.m[i0 : i0 + 1] - e0)
        h = h0 if k == 1 else np.linalg.norm(layout.calibrated(x, blk.m, blk.e), axis=1)
        blk.magnitude = h
        if layout.has_extra:
            H0 = np.concatenate([H0[0], -w0[0] @ blk.H[i0][:, layout.EXTRA]])[None]
            predicted = float(H0[0] @ kf.P @ H0[0])
        else:
            core = layout.CORE
            predicted = float(H0[0] @ kf.P[core, core] @ H0[0])
        self._gate_and_update(t, blk, h, predicted, parts, cand, status, updated, nis)
        # What the block's innovations teach about the noise applies from the next block on: a span of
        # blocks is whitened at once (``whiten``), and a block's gates and update use one noise throughout.
        self._learn(t, x, blk, parts, predicted)
        return status, updated, nis

    def _gate_and_update(self, t, blk: Block, h, predicted, parts, cand, status, updated, nis) -> None:
        """Gate the candidate epochs of ``parts`` and update the filter with the accepted ones, writing their
        ``status``, ``updated`` and ``nis`` (k,) in place. ``h`` (k,) the calibrated magnitude at the
        estimate, nT; ``predicted`` its variance from the estimate's covariance, nT^2."""
        kf, k = self.filter, len(status)
        width = max(self.config.gate_nt, self.config.gate_sigma * math.sqrt(self.noise.along_var))
        distance = np.abs(h - blk.ref_mag)
        gated_any = np.count_nonzero(cand & (distance > width))
        if gated_any:  # the gate widens with the estimate's own uncertainty (3 sigma)
            off = distance > width + 3.0 * np.sqrt(predicted)
            status[cand & off] = GATED_MAGNITUDE
            on = ~off
            parts = [(model, mask & on) for model, mask in parts]
        if gated_any or len(parts) > 1:  # else the one part's epochs are the candidates, and there are some
            parts = [(model, mask) for model, mask in parts if np.count_nonzero(mask)]
            if not parts:
                return
        if blk.whitened_with is not self.noise:
            self.whiten(blk)
        part_blocks = [self._part_block(model, blk, mask) for model, mask in parts]
        if self._kernel_worth(parts, k) and self._kernel_update(t, parts[0], part_blocks[0], status, updated, nis):
            return
        lin = kf.linearise([(model, b) for (model, _), b in zip(parts, part_blocks)])
        gated = np.zeros(k, bool)
        accept_parts = []
        noise = self.noise
        for (model, mask), rows, part in zip(parts, lin.rows, part_blocks):
            idx = mask.nonzero()[0]
            nis[idx] = rows.nis
            refused = rows.nis > self._bound(self.config.innovation_prob, model.rows)
            gated[idx[refused]] = True
            accept_parts.append(~refused)
            # Heavy tails: beyond the Huber quantile an epoch is down-weighted, not refused; and each epoch
            # counts 1 / inflation of an independent one (the residuals' correlation in time), along the
            # field and across it apart.
            q = self._bound(self.config.huber_prob, model.rows)
            if part.N is not None:  # the correlation is in the whitening (``MeasurementModel.whiten``)
                if np.count_nonzero(rows.nis > q):  # else every weight is 1
                    _scale_rows(rows, np.sqrt(_huber(q, rows.nis)))
            else:
                _scale_rows(rows, np.sqrt(_huber(q, rows.nis) / noise.inflation_along))
        accept = _any_of(parts) & ~gated
        self._reacquire(t, gated, accept)
        status[gated] = GATED_INNOVATION
        if np.count_nonzero(accept):
            H = kf.update(lin, accept_parts)
            last = getattr(kf, "last_information", None)  # (H, H^T H) of the filter's latest fold, if any
            self.information += last[1] if last is not None and last[0] is H else H.T @ H
            updated[accept] = True

    def _kernel_worth(self, parts, k: int) -> bool:
        """Whether this block is gated and updated by the compiled kernel: one model's rows at the estimate (the
        EKF's, or the UKF's of a model linear in the state, which are the same) in a block of several epochs, once
        the run has filtered ``kernel.WORTH_AFTER_EPOCHS`` epochs in such blocks (the kernel loaded then)."""
        if self._kernel is False or len(parts) != 1 or k == 1:
            return False
        kf = self.filter
        if not (type(kf) is EKF or (type(kf) is UKF and getattr(parts[0][0], "linear", False))):
            return False
        if self._kernel is None:
            self._blocked_epochs += k
            if self._blocked_epochs < kernel.WORTH_AFTER_EPOCHS:
                return False
            self._kernel = kernel.load() or False
        return self._kernel is not False

    def _kernel_update(self, t, part, part_block: Block, status, updated, nis) -> bool:
        """``_gate_and_update`` of one model's epochs by the compiled kernel (``kernel.gate_and_fold``); False
        (nothing done) for a block the numpy path must take."""
        (model, mask), kf = part, self.filter
        y, H = model.linearise(kf.x, part_block)
        noise = part_block.N
        outcome, nis_k, refused, x, P, J = self._kernel(
            np.ascontiguousarray(y, float),
            np.ascontiguousarray(H, float),
            _NO_NOISE if noise is None else np.ascontiguousarray(noise, float),
            noise is not None,
            np.ascontiguousarray(kf.x, float),
            np.ascontiguousarray(kf.P, float),
            self._bound(self.config.innovation_prob, model.rows),
            self._bound(self.config.huber_prob, model.rows),
            float(self.noise.inflation_along),
        )
        if outcome == kernel.USE_NUMPY:
            return False
        idx = mask.nonzero()[0]
        nis[idx] = nis_k
        gated = np.zeros(len(status), bool)
        gated[idx[refused]] = True
        accept = mask & ~gated
        self._reacquire(t, gated, accept)
        status[gated] = GATED_INNOVATION
        if outcome == kernel.UPDATED:
            kf.x, kf.P = x, P
            self.information += J
            updated[accept] = True
        return True

    def _part_block(self, model, blk: Block, mask) -> Block:
        """The epochs ``mask`` (k,) of ``blk`` for ``model``: the run's model takes the block as it was whitened
        for it, the fallback takes it without the run's model's noise structure and whitening
        (``Block.for_fallback``)."""
        part = blk if np.count_nonzero(mask) == len(mask) else blk.take(mask)
        return part if model is self.model else part.for_fallback()

    def whiten(self, blk: Block) -> None:
        """Set the whitening of ``blk``'s epochs at the current noise (``Block.W``, ``Block.N``): the model's
        (``MeasurementModel.whiten``), with the residuals' correlation in time folded in along the field's
        frame where the model's rows allow it (``N`` is then the covariance of the model's own whitened noise
        in those rows, which the gates use). Computed once for many blocks when ``blk`` spans them
        (``Block.take`` keeps it)."""
        noise = self.noise
        self.model.whiten(self.x, blk, noise.inflations)
        blk.whitened_with = noise

    def _learn(self, t, x, blk: Block, parts, predicted: float) -> None:
        """Show the noise learner the innovations of the candidate epochs (before any gate: the learner
        winsorises them itself) and give the models what it learned. Each model gives its innovations at the
        estimate ``x`` (``MeasurementModel.innovation``), split along the field and across it by its own
        frame (``along_across``; the block's frame is the run's model's, none for the fallback)."""
        along, cross, field2, horizontal2, times = [], [], [], [], []
        for model, mask in parts:
            count = np.count_nonzero(mask)
            if not count:
                continue
            pick = slice(None) if count == len(mask) else mask  # a view when every epoch is the part's
            frame = blk.frame if model is self.model else None
            innovation = model.innovation(x, blk if model is self.model else blk.for_fallback())[pick]
            a, c = model.along_across(innovation, None if frame is None else frame[pick])
            along.append(a)
            cross.append(c)
            heading = blk.heading[pick]
            field2.append(blk.ref_mag[pick] ** 2)
            horizontal2.append((heading * heading).sum(axis=1))
            times.append(np.asarray(t)[pick])
        if not along:
            return
        if len(along) == 1:
            self.learner.observe(times[0], along[0], cross[0], field2[0], predicted, horizontal2[0])
        else:
            with_cross = [c for c in cross if c is not None]
            cr = np.concatenate(with_cross) if len(with_cross) == len(cross) else None
            self.learner.observe(
                np.concatenate(times),
                np.concatenate(along),
                cr,
                np.concatenate(field2),
                predicted,
                np.concatenate(horizontal2),
            )
        self.model.set_noise(self.learner.levels)

    def _reacquire(self, t, gated, accept) -> None:
        """After ``max_gated_s`` of innovation gating with nothing accepted, widen P so the filter can recover."""
        if np.count_nonzero(accept):
            self._gated_since = None
            return
        if not np.count_nonzero(gated):
            return
        t = np.asarray(t)
        if self._gated_since is None:
            self._gated_since = float(t[gated][0])
        if self.config.max_gated_s > 0 and float(t[gated][-1]) - self._gated_since > self.config.max_gated_s:
            self.filter.inflate(self.P0)
            self._gated_since = None
            self.reacquisitions += 1
