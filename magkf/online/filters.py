"""Kalman filters over a random-walk parameter state, behind one small interface.

The parameters follow a random walk (``F = I``), so the prediction is exact and cheap: ``x`` unchanged,
``P += Q dt``. An update takes the measurement models' linearisation of a block of epochs, already
whitened (unit noise):

    lin = kf.linearise([(model, block), ...])     # per-epoch innovations, Jacobians and NIS
    kf.update(lin, [accept, ...])                  # the accepted epochs, stacked into one update

``EKF`` linearises each model at the estimate and updates in the Joseph form (expanded so that it is
exactly symmetric), with a positive-definiteness guard. ``UKF`` draws sigma points fresh from the
current ``(x, P)`` at every update (never stale ones from an earlier prediction) with FilterPy's
``MerweScaledSigmaPoints``, and the models predict all of them in one vectorised call; rows linear in the
state, for which the unscented transform is exact, it takes as the EKF does. Both expose ``x``, ``P``,
``predict(dt)``, ``linearise``, ``update``, ``correct`` (the Kalman update of given whitened rows),
``inflate``, ``copy`` and ``prepare(models)`` (whatever the filter loads for those models, loaded now
rather than at the first update that needs it); nothing else.
``FILTERS`` (``magkf.plugins``) maps a name to its class; ``Filter`` is the interface a new filter implements.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from ..conventions import inverse3
from ..plugins import FILTERS
from .measurements import _whitening_stack

__all__ = ["Filter", "EKF", "UKF", "FILTERS", "Rows", "Linearisation", "make_filter"]


@dataclass
class Rows:
    """One model's whitened rows for k epochs: innovation ``y`` (k, r), Jacobian ``H`` (k, r, n) at the
    estimate (the information they carry), normalised innovation squared ``nis`` (k,) and, for the UKF's
    rows that are not linear, the whitened predictions at the sigma points ``h`` (S, k, r; None otherwise);
    ``linear`` the rows are linear in the state (``MeasurementModel.linear``: ``H`` is then their Jacobian
    everywhere)."""

    y: np.ndarray
    H: np.ndarray
    nis: np.ndarray
    h: np.ndarray | None = None
    linear: bool = False


@dataclass
class Linearisation:
    """Every model's rows for one update, and the UKF's sigma points (S, n) they were predicted at."""

    rows: list
    sigmas: np.ndarray | None = None


def _guard(P: np.ndarray) -> np.ndarray:
    """``P`` (symmetric) with its eigenvalues clipped if a diagonal element is not positive."""
    if np.count_nonzero(P.ravel()[:: P.shape[0] + 1] <= 0):
        w, v = np.linalg.eigh(P)
        P = (v * np.maximum(w, 1e-18 * max(w.max(), 1e-300))) @ v.T
    return P


def _add_noise(S: np.ndarray, blk) -> None:
    """Add the whitened noise of ``blk`` (``Block.N``, or the identity) to innovation covariances (k, r, r)."""
    N = getattr(blk, "N", None)
    if N is not None:  # the block was whitened for the model whose rows these are (``Estimator._part_block``)
        S += N
    else:
        r = S.shape[1]
        S[:, np.arange(r), np.arange(r)] += 1.0


def _weighted_covariance(weights: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """``sum_s weights[s] dz[s, k] dz[s, k]^T`` (k, r, r) of deviations ``dz`` (S, k, r)."""
    D = np.moveaxis(dz, 0, 1)  # (k, S, r)
    return np.swapaxes(D * weights[:, None], 1, 2) @ D


def _nis(y: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``y_k^T S_k^-1 y_k`` (k,) of innovations (k, r) with symmetric covariances (k, r, r)."""
    if S.shape[1] == 1:
        return y[:, 0] ** 2 / S[:, 0, 0]
    if S.shape[1] == 3:  # by cofactors of the upper triangle: a third of a stacked inverse's cost
        if len(S) == 1:  # one epoch (real time): in plain floats
            (a, b, c), (_, d, e), (_, _, f) = S[0].tolist()
            return np.array([_inverse_quadratic3(a, b, c, d, e, f, *y[0].tolist())])
        return _inverse_quadratic3(S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2], *y.T)
    return np.einsum("ki,kij,kj->k", y, np.linalg.inv(S), y)


def _inverse_quadratic3(a, b, c, d, e, f, y0, y1, y2):
    """``y^T S^-1 y`` for ``S = [[a, b, c], [b, d, e], [c, e, f]]`` and ``y = (y0, y1, y2)`` (floats or arrays
    of them), by cofactors."""
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    quadratic = y0 * (y0 * c00 + 2.0 * (y1 * c01 + y2 * c02)) + y1 * (y1 * (a * f - c * c) + 2.0 * y2 * (b * c - a * e))
    return (quadratic + y2 * y2 * (a * d - b * b)) / (a * c00 + b * c01 + c * c02)


class Filter(ABC):
    """The interface of a filter over the calibration's parameter state (a plug-in kind:
    ``magkf.plugins.FILTERS``).

    The estimator (``magkf.online.estimator``) drives it block by block: ``predict`` over the time since the
    last block, ``linearise`` the measurement models' rows of the block, its own gates decide which epochs
    to accept, then ``update`` with those. A filter is constructed as ``cls(x0, P0, q_rate)``.

    Parameters
    ----------
    x0 : ndarray, shape (n,)
        Initial state: ``R`` row-major, ``b`` (nT), then each effect's parameters.
    P0 : ndarray, shape (n, n)
        Initial covariance, in the state's units squared.
    q_rate : ndarray, shape (n,)
        Random-walk variance of each state per second.

    Attributes
    ----------
    name : str
        The name ``FilterConfig(filter=...)`` and ``--filter`` take.
    x : ndarray, shape (n,)
        The estimate.
    P : ndarray, shape (n, n)
        Its covariance.
    """

    name: str = "filter"
    x: np.ndarray
    P: np.ndarray

    @abstractmethod
    def predict(self, dt: float) -> None:
        """Propagate ``x`` and ``P`` over ``dt`` seconds."""

    @abstractmethod
    def linearise(self, parts) -> Linearisation:
        """The rows of each ``(model, block)`` pair of ``parts`` (``MeasurementModel``, ``Block``): whitened
        innovations, Jacobians and per-epoch NIS (``Rows``), for the gates to judge."""

    @abstractmethod
    def update(self, lin: Linearisation, accept) -> np.ndarray:
        """Update with the accepted epochs of ``lin`` (``accept``: one boolean mask (k,) per part); returns
        the whitened Jacobian (r, n) of the rows used (the information the update carried)."""

    @abstractmethod
    def correct(self, y, H, R=None) -> None:
        """The Kalman update of given rows: innovation ``y`` (r,), Jacobian ``H`` (r, n), noise ``R`` (r, r;
        None: whitened rows, the identity)."""

    @abstractmethod
    def inflate(self, P_add) -> None:
        """``P += P_add`` (n, n): widen the covariance so that the filter can re-acquire."""

    @abstractmethod
    def copy(self) -> Filter:
        """An independent copy (state, covariance and settings)."""

    def prepare(self, models) -> None:
        """Load now what an update of ``models``' rows will need (nothing by default), rather than at the first
        update that needs it."""
        return None


class _RandomWalkFilter(Filter):
    """What the EKF and the UKF share: the state, the exact random-walk prediction, inflation, a copy."""

    name = "filter"

    def __init__(self, x0, P0, q_rate):
        self.x = np.array(x0, float)
        self.P = np.array(P0, float)
        self.q_rate = np.asarray(q_rate, float)
        self._stride = len(self.x) + 1
        #: ``(H, H^T H)`` of the latest rows folded in by their information (``correct``): a caller summing the
        #: information of the updates (``Estimator.information``) takes it rather than computing it again.
        self.last_information = None

    def predict(self, dt: float) -> None:
        """Random-walk prediction over ``dt`` seconds: ``P += Q dt`` (``x`` unchanged, exact)."""
        self.P.ravel()[:: self._stride] += self.q_rate * dt

    def inflate(self, P_add) -> None:
        """``P += P_add`` (n, n): widen the covariance so that the filter can re-acquire."""
        self.P = self.P + P_add

    def copy(self):
        """An independent copy (state, covariance and settings)."""
        return copy.deepcopy(self)

    def prepare(self, models) -> None:
        """Load now what an update of ``models``' rows will need (nothing for this filter)."""

    def _update_at_estimate(self, lin: Linearisation, accept) -> np.ndarray:
        """Update with the accepted epochs of every part at once, by their rows at the estimate (``correct``);
        returns the whitened Jacobian (r, n) of the rows used. ``accept`` holds one boolean mask (k,) per part."""
        if len(lin.rows) == 1 and np.count_nonzero(accept[0]) == len(accept[0]):  # every epoch of one part: no copies
            y, H = lin.rows[0].y.ravel(), lin.rows[0].H.reshape(-1, self.x.size)
        else:
            ys = [r.y[a].ravel() for r, a in zip(lin.rows, accept)]
            Hs = [r.H[a].reshape(-1, self.x.size) for r, a in zip(lin.rows, accept)]
            y, H = np.concatenate(ys), np.vstack(Hs)
        self.correct(y, H)
        return H

    def _rows_at_estimate(self, model, blk, linear: bool = False) -> Rows:
        """``model``'s rows of ``blk`` linearised at the estimate, with per-epoch NIS ``y^T (H P H^T + N)^-1 y``
        (``N`` the block's whitened noise, ``Block.N``)."""
        y, H = model.linearise(self.x, blk)
        k, r, n = H.shape
        S = (H.reshape(k * r, n) @ self.P).reshape(k, r, n) @ H.transpose(0, 2, 1)  # one product for P
        _add_noise(S, blk)
        return Rows(y, H, _nis(y, S), linear=linear)

    def _fold_information(self, J, g) -> bool:
        """Update with the information ``J = H^T H`` (n, n) and ``g = H^T y`` (n,) of whitened rows; False
        (nothing changed) when ``P`` is not positive definite.

        With ``P = L L^T``: ``P+ = L (I + L^T J L)^-1 L^T`` and ``x+ = x + P+ g``, the Kalman update of those
        rows exactly (the information filter's ``P+^-1 = P^-1 + J`` without ever inverting ``P``); the
        matrix inverted has eigenvalues of at least 1. (numpy's factor and solve, not scipy's LAPACK called
        directly: faster by a few microseconds where scipy's BLAS runs on one thread, they were a hundred times
        slower where it did not.)
        """
        try:
            L = np.linalg.cholesky(self.P)
            C = L.T @ J @ L
            C.ravel()[:: len(J) + 1] += 1.0
            C = np.linalg.cholesky(C)
        except np.linalg.LinAlgError:
            return False
        M = np.linalg.solve(C, L.T)  # C^-1 L^T, so that P+ = M^T M
        P = M.T @ M
        self.x = self.x + P @ g
        self.P = 0.5 * (P + P.T)
        return True

    def correct(self, y, H, R=None) -> None:
        """Update with innovation ``y`` (r,), Jacobian ``H`` (r, n) and noise ``R`` (r, r; default the
        identity, for whitened rows).

        Whitened rows that outnumber the states (a block of epochs) are folded in by their information
        ``H^T H`` and ``H^T y`` (``_fold_information``): one n x n solve instead of r x r. Otherwise the Joseph
        form ``(I - K H) P (I - K H)^T + K R K^T``, expanded as ``P + M + M^T`` with
        ``M = K S K^T / 2 - K (P H^T)^T``: the same expression, valid for any gain, in two products
        instead of four and exactly symmetric by construction.
        """
        if R is None and H.shape[0] > H.shape[1]:
            J = H.T @ H
            if self._fold_information(J, H.T @ y):
                self.last_information = (H, J)  # the rows' information, for a caller that sums it
                return
        PHt = self.P @ H.T
        S = H @ PHt
        if R is None:
            S.ravel()[:: len(S) + 1] += 1.0
        else:
            S += R
        K = PHt @ inverse3(S) if S.shape == (3, 3) else np.linalg.solve(S, PHt.T).T
        self.x = self.x + K @ y
        M = (0.5 * (K @ S)) @ K.T - K @ PHt.T
        self.P = _guard(self.P + (M + M.T))


class EKF(_RandomWalkFilter):
    """Extended Kalman filter: ``x0`` (n,), ``P0`` (n, n), ``q_rate`` (n,) random-walk variance per second."""

    name = "ekf"

    def linearise(self, parts) -> Linearisation:
        """Rows of each ``(model, block)`` at the estimate (``_rows_at_estimate``)."""
        return Linearisation([self._rows_at_estimate(model, blk) for model, blk in parts])

    update = _RandomWalkFilter._update_at_estimate


class UKF(_RandomWalkFilter):
    """Unscented Kalman filter with Van der Merwe's scaled sigma points (FilterPy's
    ``MerweScaledSigmaPoints``; ``alpha=1, beta=2, kappa=0``: the centre's mean weight 0, the others'
    ``1 / 2n``).
    The prediction of a random walk is exact without sigma points.

    Rows linear in the state (``MeasurementModel.linear``: the vector models without a nonlinear effect) are
    taken at the estimate as the EKF takes them: the unscented transform of a linear function is exact, so
    its sigma points would give the same innovation, innovation covariance, cross covariance and update, to
    rounding. Sigma points are drawn, and FilterPy loaded, only for the other rows (the magnitude where the
    attitude is missing, a time lag's)."""

    name = "ukf"

    def __init__(self, x0, P0, q_rate, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        super().__init__(x0, P0, q_rate)
        self._scaling = (alpha, beta, kappa)
        self._points = None

    def _merwe(self):
        """FilterPy's ``MerweScaledSigmaPoints`` for the state, made at the first call."""
        if self._points is None:
            from filterpy.kalman import MerweScaledSigmaPoints

            alpha, beta, kappa = self._scaling
            self._points = MerweScaledSigmaPoints(len(self.x), alpha=alpha, beta=beta, kappa=kappa)
        return self._points

    def prepare(self, models) -> None:
        """Make the sigma points (FilterPy loaded) now if any of ``models`` (None entries skipped) is not
        linear; a model that is never needs them."""
        if any(m is not None and not getattr(m, "linear", False) for m in models):
            self._merwe()

    def linearise(self, parts) -> Linearisation:
        """Rows of each ``(model, block)``: those of a linear model at the estimate (``_rows_at_estimate``), the
        others predicted at one fresh set of sigma points (drawn only if there are such rows)."""
        sigmas, rows = None, []
        for model, blk in parts:
            if getattr(model, "linear", False):
                rows.append(self._rows_at_estimate(model, blk, linear=True))
                continue
            if sigmas is None:
                points = self._merwe()
                sigmas = points.sigma_points(self.x, self.P)
            h, z, H = model.sigma_predict(sigmas, self.x, blk)
            zp = np.tensordot(points.Wm, h, axes=1)
            dz = h - zp
            S = _weighted_covariance(points.Wc, dz)
            _add_noise(S, blk)
            y = z - zp
            rows.append(Rows(y, H, _nis(y, S), h))
        return Linearisation(rows, sigmas)

    def update(self, lin: Linearisation, accept) -> np.ndarray:
        """Update with the accepted epochs of every part at once; returns the whitened linear Jacobian
        (r, n) of the rows used (the information they carry).

        Rows that outnumber the states are folded in by their information (``_fold_sigma_rows``); otherwise
        rows that are all linear by the Kalman update (``correct``), and any others by the textbook unscented
        update with the stacked innovation covariance (a linear row's predictions at the sigma points are its
        Jacobian times them). With no sigma points drawn (every row linear) it is the EKF's update."""
        if lin.sigmas is None:
            return self._update_at_estimate(lin, accept)
        H_lin = np.vstack([r.H[a].reshape(-1, self.x.size) for r, a in zip(lin.rows, accept)])
        if len(H_lin) > self.x.size and self._fold_sigma_rows(lin, accept):
            return H_lin
        y = np.concatenate([r.y[a].ravel() for r, a in zip(lin.rows, accept)])
        points = self._merwe()
        sigmas, Wm, Wc = lin.sigmas, points.Wm, points.Wc
        predicted = [np.tensordot(sigmas, r.H, axes=([1], [2])) if r.h is None else r.h for r in lin.rows]
        h = np.hstack([p[:, a].reshape(len(sigmas), -1) for p, a in zip(predicted, accept)])
        zp = Wm @ h
        dz = h - zp
        S = (dz.T * Wc) @ dz + np.eye(len(y))
        Pxz = ((sigmas - self.x).T * Wc) @ dz
        K = np.linalg.solve(S, Pxz.T).T
        self.x = self.x + K @ y
        P = self.P - (K @ S) @ K.T
        self.P = _guard(0.5 * (P + P.T))
        return H_lin

    def _fold_sigma_rows(self, lin: Linearisation, accept) -> bool:
        """The update by statistical linear regression: each row's sigma-point predictions give its Jacobian
        ``H = Pxz^T P^-1`` and its linearisation error ``Omega = Pzz - H P H^T``, and the rows, whitened epoch
        by epoch by ``I + Omega``, are folded in by their information (``_fold_information``). With the
        whole ``Omega`` this is the unscented update exactly (``H P H^T + Omega + I`` is its innovation
        covariance and ``P H^T`` its cross covariance); only the linearisation error's correlation between
        different epochs is left out, which is nil for the linear vector rows. Rows linear in the state
        (``Rows.linear``, which have no sigma-point predictions) are folded in with their own Jacobian: for them
        the regression would give that Jacobian and ``Omega = 0`` exactly (the sigma points' spread cancels). False when
        it cannot be done (nothing changed)."""
        X = None  # the weighted sigma-point deviations (S, n), for the first row that is not linear
        J, g = np.zeros((self.x.size, self.x.size)), np.zeros(self.x.size)
        for rows, a in zip(lin.rows, accept):
            if rows.linear:
                Hw, yw = rows.H[a].reshape(-1, self.x.size), rows.y[a].ravel()
                J += Hw.T @ Hw
                g += Hw.T @ yw
                continue
            h = rows.h[:, a]  # (S, k, r)
            if not h.shape[1]:
                continue
            if X is None:
                points = self._merwe()
                X = (lin.sigmas - self.x) * points.Wc[:, None]
            dz = h - np.tensordot(points.Wm, h, axes=1)
            Pxz = np.tensordot(dz, X, axes=([0], [0]))  # (k, r, n)
            try:
                H = np.linalg.solve(self.P, Pxz.reshape(-1, self.x.size).T).T.reshape(Pxz.shape)
                Pzz = _weighted_covariance(points.Wc, dz)
                noise = Pzz - H @ self.P @ np.swapaxes(H, 1, 2)
                noise[:, np.arange(h.shape[2]), np.arange(h.shape[2])] += 1.0
                noise = 0.5 * (noise + np.swapaxes(noise, 1, 2))
                # the inverse Cholesky factor: written out over the stack for three rows, else LAPACK's
                W = _whitening_stack(noise) if noise.shape[1:] == (3, 3) else np.linalg.inv(np.linalg.cholesky(noise))
            except np.linalg.LinAlgError:
                return False
            if W is None:  # not positive definite
                return False
            Hw = (W @ H).reshape(-1, self.x.size)  # (k r, n)
            yw = (W @ rows.y[a][..., None]).ravel()  # (k r,)
            J += Hw.T @ Hw
            g += Hw.T @ yw
        return self._fold_information(J, g)


def make_filter(name: str, x0, P0, q_rate) -> Filter:
    """The registered filter ``name`` (``magkf.plugins.FILTERS``: ``ekf``, ``ukf``, ...) started at ``x0``
    (n,), ``P0`` (n, n) with random-walk variances ``q_rate`` (n,) per second."""
    try:
        cls = FILTERS[name]
    except KeyError:
        raise ValueError(f"unknown filter {name!r}; known: {', '.join(FILTERS)}") from None
    return cls(x0, P0, q_rate)
