"""Ellipsoid (3-axis) and ellipse (2-axis) calibration of vector sensors (method 2, CN101887068A).

Model: raw ``S_m = K S_e + S_0`` with ``K = K1 K2``, ``K1 = diag(k)``. For three axes the rows of
``K2`` are the unit sensor axes in an orthogonal frame whose z axis is the sensor's z axis and whose
x axis lies in the plane of the sensor's x and z axes:

    x = (cos alpha, 0, sin alpha),  y = (sin beta cos gamma, cos beta cos gamma, sin gamma),  z = (0, 0, 1)

For two axes ``K2 = [[1, 0], [sin alpha, cos alpha]]``. Wherever ``|S_e|`` equals a known magnitude
``F`` the samples lie on an ellipsoid (ellipse) ``|K^-1 (S_m - S_0)| = F``.

Two steps:

1. **Algebraic fit** of the quadric (conic) by the smallest singular vector of the design matrix, the
   patent's procedure: ``S_0`` is the centre and, writing the surface ``(X - S_0)^T A (X - S_0) = 1``,
   ``K K^T = A^-1 / F^2`` (the restatement's ``F^2 A^-1`` holds only for ``F = 1``).
2. **Refinement** by nonlinear least squares on the magnitude residual
   ``|K^-1 (S_m - S_0)| - F``, with the second-order noise bias that both fits share estimated by a
   seeded parametric bootstrap and removed (see ``_refine``).

Both steps are robust (``robust=True``, the default): disturbed samples (a passing truck, a bridge) are
down-weighted by iteratively reweighted least squares with Huber weights, as the online filter does
(``HUBER_K`` robust standard deviations of the magnitude residual, the scale from
its median absolute value), then, from that robust start, set aside beyond ``GATE_SIGMA`` of them, as the
filter's magnitude gate does; the standard errors are those of the weighted (M-) estimator.

Any unit works: results are in the units of the data; ``F = 1`` normalises to a unit sphere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares

from ..calibration import Calibration
from ..conventions import MAG
from ..errors import InputError
from .base import Calibrator

__all__ = [
    "MIN_THICKNESS",
    "SPHERE_CELLS",
    "CIRCLE_BINS",
    "POORLY_DETERMINED",
    "BOOTSTRAP_COPIES",
    "BOOTSTRAP_SEED",
    "ROBUST_ITERATIONS",
    "WEIGHT_TOLERANCE",
    "GATE_SIGMA",
    "huber_weights",
    "robust_algebraic_fit",
    "patent_matrix",
    "patent_parameters",
    "parameter_names",
    "algebraic_fit",
    "fibonacci_sphere",
    "coverage",
    "EllipsoidResult",
    "EllipsoidCalibrator",
]

#: Huber's threshold, in robust standard deviations, beyond which a sample is down-weighted: the online filter's
#: bootstrap takes it from here (``magkf.online.bootstrap``).
HUBER_K = 3.0
#: Smallest ratio sqrt(lambda_min / lambda_max) of the centred sample scatter for a 3-axis fit.
MIN_THICKNESS = 0.05
#: Cells of the equal-area direction grid used for the coverage figure (3-axis) and bins (2-axis).
SPHERE_CELLS = 200
CIRCLE_BINS = 36
#: A parameter is reported as poorly determined when its standard error exceeds this share of its scale
#: (the mean sensitivity for sensitivities, the field in the data's units for offsets, 1 rad for angles).
POORLY_DETERMINED = 0.05
#: Copies of the data simulated to estimate the second-order noise bias of the refined fit, and their seed.
BOOTSTRAP_COPIES = 8
BOOTSTRAP_SEED = 20240601
#: Reweightings of the robust fit at most (each step), and the largest change of a weight that ends them.
ROBUST_ITERATIONS = 12
WEIGHT_TOLERANCE = 1e-3
#: The refinement sets aside samples whose magnitude residual lies beyond this many robust standard deviations
#: (weight 0), as the online filter's magnitude gate does (``FilterConfig.gate_sigma``).
GATE_SIGMA = 5.0
#: Median absolute value of a standard normal variable: the robust scale is ``median |r| / MAD_NORMAL``.
MAD_NORMAL = 0.6744897501960817
#: ``E[z^2 | |z| <= HUBER_K]`` of a standard normal ``z``: the mean square of the samples kept at full weight
#: is this share of the noise variance.
TRUNCATED_VARIANCE = 1.0 - 2.0 * HUBER_K * np.exp(-0.5 * HUBER_K**2) / np.sqrt(2 * np.pi) / math.erf(HUBER_K / 2**0.5)


# ---------------------------------------------------------------- K parameterisations
def patent_matrix(k, angles_rad) -> np.ndarray:
    """``K = diag(k) K2`` for 3 axes (``k`` of 3, angles alpha, beta, gamma) or 2 axes (``k`` of 2, alpha)."""
    k = np.asarray(k, float)
    if k.size == 3:
        a, be, g = angles_rad
        K2 = np.array(
            [[np.cos(a), 0.0, np.sin(a)], [np.sin(be) * np.cos(g), np.cos(be) * np.cos(g), np.sin(g)], [0.0, 0.0, 1.0]]
        )
    else:
        (a,) = np.atleast_1d(angles_rad)[:1]
        K2 = np.array([[1.0, 0.0], [np.sin(a), np.cos(a)]])
    return k[:, None] * K2


def patent_parameters(S) -> tuple[np.ndarray, np.ndarray]:
    """Sensitivities and angles (radians) of ``K`` from ``S = K K^T`` (2x2 or 3x3, positive definite)."""
    S = np.asarray(S, float)
    k = np.sqrt(np.diag(S))
    C = S / np.outer(k, k)
    if len(k) == 2:
        return k, np.array([np.arcsin(np.clip(C[0, 1], -1, 1))])
    sa, sg = C[0, 2], C[1, 2]
    a, g = np.arcsin(np.clip(sa, -1, 1)), np.arcsin(np.clip(sg, -1, 1))
    sb = (C[0, 1] - sa * sg) / (np.cos(a) * np.cos(g))
    return k, np.array([a, np.arcsin(np.clip(sb, -1, 1)), g])


def parameter_names(axes: int) -> tuple[str, ...]:
    if axes == 3:
        return ("kx", "ky", "kz", "alpha_deg", "beta_deg", "gamma_deg", "S0_x", "S0_y", "S0_z")
    return ("kx", "ky", "alpha_deg", "S0_x", "S0_y")


# ---------------------------------------------------------------- algebraic fit
def algebraic_fit(X: np.ndarray, field: float, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """Quadric (conic) least-squares fit; returns ``(K K^T, S_0)`` for samples ``X`` of shape (N, d).

    The data are centred and scaled before the fit for conditioning. ``weights`` (N,), between 0 and 1,
    weigh each sample's squared algebraic residual (None: all 1). Raises InputError when the fitted
    surface is not an ellipsoid (ellipse).
    """
    d = X.shape[1]
    w = np.ones(len(X)) if weights is None else np.asarray(weights, float)
    mean = w @ X / w.sum()
    scale = np.sqrt(w @ np.sum((X - mean) ** 2, axis=1) / w.sum())
    Y = (X - mean) / scale
    iu = np.triu_indices(d)
    quad = Y[:, iu[0]] * Y[:, iu[1]] * np.where(iu[0] == iu[1], 1.0, 2.0)
    D = np.column_stack([quad, 2 * Y, np.ones(len(Y))]) * np.sqrt(w)[:, None]
    v = np.linalg.svd(D, full_matrices=False)[2][-1]
    A = np.zeros((d, d))
    A[iu] = v[: len(iu[0])]
    A = A + np.triu(A, 1).T
    p, g = v[len(iu[0]) : len(iu[0]) + d], v[-1]
    try:
        centre = -np.linalg.solve(A, p)
    except np.linalg.LinAlgError:
        raise InputError("the samples do not lie on an ellipsoid: the algebraic fit found another quadric") from None
    k = centre @ A @ centre - g
    M = A / k
    w = np.linalg.eigvalsh(M)
    if w.min() <= 0:
        raise InputError("the samples do not lie on an ellipsoid: the algebraic fit found another quadric")
    S = np.linalg.inv(M) * scale**2 / field**2  # (X - S0)^T A (X - S0) = 1 with |K^-1 (X - S0)| = F
    return S, centre * scale + mean


def huber_weights(residuals: np.ndarray, gate: float | None = None) -> tuple[np.ndarray, float]:
    """Huber weights of residuals and their robust scale.

    Parameters
    ----------
    residuals : numpy.ndarray
        (N,) residuals of a fit, each of the same noise standard deviation (any unit).
    gate : float or None, optional
        Residuals beyond this many robust standard deviations get weight 0 (None: no gate).

    Returns
    -------
    weights : numpy.ndarray
        (N,): 1 up to ``HUBER_K`` robust standard deviations, ``HUBER_K * scale / |r|`` beyond, 0 beyond
        ``gate``.
    scale : float
        The robust standard deviation ``median |r| / MAD_NORMAL`` in the residuals' unit; 0 (and all weights 1)
        when most residuals are exactly 0, which leaves no noise to judge by.
    """
    r = np.abs(np.asarray(residuals, float))
    scale = float(np.median(r)) / MAD_NORMAL
    if not (np.isfinite(scale) and scale > 0):
        return np.ones(len(r)), 0.0
    weights = np.minimum(1.0, HUBER_K * scale / np.maximum(r, 1e-300))
    if gate is not None:
        weights[r > gate * scale] = 0.0
    return weights, scale


def _normalised_residuals(X, x, F, d) -> np.ndarray:
    """Magnitude residuals (N,) of the parameters ``x`` over the standard deviation each has per unit raw noise:
    residuals of one noise level, in the data's units."""
    return (_magnitudes(X, x, d) - F) / np.sqrt(_radial_variance(X, x, d))


def _parameters(S, centre) -> np.ndarray:
    """The parameter vector (sensitivities, angles in radians, offsets) of ``K K^T`` and ``S_0``."""
    k, ang = patent_parameters(S)
    return np.concatenate([k, ang, centre])


def robust_algebraic_fit(X: np.ndarray, field: float, robust: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The algebraic fit (``algebraic_fit``) with disturbed samples down-weighted.

    Iteratively reweighted: Huber weights of the magnitude residuals (``huber_weights``) until no weight changes
    by ``WEIGHT_TOLERANCE``, then, from that robust start, the same with the samples beyond ``GATE_SIGMA``
    robust standard deviations set aside (a gate is not convex: it needs a start the disturbances do not pull).

    Parameters
    ----------
    X : numpy.ndarray
        Samples (N, d), data units.
    field : float
        The true magnitude, data units.
    robust : bool, optional
        False: the plain fit, every weight 1.

    Returns
    -------
    x : numpy.ndarray
        Parameters (sensitivities, angles in radians, offsets), as ``parameter_names`` orders them.
    weights : numpy.ndarray
        (N,) Huber weights of the samples' magnitude residuals at ``x`` (``huber_weights``), 1 for an
        undisturbed sample; all 1 without ``robust``.

    Raises
    ------
    InputError
        A fitted surface that is not an ellipsoid (ellipse).
    """
    d = X.shape[1]
    weights = np.ones(len(X))
    x = _parameters(*algebraic_fit(X, field))
    if not robust:
        return x, weights
    for gate in (None, GATE_SIGMA):
        for _ in range(ROBUST_ITERATIONS):
            new, _ = huber_weights(_normalised_residuals(X, x, field, d), gate)
            if np.max(np.abs(new - weights)) < WEIGHT_TOLERANCE:
                break
            weights = new
            x = _parameters(*algebraic_fit(X, field, weights))
    return x, weights


# ---------------------------------------------------------------- coverage
def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly equal-area cell centres on the unit sphere, shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z**2)
    t = np.pi * (1 + 5**0.5) * i
    return np.column_stack([r * np.cos(t), r * np.sin(t), z])


def coverage(directions: np.ndarray) -> float:
    """Share (0 to 1) of the sphere (3-D) or circle (2-D) that the unit ``directions`` (N, d) visit."""
    if directions.shape[1] == 3:
        cells = fibonacci_sphere(SPHERE_CELLS)
        hit = np.zeros(SPHERE_CELLS, bool)
        for chunk in np.array_split(directions, max(1, len(directions) // 20000 + 1)):
            hit[np.argmax(chunk @ cells.T, axis=1)] = True
        return float(hit.mean())
    angle = np.arctan2(directions[:, 1], directions[:, 0])
    bins = np.floor((angle + np.pi) / (2 * np.pi) * CIRCLE_BINS).astype(int) % CIRCLE_BINS
    return float(np.unique(bins).size / CIRCLE_BINS)


# ---------------------------------------------------------------- result
@dataclass(frozen=True)
class EllipsoidResult:
    """Outcome of an ellipsoid (``axes=3``) or ellipse (``axes=2``) fit.

    ``R`` (d, d) and ``b`` (d,) are in ``S_m = R S_e + b`` (data units); ``parameters`` and
    ``standard_errors`` use the patent's names (``kx, ..., alpha_deg, ..., S0_x, ...``);
    ``algebraic`` holds the unrefined parameters; ``residual_rms`` is the RMS of
    ``|R^-1 (S_m - b)| - field`` (data units after calibration); ``magnitude_spread_before`` and
    ``_after`` are the standard deviations of the magnitude divided by its mean, raw and calibrated;
    ``coverage`` the visited share of the sphere or circle; ``poorly_determined`` lists parameters
    whose standard error is large (all of them when the refinement did not converge: ``converged`` False);
    ``downweighted_share`` is the share (0 to 1) of the samples the robust fit down-weighted as disturbed
    (0 for a fit that is not robust).
    """

    axes: int
    field: float
    R: np.ndarray
    b: np.ndarray
    parameters: dict
    standard_errors: dict
    algebraic: dict
    residual_rms: float
    magnitude_spread_before: float
    magnitude_spread_after: float
    coverage: float
    n_samples: int
    poorly_determined: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    converged: bool = True
    downweighted_share: float = 0.0

    def scaled_to(self, magnitude: float) -> EllipsoidResult:
        """The same fit expressed for a field of ``magnitude`` (data units) instead of ``field``.

        ``|K^-1 (S_m - S_0)| = F`` is ``|(K F / F')^-1 (S_m - S_0)| = F'``: the sensitivities (and ``R``) and
        their standard errors scale by ``F / F'``, the residual by ``F' / F``; offsets, angles and the
        relative figures stay.

        Parameters
        ----------
        magnitude : float
            The new field magnitude ``F'``, data units, positive.

        Returns
        -------
        EllipsoidResult
            The rescaled result.
        """
        ratio = self.field / float(magnitude)

        def scaled(values: dict) -> dict:
            return {n: v * ratio if n in ("kx", "ky", "kz") else v for n, v in values.items()}

        return replace(
            self,
            field=float(magnitude),
            R=self.R * ratio,
            parameters=scaled(self.parameters),
            standard_errors=scaled(self.standard_errors),
            algebraic=scaled(self.algebraic),
            residual_rms=self.residual_rms / ratio,
            warnings=list(self.warnings),
            poorly_determined=list(self.poorly_determined),
        )

    @property
    def unit_determinant_field(self) -> float:
        """The field magnitude (data units) at which ``R`` has determinant 1: the sensor's own mean sensitivity
        (the geometric mean of ``R``'s singular values) taken as 1."""
        return self.field * abs(float(np.linalg.det(self.R))) ** (1.0 / self.axes)

    def to_calibration(self, source: str | None = None, field_unit: str = "nT") -> Calibration:
        """A 3x3 calibration; for two axes the z row and offset are identity and zero (not calibrated).

        Parameters
        ----------
        source : str or None, optional
            The data the calibration was computed from.
        field_unit : str, optional
            What the field of ``b`` and of the corrected field is measured in (``Calibration.field_unit``):
            ``"nT"``, ``"unit-sphere"`` or ``"counts"``.

        Returns
        -------
        Calibration
            Method ``ellipsoid`` or ``ellipse``, with the parameters, standard errors and fit statistics.
        """
        R, b = np.eye(3), np.zeros(3)
        R[: self.axes, : self.axes], b[: self.axes] = self.R, self.b
        quality = {k: v for k, v in self.summary().items() if k not in ("R", "b", "parameters", "standard_errors")}
        return Calibration(
            R=R,
            b=b,
            method="ellipsoid" if self.axes == 3 else "ellipse",
            parameters=self.parameters,
            standard_errors=self.standard_errors,
            quality=quality,
            source=source,
            field_unit=field_unit,
        )

    def summary(self) -> dict:
        return {
            "axes": self.axes,
            "field": self.field,
            "R": self.R.tolist(),
            "b": self.b.tolist(),
            "parameters": self.parameters,
            "standard_errors": self.standard_errors,
            "algebraic": self.algebraic,
            "residual_rms": self.residual_rms,
            "magnitude_spread_before": self.magnitude_spread_before,
            "magnitude_spread_after": self.magnitude_spread_after,
            "coverage": self.coverage,
            "n_samples": self.n_samples,
            "downweighted_share": self.downweighted_share,
            "poorly_determined": self.poorly_determined,
            "warnings": self.warnings,
        }


# ---------------------------------------------------------------- calibrator
class EllipsoidCalibrator(Calibrator):
    """Ellipsoid (``axes=3``) or ellipse (``axes=2``) calibration of a vector sensor.

    ``fit(X)`` takes samples (N, axes), an array or a DataFrame (its ``mag_x, mag_y [, mag_z]`` columns when
    present, else its first ``axes`` columns), and returns ``self``; the result is ``result_`` (and ``R_``,
    ``b_``, ``calibration_``). The scikit-learn contract of ``magkf.offline.base``: the settings are stored as
    given and checked by ``fit``.

    Parameters
    ----------
    axes : int, optional
        3 for an ellipsoid, 2 for an ellipse.
    field : float, optional
        The true magnitude in data units (1.0 for a unit sphere, 9.80665 for an accelerometer in m/s^2, an
        IGRF magnitude in nT for a magnetometer).
    refine : bool, optional
        False stops after the algebraic fit.
    robust : bool, optional
        True (default): samples whose magnitude residual lies beyond ``HUBER_K`` robust standard deviations are
        down-weighted (Huber weights, iterated), in the algebraic fit and in its refinement; False: plain
        least squares.

    Attributes
    ----------
    result_ : EllipsoidResult
        The fit: ``R``, ``b``, the patent's parameters, their standard errors, residual, coverage, warnings.
    R_ : numpy.ndarray
        Fitted ``R`` of ``m = R B + b``: (3, 3), or (2, 2) for an ellipse.
    b_ : numpy.ndarray
        Fitted ``b`` in the data's units: (3,), or (2,) for an ellipse.
    calibration_ : Calibration
        The fitted calibration (3x3; for two axes the z row and offset are identity and zero).

    Examples
    --------
    >>> fit = EllipsoidCalibrator(axes=3, field=1.0).fit(samples)  # doctest: +SKIP
    >>> fit.R_, fit.b_, fit.get_params()  # doctest: +SKIP
    """

    def __init__(self, axes: int = 3, field: float = 1.0, refine: bool = True, robust: bool = True):
        self.axes, self.field, self.refine, self.robust = axes, field, refine, robust

    def fit(self, X, source: str = "data") -> EllipsoidCalibrator:
        """Fit an ellipsoid (ellipse) to samples turned through all directions.

        An algebraic (quadric) least-squares fit, decomposed into the patent's ``K = K1 K2`` (sensitivities
        ``k``, non-orthogonality angles, offsets ``S_0``), then, with ``refine``, a weighted nonlinear least
        squares on the magnitude residual ``|K^-1 (S_m - S_0)| - field`` with its noise bias removed, which
        gives the standard errors; with ``robust`` both steps down-weight disturbed samples (Huber weights,
        reported as ``result_.downweighted_share``). Warnings (in ``result_.warnings``) say when the refinement did not
        converge, which parameters are poorly determined, and when the calibrated directions cover less than
        30 % of the sphere (circle).

        Parameters
        ----------
        X : array_like or pandas.DataFrame
            Samples (N, axes) in data units; a DataFrame's ``mag_x, mag_y [, mag_z]`` columns when present,
            else its first ``axes`` columns. At least ``4 * (parameters + 1)`` samples: 40 for an ellipsoid,
            24 for an ellipse.
        source : str, optional
            What the samples were read from, named in errors.

        Returns
        -------
        EllipsoidCalibrator
            ``self``, fitted: ``result_``, ``R_``, ``b_``, ``calibration_``.

        Raises
        ------
        ValueError
            ``axes`` not 2 or 3, ``field`` not positive, or samples not of shape (N, axes).
        InputError
            Too few samples, samples that cannot determine the fit (close to a plane for 3 axes, to a line
            for 2), or a fitted surface that is not an ellipsoid (ellipse).
        """
        if self.axes not in (2, 3):
            raise ValueError("axes must be 2 or 3")
        if not float(self.field) > 0:
            raise ValueError("the field magnitude must be positive")
        X = _samples(X, self.axes)
        d, F = self.axes, float(self.field)
        if X.ndim != 2 or X.shape[1] != d:
            raise ValueError(f"expected samples of shape (N, {d}), got {X.shape}")
        n_min = 4 * (len(parameter_names(d)) + 1)
        if len(X) < n_min:
            raise InputError(
                f"too few samples: {len(X)}, an {'ellipsoid' if d == 3 else 'ellipse'} fit needs at least {n_min}",
                source,
            )
        self._check_geometry(X, source)
        try:
            x_alg, weights = robust_algebraic_fit(X, F, bool(self.robust))
        except InputError as exc:  # the fit's own refusal names no file
            raise InputError(
                f"{exc.message}: the readings do not turn through enough orientations (a level, straight run "
                "turns through none); turn the sensor through many",
                source,
            ) from None
        names = parameter_names(d)
        algebraic = dict(zip(names, _readable(x_alg, d)))
        warnings = []
        converged = True
        if self.refine:
            x, se, converged, weights = _refine(X, x_alg, F, d, weights, bool(self.robust))
            if not converged:
                warnings.append(
                    f"the refinement did not converge in {MAX_ITERATIONS} evaluations: the samples do not determine "
                    "the ellipsoid"
                )
        else:
            x, se = x_alg, np.full(x_alg.size, np.nan)
        K, b = patent_matrix(x[:d], x[d:-d]), x[-d:]
        calibrated = np.linalg.solve(K, (X - b).T).T
        mags = np.linalg.norm(calibrated, axis=1)
        raw = np.linalg.norm(X, axis=1)
        cov = coverage(calibrated / mags[:, None])
        poorly = [
            n for n, s, sc in zip(names, se, _scales(d, F, x)) if not np.isfinite(s) or s > POORLY_DETERMINED * sc
        ]
        if self.refine and poorly:
            warnings.append("poorly determined: " + ", ".join(poorly) + "; add samples with other orientations")
        if cov < 0.3:
            warnings.append(f"the data cover only {100 * cov:.0f}% of the {'sphere' if d == 3 else 'circle'}")
        self._result = EllipsoidResult(
            axes=d,
            field=F,
            R=K,
            b=b,
            parameters=dict(zip(names, _readable(x, d))),
            standard_errors=dict(zip(names, _readable(se, d, offsets=False))),
            algebraic=algebraic,
            residual_rms=float(np.sqrt(np.mean((mags - F) ** 2))),
            magnitude_spread_before=float(raw.std() / raw.mean()),
            magnitude_spread_after=float(mags.std() / mags.mean()),
            coverage=cov,
            n_samples=len(X),
            poorly_determined=poorly,
            warnings=warnings,
            converged=converged,
            downweighted_share=float(np.mean(weights < 1.0)),
        )
        return self

    def _check_geometry(self, X: np.ndarray, source: str) -> None:
        """Refuse samples that cannot determine the fit (all in a plane for 3 axes, on a line for 2)."""
        w, v = np.linalg.eigh(np.cov(X.T))
        thickness = np.sqrt(max(w[0], 0) / w[-1]) if w[-1] > 0 else 0.0
        if thickness < MIN_THICKNESS:
            normal = ", ".join(f"{c:+.2f}" for c in v[:, 0])
            if self.axes == 3:
                raise InputError(
                    f"degenerate geometry: the samples lie close to a plane (normal ({normal}) in sensor axes, "
                    f"thickness {thickness:.3f}); a 3-axis fit cannot determine the sensitivity, offset and "
                    "tilt along that normal: use --axes 2 for planar data or add samples with that axis turned",
                    source,
                )
            raise InputError(
                f"degenerate geometry: the samples lie close to a line (thickness {thickness:.3f}); "
                "turn the sensor through a wider arc",
                source,
            )


def _magnitudes(X, x, d) -> np.ndarray:
    K, b = patent_matrix(x[:d], x[d:-d]), x[-d:]
    return np.linalg.norm(np.linalg.solve(K, (X - b).T), axis=0)


#: Evaluations of the magnitude residual (those of its finite-difference Jacobian not counted, as scipy counts
#: them from 1.16 on) before the refinement's Levenberg-Marquardt solve stops unconverged: a well-posed fit
#: takes under ten; samples that do not determine the ellipsoid (a patch of the sphere) wander for tens of
#: thousands (16 s on 6 000 samples), towards an ellipsoid of any size through the patch.
MAX_ITERATIONS = 200


def _least_squares(X, x0, F, d, weight=None):
    """The Levenberg-Marquardt solve of the magnitude residual from ``x0``; ``status`` 0 when it stopped at
    ``MAX_ITERATIONS``."""
    scale = np.concatenate([np.abs(x0[:d]), np.full(len(x0) - 2 * d, 1e-2), np.full(d, F)])
    w = 1.0 if weight is None else weight
    return least_squares(
        lambda p: (_magnitudes(X, p, d) - F) * w, x0, method="lm", x_scale=scale, max_nfev=MAX_ITERATIONS
    )


def _radial_variance(X, x, d) -> np.ndarray:
    """Variance (N,) of each sample's calibrated magnitude per unit isotropic raw noise variance."""
    L = np.linalg.inv(patent_matrix(x[:d], x[d:-d]))
    u = (X - x[-d:]) @ L.T
    u /= np.linalg.norm(u, axis=1)[:, None]
    return np.einsum("ni,ij,nj->n", u, L @ L.T, u)


def _samples(X, axes: int) -> np.ndarray:
    """Samples (N, axes) of an array or a DataFrame (``mag_x, mag_y[, mag_z]`` if present, else its first columns)."""
    if hasattr(X, "columns"):
        names = [c for c in MAG[:axes] if c in X.columns]
        X = X[names] if len(names) == axes else X.iloc[:, :axes]
    X = np.asarray(X, float)
    if X.ndim != 2 or X.shape[1] != axes:
        raise ValueError(f"expected samples of shape (N, {axes}), got {X.shape}")
    return X


def _refine(X, x0, F, d, weights, robust: bool = True):
    """Weighted nonlinear least squares on the magnitude residual, with its noise bias removed.

    Isotropic raw noise gives each sample's calibrated magnitude a variance proportional to
    ``u^T L L^T u`` (``L = K^-1``, ``u`` its direction); residuals are weighted by its inverse square
    root, so the standard errors from the Jacobian hold. With ``robust``, each sample's weight is also
    its Huber weight (``huber_weights``), iterated from the algebraic fit's ``weights`` (N,) until no weight
    changes by ``WEIGHT_TOLERANCE``; the standard errors are then the M-estimator's sandwich (``_covariance``).
    Least squares on ``|K^-1 (S_m - S_0)| - F`` is
    biased at second order in the noise (the noise across the radius lengthens every sample, and the
    residual's gradient grows with the noise). The bias is estimated by a parametric bootstrap and
    subtracted: the fitted surface is sampled at the observed directions, ``BOOTSTRAP_COPIES`` times,
    with raw noise of the estimated variance (fixed seed, so a fit is repeatable), refitted, and the
    shift of the estimate is the bias. The standard errors include the bootstrap's own scatter.

    Returns ``(x, standard errors, converged, weights (N,))``.
    """
    first = _least_squares(X, x0, F, d, np.sqrt(weights))
    x = first.x
    if first.status == 0:  # no minimum in reach: nothing is determined
        return x, np.full(len(x), np.nan), False, weights
    radial = _radial_variance(X, x, d)
    if not robust:
        weights = np.ones(len(X))
    for iteration in range(ROBUST_ITERATIONS + 1):  # the last one fits the last reweighting
        fit = _least_squares(X, x, F, d, np.sqrt(weights / radial))
        x = fit.x
        if fit.status == 0:
            return x, np.full(len(x), np.nan), False, weights
        if not robust or iteration == ROBUST_ITERATIONS:
            break
        new, _ = huber_weights((_magnitudes(X, x, d) - F) / np.sqrt(radial), GATE_SIGMA)
        if np.max(np.abs(new - weights)) < WEIGHT_TOLERANCE:
            break
        weights = new
    K, b = patent_matrix(x[:d], x[d:-d]), x[-d:]
    u = np.linalg.solve(K, (X - b).T).T
    u /= np.linalg.norm(u, axis=1)[:, None]
    s2 = _noise_variance(fit.fun, weights)
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    clean = np.tile(F * u @ K.T + b, (BOOTSTRAP_COPIES, 1))
    copies = clean + rng.normal(scale=np.sqrt(s2), size=clean.shape)
    shift = _least_squares(copies, x, F, d, np.tile(1 / np.sqrt(radial), BOOTSTRAP_COPIES)).x - x
    try:
        se = np.sqrt(np.clip(np.diag(_covariance(fit, weights, robust)), 0, None) * (1 + 1 / BOOTSTRAP_COPIES))
    except np.linalg.LinAlgError:
        se = np.full(len(x), np.nan)
    return x - shift, se, True, weights


def _noise_variance(residuals, weights) -> float:
    """The raw noise variance (data units squared) from the weighted residuals (N,) ``sqrt(w / radial) r`` of a
    fit: the mean square of the samples at full weight (all of them when none is down-weighted), divided by
    ``TRUNCATED_VARIANCE`` when some are, since a normal sample beyond ``HUBER_K`` standard deviations is
    down-weighted too."""
    kept = weights >= 1.0
    if kept.all():
        return float(np.mean(residuals**2))
    return float(np.mean(residuals[kept] ** 2)) / TRUNCATED_VARIANCE


def _covariance(fit, weights, robust: bool) -> np.ndarray:
    """The parameters' covariance (p, p) of the refined fit (a ``least_squares`` result, its residuals and
    Jacobian weighted by ``sqrt(weights / radial)``).

    Plain least squares: ``(J^T J)^-1`` times the residuals' mean square over ``N - p``. Robust: Huber's
    M-estimator sandwich ``A^-1 B A^-1 N / (N - p)``, ``A = sum psi'(r_i) J_i J_i^T`` over the samples at full
    weight (where ``psi' = 1``; 0 beyond the threshold), ``B = sum psi(r_i)^2 J_i J_i^T`` over all samples with
    ``psi(r) = w r``; with the residuals and Jacobian rows weighted by ``sqrt(w)`` this is ``B = sum f_i^2
    j_i j_i^T``. For a fit that down-weighted none, both give the same in expectation.
    """
    J, f = fit.jac, fit.fun
    n, p = J.shape
    dof = max(n - p, 1)
    if not robust:
        return np.linalg.inv(J.T @ J) * (2 * fit.cost / dof)
    kept = J[weights >= 1.0]
    A_inv = np.linalg.inv(kept.T @ kept)
    B = (J * f[:, None] ** 2).T @ J
    return A_inv @ B @ A_inv * (n / dof)


def _scales(d, F, x):
    """The scale each parameter's standard error is judged against (see ``POORLY_DETERMINED``)."""
    s = float(np.mean(np.abs(x[:d])))
    return [s] * d + [1.0] * (1 if d == 2 else 3) + [F * s] * d


def _readable(x, d, offsets=True) -> list:
    """Parameter vector with angles turned into degrees."""
    x = np.asarray(x, float).copy()
    n_ang = 1 if d == 2 else 3
    x[d : d + n_ang] = np.degrees(x[d : d + n_ang])
    return [float(v) for v in x]
