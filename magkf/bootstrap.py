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

from .errors import InputError

#: Weak prior of the bootstrap: standard deviation of each element of R and of each offset (nT).
PRIOR_R_STD = 0.1
PRIOR_B_STD = 5000.0
#: Variance inflation of the bootstrap covariance (the filter sees the same epochs again).
INFLATION = 100.0
HUBER_K = 3.0
MIN_EPOCHS = 50


@dataclass(frozen=True)
class Bootstrap:
    """``x`` (12,) and covariance ``P`` (12, 12) of the core parameters, and what they came from."""

    x: np.ndarray
    P: np.ndarray
    method: str
    n_epochs: int
    span_s: float


def vector_least_squares(m, field_body, noise_nt: float, prior_mean=None, prior_std=None):
    """Weighted, robust least squares of ``m = R B + b``; returns ``(x (12,), cov (12, 12), weights (N,))``.

    ``m`` and ``field_body`` are (N, 3) nT. A Gaussian prior (12,) mean and std may be given.
    """
    m, B = np.asarray(m, float), np.asarray(field_body, float)
    n = len(m)
    X = np.column_stack([B, np.ones(n)])  # one design for the three rows of [R | b]
    w = np.ones(n)
    if prior_mean is None:
        prior_mean, prior_std = np.zeros(12), np.full(12, np.inf)
    order = np.r_[0:3, 9, 3:6, 10, 6:9, 11]  # state index of [R_i1, R_i2, R_i3, b_i] for i = 1..3
    mu, info_prior = prior_mean[order].reshape(3, 4), (1.0 / np.asarray(prior_std, float)[order] ** 2).reshape(3, 4)
    for _ in range(8):
        A = (X * w[:, None]).T @ X / noise_nt**2
        coef = np.empty((3, 4))
        covs = []
        for i in range(3):
            Ai = A + np.diag(info_prior[i])
            rhs = (X * w[:, None]).T @ m[:, i] / noise_nt**2 + info_prior[i] * mu[i]
            coef[i] = np.linalg.solve(Ai, rhs)
            covs.append(np.linalg.inv(Ai))
        r = np.linalg.norm(m - X @ coef.T, axis=1) / (noise_nt * np.sqrt(3))
        w_new = np.minimum(1.0, HUBER_K / np.maximum(r, 1e-12))
        if np.allclose(w_new, w, atol=1e-4):
            break
        w = w_new
    x = np.empty(12)
    cov = np.zeros((12, 12))
    for i in range(3):
        idx = order[4 * i:4 * i + 4]
        x[idx] = coef[i]
        cov[np.ix_(idx, idx)] = covs[i]
    return x, cov, w


def completion_prior(x: np.ndarray) -> np.ndarray:
    """Prior mean (12,): ``R``'s first two columns kept, the third the right-handed completion."""
    R = x[:9].reshape(3, 3)
    c1, c2 = R[:, 0], R[:, 1]
    c3 = np.cross(c1, c2)
    c3 *= np.sqrt(np.linalg.norm(c1) * np.linalg.norm(c2)) / max(np.linalg.norm(c3), 1e-12)
    prior = np.concatenate([np.column_stack([c1, c2, c3]).ravel(), np.zeros(3)])
    return prior


def bootstrap_vector(m, field_body, time, noise_nt: float, span_s: float) -> Bootstrap:
    """Bootstrap from good epochs with attitude: ``m``, ``field_body`` (N, 3) nT, ``time`` (N,) s.

    Uses the first ``span_s`` seconds; the whole log if that stretch has too few epochs or does not
    turn the sensor through enough headings to fix the first two columns of ``R``.
    """
    if len(m) < MIN_EPOCHS:
        raise InputError(f"too few usable epochs ({len(m)}) to bootstrap a calibration; give --init CAL.json")
    stretch = time <= time[0] + span_s
    if stretch.sum() < MIN_EPOCHS or _heading_spread(field_body[stretch]) < 120.0:
        stretch = np.ones(len(m), bool)
    m_s, B_s = m[stretch], field_body[stretch]
    flat = np.full(12, np.inf)
    flat[:9], flat[9:] = 1e3, 1e7  # nearly flat prior: only keeps the first solve well posed
    x1, _, _ = vector_least_squares(m_s, B_s, noise_nt, np.zeros(12), flat)
    prior = completion_prior(x1)
    std = np.concatenate([np.full(9, PRIOR_R_STD), np.full(3, PRIOR_B_STD)])
    x, cov, _ = vector_least_squares(m_s, B_s, noise_nt, prior, std)
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


def bootstrap_magnitude(m, reference_magnitude, time, span_s: float) -> Bootstrap:
    """Bootstrap without attitude: an ellipsoid fit to ``m`` (N, 3) with the median reference magnitude."""
    from .ellipsoid import EllipsoidCalibrator, parameter_names, patent_matrix
    from .estimator import rotation_directions

    stretch = time <= time[0] + span_s
    if stretch.sum() < 200:
        stretch = np.ones(len(m), bool)
    field = float(np.median(reference_magnitude[stretch]))
    try:
        fit = EllipsoidCalibrator(3, field).fit(m[stretch], "log").result_
    except InputError:
        fit = EllipsoidCalibrator(3, field).fit(m, "log").result_
        stretch = np.ones(len(m), bool)
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
