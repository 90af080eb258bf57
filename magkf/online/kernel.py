"""A compiled kernel for the EKF's gates and update of one block of epochs, for long logs.

Given one measurement model's whitened rows of a block at the estimate (innovations ``y`` (k, r), Jacobians
``H`` (k, r, n)) and the block's whitened noise ``N`` (k, r, r; or the identity), ``gate_and_fold`` does in one
compiled call what ``Estimator._gate_and_update`` does in numpy for such a block: each epoch's normalised
innovation squared ``y^T (H P H^T + N)^-1 y``, the innovation gate, the Huber weights (and the correlation's
inflation where the noise carries none), and the Kalman update of the accepted rows folded in by their
information (``EKF._fold_information``: ``P+ = L (I + L^T J L)^-1 L^T``, ``P = L L^T``). Its products are
those of the numpy path in another order, so its results agree with it to rounding (``tests/unit/
test_kernel.py`` measures how closely).

The kernel is written for numba, which is imported only by ``load`` (a run that never calls it never pays
numba's import and the cached code's loading, about a second): the estimator loads it once it has filtered
``WORTH_AFTER_EPOCHS`` epochs in blocks, i.e. only for logs long enough to pay for it (see ``Estimator``).
Compiled once and cached on disk (``cache=True``, beside this module or in ``NUMBA_CACHE_DIR``): the first run
of an installation compiles it (about 15 s), later runs load it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["available", "load", "gate_and_fold", "WORTH_AFTER_EPOCHS", "UPDATED", "NOTHING_ACCEPTED", "USE_NUMPY"]

#: The kernel is loaded once a run has filtered this many epochs in blocks (5.5 hours at 100 Hz). Loading it
#: (numba's import and the cached kernel's first call) took 1.1 s, and it saved 0.55 us of the filter loop's
#: 5.9 us per epoch (``scripts/bench_kernel.py``, a 1-hour log, 2026-11-28): the load is repaid after this many
#: epochs. Loading it only then, a run that stops sooner pays nothing for it, and one that goes on pays at most
#: twice what the best choice made knowing the log's length would have cost (the ski-rental argument).
WORTH_AFTER_EPOCHS = 2_000_000

#: ``gate_and_fold``'s outcomes: the state was updated; no epoch was accepted (nothing changed); the block is one
#: the numpy path must take (too few rows to fold by their information, or ``P`` or the folded matrix not
#: positive definite: nothing changed).
UPDATED, NOTHING_ACCEPTED, USE_NUMPY = 0, 1, 2

_kernel = None


def available() -> bool:
    """Whether numba can be imported (without importing it)."""
    from importlib.util import find_spec

    return find_spec("numba") is not None


def load():
    """``gate_and_fold`` compiled by numba (imported now; the compiled code cached on disk), or None where numba
    is not installed or cannot be imported."""
    global _kernel, _cholesky, _inverse_quadratic, _gate, _information, _folded_factor
    if _kernel is None and available():
        try:
            from numba import njit
        except ImportError:  # installed but not importable (e.g. built for another numpy): the numpy path
            return None

        # compiled in place, so that the kernel's calls to them are compiled calls
        _cholesky = njit(cache=True)(_cholesky)
        _inverse_quadratic = njit(cache=True)(_inverse_quadratic)
        _gate = njit(cache=True)(_gate)
        _information = njit(cache=True)(_information)
        _folded_factor = njit(cache=True)(_folded_factor)
        _kernel = njit(cache=True)(gate_and_fold)
    return _kernel


def _cholesky(A, L) -> bool:
    """The lower Cholesky factor of ``A`` (n, n) written into ``L`` (n, n, zeros above the diagonal); False
    when ``A`` is not positive definite."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for p in range(j):
            s -= L[j, p] * L[j, p]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for p in range(j):
                s -= L[i, p] * L[j, p]
            L[i, j] = s / d
    return True


def _inverse_quadratic(S, y) -> float:
    """``y^T S^-1 y`` of a symmetric positive ``S`` (r, r) and ``y`` (r,): by cofactors for three rows (as
    ``filters._nis``), else by a solve."""
    r = S.shape[0]
    if r == 1:
        return y[0] * y[0] / S[0, 0]
    if r == 3:
        a, b, c, d, e, f = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
        c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
        y0, y1, y2 = y[0], y[1], y[2]
        quadratic = y0 * (y0 * c00 + 2.0 * (y1 * c01 + y2 * c02)) + y1 * (
            y1 * (a * f - c * c) + 2.0 * y2 * (b * c - a * e)
        )
        return (quadratic + y2 * y2 * (a * d - b * b)) / (a * c00 + b * c01 + c * c02)
    return float(y @ np.linalg.solve(S, y))


def gate_and_fold(y, H, N, has_noise, x, P, bound, huber_q, inflation):
    """Gate and update one block's rows (see the module's docstring).

    Parameters
    ----------
    y : ndarray, shape (k, r)
        Whitened innovations.
    H : ndarray, shape (k, r, n)
        Whitened Jacobians at the estimate.
    N : ndarray, shape (k, r, r)
        The rows' whitened noise (``Block.N``); read only when ``has_noise`` (else the identity).
    has_noise : bool
        Whether ``N`` is given.
    x : ndarray, shape (n,)
        The estimate.
    P : ndarray, shape (n, n)
        Its covariance.
    bound : float
        The innovation gate's chi-square quantile: an epoch beyond it is refused.
    huber_q : float
        The Huber quantile: beyond it an epoch counts ``sqrt(huber_q / nis)`` of one.
    inflation : float
        Each epoch counts ``1 / inflation`` of an independent one (used only without ``N``).

    Returns
    -------
    outcome : int
        ``UPDATED``, ``NOTHING_ACCEPTED`` or ``USE_NUMPY``.
    nis : ndarray, shape (k,)
        Normalised innovation squared of each epoch.
    refused : ndarray, shape (k,)
        The epochs the gate refused.
    x_new, P_new : ndarray, shapes (n,) and (n, n)
        The updated estimate and covariance (``x``, ``P`` unless ``UPDATED``).
    J : ndarray, shape (n, n)
        The information ``H^T H`` of the weighted accepted rows (zeros unless ``UPDATED``).
    """
    k, r, n = H.shape
    nis = np.empty(k)
    refused = np.zeros(k, np.bool_)
    J = np.zeros((n, n))
    L = np.zeros((n, n))
    if not _cholesky(P, L):
        return USE_NUMPY, nis, refused, x, P, J
    accepted = _gate(y, H, N, has_noise, L, bound, nis, refused)
    if accepted == 0:
        return NOTHING_ACCEPTED, nis, refused, x, P, J
    if accepted * r <= n:
        return USE_NUMPY, nis, refused, x, P, J
    g = _information(y, H, has_noise, nis, refused, huber_q, inflation, J)
    M = _folded_factor(L, J)
    if M.shape[0] == 0:
        return USE_NUMPY, nis, refused, x, P, np.zeros((n, n))
    P_new = M.T @ M
    P_new = 0.5 * (P_new + P_new.T)
    x_new = x + P_new @ g
    return UPDATED, nis, refused, x_new, P_new, J


def _gate(y, H, N, has_noise, L, bound, nis, refused) -> int:
    """Each epoch's normalised innovation squared into ``nis`` (k,) with ``P = L L^T``, and the gate's refusals
    into ``refused`` (k,); returns the epochs accepted."""
    k, r, n = H.shape
    G = np.empty((r, n))
    S = np.empty((r, r))
    accepted = 0
    for e in range(k):
        for i in range(r):  # G = H_e L (L lower triangular), so that H_e P H_e^T = G G^T
            for j in range(n):
                s = 0.0
                for p in range(j, n):
                    s += H[e, i, p] * L[p, j]
                G[i, j] = s
        for i in range(r):
            for j in range(i, r):
                s = 0.0
                for p in range(n):
                    s += G[i, p] * G[j, p]
                if has_noise:
                    s += N[e, i, j]
                elif i == j:
                    s += 1.0
                S[i, j] = s
                S[j, i] = s
        nis[e] = _inverse_quadratic(S, y[e])
        if nis[e] > bound:
            refused[e] = True
        else:
            accepted += 1
    return accepted


def _information(y, H, has_noise, nis, refused, huber_q, inflation, J):
    """The information of the accepted rows, each epoch weighted by its Huber weight (and ``1 / inflation``
    without ``N``): ``J = sum w H^T H`` (n, n) summed into ``J``, and ``g = sum w H^T y`` (n,) returned."""
    k, r, n = H.shape
    g = np.zeros(n)
    for e in range(k):
        if refused[e]:
            continue
        w = min(1.0, np.sqrt(huber_q / max(nis[e], 1e-300)))
        if not has_noise:
            w = w / inflation
        for i in range(r):
            for a in range(n):
                ha = w * H[e, i, a]
                g[a] += ha * y[e, i]
                for b in range(a, n):
                    J[a, b] += ha * H[e, i, b]
    for a in range(n):
        for b in range(a + 1, n):
            J[b, a] = J[a, b]
    return g


def _folded_factor(L, J):
    """``M = C^-1 L^T`` (n, n) with ``C`` the Cholesky factor of ``I + L^T J L``, so that ``P+ = M^T M``; an
    empty (0, n) array when that matrix is not positive definite."""
    n = L.shape[0]
    C = L.T @ J @ L
    for a in range(n):
        C[a, a] += 1.0
    Lc = np.zeros((n, n))
    if not _cholesky(C, Lc):
        return np.empty((0, n))
    M = np.empty((n, n))  # by forward substitution
    for col in range(n):
        for i in range(n):
            s = L[col, i]
            for p in range(i):
                s -= Lc[i, p] * M[p, col]
            M[i, col] = s / Lc[i, i]
    return M
