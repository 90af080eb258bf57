"""The diagnosis's statistical helpers against the scipy functions they stand in for (seeded)."""

import numpy as np
from scipy import special, stats

from magkf.diagnostics.inference import f_sf


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
