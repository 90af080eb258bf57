"""The diagnosis's fast decompositions against the textbook ones (seeded)."""

import numpy as np
import pytest

from magkf.diagnostics.fitting import GRAM_RESOLUTION, tall_svd
from magkf.diagnostics.inference import _wishart_bartlett


@pytest.mark.parametrize("seed", range(3))
def test_tall_svd_through_the_gram_matrix_is_lapacks(seed):
    """A tall matrix with one column a millionth of the others and one nearly a copy of another: the singular
    values resolved agree with LAPACK's to 1e-9 of the largest, their vectors span the same directions, and the
    one below the Gram matrix's resolution is reported as 0 with a zero column of u."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(20_000, 6))
    A[:, 4] *= 1e-6
    A[:, 5] = A[:, 0] + 1e-10 * rng.normal(size=len(A))
    u, s, vt = tall_svd(A)
    u_ref, s_ref, vt_ref = np.linalg.svd(A, full_matrices=False)
    resolved = s_ref > GRAM_RESOLUTION * s_ref[0]
    assert resolved.sum() == 5
    assert np.allclose(s[resolved], s_ref[resolved], rtol=0, atol=1e-9 * s_ref[0])
    assert np.all(s[~resolved] == 0) and np.all(u[:, ~resolved] == 0)
    k = int(resolved.sum()) - 1  # the singular vectors of the tiny column are its own; the rest to 1e-6
    assert np.allclose(np.abs(np.sum(u[:, :k] * u_ref[:, :k], axis=0)), 1.0, atol=1e-6)
    assert np.allclose(np.abs(np.sum(vt[:k] * vt_ref[:k], axis=1)), 1.0, atol=1e-9)


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
