"""A model fitted to a set of epochs at its own best fit: the diagnosis's and the validation's workhorse.

``EpochSet`` holds the raw readings and effect data of the epochs; ``EpochSet.at(layout, x)`` whitens the
vector measurement and linearises the model at state ``x`` (a Gauss-Newton step for nonlinear effects) and
``EpochSet.fit`` iterates that to the whole-set least-squares estimate, so that the whitening and the
effects' linearisation (``EpochData.R0``) follow the estimate instead of a starting value that a missing
effect has pulled off.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..online.measurements import measurement_model
from ..online.state import StateLayout

__all__ = [
    "REFIT_ITERATIONS",
    "REFIT_TOLERANCE",
    "OUTLIER_SIGMA",
    "Linearised",
    "EpochSet",
    "inliers",
    "span_basis",
    "finite_regressors",
]

#: Iterations of the refit (whitening and linearisation at the estimate), and its tolerance on the change
#: of the state relative to the prior standard deviations.
REFIT_ITERATIONS = 4
REFIT_TOLERANCE = 1e-3
#: Whitened residual, in units of its robust (MAD) scale per component, beyond which an epoch is an outlier.
OUTLIER_SIGMA = 5.0


def span_basis(A: np.ndarray) -> np.ndarray:
    """An orthonormal basis (rows, rank) of the span of ``A`` (rows, p), directions below ``1e-9`` of the
    largest singular value left out."""
    u, sv, _ = np.linalg.svd(A, full_matrices=False)
    return u[:, : _rank(sv)]


def _rank(sv: np.ndarray) -> int:
    """Numerical rank from singular values in descending order."""
    return int(np.sum(sv > 1e-9 * sv[0])) if sv.size and sv[0] > 0 else 0


def finite_regressors(effect, data) -> np.ndarray:
    """``effect.regressors(data)`` (n, 3, q) with epochs where any is not finite set to zero (they add
    nothing to a fit)."""
    G = effect.regressors(data)
    return np.where(np.all(np.isfinite(G), axis=(1, 2))[:, None, None], G, 0.0)


def inliers(residual: np.ndarray) -> np.ndarray:
    """Mask (n,) of the epochs whose whitened residual (n, 3) lies within ``OUTLIER_SIGMA`` robust scales
    (1.4826 times the median absolute deviation, per component) of its median."""
    centred = residual - np.median(residual, axis=0)
    scale = np.maximum(1.4826 * np.median(np.abs(centred), axis=0), 1e-12)
    return np.all(np.abs(centred) <= OUTLIER_SIGMA * scale, axis=1)


@dataclass(frozen=True)
class Linearised:
    """A model linearised and whitened at state ``x`` on the diagnosed epochs: ``data`` with ``R0`` of ``x``;
    ``W`` (n, 3, 3) the whitening; ``A`` (3n, p) the whitened Jacobian and ``basis`` an orthonormal basis of
    its span; ``y`` (3n,) the whitened reading and ``r`` (3n,) what the span leaves of it; ``x_fit`` the
    least-squares estimate (kept at ``x`` in directions the data do not determine)."""

    layout: StateLayout
    x: np.ndarray
    data: object
    W: np.ndarray
    A: np.ndarray
    basis: np.ndarray
    y: np.ndarray
    r: np.ndarray
    x_fit: np.ndarray


class EpochSet:
    """Epochs and how a model is fitted to them: the raw readings ``m`` (n, 3) nT, the effect data
    (``EpochData``), the heading axes (n, 3) and the measurement settings whose whitening weighs the
    residuals."""

    def __init__(self, data, m, heading, config, noise=None):
        self.data, self.m, self.heading = data, m, heading
        self.config, self.noise = config, noise

    @classmethod
    def of(cls, prep, used, config, noise=None) -> EpochSet:
        """The epochs ``used`` (mask) of a ``PreparedLog``, weighed with ``noise`` (a ``NoiseLevels``; None:
        the configured noise)."""
        return cls(prep.data.take(used), prep.m[used], prep.heading[used], config, noise)

    def take(self, keep) -> EpochSet:
        """The epochs ``keep`` (mask or index) of this set."""
        return EpochSet(self.data.take(keep), self.m[keep], self.heading[keep], self.config, self.noise)

    def less(self, terms) -> EpochSet:
        """The same epochs with ``terms`` (n, 3) nT taken off the readings (effects held fixed)."""
        return EpochSet(self.data, self.m - terms, self.heading, self.config, self.noise)

    def __len__(self):
        return len(self.m)

    def at(self, layout: StateLayout, x) -> Linearised:
        """The model ``layout`` linearised and whitened at ``x``, and its least-squares fit."""
        x = np.asarray(x, float)
        R = layout.R(x)
        data = replace(self.data, R0=R)
        H = layout.linear_jacobian(data)
        offset = np.zeros_like(self.m)  # nonlinear effects, linearised at x (a Gauss-Newton step)
        for effect, sl in layout.nonlinear:
            H[:, :, sl] = effect.jacobian(x[sl], data)
            offset += effect.contribution(x[sl], data) - H[:, :, sl] @ x[sl]
        model = measurement_model(self.config, layout, x)
        if self.noise is not None:
            model.set_noise(self.noise)
        W = model.whitening(data.field_body, R, self.heading)
        n, p = len(self.m), layout.size
        A = (W @ H).reshape(3 * n, p)
        y = np.einsum("nij,nj->ni", W, self.m - offset).ravel()
        u, sv, vt = np.linalg.svd(A, full_matrices=False)
        rank = _rank(sv)
        basis = u[:, :rank]
        r = y - basis @ (basis.T @ y)
        # the least-squares step from x in the determined directions only
        step = vt[:rank].T @ ((basis.T @ (y - A @ x)) / sv[:rank])
        return Linearised(layout, x, data, W, A, basis, y, r, x + step)

    def fit(self, layout: StateLayout, x) -> Linearised:
        """``at`` iterated until the estimate stops moving: the model at its own best fit."""
        prior_std = np.sqrt(np.diag(layout.prior()[1]))
        f = self.at(layout, x)
        for _ in range(REFIT_ITERATIONS):
            change = np.max(np.abs(f.x_fit - f.x) / prior_std)
            if change < REFIT_TOLERANCE or not np.all(np.isfinite(f.x_fit)):
                break
            f = self.at(layout, f.x_fit)
        return f
