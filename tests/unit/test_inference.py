"""The diagnosis's statistical helpers against the scipy functions they stand in for (seeded)."""

import numpy as np
import pytest
from scipy import fft, special, stats

from magkf.diagnostics.inference import CONSTANCY_TERMS, dct_head, f_sf, high_passed


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


@pytest.mark.parametrize("n", [1, 2, 7, 97, 1000, 4096, 10007, 65536, 350906, 360000, 1000003])
def test_dct_head_is_scipy_dct(n):
    """``dct_head`` gives ``scipy.fft.dct``'s first coefficients for lengths that are primes, powers of two,
    round and of a large prime factor (the hour's 350 906 = 2 x 175 453), on white data and on a random walk
    with a mean (whose low coefficients are far larger than the rest), within an FFT's rounding (about
    ``1e-12`` of the data's norm at a million points, ``2e-13`` of it seen)."""
    rng = np.random.default_rng(n)
    x = np.c_[rng.normal(size=n), 5.0 + np.cumsum(rng.normal(size=n))]
    m = min(n, 2000)
    expected = fft.dct(x, type=2, axis=0)[:m]
    got = dct_head(x, m)
    assert got.shape == (m, 2)
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
