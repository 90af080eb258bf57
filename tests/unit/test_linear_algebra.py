"""The diagnosis's fast decompositions against the textbook ones (seeded)."""

import numpy as np
import pytest

from magkf.diagnostics.fitting import GRAM_CONDITION, OUTLIER_SIGMA, gram_svd, inliers, tall_svd
from magkf.diagnostics.inference import _wishart_bartlett, held_out_residuals


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("small", [1e-2, 1e-6])
def test_tall_svd_is_lapacks(seed, small):
    """A tall matrix with one column ``small`` times the others: its singular values agree with LAPACK's to 1e-9
    of the largest and its singular vectors span the same directions, whether it is well conditioned (through
    the Gram matrix) or not (handed to LAPACK)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(20_000, 6))
    A[:, 4] *= small
    u, s, vt = tall_svd(A)
    u_ref, s_ref, vt_ref = np.linalg.svd(A, full_matrices=False)
    assert (s_ref[-1] >= GRAM_CONDITION * s_ref[0]) == (small > GRAM_CONDITION)
    assert np.allclose(s, s_ref, rtol=0, atol=1e-9 * s_ref[0])
    assert np.allclose(np.abs(np.sum(u * u_ref, axis=0)), 1.0, atol=1e-6)
    assert np.allclose(np.abs(np.sum(vt * vt_ref, axis=1)), 1.0, atol=1e-9)
    assert np.allclose(u.T @ u, np.eye(6), atol=1e-7)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("small", [1e-2, 1e-6, 1e-9, 0.0])
def test_gram_svd_from_blocks_is_lapacks(seed, small):
    """The SVD from the Gram matrix and blocks of rows (one more pass when ill-conditioned) of a tall matrix
    with one direction ``small`` times the others (0: rank-deficient): singular values within 1e-12 of the
    largest of LAPACK's, and the same right singular vectors where the singular values are apart."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(30_000, 6)) @ rng.normal(size=(6, 6))
    u, s_ref, vt_ref = np.linalg.svd(A, full_matrices=False)
    s_ref[-1] = small * s_ref[0]
    A = (u * s_ref) @ vt_ref
    s, vt = gram_svd(A.T @ A, lambda: (A[a : a + 7000] for a in range(0, len(A), 7000)), len(A))
    assert np.allclose(s, s_ref, rtol=0, atol=1e-12 * s_ref[0])
    apart = np.r_[np.diff(s_ref) < -1e-3 * s_ref[0], True] & np.r_[True, np.diff(s_ref) < -1e-3 * s_ref[0]]
    assert np.allclose(np.abs(np.sum(vt * vt_ref, axis=1))[apart], 1.0, atol=1e-6)


def test_gram_svd_of_zero_rows():
    """A matrix of zeros (a candidate whose regressors all vanish): singular values zero, without overflow."""
    s, vt = gram_svd(np.zeros((3, 3)), lambda: [np.zeros((300, 3))], 300)
    assert np.array_equal(s, np.zeros(3)) and np.allclose(vt @ vt.T, np.eye(3))


def test_held_out_fit_leaves_what_only_the_held_out_block_determines_at_zero():
    """A regressor that is zero outside one held-out block: that block is predicted by the fit of the other
    regressors on the other blocks (the column's coefficient exactly undetermined there, so zero), the same
    whichever chunks the rows come in."""
    rng = np.random.default_rng(3)
    n = 3000
    X = np.hstack([rng.normal(size=(3 * n, 3)), np.zeros((3 * n, 1))])
    X[3000:6000, 3] = rng.normal(size=3000)  # epochs 1000 to 2000: the second of three blocks
    y = X @ np.array([1.0, 2.0, 3.0, 5.0]) + rng.normal(size=3 * n)
    edges = np.array([0, 1000, 2000, 3000])
    others = np.r_[0:3000, 6000:9000]
    beta = np.linalg.lstsq(X[others, :3], y[others], rcond=None)[0]
    for chunks in ([(0, n)], [(0, 1500), (1500, 2600), (2600, n)]):
        held = np.concatenate([r for _, _, r in held_out_residuals(lambda a, b: X[3 * a : 3 * b], y, edges, chunks)])
        assert np.allclose(held[3000:6000], y[3000:6000] - X[3000:6000, :3] @ beta, rtol=0, atol=1e-9)


def test_bartlett_draws_are_wishart():
    """Sums of K outer products of standard normal 3-vectors: mean K I, variance 2K on the diagonal and K off
    it, and E det = K (K - 1) (K - 2); each checked within 4 Monte Carlo standard errors."""
    rng = np.random.default_rng(5)
    draws, K, q = 100_000, 7, 3
    W = _wishart_bartlett(rng, draws, K, q)
    mean = np.where(np.eye(q, dtype=bool), float(K), 0.0)
    var = np.where(np.eye(q, dtype=bool), 2.0 * K, float(K))
    assert np.all(np.abs(W.mean(axis=0) - mean) < 4 * np.sqrt(var / draws))
    # the sample variance of a Wishart entry has a relative standard error below 3 / sqrt(draws) here
    assert np.allclose(W.var(axis=0), var, rtol=4 * 3 / np.sqrt(draws))
    det = np.linalg.det(W)
    assert abs(det.mean() - K * (K - 1) * (K - 2)) < 4 * det.std() / np.sqrt(draws)


@pytest.mark.parametrize("n", [1, 2, 11, 1000, 100_001])
def test_inliers_one_component_at_a_time_are_the_whole_arrays_rule(n):
    """The outlier rule centred in place one component at a time keeps the epochs the rule on the whole (n, 3)
    array keeps (median, 1.4826 times the median absolute deviation, ``OUTLIER_SIGMA`` of it), on heavy-tailed
    residuals of unequal scales and on an all-zero residual (the scale's floor)."""
    rng = np.random.default_rng(n)
    for residual in (rng.standard_t(2, (n, 3)) * rng.uniform(0.1, 10.0, 3), np.zeros((n, 3))):
        centred = residual - np.median(residual, axis=0)
        scale = np.maximum(1.4826 * np.median(np.abs(centred), axis=0), 1e-12)
        expected = np.all(np.abs(centred) <= OUTLIER_SIGMA * scale, axis=1)
        np.testing.assert_array_equal(inliers(residual.copy()), expected)


@pytest.mark.parametrize("n", [5, 4096, 4097, 100_003])
def test_within_bin_squares_a_chunk_at_a_time_are_bincounts(n):
    """The binned signals' within-bin sums of squares, added a chunk at a time, are ``np.bincount``'s of the whole
    array to the bit (heavy-tailed values, chunk edges at and beside ``CHUNK``)."""
    from magkf.diagnostics.diagnose import _within_squares

    rng = np.random.default_rng(n)
    k = min(n, 12)
    group, x = rng.integers(0, k, n), 50.0 * rng.standard_t(3, n)
    means = np.bincount(group, x, minlength=k) / np.maximum(np.bincount(group, minlength=k), 1)
    expected = np.bincount(group, (x - means[group]) ** 2, minlength=k)
    np.testing.assert_array_equal(_within_squares(group, x, means), expected)
