"""The diagnosis's statistical helpers against the scipy functions they stand in for (seeded)."""

import numpy as np
import pytest
from scipy import fft, signal, special, stats

from magkf.diagnostics.fitting import SPARSE_COLUMNS, HeadingWander, Linearised
from magkf.diagnostics.inference import (
    CONSTANCY_TERMS,
    SHORT_LAGS,
    SOKAL_C,
    dct_head,
    f_sf,
    high_passed,
    integrated_time,
)


def test_f_sf_is_scipy_stats_f_sf():
    """``f_sf`` gives ``scipy.stats.f.sf``'s values over statistics from below 0 to far in the tail, integer
    and fractional degrees of freedom (as the binned analysis of variance uses), and at inf and nan; the t
    distribution's sf and cdf used by the validation are ``special.stdtr`` likewise."""
    rng = np.random.default_rng(3)
    F = np.r_[-1.0, 0.0, rng.uniform(0.0, 5.0, 40), 50.0, 1e3, np.inf, np.nan]
    for dof, den in [(1, 1990), (3, 1988), (9, 1982), (11, 0.7), (11, 3512.4)]:
        np.testing.assert_allclose(f_sf(F, dof, den), stats.f.sf(F, dof, den), rtol=1e-14, atol=0)
    t = np.r_[-np.inf, rng.normal(0.0, 3.0, 40), np.inf]
    for dof in (1, 4, 9):
        np.testing.assert_allclose(special.stdtr(dof, -t), stats.t.sf(t, dof), rtol=1e-14, atol=0)
        np.testing.assert_allclose(special.stdtr(dof, t), stats.t.cdf(t, dof), rtol=1e-14, atol=0)


def _fft_rounding(n: int) -> float:
    """A bound of the rounding error of an FFT-based transform of n points relative to the 2-norm of the
    data, per coefficient: the FFT's norm-wise bound ``eps log2 L`` (relative to the norm of all ``L`` outputs,
    Higham, "Accuracy and stability of numerical algorithms", 2nd ed., section 24.1), that norm ``sqrt(L)``
    times the data's for a convolution with a chirp of modulus 1, with one output taking all of the error at
    worst; ``L`` at most ``2 n + 2000`` (the transform's length), twice for the two transforms compared."""
    size = 2 * n + 2000
    return 2.0 * np.finfo(float).eps * np.log2(size) * np.sqrt(size)


@pytest.mark.parametrize(
    "n", [1, 2, 7, 97, 1000, 4096, 10007, 65536, 350906, 360000, pytest.param(1000003, marks=pytest.mark.slow)]
)
def test_dct_head_is_scipy_dct(n):
    """``dct_head`` gives ``scipy.fft.dct``'s first coefficients for lengths that are primes, powers of two,
    round and of a large prime factor (the hour's 350 906 = 2 x 175 453), on a random walk with a mean (whose
    low coefficients are far larger than the rest) transformed with white data a million times smaller (two
    columns go through one transform), and on white data alone, each within an FFT's rounding of its own
    norm (about ``1e-12`` of it at a million points, ``7e-13`` seen)."""
    rng = np.random.default_rng(n)
    x = np.c_[5.0 + np.cumsum(rng.normal(size=n)), 1e-6 * rng.normal(size=n), rng.normal(size=n)]
    m = min(n, 2000)
    expected = fft.dct(x, type=2, axis=0)[:m]
    got = dct_head(x, m)
    assert got.shape == (m, 3)
    assert np.max(np.abs(got - expected) / np.linalg.norm(x, axis=0)) < _fft_rounding(n)


@pytest.mark.parametrize("n", [5, 9, 1000, 10007, 350906])
def test_high_passed_is_the_transform_with_its_lowest_coefficients_zeroed(n):
    """``high_passed`` equals zeroing the ``CONSTANCY_TERMS + 1`` lowest type-II cosine coefficients and
    transforming back with scipy, within rounding (relative to the data's RMS)."""
    rng = np.random.default_rng(n)
    x = np.c_[rng.normal(size=n), 3.0 + np.cumsum(rng.normal(size=n)), np.sin(np.arange(n) / (n / 7.0))]
    c = fft.dct(x, type=2, axis=0)
    c[: CONSTANCY_TERMS + 1] = 0.0
    expected = fft.idct(c, type=2, axis=0)
    got = high_passed(x)
    assert np.max(np.abs(got - expected) / np.linalg.norm(x, axis=0)) < _fft_rounding(n)


def _integrated_time_by_fft(x):
    """Sokal's integrated time of each column from the whole FFT autocorrelation (the reference)."""
    out = 1.0
    for column in x.T:
        column = column - column.mean()
        acf = fft.irfft(np.abs(fft.rfft(column, n=2 * len(column))) ** 2)[: len(column)]
        taus = 1.0 + 2.0 * np.cumsum(acf[1:] / acf[0])
        window = np.flatnonzero(np.arange(1, len(column)) >= SOKAL_C * taus)
        out = max(out, taus[window[0]] if window.size else taus[-1])
    return out


@pytest.mark.parametrize("phi", [0.0, 0.5, 0.8, 0.97])
def test_integrated_time_from_the_first_lags_is_that_of_the_whole_autocorrelation(phi):
    """AR(1) series whose Sokal window ends within ``SHORT_LAGS`` (white, phi 0.5: tau 3) and beyond it
    (phi 0.8: tau 9, 0.97: tau 66): the same integrated time as from the whole FFT autocorrelation, within
    rounding; and near the AR(1) value ``(1 + phi) / (1 - phi)`` (within 5 standard errors of Sokal's,
    ``tau sqrt(2 (2M + 1) / n)``)."""
    rng = np.random.default_rng(11)
    n = 200_000
    x = signal.lfilter([1.0], [1.0, -phi], rng.normal(size=(n, 2)), axis=0)
    tau = integrated_time(x)
    assert tau == pytest.approx(_integrated_time_by_fft(x), rel=1e-12)
    truth = (1 + phi) / (1 - phi)
    assert abs(tau - truth) < 5 * truth * np.sqrt(2 * (2 * SOKAL_C * truth + 1) / n)
    assert (SOKAL_C * truth < SHORT_LAGS) == (phi <= 0.5)


def test_whitened_leaves_zero_columns_zero_and_the_others_as_made_in_full():
    """``Linearised.whitened`` of a wide block whose columns are mostly zero over the epochs (a drift's hat
    functions) computes only the others: exactly the values of the whole block whitened and taken off the
    heading wander, with and without the wander."""
    rng = np.random.default_rng(5)
    n, q = 1200, SPARSE_COLUMNS + 3
    t = np.arange(n) * 0.05
    W = rng.normal(size=(n, 3, 3))
    G = np.zeros((n, 3, q))
    G[:, :, [1, 4, 5]] = rng.normal(size=(n, 3, 3))
    for wander in (None, HeadingWander(rng.normal(size=(n, 3)), t, 10.0)):
        fit = Linearised(None, None, None, W, np.zeros((3 * n, 0)), None, None, None, None, wander)
        dense = (W @ G).reshape(3 * n, q)
        dense = dense if wander is None else wander.remove(dense)
        got = fit.whitened(G)
        assert np.array_equal(got, dense)
        assert not got[:, [0, 2, 3]].any()


def _blocked_rounding(n: int, block: int, m: int) -> float:
    """``_fft_rounding``'s bound for a transform convolved ``block`` points at a time: each block's error within its
    own transform's bound (length ``block + 2m``) relative to the block's norm, and the blocks' norms summing to at
    most ``sqrt(blocks)`` times the data's (Cauchy-Schwarz)."""
    size, blocks = block + 2 * m, -(-n // block)
    return 2.0 * np.finfo(float).eps * np.log2(size) * np.sqrt(size) * np.sqrt(blocks)


@pytest.mark.parametrize("block", [1, 7, 64, 4096])
@pytest.mark.parametrize("n", [97, 10007])
def test_dct_head_convolved_in_blocks_is_scipy_dct(monkeypatch, n, block):
    """The chirp-z transform convolved a block at a time (``DCT_BLOCK``) gives ``scipy.fft.dct``'s coefficients for
    blocks of one point, of a prime number of points, shorter and longer than the coefficients asked (300) and
    longer than the data, within the rounding of its blocks' transforms."""
    from magkf.diagnostics import inference

    monkeypatch.setattr(inference, "DCT_BLOCK", block)
    monkeypatch.setattr(inference, "DCT_BLOCK_HEADS", 0)
    rng = np.random.default_rng(n + block)
    x = np.c_[5.0 + np.cumsum(rng.normal(size=n)), 1e-6 * rng.normal(size=n), rng.normal(size=n)]
    m = min(n, 300)
    got = dct_head(x, m)
    expected = fft.dct(x, type=2, axis=0)[:m]
    assert np.max(np.abs(got - expected) / np.linalg.norm(x, axis=0)) < _blocked_rounding(n, block, m)
    assert dct_head(x, 0).shape == (0, 3)


def test_dct_head_holds_a_block_not_the_data(monkeypatch):
    """``dct_head`` of many columns at a length of a large prime factor holds, beyond its output and the sums of
    its coefficients, no more than one complex buffer of a block and its kernel's spectrum (16 bytes a point each)
    and a piece of a chirp at a time (traced): no copy of the data (``np.linalg.norm`` of all columns made one),
    no buffer of the data's length (one would not fit)."""
    import tracemalloc

    from magkf.diagnostics import inference

    monkeypatch.setattr(inference, "DCT_BLOCK", 8192)
    n, q, m = 200003, 9, 400  # a prime: the chirp-z path
    x = np.random.default_rng(8).normal(size=(n, q))
    block = max(inference.DCT_BLOCK, inference.DCT_BLOCK_HEADS * m)
    size = fft.next_fast_len(block + 2 * m - 2)
    sums = 16 * (2 * m - 1) * -(-q // 2)
    tracemalloc.start()
    try:
        got = dct_head(x, m)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    piece = inference.CHIRP_PIECE * (3 * 8 + 16)  # a piece's integers, angles and complex chirp
    assert peak <= 2 * 16 * size + 2 * piece + got.nbytes + sums + 64 * m + 4096
    assert peak < 16 * n  # one complex buffer of the data's length would not fit
    expected = fft.dct(x, type=2, axis=0)[:m]
    np.testing.assert_allclose(got, expected, rtol=0, atol=_blocked_rounding(n, block, m) * np.sqrt(n))


def test_heading_wander_made_a_chunk_at_a_time_is_the_held_one():
    """A ``HeadingWander`` whose whitened heading axis is made for the epochs asked (``WhitenedHeading``, from a
    ``ChunkWhitening``) takes the wander out of rows exactly as one built from the whole axis held, chunk by chunk
    and whole."""
    from magkf.config import FilterConfig
    from magkf.online.determined import ChunkWhitening, WhitenedHeading, wander_chunks
    from magkf.online.measurements import measurement_model
    from magkf.online.state import StateLayout

    rng = np.random.default_rng(11)
    n = 3000
    t = np.arange(n) * 0.01
    layout = StateLayout.with_core()
    x = layout.prior()[0]
    R = layout.R(x)
    field = 2e4 * rng.normal(size=(n, 3))
    heading = rng.normal(size=(n, 3))
    heading /= np.linalg.norm(heading, axis=1, keepdims=True)
    W = ChunkWhitening(measurement_model(FilterConfig(), layout, x), field, R, heading)
    lazy = HeadingWander(WhitenedHeading(W, heading, R), t, 10.0)
    held = HeadingWander(np.einsum("nij,nj->ni", W[0:n], heading @ R.T), t, 10.0)
    assert np.array_equal(lazy.inverse, held.inverse)
    X = rng.normal(size=(3 * n, 4))
    for a, b in wander_chunks(n, held):
        assert np.array_equal(lazy.remove(X[3 * a : 3 * b], a, b), held.remove(X[3 * a : 3 * b], a, b))
    assert np.array_equal(lazy.remove(X), held.remove(X))


@pytest.mark.parametrize("n", [13, 40, 1001])
def test_autocovariance_by_fft_is_the_direct_sums(n):
    """The autocovariance the FFT gives (``_autocovariance``, zero-padded to ``next_fast_len(2n)`` points, odd at
    n = 13 and 40) equals the direct sums at every lag, to rounding: the inverse transform is of the padded length
    itself (at an odd length, one point fewer had shifted every lag)."""
    from magkf.diagnostics.inference import _autocovariance

    x = np.random.default_rng(n).normal(size=n)
    padded = np.zeros(fft.next_fast_len(2 * n))
    padded[:n] = x
    got = _autocovariance(padded, n)
    expected = np.array([x[: n - lag] @ x[lag:] for lag in range(n)])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * (x @ x))


def _kept_in_a_file(folder, x, piece: int = 5000):
    """The rows of ``x`` (n, q) appended to a ``Spill`` in ``folder`` ``piece`` rows at a time, as the diagnosis
    writes a candidate's scores."""
    from magkf.online.chunked import Spill

    spill = Spill(folder, "scores", float, (x.shape[1],))
    for a in range(0, len(x), piece):
        spill.append(x[a : a + piece])
    return spill


@pytest.mark.parametrize("n", [97, 70001, 200003])
def test_series_kept_in_a_file_give_the_held_ones_statistics(tmp_path, monkeypatch, n):
    """Scores kept in a file and read a block at a time (``_Series``) give what the held array gives: the same
    integrated time, also above the short lags (an AR(1) of correlation time 20 epochs, taken by the FFT), the
    same high-passed series, the same cosine coefficients of a length of a large prime factor (each path convolves
    by the same blocks; blocks of 4 096 rows so that 200 003 points span many), and so the same score and constancy
    tests, to the bit."""
    from magkf.diagnostics import inference
    from magkf.diagnostics.inference import constancy_test, score_test

    monkeypatch.setattr(inference, "READ_ROWS", 4096)
    monkeypatch.setattr(inference, "_COSINE_ROWS", 4096)
    rng = np.random.default_rng(n)
    white = rng.normal(size=(n, 3))
    x = np.empty_like(white)
    x[0] = white[0]
    for t in range(1, n):  # AR(1), phi = 0.9: integrated time 19 epochs
        x[t] = 0.9 * x[t - 1] + white[t]
    x += np.array([0.5, -2.0, 0.0])
    spill = _kept_in_a_file(tmp_path, x)
    assert integrated_time(spill) == integrated_time(x)
    assert integrated_time(x) > SHORT_LAGS / SOKAL_C  # beyond the lags summed directly
    lazy = high_passed(spill)
    assert np.array_equal(inference._Series(lazy).read(0, n), high_passed(x))
    assert integrated_time(lazy) == integrated_time(high_passed(x))
    assert integrated_time(high_passed(x, held=False)) == integrated_time(high_passed(x))
    assert fft.next_fast_len(n, real=True) != n
    m = min(n, 300)
    assert np.array_equal(dct_head(spill, m), dct_head(x, m))
    theta = x.sum(axis=0)
    held, kept = score_test(x, theta), score_test(spill, theta)
    if n == 97:  # 97 epochs correlated over 19 leave too few cosine terms for three parameters: no test either way
        assert held is None and kept is None
    else:
        assert (kept.F, kept.terms, kept.tau, kept.p_value) == (held.F, held.terms, held.tau, held.p_value)
    centred = x - x.mean(axis=0)
    (tmp_path / "centred").mkdir()
    held, kept = constancy_test(centred), constancy_test(_kept_in_a_file(tmp_path / "centred", centred))
    assert (kept.F, kept.terms, kept.tau, kept.p_value) == (held.F, held.terms, held.tau, held.p_value)


def test_dct_head_of_a_fast_length_kept_in_a_file_is_scipy_dct(tmp_path):
    """At a length scipy transforms whole (360 000 points), rows kept in a file are convolved by blocks instead
    (nothing of the length held): scipy's coefficients within the blocks' rounding."""
    from magkf.diagnostics import inference

    n, m = 360000, 2000
    rng = np.random.default_rng(5)
    x = np.c_[5.0 + np.cumsum(rng.normal(size=n)), 1e-6 * rng.normal(size=n), rng.normal(size=n)]
    got = dct_head(_kept_in_a_file(tmp_path, x, 65536), m)
    expected = fft.dct(x, type=2, axis=0)[:m]
    block = max(inference.DCT_BLOCK, inference.DCT_BLOCK_HEADS * m)
    assert np.max(np.abs(got - expected) / np.linalg.norm(x, axis=0)) < _blocked_rounding(n, block, m)
