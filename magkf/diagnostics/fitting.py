"""A model fitted to a set of epochs at its own best fit: the diagnosis's and the validation's workhorse (the
heading's wander, the whitening and what the data determine are ``magkf.online.determined``'s, shared with the run).

``EpochSet`` holds the epochs as their rows of the log (``magkf.online.prepared_rows.PreparedRows``: the raw
readings and the effect data made a chunk at a time when read); ``EpochSet.at(layout, x)`` whitens the
vector measurement and linearises the model at state ``x`` (a Gauss-Newton step for nonlinear effects) and
``EpochSet.fit`` iterates that to the whole-set least-squares estimate, so that the whitening and the
effects' linearisation (``EpochData.R0``) follow the estimate instead of a starting value that a missing
effect has pulled off.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from ..online.determined import CHUNK, DETERMINED, WANDER_BLOCK_S, ChunkCache, HeadingWander, whitened_gram, whitening
from ..online.determined import model_jacobian as _jacobian
from ..online.determined import wander_chunks as _chunks
from ..online.prepared_rows import PreparedRows
from ..online.state import StateLayout

__all__ = [
    "REFIT_ITERATIONS",
    "WANDER_BLOCK_S",
    "HeadingWander",
    "REFIT_TOLERANCE",
    "DETERMINED",
    "determined",
    "OUTLIER_SIGMA",
    "Linearised",
    "EpochSet",
    "inliers",
    "span_coefficients",
    "gram_svd",
    "CHUNK",
    "finite_regressors",
    "inverse_stack",
]

#: Iterations of the refit (whitening and linearisation at the estimate), and its tolerance on the change
#: of the state relative to the prior standard deviations.
REFIT_ITERATIONS = 4
REFIT_TOLERANCE = 1e-3
#: Whitened residual, in units of its robust (MAD) scale per component, beyond which an epoch is an outlier.
OUTLIER_SIGMA = 5.0
#: A block of whitened regressors with at least this many columns is first checked for columns that are zero
#: over the chunk (``Linearised.whitened``): a check that costs more than it saves on a few columns.
SPARSE_COLUMNS = 12


def span_coefficients(gram: np.ndarray, rows, n_rows: int) -> np.ndarray:
    """Coefficients ``M`` (p, rank) such that ``A @ M`` is an orthonormal basis of the span of a matrix ``A`` of
    ``n_rows`` rows and p columns, directions below ``1e-9`` of the largest singular value left out; ``gram`` is
    ``A^T A`` and ``rows()`` yields ``A``'s rows a block at a time (``gram_svd``)."""
    sv, vt = gram_svd(gram, rows, n_rows)
    rank = _rank(sv)
    return vt[:rank].T / sv[:rank]


#: ``tall_svd`` goes through the Gram matrix only when every singular value is at least this share of the
#: largest: the Gram matrix squares the condition number, and its vectors are then still orthonormal to
#: about ``eps / GRAM_CONDITION^2`` (2e-8).
GRAM_CONDITION = 1e-4


def tall_svd(A: np.ndarray, want_u: bool = True):
    """Thin SVD ``(u, s, vt)`` of ``A`` (rows, q), singular values in descending order. A well-conditioned
    matrix of many more rows than columns (the diagnosis's whitened regressors: three rows an epoch) is
    decomposed through its Gram matrix ``A^T A`` (one matrix product and a q x q eigen-decomposition: a small
    fraction of LAPACK's SVD of a million rows); any other (a singular value below ``GRAM_CONDITION`` of the
    largest, or few rows) by ``np.linalg.svd``. ``want_u`` False skips ``u`` (None)."""
    rows, q = A.shape
    if rows >= 8 * q and q > 0:
        found = _gram_eigen(A.T @ A)
        if found is not None:
            s, vt = found
            return (A @ (vt.T / s) if want_u else None), s, vt
    if not want_u:
        return None, *np.linalg.svd(A, full_matrices=False)[1:]
    return np.linalg.svd(A, full_matrices=False)


def _gram_eigen(gram: np.ndarray):
    """``(s, vt)`` of a matrix from its Gram matrix ``gram`` (q, q) when every singular value is at least
    ``GRAM_CONDITION`` of the largest; else None."""
    w, V = np.linalg.eigh(gram)
    w, V = w[::-1].copy(), V[:, ::-1]
    if w[0] > 0 and w[-1] >= (GRAM_CONDITION**2) * w[0]:
        return np.sqrt(w), np.ascontiguousarray(V.T)
    return None


def gram_svd(gram: np.ndarray, rows, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """``(s, vt)`` of the thin SVD of a matrix ``X`` of ``n_rows`` rows given its Gram matrix ``gram = X^T X``
    (q, q); ``rows()`` yields ``X``'s rows a block at a time (read again only when needed). ``X @ vt.T / s``
    are the left singular vectors.

    Well conditioned (every singular value at least ``GRAM_CONDITION`` of the largest), from ``gram`` as
    ``tall_svd``. Otherwise by one more pass (shifted Cholesky-QR2; Fukaya, Kannan, Nakatsukasa, Yamamoto and
    Yanagisawa, SIAM J. Sci. Comput. 42 (2020) A477): ``T`` from ``gram``'s eigen-decomposition, its eigenvalues
    floored at ``q eps`` of the largest, makes ``X T`` well conditioned; the Gram matrix of ``X T``, summed
    over the blocks, gives ``X T = Q S2 V2^T``, and the SVD of the small ``S2 V2^T T^-1`` that of ``X``, its
    small singular values to about ``eps`` of the largest (as LAPACK's) instead of ``sqrt(eps)``."""
    q = gram.shape[0]
    if q == 0 or n_rows < 8 * q:
        return tall_svd(np.vstack(list(rows())) if q else np.zeros((n_rows, 0)), want_u=False)[1:]
    found = _gram_eigen(gram)
    if found is not None:
        return found
    w, V = np.linalg.eigh(gram)
    if not w[-1] > 0:  # X is zero
        return np.zeros(q), np.eye(q)
    scale = np.sqrt(np.maximum(w, q * np.finfo(float).eps * w[-1]))
    T = V / scale
    second = sum(Y.T @ Y for Y in (X @ T for X in rows()))
    w2, V2 = np.linalg.eigh(second)
    _, s, vt = np.linalg.svd((np.sqrt(np.clip(w2, 0.0, None))[:, None] * V2.T) @ (scale[:, None] * V.T))
    return s, vt


def inverse_stack(A: np.ndarray) -> np.ndarray:
    """Inverses (m, 3, 3) of a stack of 3x3 matrices ``A`` (m, 3, 3), by cofactors over the stack (LAPACK's
    stacked ``inv`` costs a call per matrix; the two agree to rounding for the well-conditioned whitenings)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    cof = np.stack(
        [
            np.stack([e * i - f * h, c * h - b * i, b * f - c * e], axis=1),
            np.stack([f * g - d * i, a * i - c * g, c * d - a * f], axis=1),
            np.stack([d * h - e * g, b * g - a * h, a * e - b * d], axis=1),
        ],
        axis=1,
    )
    det = a * cof[:, 0, 0] + b * cof[:, 1, 0] + c * cof[:, 2, 0]
    return cof / det[:, None, None]


def _rank(sv: np.ndarray) -> int:
    """Numerical rank from singular values in descending order."""
    return int(np.sum(sv > 1e-9 * sv[0])) if sv.size and sv[0] > 0 else 0


def determined(sv: np.ndarray) -> int:
    """How many of the directions with singular values ``sv`` (descending) of whitened regressors scaled by the
    parameters' prior spread the data determine: standard error ``1 / sv`` below ``DETERMINED`` prior spreads."""
    return min(_rank(sv), int(np.sum(sv > 1.0 / DETERMINED)))


def finite_regressors(effect, data, rows=None) -> np.ndarray:
    """``effect.regressors(data, rows=rows)`` (n, 3, q) with epochs where any is not finite set to zero (they
    add nothing to a fit)."""
    G = effect.regressors(data, rows=rows)
    bad = ~np.all(np.isfinite(G), axis=(1, 2))
    if bad.any():
        G = G if G.flags.writeable else G.copy()
        G[bad] = 0.0
    return G


def inliers(residual: np.ndarray) -> np.ndarray:
    """Mask (n,) of the epochs whose whitened residual (n, 3) lies within ``OUTLIER_SIGMA`` robust scales
    (1.4826 times the median absolute deviation, per component) of its median. ``residual`` is centred in place,
    one component at a time (the caller's own array, let go after): what is made beside it is 16 bytes an epoch,
    not the 72 of centring every component at once."""
    keep = np.ones(len(residual), bool)
    distance = np.empty(len(residual))
    for k in range(residual.shape[1]):
        component = residual[:, k]
        component -= np.median(component)
        np.abs(component, out=distance)
        scale = np.maximum(1.4826 * np.median(distance, overwrite_input=True), 1e-12)
        keep &= np.abs(component, out=distance) <= OUTLIER_SIGMA * scale
    return keep


@dataclass(frozen=True)
class Linearised:
    """A model linearised and whitened at state ``x`` on the diagnosed epochs: ``data`` with ``R0`` of ``x``;
    ``W`` (n, 3, 3) the whitening; ``kept`` (3n, k) the first k columns of the whitened Jacobian kept whole
    (``EpochSet.at`` keeps none: ``rows`` makes all p of them again a chunk at a time, so that nothing of three
    rows an epoch and p columns is held) and ``span`` (p, k) the coefficients of an orthonormal basis
    ``A @ span`` of the directions the data determine (``A`` the whitened Jacobian); ``y`` (3n,) the whitened
    reading and ``coef`` (p,) the coefficients of its projection on that basis, whose residual ``r`` (3n,) is made
    when asked (``r``, ``r_of``) rather than held; ``x_fit`` the least-squares estimate (kept at ``x`` in
    directions the data do not determine). ``cache`` keeps the rows made, a chunk at a time (``ChunkCache``):
    a short set's within ``determined.CACHE_BYTES``, made once; a longer set's (``determined.CACHED_EPOCHS``)
    made again at each pass."""

    layout: StateLayout
    x: np.ndarray
    data: object
    W: np.ndarray
    kept: np.ndarray
    span: np.ndarray
    y: np.ndarray
    coef: np.ndarray
    x_fit: np.ndarray
    wander: HeadingWander | None = None
    cache: ChunkCache = field(default_factory=lambda: ChunkCache(None), compare=False, repr=False)

    @property
    def r(self) -> np.ndarray:
        """(3n,) what the basis of the determined directions leaves of ``y``: made a chunk at a time when asked."""
        return self.residual(self.coef)

    def r_of(self, start: int, stop: int) -> np.ndarray:
        """``r`` of the epochs ``start`` to ``stop`` (the edges of ``chunks``) (3 (stop - start),)."""
        return self.residual_at(self.coef, start, stop)

    def residual_at(self, x, start: int, stop: int) -> np.ndarray:
        """``residual(x)`` of the epochs ``start`` to ``stop`` (the edges of ``chunks``) (3 (stop - start),)."""
        return self.y[3 * start : 3 * stop] - self.rows(start, stop) @ x

    def unwhitened(self, residual_w: np.ndarray, start: int | None = None, stop: int | None = None) -> np.ndarray:
        """Whitened residuals (m, 3) of the epochs ``start`` to ``stop`` (default: all, a chunk at a time) taken
        back to nT in the sensor axes (m, 3): ``W^-1`` applied epoch by epoch, made a chunk at a time (kept within
        the cache's budget, as the rows)."""
        if start is not None:
            inverse = self.cache.get(("W^-1", start, stop), lambda: inverse_stack(self.W[start:stop]))
            return np.einsum("nij,nj->ni", inverse, residual_w)
        out = np.empty(residual_w.shape)
        for a, b in self.chunks:
            out[a:b] = self.unwhitened(residual_w[a:b], a, b)
        return out

    @cached_property
    def chunks(self) -> list:
        """``(start, stop)`` epochs of the chunks of a pass over the epochs (``CHUNK``, cut at the wander's
        stretches)."""
        return _chunks(len(self.W), self.wander)

    def whitened(self, G: np.ndarray, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Regressors ``G`` (m, 3, q) of the epochs ``start`` to ``stop`` (default: all; the edges of
        ``chunks``) whitened, less the heading wander when it is modelled: (3m, q). In a block of at least
        ``SPARSE_COLUMNS`` columns, those zero over the epochs stay zero (both steps are linear) and are not
        computed: most of a slow drift's hat functions in time are zero over a chunk."""
        stop = len(self.W) if stop is None else stop
        m = stop - start
        used = np.flatnonzero(np.any(G != 0.0, axis=(0, 1))) if G.shape[2] >= SPARSE_COLUMNS else ()
        if 0 < len(used) < G.shape[2]:
            out = np.zeros((3 * m, G.shape[2]))
            out[:, used] = self.whitened(G[:, :, used], start, stop)
            return out
        Gw = (self.W[start:stop] @ G).reshape(3 * m, -1)
        return Gw if self.wander is None else self.wander.remove(Gw, start, stop)

    def rows(self, start: int, stop: int) -> np.ndarray:
        """The whitened Jacobian's rows (3 (stop - start), p) of the epochs ``start`` to ``stop`` (the edges of
        ``chunks``): as cached, or the kept columns as kept and the others made again (read-only)."""
        return self.cache.get(("rows", start, stop), lambda: self._made_rows(start, stop))

    def _made_rows(self, start: int, stop: int) -> np.ndarray:
        """``rows`` made: the kept columns as kept, the others made again."""
        k = self.kept.shape[1]
        kept = self.kept[3 * start : 3 * stop]
        if k == self.layout.size:
            return kept
        H, _ = _jacobian(self.layout, self.x, self.data, slice(start, stop), first=k)
        made = self.whitened(H, start, stop)
        return made if k == 0 else np.hstack([kept, made])

    def residual(self, x) -> np.ndarray:
        """``y - A x`` (3n,): the whitened residual of the state ``x`` (p,) (exact at ``self.x`` for nonlinear
        effects too)."""
        out = np.empty_like(self.y)
        for a, b in self.chunks:
            out[3 * a : 3 * b] = self.residual_at(x, a, b)
        return out


class EpochSet:
    """Epochs and how a model is fitted to them: the epochs' rows of the log (``PreparedRows``: prepared a chunk
    at a time when read), whence the raw readings ``m`` (n, 3) nT, the effect data (``data``, an ``EpochData``
    read a chunk at a time) and the heading axes ``heading`` (n, 3), and the measurement settings whose
    whitening weighs the residuals."""

    def __init__(self, rows: PreparedRows, config, noise=None, wander_s=None):
        self.rows, self.config, self.noise, self.wander_s = rows, config, noise, wander_s

    @classmethod
    def of(cls, log, ref, used, config, noise=None, wander_s=None) -> EpochSet:
        """The epochs ``used`` (mask (N,)) of ``log``, with its reference field ``ref`` (N, 3) NED nT
        (``PreparedLog.ref``, or ``prepare.reference_track``'s, made for the rows read), weighed with ``noise`` (a
        ``NoiseLevels``; None: the configured noise), with the heading's error a nuisance over stretches of
        ``wander_s`` seconds (None: the logged heading taken as it is)."""
        return cls(PreparedRows(log, ref, np.flatnonzero(used)), config, noise, wander_s)

    @property
    def data(self):
        """The epochs' ``EpochData`` (a ``LazyEpochData``: read a chunk at a time)."""
        return self.rows.data()

    @property
    def m(self):
        """(n, 3) nT the raw readings (a ``ChunkedArray``)."""
        return self.rows.array("m")

    @property
    def heading(self):
        """(n, 3) the heading axes in the body frame (a ``ChunkedArray``)."""
        return self.rows.array("heading")

    def with_wander(self, wander_s) -> EpochSet:
        """The same epochs with the heading wander modelled over ``wander_s`` s (None: not modelled)."""
        return EpochSet(self.rows, self.config, self.noise, wander_s)

    def take(self, keep) -> EpochSet:
        """The epochs ``keep`` (mask or index) of this set."""
        return EpochSet(self.rows.subset(keep), self.config, self.noise, self.wander_s)

    def keep_only(self, keep) -> EpochSet:
        """This set cut to its epochs ``keep`` (mask or index) in place, and returned."""
        self.rows = self.rows.subset(keep)
        return self

    def less(self, terms) -> EpochSet:
        """The same epochs with ``terms`` (n, 3) nT taken off the readings (effects held fixed)."""
        return EpochSet(self.rows.less(terms), self.config, self.noise, self.wander_s)

    def __len__(self):
        return len(self.rows)

    def _whitening(self, layout: StateLayout, x):
        """``(data, W, wander)`` at state ``x`` (``determined.whitening``)."""
        return whitening(self.data, self.heading, self.config, self.noise, self.wander_s, layout, x)

    def gram(self, layout: StateLayout, x) -> np.ndarray:
        """``A^T A`` (p, p) of the whitened Jacobian ``A`` at state ``x``, the heading's wander taken out (as in
        ``at``; ``determined.whitened_gram``)."""
        return whitened_gram(self.data, self.heading, self.config, self.noise, self.wander_s, layout, x)

    def at(self, layout: StateLayout, x, keep: int = 0) -> Linearised:
        """The model ``layout`` linearised and whitened at ``x``, and its least-squares fit. The first ``keep``
        columns of the whitened Jacobian (where a block starts; default none) are kept for the whole set, the
        others made again a chunk at a time when they are read (``Linearised.rows``): the fit's normal equations
        are summed a chunk at a time, and only vectors of three values an epoch are held."""
        x = np.asarray(x, float)
        data, W, wander = self._whitening(layout, x)
        n, p = len(self.m), layout.size
        chunks = _chunks(n, wander)
        y, kept = np.empty(3 * n), np.empty((3 * n, keep))
        gram, moment, cache = 0.0, 0.0, ChunkCache(n)
        for a, b in chunks:  # whitened a chunk at a time, with the wander taken out stretch by stretch
            H, offset = _jacobian(layout, x, data, slice(a, b))
            ya = np.einsum("nij,nj->ni", W[a:b], self.m[a:b] - offset).ravel()
            X = (W[a:b] @ H).reshape(-1, p)
            if wander is not None:
                ya, X = wander.remove(ya, a, b), wander.remove(X, a, b)
            y[3 * a : 3 * b], kept[3 * a : 3 * b] = ya, X[:, :keep]
            gram, moment = gram + X.T @ X, moment + X.T @ ya
            cache.put(("rows", a, b), X)  # ``Linearised.rows``, kept if the budget allows
        fitted = Linearised(layout, x, data, W, kept, None, y, None, None, wander, cache)
        # Directions in units of the parameters' prior spread (``determined``). A weaker one (the part of a field
        # anomaly that a heading offset mimics, once the heading's wander is taken out) is held where it is:
        # fitted, it would take noise as values of hundreds of thousands of nT.
        spread = np.sqrt(np.diag(layout.prior()[1]))
        sv, vt = gram_svd(
            spread[:, None] * gram * spread, lambda: (fitted.rows(a, b) * spread for a, b in chunks), 3 * n
        )
        rank = determined(sv)
        span = spread[:, None] * (vt[:rank].T / sv[:rank])  # A @ span: orthonormal
        along = span.T @ moment
        step = spread * (vt[:rank].T @ ((along - span.T @ (gram @ x)) / sv[:rank]))
        return replace(fitted, span=span, coef=span @ along, x_fit=x + step)

    def fit(self, layout: StateLayout, x, keep: int = 0) -> Linearised:
        """``at`` iterated until the estimate stops moving: the model at its own best fit (``keep`` as ``at``)."""
        prior_std = np.sqrt(np.diag(layout.prior()[1]))
        f = self.at(layout, x, keep)
        for _ in range(REFIT_ITERATIONS):
            change = np.max(np.abs(f.x_fit - f.x) / prior_std)
            if change < REFIT_TOLERANCE or not np.all(np.isfinite(f.x_fit)):
                break
            x_next, f = f.x_fit, None  # one linearisation held at a time
            f = self.at(layout, x_next, keep)
        return f
