"""A model fitted to a set of epochs at its own best fit: the diagnosis's and the validation's workhorse.

``EpochSet`` holds the raw readings and effect data of the epochs; ``EpochSet.at(layout, x)`` whitens the
vector measurement and linearises the model at state ``x`` (a Gauss-Newton step for nonlinear effects) and
``EpochSet.fit`` iterates that to the whole-set least-squares estimate, so that the whitening and the
effects' linearisation (``EpochData.R0``) follow the estimate instead of a starting value that a missing
effect has pulled off.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ..effects.base import at_rows
from ..online.measurements import measurement_model
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
    "HeldDirections",
    "held_directions",
]

#: Iterations of the refit (whitening and linearisation at the estimate), and its tolerance on the change
#: of the state relative to the prior standard deviations.
REFIT_ITERATIONS = 4
#: A direction of the parameters counts as determined by the data when its standard error (noise as whitened)
#: is below this share of its prior spread: the data then say more about it than the prior does.
DETERMINED = 1.0
REFIT_TOLERANCE = 1e-3
#: Stretches (s) over which the logged heading's error is let be a straight line in time (``HeadingWander``).
WANDER_BLOCK_S = 10.0
#: Whitened residual, in units of its robust (MAD) scale per component, beyond which an epoch is an outlier.
OUTLIER_SIGMA = 5.0
#: Epochs per chunk of a pass over the diagnosed epochs (cut where a stretch of the heading wander starts):
#: a candidate's whitened regressors are made and reduced a chunk at a time, never held for the whole log.
CHUNK = 8192
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
    (1.4826 times the median absolute deviation, per component) of its median."""
    centred = residual - np.median(residual, axis=0)
    scale = np.maximum(1.4826 * np.median(np.abs(centred), axis=0), 1e-12)
    return np.all(np.abs(centred) <= OUTLIER_SIGMA * scale, axis=1)


class HeadingWander:
    """The projection that takes a slowly wandering error of the logged heading out of whitened residuals
    and regressors.

    An INS heading wanders by tenths of a degree over minutes; each tenth moves the body-frame field by
    ``0.0017 |B_h|`` (tens of nT) along the heading axis ``h`` (``heading_axis``). Unmodelled, that slow
    error dominates the residual and its correlation leaves too few independent stretches to test an effect.
    Here the heading error is a nuisance, a straight line in time over each stretch of ``block_s`` seconds
    (two coefficients a stretch), fitted and removed jointly with the model: by Frisch-Waugh, projecting
    it out of the whitened reading and of every regressor before the least-squares fit gives the fit of
    the model with the nuisance (the partial-residual treatment of a partly linear model, Speckman 1988).
    What is lost: the part of an effect that looks like a heading change within a stretch, notably a
    constant field anomaly across the horizontal field (the same thing as a heading offset).

    ``Z`` (n, 3) the whitened heading direction ``W R h`` per epoch; ``time`` (n,) s, increasing.
    """

    def __init__(self, Z: np.ndarray, time: np.ndarray, block_s: float = WANDER_BLOCK_S):
        t = np.asarray(time, float)
        block = np.floor((t - t[0]) / block_s).astype(int)
        self.starts = np.flatnonzero(np.r_[True, np.diff(block) != 0])
        self.block = np.cumsum(np.r_[False, np.diff(block) != 0])  # index of each epoch's stretch
        centre = (np.add.reduceat(t, self.starts) / np.diff(np.r_[self.starts, len(t)]))[self.block]
        s = 2.0 * (t - centre) / block_s
        self.Z = np.stack([Z, Z * s[:, None]], axis=2)  # (n, 3, 2)
        normal = np.add.reduceat(np.swapaxes(self.Z, 1, 2) @ self.Z, self.starts, axis=0)
        self.inverse = np.linalg.pinv(normal, rcond=1e-9)  # (blocks, 2, 2)

    def remove(self, X: np.ndarray, start: int = 0, stop: int | None = None) -> np.ndarray:
        """``X`` (3m,) or (3m, k), epoch-major, the rows of epochs ``start`` to ``stop`` (default: all; both at
        the start of a stretch, or the end), less its least-squares fit by the wander of each stretch."""
        stop = len(self.block) if stop is None else stop
        Xr = X.reshape(stop - start, 3, -1)
        Z, block = self.Z[start:stop], self.block[start:stop] - self.block[start]
        first, last = np.searchsorted(self.starts, [start, stop])
        # batched matrix products: about twice as fast as the same einsums on long logs
        c = np.add.reduceat(np.swapaxes(Z, 1, 2) @ Xr, self.starts[first:last] - start, axis=0)
        coef = self.inverse[first:last] @ c  # (blocks, 2, k)
        return (Xr - Z @ coef[block]).reshape(X.shape)

    def cuts(self, size: int) -> np.ndarray:
        """Edges (epoch indices, from 0 to n) of chunks of about ``size`` epochs, each cut at a stretch's start."""
        n = len(self.block)
        at = self.starts[np.searchsorted(self.starts, np.arange(size, n, size), side="right") - 1]
        return np.unique(np.r_[0, at, n])


def _chunks(n: int, wander: HeadingWander | None) -> list:
    """``(start, stop)`` of the chunks of ``CHUNK`` epochs of ``n``, cut at the ``wander``'s stretches."""
    edges = wander.cuts(CHUNK) if wander is not None else np.unique(np.r_[np.arange(0, n, CHUNK), n])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


@dataclass(frozen=True)
class Linearised:
    """A model linearised and whitened at state ``x`` on the diagnosed epochs: ``data`` with ``R0`` of ``x``;
    ``W`` (n, 3, 3) the whitening; ``kept`` (3n, k) the first k columns of the whitened Jacobian (``rows`` gives
    all p of them a chunk at a time, making the others again) and ``span`` (p, k) the coefficients of an
    orthonormal basis ``A @ span`` of the directions the data determine (``A`` the whitened Jacobian); ``y``
    (3n,) the whitened reading and ``r`` (3n,) what that basis leaves of it; ``x_fit`` the least-squares
    estimate (kept at ``x`` in directions the data do not determine)."""

    layout: StateLayout
    x: np.ndarray
    data: object
    W: np.ndarray
    kept: np.ndarray
    span: np.ndarray
    y: np.ndarray
    r: np.ndarray
    x_fit: np.ndarray
    wander: HeadingWander | None = None

    @cached_property
    def unwhitening(self) -> np.ndarray:
        """``W^-1`` (n, 3, 3): takes whitened residuals back to nT in the sensor axes (computed once per model)."""
        return np.linalg.inv(self.W)

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
        ``chunks``): the kept columns as kept, the others made again."""
        k = self.kept.shape[1]
        kept = self.kept[3 * start : 3 * stop]
        if k == self.layout.size:
            return kept
        H, _ = _jacobian(self.layout, self.x, self.data, slice(start, stop), first=k)
        return np.hstack([kept, self.whitened(H, start, stop)])

    def residual(self, x) -> np.ndarray:
        """``y - A x`` (3n,): the whitened residual of the state ``x`` (p,) (exact at ``self.x`` for nonlinear
        effects too)."""
        out = np.empty_like(self.y)
        for a, b in self.chunks:
            out[3 * a : 3 * b] = self.y[3 * a : 3 * b] - self.rows(a, b) @ x
        return out


def _jacobian(layout: StateLayout, x, data, rows, first: int = 0):
    """The model's Jacobian (m, 3, p - first) in its columns from ``first`` (where a block starts) at the epochs
    ``rows`` of ``data``, the nonlinear effects among them linearised at ``x`` (a Gauss-Newton step), and
    what their linearisation leaves (m, 3) nT; an effect's input unknown at an epoch (a rate at a gap) adds
    nothing there, as in ``finite_regressors``."""
    m = len(at_rows(data.time, rows))
    H = np.zeros((m, 3, layout.size - first))
    offset = np.zeros((m, 3))
    for effect, sl in layout.blocks(include_core=True):
        if sl.start < first:
            continue
        cols = slice(sl.start - first, sl.stop - first)
        if effect.linear:  # the Jacobian of a linear effect does not depend on its parameters
            H[:, :, cols] = effect.jacobian(np.zeros(effect.size), data, rows=rows)
        else:
            H[:, :, cols] = effect.jacobian(x[sl], data, rows=rows)
            offset += effect.contribution(x[sl], data, rows=rows) - H[:, :, cols] @ x[sl]
    return np.nan_to_num(H, copy=False, nan=0.0, posinf=0.0, neginf=0.0), np.nan_to_num(offset)


class EpochSet:
    """Epochs and how a model is fitted to them: the raw readings ``m`` (n, 3) nT, the effect data
    (``EpochData``), the heading axes (n, 3) and the measurement settings whose whitening weighs the
    residuals."""

    def __init__(self, data, m, heading, config, noise=None, wander_s=None):
        self.data, self.m, self.heading = data, m, heading
        self.config, self.noise, self.wander_s = config, noise, wander_s

    @classmethod
    def of(cls, prep, used, config, noise=None, wander_s=None) -> EpochSet:
        """The epochs ``used`` (mask) of a ``PreparedLog``, weighed with ``noise`` (a ``NoiseLevels``; None:
        the configured noise), with the heading's error a nuisance over stretches of ``wander_s`` seconds
        (None: the logged heading taken as it is)."""
        return cls(prep.data.take(used), prep.m[used], prep.heading[used], config, noise, wander_s)

    def with_wander(self, wander_s) -> EpochSet:
        """The same epochs with the heading wander modelled over ``wander_s`` s (None: not modelled)."""
        return EpochSet(self.data, self.m, self.heading, self.config, self.noise, wander_s)

    def take(self, keep) -> EpochSet:
        """The epochs ``keep`` (mask or index) of this set."""
        return EpochSet(self.data.take(keep), self.m[keep], self.heading[keep], self.config, self.noise, self.wander_s)

    def less(self, terms) -> EpochSet:
        """The same epochs with ``terms`` (n, 3) nT taken off the readings (effects held fixed)."""
        return EpochSet(self.data, self.m - terms, self.heading, self.config, self.noise, self.wander_s)

    def __len__(self):
        return len(self.m)

    def _whitening(self, layout: StateLayout, x):
        """``(data, W, wander)`` at state ``x``: the data with ``R0`` of ``x``, the whitening (n, 3, 3) of the vector
        measurement in the set's noise, and the heading's wander (None: not modelled)."""
        R = layout.R(x)
        data = replace(self.data, R0=R)
        model = measurement_model(self.config, layout, x)
        if self.noise is not None:
            model.set_noise(self.noise)
        W = model.whitening(data.field_body, R, self.heading)
        wander = None
        if self.wander_s:
            wander = HeadingWander(np.einsum("nij,nj->ni", W, self.heading @ R.T), data.time, self.wander_s)
        return data, W, wander

    def gram(self, layout: StateLayout, x) -> np.ndarray:
        """``A^T A`` (p, p) of the whitened Jacobian ``A`` at state ``x``, the heading's wander taken out (as in
        ``at``), made a chunk at a time."""
        x = np.asarray(x, float)
        data, W, wander = self._whitening(layout, x)
        p, gram = layout.size, np.zeros((layout.size, layout.size))
        for a, b in _chunks(len(self.m), wander):
            X = (W[a:b] @ _jacobian(layout, x, data, slice(a, b))[0]).reshape(-1, p)
            X = X if wander is None else wander.remove(X, a, b)
            gram += X.T @ X
        return gram

    def at(self, layout: StateLayout, x, keep: int | None = None) -> Linearised:
        """The model ``layout`` linearised and whitened at ``x``, and its least-squares fit. The first ``keep``
        columns of the whitened Jacobian (where a block starts; default all) are kept for the whole set, the
        others made again a chunk at a time when they are read (``Linearised.rows``)."""
        x = np.asarray(x, float)
        data, W, wander = self._whitening(layout, x)
        n, p = len(self.m), layout.size
        keep = p if keep is None else keep
        chunks = _chunks(n, wander)
        y, kept = np.empty(3 * n), np.empty((3 * n, keep))
        gram, moment = 0.0, 0.0
        for a, b in chunks:  # whitened a chunk at a time, with the wander taken out stretch by stretch
            H, offset = _jacobian(layout, x, data, slice(a, b))
            ya = np.einsum("nij,nj->ni", W[a:b], self.m[a:b] - offset).ravel()
            X = (W[a:b] @ H).reshape(-1, p)
            if wander is not None:
                ya, X = wander.remove(ya, a, b), wander.remove(X, a, b)
            y[3 * a : 3 * b], kept[3 * a : 3 * b] = ya, X[:, :keep]
            gram, moment = gram + X.T @ X, moment + X.T @ ya
        fitted = Linearised(layout, x, data, W, kept, None, y, None, None, wander)
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
        r = fitted.residual(span @ along)
        step = spread * (vt[:rank].T @ ((along - span.T @ (gram @ x)) / sv[:rank]))
        return replace(fitted, span=span, r=r, x_fit=x + step)

    def fit(self, layout: StateLayout, x, keep: int | None = None) -> Linearised:
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


@dataclass(frozen=True)
class HeldDirections:
    """The directions of the added effects' parameters that the data do not determine beside the rest of the model
    and the heading's wander, held at their prior mean, as the diagnosis holds them (``held_directions``).

    ``free`` (q, j): a basis of the free directions of the q effect parameters (the state after the core);
    ``projector`` (q, q): takes a change of those parameters onto the free directions (their held part dropped, in
    the metric of the parameters' prior spread); ``held_basis`` (q, h) the held directions, each scaled to one
    prior standard deviation (the prior's covariance along them is ``held_basis @ held_basis.T``); ``held``
    ``{effect label: directions held}``."""

    free: np.ndarray
    projector: np.ndarray
    held_basis: np.ndarray
    held: dict

    @property
    def held_cov(self) -> np.ndarray:
        """(q, q) the prior's covariance along the held directions: what a held parameter's uncertainty is."""
        return self.held_basis @ self.held_basis.T

    @property
    def count(self) -> int:
        """Directions held in all."""
        return int(sum(self.held.values()))

    def hold(self, x_effects, mean) -> np.ndarray:
        """Effect parameters ``x_effects`` (q,) with their held part at the prior ``mean`` (q,)."""
        mean = np.asarray(mean, float)
        return mean + self.projector @ (np.asarray(x_effects, float) - mean)

    def text(self) -> str:
        """The held directions in words ("" when none is held)."""
        parts = [f"{k} of {label}" for label, k in self.held.items() if k]
        if not parts:
            return ""
        return (
            f"held at the prior mean, as the diagnosis holds them: {', '.join(parts)} direction(s) the data do not "
            "determine beside the model and the heading's wander"
        )


def held_directions(problem: EpochSet, layout: StateLayout, x) -> HeldDirections | None:
    """The directions of each added effect's parameters (blocks after the core; an effect that ``wanders`` is left
    free) whose standard error, beside every other parameter and the heading's wander taken out
    (``EpochSet.gram``), exceeds ``DETERMINED`` prior spreads (``determined``, the diagnosis's rule; the core's spread
    the default core's, ``StateLayout.with_core``, as in the diagnosis): the data say
    less about them than the prior, and a fit would let them absorb the heading's wander. None when the layout
    adds no effect.

    In units of the prior spread ``D`` the information is ``G = D A^T A D``; a block's, beside the others (free,
    whatever their prior: a field anomaly along the field is R's scale however narrow R's prior),
    ``G_bb - G_bo G_oo^+ G_ob``; its eigenvectors with eigenvalue at least ``1 / DETERMINED^2`` are free.
    """
    n = layout.size
    q = n - layout.CORE.stop
    if q <= 0:
        return None
    # the diagnosis's spreads: the default core's (not a run's start, which the data narrowed) and the effects' own
    spread = np.sqrt(np.diag(StateLayout.with_core(layout.extra()).prior()[1]))
    G = spread[:, None] * problem.gram(layout, x) * spread[None, :]
    free, held_basis, projector, held = [], [], np.zeros((q, q)), {}
    start = layout.CORE.stop
    for key, (effect, sl) in zip(layout.keys[1:], layout.blocks()):
        local = slice(sl.start - start, sl.stop - start)
        D = spread[sl]
        if effect.wanders:
            vectors, keep = np.eye(effect.size), np.ones(effect.size, bool)
        else:
            others = np.setdiff1d(np.arange(n), np.arange(sl.start, sl.stop))
            Gbo = G[sl][:, others]
            info = G[sl, sl] - Gbo @ np.linalg.pinv(G[np.ix_(others, others)], rcond=1e-9, hermitian=True) @ Gbo.T
            values, vectors = np.linalg.eigh(0.5 * (info + info.T))
            keep = values >= 1.0 / DETERMINED**2
        Vk, Vh = vectors[:, keep], vectors[:, ~keep]
        for kept, out in ((Vk, free), (Vh, held_basis)):
            column = np.zeros((q, kept.shape[1]))
            column[local] = D[:, None] * kept
            out.append(column)
        projector[local, local] = (D[:, None] * Vk) @ (Vk.T / D[None, :])
        held[key] = int((~keep).sum())
    return HeldDirections(np.hstack(free), projector, np.hstack(held_basis), held)
