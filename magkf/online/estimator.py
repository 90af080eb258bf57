"""Gates and Kalman updates for blocks of epochs. Shared by logs (blocks of several epochs) and real
time (blocks of one).

``Estimator.process_block`` takes k consecutive epochs. The random walk's process noise for the block
is added first; then every epoch is gated on its own against the estimate before the block (magnitude
gate, then normalised innovation squared), and all accepted epochs update the state together as one
stacked measurement. For the linear vector measurement this is exactly the same as updating epoch by
epoch (the process noise is merely added at the block's start instead of spread over it); it lets the
per-log loop pay numpy's per-call cost once per block instead of once per epoch.

Which epochs a measurement model takes: those with status ``used`` (and, for a model that needs no
attitude, those with ``missing_attitude`` too); its ``fallback`` takes the ``missing_attitude`` ones.
The statuses are defined in ``magkf.status``.
"""

from __future__ import annotations

import numpy as np

from ..config import FilterConfig
from ..status import Status
from .filters import make_filter
from .measurements import Block, magnitude_jacobian, measurement_model
from .state import StateLayout

__all__ = ["Estimator"]

# Plain integers: enum members are slow to look up and to compare with in the per-block loop.
USED, MISSING_ATTITUDE = int(Status.USED), int(Status.MISSING_ATTITUDE)
GATED_MAGNITUDE, GATED_INNOVATION = int(Status.GATED_MAGNITUDE), int(Status.GATED_INNOVATION)


def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile of ``probability`` with ``dof`` degrees of freedom."""
    from scipy.special import chdtri

    return float(chdtri(dof, 1.0 - probability))


class Estimator:
    """The filter, the measurement model and the gates of one calibration run.

    ``layout`` gives the state blocks; ``x0`` (n,), ``P0`` (n, n) the initial estimate; the filter and the
    measurement model are the ones ``config`` names. ``information`` accumulates the whitened
    ``H^T H`` of every update (for the observability report).
    """

    def __init__(self, layout: StateLayout, config: FilterConfig, x0, P0):
        self.layout, self.config = layout, config
        self.filter = make_filter(config.filter, x0, P0, layout.q_rate())
        self.model = measurement_model(config, layout, x0)
        self.P0 = np.array(P0, float)
        self.information = np.zeros((layout.size, layout.size))
        self.reacquisitions = 0
        self._gated_since = None
        self._chi2 = {}

    @property
    def x(self) -> np.ndarray:
        return self.filter.x

    @property
    def P(self) -> np.ndarray:
        return self.filter.P

    def whitening(self, field_body, R):
        """The model's whitening (N, 3, 3) of epochs with body field ``field_body`` (N, 3) at ``R`` (or None)."""
        return self.model.whitening(field_body, R)

    def _bound(self, rows: int) -> float:
        if rows not in self._chi2:
            self._chi2[rows] = chi2_quantile(self.config.innovation_prob, rows)
        return self._chi2[rows]

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
        nis = np.full(k, np.nan)
        parts = self._parts(status)
        cand = parts[0][1] if len(parts) == 1 else np.logical_or.reduce([mask for _, mask in parts])
        if not np.count_nonzero(cand):
            return status, updated, nis
        x = kf.x
        if layout.has_extra:
            blk.e = layout.extra_terms(x, blk.H, blk.data)
        h = np.linalg.norm(layout.calibrated(x, blk.m, blk.e), axis=1)
        off = np.abs(h - blk.ref_mag) > self.config.gate_nt
        if np.count_nonzero(cand & off):
            # The gate widens with the estimate's own uncertainty of the calibrated magnitude (3 sigma),
            # evaluated at the block's first candidate (it changes little within a block).
            i0 = int(np.argmax(cand))
            e0 = blk.e[i0 : i0 + 1] if isinstance(blk.e, np.ndarray) else blk.e
            _, H0, _ = magnitude_jacobian(layout.core_of(x), blk.m[i0 : i0 + 1] - e0)
            core = layout.CORE
            sigma = float(np.sqrt(H0[0] @ kf.P[core, core] @ H0[0]))
            off = np.abs(h - blk.ref_mag) > self.config.gate_nt + 3.0 * sigma
        status[cand & off] = GATED_MAGNITUDE
        parts = [(model, mask & ~off) for model, mask in parts if np.count_nonzero(mask & ~off)]
        if not parts:
            return status, updated, nis
        lin = kf.linearise([(model, blk if mask.all() else blk.take(mask)) for model, mask in parts])
        gated = np.zeros(k, bool)
        accept_parts = []
        for (model, mask), rows in zip(parts, lin.rows):
            idx = np.flatnonzero(mask)
            nis[idx] = rows.nis
            refused = rows.nis > self._bound(model.rows)
            gated[idx[refused]] = True
            accept_parts.append(~refused)
        accept = (parts[0][1] if len(parts) == 1 else np.logical_or.reduce([mask for _, mask in parts])) & ~gated
        self._reacquire(t, gated, accept)
        status[gated] = GATED_INNOVATION
        if np.count_nonzero(accept):
            H = kf.update(lin, accept_parts)
            self.information += H.T @ H
            updated[accept] = True
        return status, updated, nis

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
