"""Gates and Kalman updates for blocks of epochs. Shared by logs (blocks of several epochs) and real
time (blocks of one).

``Estimator.process_block`` takes k consecutive epochs. The random walk's process noise for the block
is added first; then every epoch is gated on its own against the estimate before the block (magnitude
gate, then normalised innovation squared), and all accepted epochs update the state together as one
stacked measurement. For the linear vector measurement this is exactly the same as updating epoch by
epoch (the process noise is merely added at the block's start instead of spread over it); it lets the
per-log loop pay numpy's per-call cost once per block instead of once per epoch.

Statuses, in order of precedence:

``missing_mag``        a magnetometer value is missing: no update.
``missing_position``   no reference field (no position and no ``ref_*``): no update.
``gated_dop``          ``dop > dop_max``: no update.
``missing_column``     a column an added effect needs is empty at this epoch: no update.
``gated_magnitude``    ``| |calibrated m| - |B_ref| | > gate_nt + 3 sigma``, sigma the standard deviation of the
                       calibrated magnitude that the estimate's covariance implies: no update.
``gated_innovation``   normalised innovation squared above the chi-square bound: no update.
``missing_attitude``   no attitude: a magnitude-only update (``updated`` tells whether it was made).
``used``               updated with the configured measurement.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from ..config import FilterConfig
from .filters import RandomWalkEKF, RandomWalkUKF, inv_small
from .measurements import magnitude_jacobian, magnitude_noise
from .state import StateLayout

STATUSES = ("used", "gated_dop", "gated_magnitude", "gated_innovation", "missing_attitude",
            "missing_position", "missing_mag", "missing_column")
(USED, GATED_DOP, GATED_MAGNITUDE, GATED_INNOVATION, MISSING_ATTITUDE, MISSING_POSITION, MISSING_MAG,
 MISSING_COLUMN) = range(8)


class Estimator:
    """The filter and its gates for one calibration run.

    ``layout`` gives the state blocks; ``x0`` (n,), ``P0`` (n, n) the initial estimate. Linear effects
    enter through the per-epoch Jacobian ``H`` (k, 3, n) that the caller supplies (``m = H x`` for the
    vector model); nonlinear effects (``Effect.linear`` False) are evaluated here.
    """

    def __init__(self, layout: StateLayout, config: FilterConfig, x0, P0):
        self.layout, self.config = layout, config
        filter_class = RandomWalkEKF if config.filter == "ekf" else RandomWalkUKF
        self.kf = filter_class(x0, P0, layout.q_rate())
        self.P0 = np.array(P0, float)
        self.chi2_vector = float(stats.chi2.ppf(config.innovation_prob, 3))
        self.chi2_scalar = float(stats.chi2.ppf(config.innovation_prob, 1))
        self.nonlinear = [(e, layout.slices[e.name]) for e in layout.extra() if not e.linear]
        self.extra = layout.size > 12
        self.magnitude_only = config.measure == "magnitude"
        self.information = np.zeros((layout.size, layout.size))  # sum of whitened H^T H over updates
        # Magnitude-only: a rotation R -> R Q changes no magnitude. Keep the EKF from gaining spurious
        # information along it (observability-constrained EKF): project the magnitude Jacobians off the
        # rotation directions of the initial R.
        self._rotation_projector = None
        if self.magnitude_only:
            N = rotation_directions(np.asarray(x0)[:9].reshape(3, 3), layout.size)
            self._rotation_projector = np.eye(layout.size) - N @ np.linalg.solve(N.T @ N, N.T)
        self.reacquisitions = 0
        self._gated_since = None

    @property
    def x(self) -> np.ndarray:
        return self.kf.x

    @property
    def P(self) -> np.ndarray:
        return self.kf.P

    # ------------------------------------------------------------ a block of epochs
    def process_block(self, t, dt_total: float, m, ref_mag, H, W, base, data=None):
        """Process k epochs; returns ``(status (k,) int, updated (k,) bool, nis (k,) float)``.

        ``t`` (k,) s; ``dt_total`` seconds since the previous block's last epoch; ``m`` (k, 3) raw nT;
        ``ref_mag`` (k,) reference magnitude nT; ``H`` (k, 3, n) Jacobian of the linear blocks (NaN rows
        without attitude); ``W`` (k, 3, 3) whitening of the vector measurement (``W R W^T = I`` for its
        sensor-frame noise ``R``, see ``magkf.measurements.whitening``); ``base``
        (k,) status known before filtering (``USED`` for a candidate with attitude, ``MISSING_ATTITUDE``
        for one without); ``data`` the block's ``EpochData`` when nonlinear effects are present.
        """
        kf = self.kf
        if dt_total > 0:
            kf.predict_dt(dt_total)
        status = np.array(base, dtype=np.int8)
        k = len(status)
        updated = np.zeros(k, bool)
        nis = np.full(k, np.nan)
        vector = (status == USED) & (not self.magnitude_only)
        scalar = (status == MISSING_ATTITUDE) | ((status == USED) & self.magnitude_only)
        if self.config.measure == "vector":
            scalar &= status != MISSING_ATTITUDE
        cand = vector | scalar
        if not np.count_nonzero(cand):
            return status, updated, nis
        x = kf.x
        m_clean = m - self._extra_terms(x, H, data) if self.extra else m
        Rinv = inv_small(x[:9].reshape(3, 3))
        c = (m_clean - x[9:12]) @ Rinv.T
        h = np.sqrt(np.einsum("ki,ki->k", c, c))
        off = np.abs(h - ref_mag) > self.config.gate_nt
        if np.count_nonzero(cand & off):
            # The gate widens with the estimate's own uncertainty of the calibrated magnitude (3 sigma),
            # evaluated at the block's first candidate (it changes little within a block).
            i0 = int(np.argmax(cand))
            w0 = (c[i0] / h[i0]) @ Rinv
            H0 = np.concatenate([-np.outer(w0, c[i0]).ravel(), -w0])
            off = np.abs(h - ref_mag) > self.config.gate_nt + 3.0 * np.sqrt(H0 @ self.kf.P[:12, :12] @ H0)
        gated_mag = cand & off
        status[gated_mag] = GATED_MAGNITUDE
        vector &= ~off
        scalar &= ~off
        if not (np.count_nonzero(vector) or np.count_nonzero(scalar)):
            return status, updated, nis
        if isinstance(kf, RandomWalkEKF):
            rows = self._ekf_rows(x, m, m_clean, ref_mag, H, W, vector, scalar, data)
        else:
            rows = self._ukf_rows(m, m_clean, ref_mag, H, W, vector, scalar, data)
        nis[vector | scalar] = rows["nis"]
        bound = np.where(vector, self.chi2_vector, self.chi2_scalar)
        gated = (vector | scalar) & (nis > bound)
        accept = (vector | scalar) & ~gated
        self._reacquire(t, gated, accept)
        status[gated] = GATED_INNOVATION
        if np.count_nonzero(accept):
            self._update(rows, accept[vector | scalar])
            updated[accept] = True
        return status, updated, nis

    # ------------------------------------------------------------ rows of the stacked measurement
    def _extra_terms(self, x, H, data):
        """Raw-field terms (k, 3) of the effects after the core block at state ``x``."""
        e = np.einsum("kij,j->ki", H[:, :, 12:], x[12:])
        if self.nonlinear:
            e = e + self._nonlinear(x, data)
        return e

    def _nonlinear(self, x, data):
        total = 0.0
        for effect, sl in self.nonlinear:
            total = total + effect.contribution(x[..., sl], data)
        return total

    def _ekf_rows(self, x, m, m_clean, ref_mag, H, W, vector, scalar, data):
        """Whitened, linearised rows of every candidate epoch: per-epoch NIS, and what the update needs."""
        P = self.kf.P
        idx = np.flatnonzero(vector | scalar)
        nis = np.empty(len(idx))
        rows = {"order": idx, "vector_mask": vector[idx], "scalar_mask": scalar[idx]}
        if np.count_nonzero(vector):
            Hv = H[vector]
            if self.nonlinear:
                Hv = Hv.copy()
                dv = data.take(vector)
                for effect, sl in self.nonlinear:
                    Hv[:, :, sl] = effect.jacobian(x[sl], dv)
                yv = m[vector] - Hv @ x - self._nonlinear(x, dv)
            else:
                yv = m[vector] - Hv @ x
            Wv = W[vector]
            Hv = Wv @ Hv
            yv = np.einsum("kij,kj->ki", Wv, yv)
            S = Hv @ P @ Hv.transpose(0, 2, 1) + np.eye(3)
            nis[vector[idx]] = np.einsum("ki,kij,kj->k", yv, inv_small(S), yv)
            rows["vector"] = (yv, Hv)
        if np.count_nonzero(scalar):
            h, Hs_core, w = magnitude_jacobian(x[:12], m_clean[scalar])
            Hs = np.zeros((len(h), self.layout.size))
            Hs[:, :12] = Hs_core
            if self.extra:
                Hs[:, 12:] = -np.einsum("ki,kij->kj", w, H[scalar][:, :, 12:])
            if self._rotation_projector is not None:
                Hs = Hs @ self._rotation_projector
            sd = np.sqrt(magnitude_noise(w, self.config))
            Hs, ys = Hs / sd[:, None], (ref_mag[scalar] - h) / sd
            nis[scalar[idx]] = ys**2 / (np.einsum("ki,ij,kj->k", Hs, P, Hs) + 1.0)
            rows["scalar"] = (ys, Hs)
            rows["scalar_H"] = Hs
        rows["nis"] = nis
        return rows

    def _ukf_rows(self, m, m_clean, ref_mag, H, W, vector, scalar, data):
        """Sigma-point predictions for every candidate epoch (one set of fresh sigma points per block)."""
        kf = self.kf
        sigmas = kf.points_fn.sigma_points(kf.x, kf.P)
        idx = np.flatnonzero(vector | scalar)
        nis = np.empty(len(idx))
        rows = {"sigmas": sigmas, "order": idx, "vector_mask": vector[idx], "scalar_mask": scalar[idx]}
        Wm, Wc = kf.Wm, kf.Wc
        if np.count_nonzero(vector):
            Hv = H[vector]
            hv = np.einsum("kij,sj->ski", Hv, sigmas)  # (S, k, 3)
            if self.nonlinear:
                hv = hv + self._nonlinear(sigmas, data.take(vector))
            Wv = W[vector]
            hv = np.einsum("kij,skj->ski", Wv, hv)  # whitened: unit noise
            rows["vector_H"] = Wv @ Hv
            zp = np.einsum("s,ski->ki", Wm, hv)
            dz = hv - zp
            S = np.einsum("s,ski,skj->kij", Wc, dz, dz) + np.eye(3)
            yv = np.einsum("kij,kj->ki", Wv, m[vector]) - zp
            nis[vector[idx]] = np.einsum("ki,kij,kj->k", yv, inv_small(S), yv)
            rows["vector"] = (yv, hv)
        if np.count_nonzero(scalar):
            mc = m_clean[scalar]
            if self.extra:  # the other effects' terms move with the sigma points too
                mc = mc[None] - np.einsum("kij,sj->ski", H[scalar][:, :, 12:], sigmas[:, 12:] - kf.x[12:])
            Rs = sigmas[:, :9].reshape(-1, 1, 3, 3)
            cs = np.linalg.solve(Rs, (mc - sigmas[:, None, 9:12])[..., None])[..., 0]
            hs = np.linalg.norm(cs, axis=2)  # (S, k)
            _, H_core, w = magnitude_jacobian(kf.x[:12], m_clean[scalar])
            sd = np.sqrt(magnitude_noise(w, self.config))
            H_lin = np.zeros((len(sd), self.layout.size))
            H_lin[:, :12] = H_core
            if self.extra:
                H_lin[:, 12:] = -np.einsum("ki,kij->kj", w, H[scalar][:, :, 12:])
            rows["scalar_H"] = H_lin / sd[:, None]  # for the information only
            hs = hs / sd  # whitened
            zp = Wm @ hs
            ys = ref_mag[scalar] / sd - zp
            nis[scalar[idx]] = ys**2 / (np.einsum("s,sk->k", Wc, (hs - zp) ** 2) + 1.0)
            rows["scalar"] = (ys, hs)
        rows["nis"] = nis
        return rows

    # ------------------------------------------------------------ the stacked update
    def _update(self, rows, accept):
        """Update with the accepted epochs' whitened rows, all at once (unit noise)."""
        vmask, smask = rows["vector_mask"], rows["scalar_mask"]
        va, sa = accept[vmask], accept[smask]
        kf = self.kf
        ys, Hs = [], []
        if np.count_nonzero(va):
            y, Hv = rows["vector"]
            ys.append(y[va].ravel())
            Hs.append(Hv[va].reshape(-1, Hv.shape[2]) if isinstance(kf, RandomWalkEKF)
                      else Hv[:, va].reshape(Hv.shape[0], -1))
        if np.count_nonzero(sa):
            y, Hsc = rows["scalar"]
            ys.append(y[sa])
            Hs.append(Hsc[sa] if isinstance(kf, RandomWalkEKF) else Hsc[:, sa])
        y = np.concatenate(ys)
        if isinstance(kf, RandomWalkEKF):
            Hst = np.vstack(Hs)
            kf.correct_stacked(y, Hst)
            self.information += Hst.T @ Hst
        else:
            kf.correct_sigmas(rows["sigmas"], np.hstack(Hs), y)
            if np.count_nonzero(va):  # information of the (linear) vector rows: H_whitened^T H_whitened
                Hl = rows["vector_H"][va].reshape(-1, self.layout.size)
                self.information += Hl.T @ Hl
            if np.count_nonzero(sa):
                Hl = rows["scalar_H"][sa]
                self.information += Hl.T @ Hl

    def _reacquire(self, t, gated, accept) -> None:
        """After ``max_gated_s`` of innovation gating with nothing accepted, widen P so the filter can recover."""
        if np.count_nonzero(accept):
            self._gated_since = None
            return
        if not np.count_nonzero(gated):
            return
        t_g = float(np.asarray(t)[gated][0])
        if self._gated_since is None:
            self._gated_since = t_g
        if self.config.max_gated_s > 0 and float(np.asarray(t)[gated][-1]) - self._gated_since > self.config.max_gated_s:
            self.kf.P = self.kf.P + self.P0
            self._gated_since = None
            self.reacquisitions += 1


def rotation_directions(R: np.ndarray, size: int) -> np.ndarray:
    """State directions (size, 3) of ``R -> R (I + Omega)`` for the three infinitesimal rotations Omega."""
    out = np.zeros((size, 3))
    for k in range(3):
        omega = np.zeros((3, 3))
        i, j = [(1, 2), (2, 0), (0, 1)][k]
        omega[i, j], omega[j, i] = -1.0, 1.0
        out[:9, k] = (R @ omega).ravel()
    return out
