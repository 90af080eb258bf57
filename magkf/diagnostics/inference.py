"""Tests of added regressors that stay valid when the residuals are correlated in time.

The diagnosis asks whether regressors ``U`` (an effect's columns, whitened and made orthogonal to the
model already fitted) explain the residual beyond chance. Real residuals are correlated over seconds
(attitude errors, slow interference, coloured sensor noise), so the epochs are not independent and a
likelihood-ratio test that treats them so calls everything significant. Here:

* **The test** is a Wald test whose covariance is a long-run (heteroscedasticity and autocorrelation
  consistent) variance of the per-epoch scores ``s_t = U_t^T e_t`` (``e`` the residual with the
  regressors), estimated by the equal-weighted cosine series of Sun (2013): the first ``K`` type-II
  cosine transforms of the scores, each an independent estimate of the long-run variance. With that
  estimator the Wald statistic ``W`` scaled as ``F = W (K - q + 1) / (K q)`` follows Snedecor's F with
  ``(q, K - q + 1)`` degrees of freedom (fixed-K asymptotics), which keeps the test's size at small ``K``
  where a chi-square would not (Lazarus, Lewis, Stock and Watson 2018 recommend this test in practice).
* **K** follows the scores' own correlation: the series must be flat over the ``K`` lowest frequencies,
  so ``K = FLAT_SHARE * n / tau`` with ``tau`` the scores' integrated autocorrelation time (Sokal's
  automatic window), capped at ``0.4 n^(2/3)`` (the rule of Lazarus et al. for nearly white scores).
* **An effect whose parameters wander** (a random-walk offset) has no fixed value to test: its test is
  Nyblom's (1989) test of constancy against a random walk, the locally most powerful one, made robust to
  correlation as Hansen (1992) does with a long-run variance ``V`` of the parameters' scores: here the
  statistic's cosine series over its lowest frequencies, ``V`` from the frequencies above them (see
  ``constancy_test``), the p-value from the ratio's exact null distribution by a seeded Monte Carlo.
* **The residual expected after adding an effect** is measured on held-out data: contiguous blocks of the
  log, each predicted by a fit on the others (time-blocked cross-validation), the blocks much longer than
  the residual's correlation time.

References: Y. Sun, "A heteroskedasticity and autocorrelation robust F test using an orthonormal series
variance estimator", Econometrics Journal 16 (2013) 1-26; E. Lazarus, D. J. Lewis, J. H. Stock and
M. W. Watson, "HAR inference: recommendations for practice", J. Business & Economic Statistics 36 (2018)
541-559; A. D. Sokal, "Monte Carlo methods in statistical mechanics", Cargese lectures (1996), for the
automatic window; J. Nyblom, "Testing for the constancy of parameters over time", J. American Statistical
Association 84 (1989) 223-230; B. E. Hansen, "Testing for parameter instability in linear models",
J. Policy Modeling 14 (1992) 517-533.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft, special

__all__ = [
    "FLAT_SHARE",
    "SOKAL_C",
    "MAX_FOLDS",
    "RobustTest",
    "integrated_time",
    "dct_head",
    "cosine_terms",
    "robust_test",
    "score_test",
    "constancy_test",
    "high_passed",
    "fold_edges",
    "held_out_residuals",
    "HeldOut",
    "f_sf",
    "WALK_RATIOS",
    "WalkRate",
    "walk_rate",
]

#: ``K`` is at most this share of the number of independent epochs ``n / tau``: the scores' spectrum then
#: falls by less than about 5 % over the frequencies used (a first-order Gauss-Markov spectrum).
FLAT_SHARE = 0.1
#: Sokal's window: the autocorrelation is summed up to the first lag ``M >= SOKAL_C tau(M)``.
SOKAL_C = 5.0
#: Blocks of the held-out check: at most this many, each at least ``BLOCK_TAUS`` correlation times long.
MAX_FOLDS = 10
BLOCK_TAUS = 20.0


@dataclass(frozen=True)
class RobustTest:
    """Outcome of ``robust_test``: ``F`` with ``(dof, dof_denominator)`` degrees of freedom and its p-value;
    ``terms`` the cosine terms ``K``; ``tau`` the scores' integrated autocorrelation time in epochs;
    ``theta`` (q,) the coefficients of ``U`` and ``cov`` (q, q) their correlation-robust covariance."""

    F: float
    dof: int
    dof_denominator: int
    p_value: float
    terms: int
    tau: float
    theta: np.ndarray
    cov: np.ndarray


def f_sf(F, dof: float, dof_denominator: float):
    """Survival function of Snedecor's F with ``(dof, dof_denominator)`` degrees of freedom (positive, not
    necessarily integers) at ``F``: ``scipy.stats.f.sf``'s value (the same ``scipy.special.fdtrc``, 1 at
    ``F <= 0``) without the half second ``scipy.stats`` takes to import."""
    return special.fdtrc(dof, dof_denominator, np.maximum(F, 0.0))


#: Lags of the autocorrelation that ``integrated_time`` sums directly before it turns to the FFT: Sokal's window
#: ends within them when the correlation time is below ``SHORT_LAGS / SOKAL_C`` epochs.
SHORT_LAGS = 32

#: Rows of a series read at a time from a file (``_Series``); ``high_passed``'s blocks of ``_COSINE_ROWS`` are the same.
READ_ROWS = 65536


class _Series:
    """A series of ``n`` vectors of ``k`` numbers, read ``READ_ROWS`` rows at a time: given as an (n, k) array (or
    (n,)), or as rows kept in a file (``magkf.online.chunked.Spill``: ``rows`` the count, ``read(a, b)`` rows ``a``
    to ``b``), such as a long log's scores, which are then never held whole (``in_memory`` False)."""

    def __init__(self, x):
        self.in_memory = not hasattr(x, "read")
        if self.in_memory:
            self.array = np.asarray(x, float).reshape(len(x), -1)
            self.n, self.k = self.array.shape
        else:
            self.file, self.n, self.k = x, int(x.rows), int(np.prod(x.shape, dtype=np.int64))

    def read(self, a: int, b: int) -> np.ndarray:
        """Rows ``a`` to ``b`` (b - a, k)."""
        if self.in_memory:
            return self.array[a:b]
        return self.file.read(a, b).reshape(-1, self.k)

    def pieces(self, rows: int = READ_ROWS):
        """``(a, b, rows a to b)`` in order, ``rows`` at a time."""
        for a in range(0, self.n, rows):
            b = min(a + rows, self.n)
            yield a, b, self.read(a, b)

    def column(self, j: int) -> np.ndarray:
        """The column ``j`` (n,) (a view of an array given; from a file, one column held)."""
        if self.in_memory:
            return self.array[:, j]
        out = np.empty(self.n)
        for a, b, piece in self.pieces():
            out[a:b] = piece[:, j]
        return out


def integrated_time(x) -> float:
    """Integrated autocorrelation time (epochs, 1 for white) of a series (n,) or the largest over the
    columns of (n, k) (an array, or rows kept in a file: ``_Series``): ``1 + 2 sum rho(l)`` up to Sokal's
    window, a column at a time. The autocorrelation is
    summed lag by lag up to ``SHORT_LAGS`` (a few products of n, where the window of a nearly white series
    ends), else taken from the FFT (the zero-padded transform of all columns at once would hold several
    times their size); the window found within the first lags is the same either way."""
    x = _Series(x)
    n = x.n
    if n < 8:
        return 1.0
    out = 1.0
    for k in range(x.k):
        column = x.column(k)
        if x.in_memory:
            column = column - column.mean()
        else:  # read from the file: its own array, centred in place
            column -= column.mean()
        variance = column @ column
        if not variance > 0:
            continue
        short = min(SHORT_LAGS, n - 1)
        acf = np.array([variance] + [column[:-lag] @ column[lag:] for lag in range(1, short + 1)])
        tau = _sokal(acf, more=short < n - 1)
        if tau is None:  # the window lies further out
            padded = np.zeros(fft.next_fast_len(2 * n))  # zero-padded for the FFT: no lag wraps round
            padded[:n] = column
            del column
            tau = _sokal(_autocovariance(padded, n))
            del padded
        out = max(out, tau)
    return out


def _autocovariance(padded: np.ndarray, n: int) -> np.ndarray:
    """The sums ``sum_j x_j x_(j+l)`` (n,) at every lag ``l`` of a series ``x`` (n,) given zero-padded to at least
    2n points (``padded``, the caller's, let go once transformed: at most two arrays of its length are held at
    once)."""
    size = len(padded)
    power = fft.rfft(padded)
    padded.resize(0, refcheck=False)  # the caller holds no view of it
    power = np.abs(power)
    power *= power
    return fft.irfft(power, n=size)[:n]


def _sokal(acf: np.ndarray, more: bool = False) -> float | None:
    """``tau(M) = 1 + 2 sum_{l <= M} acf[l] / acf[0]`` at the first lag ``M >= SOKAL_C tau(M)`` of the
    autocovariance ``acf`` (lags 0 .., ``acf[0] > 0``); when no lag of ``acf`` reaches it, None if the series
    has ``more`` lags, else ``tau`` at the last."""
    taus = 1.0 + 2.0 * np.cumsum(acf[1:] / acf[0])  # tau(M) for M = 1 ..
    window = np.flatnonzero(np.arange(1, len(acf)) >= SOKAL_C * taus)
    if window.size:
        return float(taus[window[0]])
    return None if more else float(taus[-1])


def _angle(r: np.ndarray, n: int) -> np.ndarray:
    """The angle ``pi r / (2n)`` (rad) of integers ``r`` (int64) reduced modulo ``4n`` (a whole turn) before the
    product with ``pi / (2n)``: it is then below ``2 pi`` and exact to float64's rounding, where ``r`` itself
    (a square, up to ``n^2``) would lose its last digits at n of millions."""
    return (np.pi / (2 * n)) * (r % (4 * n))


def _turn(r: np.ndarray, n: int, sign: float) -> np.ndarray:
    """``exp(sign i pi r / (2n))`` for integers ``r`` (``_angle``)."""
    return np.exp((sign * 1j) * _angle(r, n))


#: Points of ``dct_head``'s chirp made at a time: it is made again for each pair of columns, into the transform's
#: own buffer, rather than held (16 bytes a point).
CHIRP_PIECE = 16384


def _chirp_into(out: np.ndarray, n: int, sign: float, first: int = 0) -> None:
    """``out[p] *= exp(sign i pi d^2 / (2n))`` with ``d = first + p`` at each position ``p`` of ``out``, made
    ``CHIRP_PIECE`` points at a time."""
    for a in range(0, len(out), CHIRP_PIECE):
        j = np.arange(first + a, first + min(a + CHIRP_PIECE, len(out)), dtype=np.int64)
        out[a : a + CHIRP_PIECE] *= _turn(j * j, n, sign)


#: Points of the data ``dct_head`` convolves at a time (at least ``DCT_BLOCK_HEADS`` times the coefficients asked):
#: its buffers are a block's, not the data's length (on the hour's 350 906 points, 8 in place of 22 MB).
DCT_BLOCK = 65536
DCT_BLOCK_HEADS = 8


def _kernel_spectrum(n: int, first: int, length: int, m: int, size: int) -> np.ndarray:
    """The FFT (size,) of the chirp ``exp(+i pi d^2 / (2n))`` at the lags ``d`` that ``dct_head``'s coefficients
    ``-m < k < m`` take from the data points ``first`` to ``first + length``: ``d = e - (m - 1) - (first + length -
    1)`` at positions ``e < length + 2m - 2``, the rest of the ``size`` points zero."""
    lags = length + 2 * m - 2
    lowest = -(m - 1) - (first + length - 1)  # the lag at position 0
    negative = min(lags, -lowest)  # positions of negative lags, whose chirp is that of -d
    out = np.ones(size, complex)
    out[lags:] = 0.0
    _chirp_into(out[:negative][::-1], n, 1.0, first=-(lowest + negative - 1))  # -d from the last of them back
    _chirp_into(out[negative:lags], n, 1.0, first=lowest + negative)
    return fft.fft(out, overwrite_x=True)


def dct_head(x, m: int) -> np.ndarray:
    """The first ``m`` coefficients (m, k) of the type-II cosine transform of the columns of ``x`` (n, k), as
    ``scipy.fft.dct(x, type=2, axis=0)[:m]``: ``y_k = 2 sum_j x_j cos(pi k (2j + 1) / (2n))`` (at most n).

    A length whose transform is fast (``next_fast_len``: only small prime factors) is transformed whole by
    scipy. Any other, such as the hour's n = 2 x 175 453, for which pocketfft's cosine transform is seven times
    slower than at 360 000: ``y_k = 2 Re(exp(-i pi k / (2n)) X_k)`` with ``X_k = sum_j x_j exp(-i pi j k / n)``,
    made by Bluestein's chirp-z transform (``jk = (j^2 + k^2 - (k - j)^2) / 2`` turns the sum into a
    convolution), the data convolved a block of ``DCT_BLOCK`` points at a time (overlap-save: each block's
    contribution to the ``2m - 1`` coefficients ``-m < k < m`` from one circular convolution of
    ``next_fast_len(block + 2m - 2)`` points, its kernel's spectrum made once for all columns), whose cost does not
    depend on n's factors. Two columns go through one complex transform, ``z = x1 + i x2`` at ``k`` and ``-k``:
    ``X1_k = (Z_k + conj Z_-k) / 2`` and ``X2_k = (Z_k - conj Z_-k) / 2i`` as the columns are real; each column
    scaled first by a power of two near its norm (exactly), so that neither's rounding is the other's. The chirps'
    phases are reduced in integers (``_turn``); the rounding error is that of FFTs of that length (seen: 1e-15 of
    the largest coefficient, below 1e-12 of the data's 2-norm at a million points). It holds the block's buffer,
    its kernel's spectrum and the sums of the coefficients: 32 bytes a point of a block, not of the data. ``x`` may
    also be rows kept in a file (``_Series``), read a block at a time: always transformed by blocks then."""
    x = _Series(x)
    n, k = x.n, x.k
    m = min(int(m), n)
    if x.in_memory and fft.next_fast_len(n, real=True) == n:
        return fft.dct(np.ascontiguousarray(x.array.T), type=2)[:, :m].T  # made along contiguous rows (faster)
    if m == 0:
        return np.empty((0, k))
    block = min(n, max(DCT_BLOCK, DCT_BLOCK_HEADS * m))
    size = fft.next_fast_len(block + 2 * m - 2)
    if x.in_memory:
        norms = np.sqrt(np.einsum("ij,ij->j", x.array, x.array))  # (np.linalg.norm would square a copy of x)
    else:
        norms = np.sqrt(sum(np.einsum("ij,ij->j", piece, piece) for _, _, piece in x.pieces()))
    scale = np.exp2(np.round(np.log2(np.where(norms > 0, norms, 1.0))))
    pairs = range(0, k, 2)
    sums = np.zeros((len(pairs), 2 * m - 1), complex)  # Z_k of each pair of columns, k = -(m - 1) .. m - 1
    z = np.empty(size, complex)
    for first in range(0, n, block):
        length = min(block, n - first)
        data = x.read(first, first + length)
        spectrum = _kernel_spectrum(n, first, length, m, size)
        for p, c in enumerate(pairs):  # two columns at a time, in place in one buffer
            z[length:] = 0.0
            np.divide(data[:, c], scale[c], out=z[:length].real)
            if c + 1 < k:
                np.divide(data[:, c + 1], scale[c + 1], out=z[:length].imag)
            else:
                z[:length].imag = 0.0
            _chirp_into(z[:length], n, -1.0, first=first)
            z = fft.fft(z, overwrite_x=True)  # in place (scipy transforms a complex array in place when let)
            z *= spectrum
            z = fft.ifft(z, overwrite_x=True)
            sums[p] += z[length - 1 : length + 2 * m - 2]
        del spectrum, data
    head = np.arange(m, dtype=np.int64)
    chirp, shift = _turn(head * head, n, -1.0), _turn(head, n, -1.0)  # Bluestein's chirp of X_k; exp(-i pi k / 2n)
    out = np.empty((m, k))
    for p, c in enumerate(pairs):
        ahead, behind = chirp * sums[p, m - 1 + head], np.conj(chirp * sums[p, m - 1 - head])  # Z_k, conj Z_-k
        out[:, c] = scale[c] * (shift * (ahead + behind)).real
        if c + 1 < k:
            out[:, c + 1] = scale[c + 1] * (shift * (ahead - behind)).imag
    return out


def cosine_terms(n: int, tau: float) -> int:
    """The number ``K`` of cosine terms for ``n`` epochs of scores with integrated time ``tau`` (epochs)."""
    return int(max(1, np.floor(min(0.4 * n ** (2.0 / 3.0), FLAT_SHARE * n / max(tau, 1.0)))))


def robust_test(U: np.ndarray, residual: np.ndarray) -> RobustTest | None:
    """Correlation-robust Wald F test that the regressors ``U`` explain ``residual``.

    ``U`` (n, 3, q): whitened regressors of n epochs, orthonormal as (3n, q) columns and orthogonal to the
    model already fitted; ``residual`` (n, 3): the whitened residual of that model. Returns None when the
    scores' correlation leaves fewer cosine terms than ``q + 2`` (too few independent stretches to test).
    """
    theta = np.einsum("nik,ni->k", U, residual)
    e = residual - np.einsum("nik,k->ni", U, theta)
    return score_test(np.einsum("nik,ni->nk", U, e), theta)


def score_test(scores, theta: np.ndarray) -> RobustTest | None:
    """``robust_test`` from its per-epoch scores ``s_t = U_t^T e_t`` (n, q), ``e`` the residual with the
    regressors, and the coefficients ``theta = U^T residual`` (q,). The scores may be kept in a file
    (``_Series``): they are then read a block at a time."""
    series = _Series(scores)
    n, q = series.n, series.k
    tau = integrated_time(scores)
    K = cosine_terms(n, tau)
    if K < q + 2:
        return None
    transform = dct_head(scores, K + 1)[1:] * np.sqrt(2.0 / n) / 2.0  # (K, q)
    lrv = transform.T @ transform / K  # long-run variance of one epoch's score
    cov = n * lrv  # of theta = sum of the scores under the null
    try:
        wald = float(theta @ np.linalg.solve(cov, theta))
    except np.linalg.LinAlgError:
        return None
    F = wald * (K - q + 1) / (K * q)
    return RobustTest(F, q, K - q + 1, float(f_sf(F, q, K - q + 1)), K, tau, theta, cov)


#: Lowest cosine frequencies that carry the constancy statistic (93 % of its weight ``1 / k^2``); its
#: long-run variance comes from the frequencies above them, so that a wander, whose power falls as
#: ``1 / k^2``, inflates the variance little, and the two are independent.
CONSTANCY_TERMS = 8
#: Monte Carlo draws of the constancy statistic's null distribution (seeded; p-values below about
#: ``1 / CONSTANCY_DRAWS`` are reported as that bound).
CONSTANCY_DRAWS = 20000
#: Null draws of ``_constancy_null`` already made, by (q, K).
_NULL_DRAWS: dict = {}


def _wishart_bartlett(rng, draws: int, K: int, q: int) -> np.ndarray:
    """``draws`` sums (draws, q, q) of ``K`` outer products of independent standard normal q-vectors, drawn as
    Wishart matrices by Bartlett's decomposition ``A A^T`` (``A`` lower triangular, ``A_ii^2`` chi-square with
    ``K - i`` degrees of freedom, ``A_ij`` standard normal below the diagonal): O(q^2) numbers a draw instead
    of ``K q`` (Bartlett, "On the theory of statistical regression", Proc. R. Soc. Edinburgh 53, 1933)."""
    A = np.tril(rng.normal(size=(draws, q, q)), -1)
    idx = np.arange(q)
    A[:, idx, idx] = np.sqrt(rng.chisquare(K - idx, size=(draws, q)))
    return A @ np.swapaxes(A, 1, 2)


def _constancy_null(q: int, K: int) -> np.ndarray:
    """Sorted draws of ``sum_{k<=CONSTANCY_TERMS} c_k^T Vhat^-1 c_k / (k pi)^2`` with ``c_k`` independent
    standard normal q-vectors and ``Vhat`` the mean of ``K`` more outer products (the statistic's exact
    null distribution for white scores; it does not depend on the true variance)."""
    key = (q, K)
    if key not in _NULL_DRAWS:
        rng = np.random.default_rng(1989 + 1000 * q + K)
        weights = 1.0 / (np.arange(1, CONSTANCY_TERMS + 1) * np.pi) ** 2
        out = np.empty(CONSTANCY_DRAWS)
        for start in range(0, CONSTANCY_DRAWS, 2000):
            c = rng.normal(size=(2000, CONSTANCY_TERMS, q))
            V = _wishart_bartlett(rng, 2000, K, q) / K
            sol = np.linalg.solve(V, np.swapaxes(c, 1, 2))  # (d, q, terms)
            out[start : start + 2000] = np.einsum("dti,dit,t->d", c, sol, weights)
        _NULL_DRAWS[key] = np.sort(out)
    return _NULL_DRAWS[key]


#: Epochs per block of ``high_passed``'s cosines (a few MB of them at a time).
_COSINE_ROWS = READ_ROWS


def high_passed(x, held: bool = True):
    """``x`` (n, k) without its mean and ``CONSTANCY_TERMS`` lowest cosine frequencies (periods longer than a
    quarter of the log): what its correlation time is measured on where a wander would otherwise dominate it.

    The same as zeroing those type-II cosine coefficients and transforming back, written as taking off the
    projections on those cosines ``cos(pi k (2j + 1) / (2n))``, ``k = 0 .. CONSTANCY_TERMS`` (orthogonal,
    squared norms n for k = 0 and n / 2 above): O(n k CONSTANCY_TERMS) work whatever n's factors, the
    cosines made a block of ``_COSINE_ROWS`` epochs at a time by Chebyshev's recurrence
    ``cos(k t) = 2 cos(t) cos((k - 1) t) - cos((k - 2) t)`` from ``cos(t)`` (a rounding error growing as k^2:
    1e-14 at k = 8).

    Rows kept in a file (``_Series``), or an array with ``held`` False, give rows read as the data's less those
    frequencies, made when read (a ``_LowFrequenciesOff``, which ``integrated_time`` and ``dct_head`` take): no copy
    of the data is held."""
    series = _Series(x)
    lazy = _LowFrequenciesOff(series)
    if not (held and series.in_memory):
        return lazy
    out = np.empty_like(series.array)
    for a in range(0, series.n, _COSINE_ROWS):
        b = min(a + _COSINE_ROWS, series.n)
        out[a:b] = lazy.read(a, b)
    return out.reshape(np.shape(x))


def _cosines(n: int, terms: int, a: int, b: int) -> np.ndarray:
    """``cos(pi k (2j + 1) / (2n))`` (b - a, terms) at epochs ``j = a .. b - 1``, ``k = 0 .. terms - 1``, by
    Chebyshev's recurrence (``high_passed``)."""
    out = np.empty((b - a, terms))
    out[:, 0] = 1.0
    if terms > 1:
        out[:, 1] = np.cos((np.pi / (2 * n)) * (2 * np.arange(a, b) + 1))
    for k in range(2, terms):
        out[:, k] = 2.0 * out[:, 1] * out[:, k - 1] - out[:, k - 2]
    return out


class _LowFrequenciesOff:
    """``high_passed`` made when read, of ``series`` (a ``_Series``: rows kept in a file or an array): the rows
    (``rows`` of ``shape``) read as the series' less their mean and ``CONSTANCY_TERMS`` lowest cosine frequencies,
    whose coefficients are found here in one reading; each ``read`` of ``_COSINE_ROWS``-aligned blocks gives
    ``high_passed``'s numbers for them."""

    def __init__(self, series: _Series):
        n = series.n
        self.series, self.rows, self.shape = series, n, (series.k,)
        self.terms = min(CONSTANCY_TERMS + 1, n)  # above n - 1 the cosines repeat
        weight = np.where(np.arange(self.terms) == 0, 1.0 / n, 2.0 / n)  # inverse squared norms
        self.coef = weight[:, None] * sum(
            _cosines(n, self.terms, a, b).T @ piece for a, b, piece in series.pieces(_COSINE_ROWS)
        )

    def read(self, a: int, b: int) -> np.ndarray:
        return self.series.read(a, b) - _cosines(self.series.n, self.terms, a, b) @ self.coef


def constancy_test(scores) -> RobustTest | None:
    """Nyblom's test that parameters with per-epoch ``scores`` (n, q) are constant against a random walk,
    robust to the scores' correlation; the scores sum to zero (the parameters fitted).

    The statistic is Nyblom's ``sum_t S_t^T V^-1 S_t / n^2`` (``S_t`` partial sums) written in its cosine
    series, ``sum_k c_k^T V^-1 c_k / (k pi)^2``, kept to the ``CONSTANCY_TERMS`` lowest frequencies, with
    ``V`` the mean of ``c_k c_k^T`` over the next ``K`` frequencies, ``K`` from ``cosine_terms`` with the
    correlation time measured above those lowest frequencies (``high_passed``), where a wander would
    dominate it. On AR(1) scores with 160 independent stretches the size at 5 % is 5.7 %; with 45 it is
    8 % (the band then reaches where the spectrum falls): the test is meant for long logs. Its p-value is
    from the exact null distribution of that ratio (``_constancy_null``). The scores may be kept in a file
    (``_Series``): they are then read a block at a time, and their high-passed series made when read. Returned
    as a ``RobustTest`` whose ``F`` is the statistic, ``dof`` q and ``dof_denominator`` K (``theta`` and ``cov``
    empty); None when ``K < q + 2``.
    """
    series = _Series(scores)
    n, q = series.n, series.k
    tau = integrated_time(high_passed(scores))
    K = cosine_terms(n, tau)
    if K < q + 2:
        return None
    c = dct_head(scores, CONSTANCY_TERMS + 1 + K) * np.sqrt(2.0 / n) / 2.0  # c_k ~ N(0, V) for k >= 1 (c_0: the mean)
    band = c[CONSTANCY_TERMS + 1 : CONSTANCY_TERMS + 1 + K]
    V = band.T @ band / K
    low = c[1 : CONSTANCY_TERMS + 1]
    weights = 1.0 / (np.arange(1, CONSTANCY_TERMS + 1) * np.pi) ** 2
    try:
        L = float(np.einsum("ti,it,t->", low, np.linalg.solve(V, low.T), weights))
    except np.linalg.LinAlgError:
        return None
    null = _constancy_null(q, K)
    p = (np.sum(null >= L) + 1.0) / (len(null) + 1.0)
    return RobustTest(L, q, K, float(p), K, tau, np.zeros(0), np.zeros((0, 0)))


#: The walk's squared step, relative to the unconstrained fit's, tried for a wander's held-out prediction.
WALK_STEPS = np.logspace(-6.0, 0.0, 13)


def fold_edges(n: int, tau: float) -> np.ndarray:
    """Edges (epoch indices) of the contiguous held-out blocks: at most ``MAX_FOLDS``, each at least
    ``BLOCK_TAUS`` correlation times ``tau`` (epochs) long, and at least two."""
    folds = int(np.clip(n / (BLOCK_TAUS * max(tau, 1.0)), 2, MAX_FOLDS))
    return np.linspace(0, n, folds + 1).astype(int)


class HeldOut:
    """Time-blocked cross-validation of the least-squares fit of ``y ~ X``: each block's residual predicted
    by the fit on the other blocks, from the blocks' normal equations, made a chunk of rows at a time.

    ``y`` (3n,) whitened, three rows an epoch; ``edges`` from ``fold_edges``. ``add`` the regressors of each
    chunk of epochs in turn, then ``coefficients``, then ``residual`` of each chunk."""

    def __init__(self, y: np.ndarray, edges: np.ndarray):
        self.y, self.edges = y, np.asarray(edges)
        folds = len(self.edges) - 1
        self.N, self.c, self.yy = [0.0] * folds, [0.0] * folds, np.zeros(folds)

    def pieces(self, a: int, b: int):
        """``(block, rows of the chunk, rows of y)`` of the chunk of epochs ``a`` to ``b`` cut at the edges."""
        edges = self.edges
        for f in range(np.searchsorted(edges, a, side="right") - 1, np.searchsorted(edges, b, side="left")):
            lo, hi = max(a, edges[f]), min(b, edges[f + 1])
            if hi > lo:
                yield f, slice(3 * (lo - a), 3 * (hi - a)), slice(3 * lo, 3 * hi)

    def add(self, X, a: int, b: int) -> None:
        """The regressors ``X`` (3 (b - a), p) of epochs ``a`` to ``b``, or a tuple of blocks of their columns
        side by side (the products taken block by block, without copying them into one array)."""
        blocks = X if isinstance(X, tuple) else (X,)
        for f, rows, sl in self.pieces(a, b):
            parts, yf, k = [B[rows] for B in blocks], self.y[sl], range(len(blocks))
            upper = {(i, j): parts[i].T @ parts[j] for i in k for j in k if i <= j}
            # the lower blocks the upper ones transposed: N exactly symmetric, as X^T X is
            N = np.block([[upper[i, j] if i <= j else upper[j, i].T for j in k] for i in k])
            c = np.concatenate([P.T @ yf for P in parts])
            self.N[f], self.c[f], self.yy[f] = self.N[f] + N, self.c[f] + c, self.yy[f] + yf @ yf

    @property
    def normal(self) -> np.ndarray:
        """``X^T X`` over every block."""
        return sum(self.N)

    def coefficients(self, increments: np.ndarray | None = None) -> list:
        """Each block's coefficients (p,), fitted on the others. ``increments`` (m, p) the steps between knots
        of a wander among the coefficients: they get a zero-mean Gaussian prior, so that coefficients the
        other blocks leave open are interpolated from their neighbours. The prior's spread (the walk's step)
        is the one of ``WALK_STEPS`` that predicts the held-out blocks best (their sums of squares from the
        normal equations): the smallest makes the wander a constant, so the result is never worse than the
        model without it, and whether it wanders is for ``constancy_test`` to say."""
        N, c = sum(self.N), sum(self.c)
        # the other blocks' normal equations summed, not the block's taken off the whole: coefficients that
        # only the block determines (a wander's knots inside it) are then exactly undetermined, not rounding
        folds = range(len(self.N))
        others = [(sum(self.N[:f] + self.N[f + 1 :]), sum(self.c[:f] + self.c[f + 1 :])) for f in folds]

        def fitted(prior):
            return [np.linalg.lstsq(No + prior, co, rcond=None)[0] for No, co in others]

        if increments is None:
            return fitted(0.0)
        # steps relative to those of the unconstrained fit to all blocks, which noise inflates
        raw = float(np.mean((increments @ np.linalg.lstsq(N, c, rcond=None)[0]) ** 2))
        P = increments.T @ increments / max(raw, 1e-300)
        trials = [fitted(P / step) for step in WALK_STEPS]
        squares = [
            sum(yy - 2.0 * b @ cf + b @ Nf @ b for b, Nf, cf, yy in zip(beta, self.N, self.c, self.yy))
            for beta in trials
        ]
        return trials[int(np.argmin(squares))]

    def residual(self, X, a: int, b: int, beta: list) -> np.ndarray:
        """The held-out residual (3 (b - a),) of epochs ``a`` to ``b`` of regressors ``X`` (as in ``add``), from
        ``coefficients``."""
        blocks = X if isinstance(X, tuple) else (X,)
        cuts = np.cumsum([0] + [B.shape[1] for B in blocks])
        out = np.empty(3 * (b - a))
        for f, rows, sl in self.pieces(a, b):
            out[rows] = self.y[sl] - sum(B[rows] @ beta[f][i:j] for B, i, j in zip(blocks, cuts[:-1], cuts[1:]))
        return out


def held_out_residuals(rows, y: np.ndarray, edges: np.ndarray, chunks):
    """``HeldOut``'s residual of ``y`` on the regressors ``rows(a, b)`` (3 (b - a), p) of each chunk ``(a, b)`` of
    ``chunks`` (consecutive epochs, first to last), a chunk at a time: ``(a, b, residual (3 (b - a),))`` in order,
    the rows made twice (their normal equations per block first)."""
    held = HeldOut(y, edges)
    for a, b in chunks:
        held.add(rows(a, b), a, b)
    beta = held.coefficients()
    for a, b in chunks:
        yield a, b, held.residual(rows(a, b), a, b, beta)


#: Ratios of a random walk's variance over the whole stretch of data to the noise variance of one stretch
#: mean tried by ``walk_rate`` (the walk's rate is profiled over them; 0 is tried too).
WALK_RATIOS = np.logspace(-6.0, 6.0, 481)


@dataclass(frozen=True)
class WalkRate:
    """Outcome of ``walk_rate``: the rate ``rate`` (nT per sqrt(s)) of a random-walk offset the stretch means
    show, and its ``confidence`` interval ``low`` to ``high``; ``noise_nt`` the standard deviation of a stretch
    mean's noise per axis (at the median count of epochs), ``stretches`` the stretches used and ``axes`` the
    directions used per stretch."""

    rate: float
    low: float
    high: float
    confidence: float
    noise_nt: float
    stretches: int
    axes: int


def walk_rate(means, start, stop, counts, drop=None, confidence: float = 0.95) -> WalkRate | None:
    """The rate of a random walk on an offset from the means of a residual over consecutive stretches of time.

    ``means`` (K, 3) nT: the residual's mean in each stretch, per sensor axis; ``start`` and ``stop`` (K,) s
    the stretches' ends; ``counts`` (K,) their epochs. The model: ``means_k = c + w_k + e_k`` with ``c`` an
    unknown constant (the offset the core fits), ``w_k`` the mean over stretch k of a random walk of rate ``q``
    nT/sqrt(s) on each axis (independent axes, one rate), ``e_k`` independent noise of variance ``s^2 / counts_k``
    per axis. Stretch means of a walk ``W`` (from the first stretch's start) have covariance ``q^2`` times
    ``(a_j + b_j) / 2`` for stretches ``j`` before ``k`` and ``a_k + L_k / 3`` on the diagonal (``a`` the start,
    ``b`` the end, ``L`` the length). ``drop`` (K, 3) unit vectors: a direction per stretch left out of the
    means (where a nuisance, the logged heading's error, has been or would be taken out); None: all three axes.

    ``q`` and ``s`` are estimated by restricted maximum likelihood (the constant integrated out), ``s``
    profiled analytically and ``q`` over a grid of the walk's to the noise's variance (``WALK_RATIOS``), all of
    them at the cost of one eigen-decomposition; the interval is the profile likelihood's (a likelihood ratio
    within the chi-square quantile of one degree of freedom). None with fewer than four stretches.
    """
    means, counts = np.asarray(means, float), np.asarray(counts, float)
    start, stop = np.asarray(start, float), np.asarray(stop, float)
    K = len(means)
    if K < 4:
        return None
    if drop is None:
        U = np.broadcast_to(np.eye(3), (K, 3, 3))
    else:
        U = np.swapaxes(np.linalg.svd(np.asarray(drop, float)[:, None, :])[2][:, 1:, :], 1, 2)  # (K, 3, 2)
    m = U.shape[2]
    a, length = start - start[0], stop - start
    span = max(stop[-1] - start[0], 1e-9)
    mid = a + length / 2.0
    B = np.minimum.outer(mid, mid)  # E[w_j w_k] / q^2 for j != k: the earlier stretch's midpoint
    B[np.diag_indices(K)] = a + length / 3.0
    weight = np.sqrt(np.median(counts) / counts)  # noise standard deviation of each mean, relative
    G = np.einsum("jam,kan->jmkn", U, U) * (B / span)[:, None, :, None]
    G = G.reshape(K * m, K * m) / np.repeat(weight, m)[:, None] / np.repeat(weight, m)[None, :]
    y = np.einsum("kam,ka->km", U, means).ravel() / np.repeat(weight, m)
    X = np.swapaxes(U, 1, 2).reshape(K * m, 3) / np.repeat(weight, m)[:, None]
    d, Q = np.linalg.eigh(G)
    d = np.clip(d, 0.0, None)
    yt, Xt = Q.T @ y, Q.T @ X
    n_free = K * m - 3
    ratios = np.r_[0.0, WALK_RATIOS]
    w = 1.0 / (ratios[:, None] * d + 1.0)  # (ratios, N): the inverse covariance's eigenvalues, noise as unit
    normal = np.einsum("rn,ni,nj->rij", w, Xt, Xt)
    beta = np.linalg.solve(normal, ((w * yt) @ Xt)[..., None])[..., 0]
    noise = np.sum(w * (yt - beta @ Xt.T) ** 2, axis=1) / n_free
    loglik = -0.5 * (n_free * np.log(noise) - np.sum(np.log(w), axis=1) + np.linalg.slogdet(normal)[1])
    rates = np.sqrt(ratios * noise / span)
    best = int(np.argmax(loglik))
    inside = 2.0 * (loglik[best] - loglik) <= special.chdtri(1, 1.0 - confidence)
    # at large ratios the noise's estimate falls as 1 / ratio and the rate tends to that of a walk without noise:
    # the grid's last point stands for the limit
    high = float(np.max(rates[inside]))
    low = 0.0 if inside[0] else float(np.min(rates[inside]))
    return WalkRate(float(rates[best]), low, high, confidence, float(np.sqrt(noise[best])), K, m)
