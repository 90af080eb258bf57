"""Statistical bounds for the Monte Carlo tests."""

import numpy as np
from scipy import stats


def assert_standard_normal(z, alpha=1e-3, label=""):
    """Assert that samples ``z`` (runs, k) behave as standard normal per column.

    Per column: the mean lies within the two-sided ``1 - alpha`` bound ``z_{alpha/2} / sqrt(n)``, and
    ``sum z^2`` lies within the two-sided ``1 - alpha`` chi-square(n) band. ``alpha`` is split over the
    columns (Bonferroni), so the whole check fails by chance with probability below ``2 alpha``.
    """
    z = np.atleast_2d(np.asarray(z, float))
    n, k = z.shape
    a = alpha / k
    mean_bound = stats.norm.ppf(1 - a / 2) / np.sqrt(n)
    lo, hi = stats.chi2.ppf(a / 2, n), stats.chi2.ppf(1 - a / 2, n)
    means, ss = z.mean(axis=0), (z**2).sum(axis=0)
    assert np.all(np.abs(means) < mean_bound), f"{label} mean z {means} outside +-{mean_bound:.3f}"
    assert np.all((ss > lo) & (ss < hi)), f"{label} sum z^2 {ss} outside chi2({n}) band [{lo:.1f}, {hi:.1f}]"


def assert_biased(errors, alpha=1e-3, label=""):
    """Assert that the mean of ``errors`` (runs,) is significantly non-zero (t test at level ``alpha``)."""
    e = np.asarray(errors, float)
    t = e.mean() / (e.std(ddof=1) / np.sqrt(len(e)))
    bound = stats.t.ppf(1 - alpha / 2, len(e) - 1)
    assert abs(t) > bound, f"{label} t = {t:.2f} within +-{bound:.2f}: no bias detected"
