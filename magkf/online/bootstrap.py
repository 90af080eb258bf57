"""Initial calibration from the log itself, when no offline calibration is given.

With attitude, ``m = R B_b + b`` is linear in the 12 parameters, so a least-squares fit over the first
stretch of good epochs needs no starting point and no hint about the mounting: a permuted or flipped
sensor is just another ``R``. Disturbances are down-weighted by iteratively reweighted least squares
(Huber weights). Directions the stretch does not determine (for a level drive: the third column of
``R`` against ``b``) are held by a weak prior: ``R``'s third column completing its first two to a
right-handed, orthogonal-like matrix, ``b`` near zero.

Without attitude, the ellipsoid fit gives ``R`` up to a rotation; magkf takes the patent's
``K = K1 K2`` form, with the fit's uncertainty for ``R R^T`` and ``b`` and a weak prior for the rotation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..offline.ellipsoid import HUBER_K

__all__ = [
    "PRIOR_R_STD",
    "PRIOR_B_STD",
    "INFLATION",
    "HUBER_K",
    "MIN_EPOCHS",
    "Bootstrap",
    "vector_least_squares",
    "completion_prior",
    "bootstrap_vector",
    "bootstrap_magnitude",
]

#: Weak prior of the bootstrap: standard deviation of each element of R and of each offset (nT).
PRIOR_R_STD = 0.1
PRIOR_B_STD = 5000.0
#: Variance inflation of the bootstrap covariance (the filter sees the same epochs again).
INFLATION = 100.0
MIN_EPOCHS = 50


@dataclass(frozen=True)
class Bootstrap:
    """``x`` (12,) and covariance ``P`` (12, 12) of the core parameters, and what they came from."""

    x: np.ndarray
    P: np.ndarray
    method: str
    n_epochs: int
    span_s: float


#: Epochs whose regressors ``vector_least_squares`` makes at a time.
FIT_CHUNK = 8192


def vector_least_squares(m, field_body, noise_nt: float, prior_mean=None, prior_std=None, extra=None):
    """Robust least squares of ``m = R B + b + G theta``; returns ``(x (12+k,), cov, weights (N,))``.

    ``m`` and ``field_body`` are (N, 3) nT; ``extra`` (N, 3, k) holds the regressors of added linear
    effects. A Gaussian prior (mean, std over all 12 + k parameters) may be given. Epochs are
    re-weighted with Huber weights on their residual norm.
    """
    from ..effects.core import core_jacobian

    m = np.asarray(m, float)

    def regressors(at: slice) -> np.ndarray:  # (k, 3, p), made a chunk at a time: 288 bytes an epoch and more
        A = core_jacobian(field_body[at])
        return A if extra is None else np.concatenate([A, extra[at]], axis=2)

    p = 12 + (0 if extra is None else extra.shape[2])
    if prior_mean is None:
        prior_mean, prior_std = np.zeros(p), np.full(p, np.inf)
    info_prior = 1.0 / np.asarray(prior_std, float) ** 2
    n = len(m)
    w = np.ones(n)
    chunks = [slice(a, a + FIT_CHUNK) for a in range(0, n, FIT_CHUNK)]
    for _ in range(8):
        info, rhs = np.diag(info_prior), info_prior * prior_mean
        for at in chunks:
            A = regressors(at)
            Aw = A * w[at, None, None]
            info = info + np.einsum("nki,nkj->ij", Aw, A) / noise_nt**2
            rhs = rhs + np.einsum("nki,nk->i", Aw, m[at]) / noise_nt**2
        cov = np.linalg.inv(info)
        x = cov @ rhs
        r = np.empty(n)
        for at in chunks:
            r[at] = np.linalg.norm(m[at] - np.einsum("nki,i->nk", regressors(at), x), axis=1)
        r /= noise_nt * np.sqrt(3)
        w_new = np.minimum(1.0, HUBER_K / np.maximum(r, 1e-12))
        if np.allclose(w_new, w, atol=1e-4):
            break
        w = w_new
    return x, 0.5 * (cov + cov.T), w


def completion_prior(x: np.ndarray) -> np.ndarray:
    """Prior mean (12,): ``R``'s first two columns kept, the third the right-handed completion."""
    R = x[:9].reshape(3, 3)
    c1, c2 = R[:, 0], R[:, 1]
    c3 = np.cross(c1, c2)
    c3 *= np.sqrt(np.linalg.norm(c1) * np.linalg.norm(c2)) / max(np.linalg.norm(c3), 1e-12)
    prior = np.concatenate([np.column_stack([c1, c2, c3]).ravel(), np.zeros(3)])
    return prior


def bootstrap_vector(m, field_body, time, noise_nt: float, span_s: float, extra=None, extra_prior=None) -> Bootstrap:
    """Bootstrap from good epochs with attitude: ``m``, ``field_body`` (N, 3) nT, ``time`` (N,) s.

    Uses the first ``span_s`` seconds; the whole log if that stretch has too few epochs or does not
    turn the sensor through enough headings to fix the first two columns of ``R``. ``extra`` (N, 3, k)
    are the regressors of added linear effects, fitted jointly (so that a direction they share with
    ``R`` or ``b`` is not pinned by a fit that ignored them), with ``extra_prior`` (mean, std) (k,).
    The result's ``x`` and ``P`` cover the core and those effects.
    """
    if len(m) < MIN_EPOCHS:
        raise InputError(f"too few usable epochs ({len(m)}) to bootstrap a calibration; give --init CAL.json")
    stretch = time <= time[0] + span_s
    if stretch.sum() < MIN_EPOCHS or _heading_spread(field_body[stretch]) < 120.0:
        stretch = np.ones(len(m), bool)
    m_s, B_s = m[stretch], field_body[stretch]
    G = None if extra is None else extra[stretch]
    e_mean, e_std = (np.zeros(0), np.zeros(0)) if extra is None else extra_prior
    # First the core alone (with a nearly flat prior that only keeps the solve well posed): its R columns
    # give the prior's right-handed completion. Then the core and the effects together.
    flat = np.concatenate([np.full(9, 1e3), np.full(3, 1e7)])
    x1, _, _ = vector_least_squares(m_s, B_s, noise_nt, np.zeros(12), flat)
    prior = np.concatenate([completion_prior(x1), e_mean])
    std = np.concatenate([np.full(9, PRIOR_R_STD), np.full(3, PRIOR_B_STD), e_std])
    x, cov, _ = vector_least_squares(m_s, B_s, noise_nt, prior, std, G)
    info_prior = np.diag(1.0 / std**2)
    info_data = np.linalg.inv(cov) - info_prior
    P = np.linalg.inv(info_data / INFLATION + info_prior)  # the data's information counted 1/INFLATION
    P = 0.5 * (P + P.T)
    return Bootstrap(x, P, "bootstrap-vector", int(stretch.sum()), float(time[stretch][-1] - time[stretch][0]))


def _heading_spread(field_body: np.ndarray) -> float:
    """Degrees of the circle spanned by the horizontal body-field direction."""
    a = np.sort(np.degrees(np.arctan2(field_body[:, 1], field_body[:, 0])) % 360.0)
    if len(a) < 2:
        return 0.0
    return float(360.0 - np.diff(np.concatenate([a, [a[0] + 360.0]])).max())


def _plausible_fit(m, field: float):
    """``(fit, why)``: the ellipsoid fit (``EllipsoidResult``) of readings ``m`` (k, 3) to a field of ``field`` nT,
    or None and why, in words, when the fit fails, does not converge, or its calibration would be refused
    (``plausibility.check_calibration``): over a small patch of the sphere a fit can wander to a huge ellipsoid
    through it (offsets of 1e9 nT and sensitivities of 1e4, with standard errors that look small against them,
    were seen over 0.5 % of it)."""
    from ..offline.ellipsoid import EllipsoidCalibrator
    from ..plausibility import check_calibration

    try:
        fit = EllipsoidCalibrator(3, field).fit(m, "log").result_
        # the refusal is about the geometry: --mag-unit does not apply to every log (a .bin states its unit)
        check_calibration(fit.R, fit.b / field, "log", lacks="too small a patch of the sphere", unit_option=False)
    except InputError as exc:
        return None, exc.message.replace(" (nothing written)", "")
    if not fit.converged:
        return None, f"it did not converge, over {100 * fit.coverage:.0f} % of the sphere"
    return fit, None


def bootstrap_magnitude(m, reference_magnitude, time, span_s: float) -> Bootstrap:
    """Bootstrap without attitude: an ellipsoid fit to ``m`` (N, 3) with the median reference magnitude."""
    from ..offline.ellipsoid import parameter_names, patent_matrix
    from .measurements import rotation_directions

    stretch = time <= time[0] + span_s
    if stretch.sum() < 200:
        stretch = np.ones(len(m), bool)
    field = float(np.median(reference_magnitude[stretch]))
    fit, why = _plausible_fit(m[stretch], field)
    if fit is None and not stretch.all():  # the whole log, which may turn through more of the sphere
        stretch = np.ones(len(m), bool)
        fit, why = _plausible_fit(m, field)
    if fit is None:
        raise InputError(
            f"the magnitudes do not determine a starting calibration (an ellipsoid fit to them: {why}); turn the "
            "sensor through more orientations, or give --init CAL.json"
        )
    x = np.concatenate([fit.R.ravel(), fit.b])
    names = parameter_names(3)
    p = np.array([fit.parameters[n] for n in names])
    se = np.array([fit.standard_errors[n] for n in names])
    p[3:6], se[3:6] = np.radians(p[3:6]), np.radians(se[3:6])
    # R R^T is what the fit knows (its standard errors, mapped to R's elements); a rotation R -> R Q is
    # what no magnitude can see: give that, and only that, the weak prior.
    J = np.empty((9, 6))
    for j in range(6):
        step = 1e-6 * max(abs(p[j]), 1.0)
        hi, lo = p.copy(), p.copy()
        hi[j] += step
        lo[j] -= step
        J[:, j] = (patent_matrix(hi[:3], hi[3:6]) - patent_matrix(lo[:3], lo[3:6])).ravel() / (2 * step)
    N = rotation_directions(fit.R, 9)
    N /= np.linalg.norm(N, axis=0)
    P = np.zeros((12, 12))
    P[:9, :9] = INFLATION * (J * se[:6] ** 2) @ J.T + PRIOR_R_STD**2 * N @ N.T
    P[9:, 9:] = np.diag(INFLATION * np.maximum(se[6:], 1.0) ** 2)
    return Bootstrap(x, P, "bootstrap-ellipsoid", int(stretch.sum()), float(time[stretch][-1] - time[stretch][0]))
