"""Sine-fit calibration of a three-axis magnetometer on a turntable (method 1).

Model (the paper's eq. 1): raw ``m = K B_o + b0`` with the lower-triangular

    K = [[kx,                 0,                  0       ],
         [ky sin a,           ky cos a,           0       ],
         [kz cos b sin g,     kz sin b sin g,     kz cos g]]

Turntable geometry (see ``docs/data-contract.md``): in plane ``xy`` the sensor is level (roll 0, Z down);
in plane ``xz`` it is rolled +90 deg about X (Y down). ``angle_deg`` turns the table clockwise seen from
above. With horizontal field ``H = B cos I`` and vertical ``V = B sin I`` the field in the sensor's
orthogonal frame at table angle ``psi`` is ``(H cos psi, -H sin psi, V)`` in plane ``xy`` and
``(H cos psi, V, H sin psi)`` in plane ``xz`` (``(H cos psi, -V, -H sin psi)`` if the sensor was rolled
-90 deg instead; the exact method detects which).

Two solvers:

``method="paper"``
    The published closed-form equations (5)-(16): phases, amplitudes and offsets of the fitted curves,
    ``kx`` from one sample (eq. 15-16). Eq. (7) prints ``kyx = A_x / A_y``, but ``kyx = ky/kx`` and the
    paper's own value 1.2607 is ``A_y / A_x``; magkf uses the latter. Eq. (11) ``Bz0 = D'_z`` ignores the
    vertical field that leaks into Zm through ``kz sin b sin g`` in plane ``xz``; kept as published.
``method="exact"``
    Starts from the closed form with the leak removed, then solves the nine parameters (plus the
    unknown table heading of each plane) by nonlinear least squares over every sample of both planes,
    and reports standard errors from the Jacobian. Noiseless consistent data give the parameters back
    to rounding error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from ..calibration import Calibration
from ..conventions import ANGLE, MAG, PLANE, wrap_deg
from ..errors import InputError
from ..io.tables import require_rows
from .base import Calibrator

__all__ = [
    "PLANES",
    "PARAMETER_NAMES",
    "MIN_SAMPLES_PER_PLANE",
    "MIN_ARC_DEG",
    "arc_span_deg",
    "SineFitParameters",
    "SineCurve",
    "fit_sine",
    "turntable_field",
    "SineFitResult",
    "paper_equations",
    "paper_from_curves",
    "SineFitCalibrator",
    "model_residuals",
    "exact_jacobian",
    "read_turntable",
    "read_curves",
]

PLANES = ("xy", "xz")
PARAMETER_NAMES = ("alpha_deg", "beta_deg", "gamma_deg", "kx", "ky", "kz", "b_x", "b_y", "b_z")
MIN_SAMPLES_PER_PLANE = 8
#: Smallest arc of table angle per plane that determines phase, amplitude and offset apart.
MIN_ARC_DEG = 180.0


def arc_span_deg(angle_deg) -> float:
    """Degrees of the circle spanned by the angles: 360 minus the largest gap between neighbours."""
    a = np.sort(np.asarray(angle_deg, float) % 360.0)
    if a.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate([a, [a[0] + 360.0]]))
    return float(360.0 - gaps.max())


# ---------------------------------------------------------------- the nine parameters
@dataclass(frozen=True)
class SineFitParameters:
    """The paper's nine calibration parameters: angles in degrees, sensitivities, offsets ``b`` in nT.

    They make the lower-triangular ``K`` of eq. (1) (``matrix``), which is ``R`` in ``m = R B + b``::

        K = [[kx,                          0,                           0          ],
             [ky sin(alpha),               ky cos(alpha),               0          ],
             [kz cos(beta) sin(gamma),     kz sin(beta) sin(gamma),     kz cos(gamma)]]

    Parameters
    ----------
    alpha_deg : float
        The angle by which the sensor's Ym axis, in the XY plane, is turned from Y, degrees.
    beta_deg : float
        The angle between X and the projection of the sensor's Zm axis on the XY plane, degrees.
    gamma_deg : float
        The angle between the sensor's Zm axis and Z, degrees.
    kx : float
        Sensitivity of the X axis.
    ky : float
        Sensitivity of the Y axis.
    kz : float
        Sensitivity of the Z axis.
    b : tuple of float, optional
        (3,) offsets, nT.
    """

    alpha_deg: float
    beta_deg: float
    gamma_deg: float
    kx: float
    ky: float
    kz: float
    b: tuple = (0.0, 0.0, 0.0)

    @property
    def phi_deg(self) -> float:
        """Angle between Xm and Zm, ``cos phi = cos beta sin gamma``, degrees."""
        return float(np.degrees(np.arccos(np.cos(np.radians(self.beta_deg)) * np.sin(np.radians(self.gamma_deg)))))

    def matrix(self) -> np.ndarray:
        """The lower-triangular ``K`` of eq. (1), shape (3, 3); it is ``R`` in ``m = R B + b``.

        Returns
        -------
        numpy.ndarray
            (3, 3) ``K``.
        """
        a, be, g = np.radians([self.alpha_deg, self.beta_deg, self.gamma_deg])
        return np.array(
            [
                [self.kx, 0.0, 0.0],
                [self.ky * np.sin(a), self.ky * np.cos(a), 0.0],
                [self.kz * np.cos(be) * np.sin(g), self.kz * np.sin(be) * np.sin(g), self.kz * np.cos(g)],
            ]
        )

    def as_vector(self) -> np.ndarray:
        """``(alpha, beta, gamma, kx, ky, kz, bx, by, bz)`` with angles in degrees, shape (9,).

        Returns
        -------
        numpy.ndarray
            (9,) the parameters in that order.
        """
        return np.array([self.alpha_deg, self.beta_deg, self.gamma_deg, self.kx, self.ky, self.kz, *self.b], float)

    @classmethod
    def from_vector(cls, v) -> SineFitParameters:
        """Parameters of a vector in ``as_vector``'s order.

        Parameters
        ----------
        v : array_like
            (9,) ``(alpha, beta, gamma, kx, ky, kz, bx, by, bz)``, angles in degrees, offsets in nT.

        Returns
        -------
        SineFitParameters
            The nine parameters.
        """
        v = [float(x) for x in v]
        return cls(*v[:6], b=tuple(v[6:9]))

    @classmethod
    def from_matrix(cls, K, b) -> SineFitParameters:
        """Parameters of a lower-triangular ``K`` (3, 3) and offsets ``b`` (3,).

        Parameters
        ----------
        K : array_like
            (3, 3) lower triangular.
        b : array_like
            (3,) offsets, nT.

        Returns
        -------
        SineFitParameters
            The nine parameters.

        Raises
        ------
        ValueError
            ``K`` is not lower triangular.
        """
        K = np.asarray(K, float)
        if np.any(np.abs(np.triu(K, 1)) > 1e-12 * np.abs(K).max()):
            raise ValueError("K must be lower triangular")
        ky, kz = np.linalg.norm(K[1]), np.linalg.norm(K[2])
        alpha = np.degrees(np.arctan2(K[1, 0], K[1, 1]))
        beta = np.degrees(np.arctan2(K[2, 1], K[2, 0]))
        gamma = np.degrees(np.arccos(np.clip(K[2, 2] / kz, -1.0, 1.0)))
        return cls(
            float(alpha), float(beta), float(gamma), float(K[0, 0]), float(ky), float(kz), tuple(float(x) for x in b)
        )

    def as_dict(self) -> dict:
        """The parameters by name (``PARAMETER_NAMES``: angles in degrees, ``b_x, b_y, b_z`` in nT).

        Returns
        -------
        dict
            Name -> value.
        """
        return dict(zip(PARAMETER_NAMES, self.as_vector().tolist()))


# ---------------------------------------------------------------- one sine curve
@dataclass(frozen=True)
class SineCurve:
    """``A sin(theta + C) + D`` fitted to one axis; amplitude and offset in nT, phase in degrees.

    The ``*_se`` attributes are standard errors from the least-squares covariance; ``rms`` is the
    residual RMS (nT) and ``n`` the number of samples.
    """

    amplitude: float
    phase_deg: float
    offset: float
    amplitude_se: float = 0.0
    phase_se_deg: float = 0.0
    offset_se: float = 0.0
    rms: float = 0.0
    n: int = 0

    def __call__(self, angle_deg) -> np.ndarray:
        return self.amplitude * np.sin(np.radians(np.asarray(angle_deg, float) + self.phase_deg)) + self.offset


def fit_sine(angle_deg, values) -> SineCurve:
    """Closed-form least-squares fit of ``A sin(theta + C) + D`` with ``A >= 0``.

    ``angle_deg`` and ``values`` have shape (N,), N >= 4. Linear in ``(A cos C, A sin C, D)``; standard
    errors of ``A``, ``C`` and ``D`` follow from the covariance ``s^2 (X^T X)^-1`` by the delta method,
    with ``s^2 = RSS / (N - 3)``.
    """
    th = np.radians(np.asarray(angle_deg, float))
    y = np.asarray(values, float)
    X = np.column_stack([np.sin(th), np.cos(th), np.ones_like(th)])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    p, q, d = coef  # y = p sin(th) + q cos(th) + d = A sin(th + C) + d with p = A cos C, q = A sin C
    resid = y - X @ coef
    n = len(y)
    dof = max(n - 3, 1)
    s2 = float(resid @ resid) / dof
    cov = s2 * np.linalg.inv(X.T @ X)
    amplitude = float(np.hypot(p, q))
    phase = float(np.degrees(np.arctan2(q, p)) % 360.0)
    ja = np.array([p, q]) / amplitude if amplitude > 0 else np.zeros(2)
    jc = np.array([-q, p]) / amplitude**2 if amplitude > 0 else np.zeros(2)
    c2 = cov[:2, :2]
    return SineCurve(
        amplitude,
        phase,
        float(d),
        amplitude_se=float(np.sqrt(ja @ c2 @ ja)),
        phase_se_deg=float(np.degrees(np.sqrt(jc @ c2 @ jc))),
        offset_se=float(np.sqrt(cov[2, 2])),
        rms=float(np.sqrt(resid @ resid / n)),
        n=n,
    )


# ---------------------------------------------------------------- turntable geometry
def turntable_field(
    plane: str,
    angle_deg,
    field_nt: float,
    inclination_deg: float,
    heading_offset_deg: float = 0.0,
    xz_roll_sign: int = 1,
) -> np.ndarray:
    """Field in the sensor's orthogonal frame, (N, 3) nT, at the given table angles (N,).

    ``heading_offset_deg`` is the magnetic heading of the X axis at table angle 0; ``xz_roll_sign``
    is +1 when plane ``xz`` was reached by rolling +90 deg about X, -1 for -90 deg.
    """
    psi = np.radians(np.asarray(angle_deg, float) + heading_offset_deg)
    inc = np.radians(inclination_deg)
    h, v = field_nt * np.cos(inc), field_nt * np.sin(inc)
    c, s = h * np.cos(psi), h * np.sin(psi)
    if plane == "xy":
        return np.column_stack([c, -s, np.full_like(c, v)])
    if plane == "xz":
        return np.column_stack([c, np.full_like(c, xz_roll_sign * v), xz_roll_sign * s])
    raise ValueError(f"unknown plane {plane!r}; use 'xy' or 'xz'")


# ---------------------------------------------------------------- results
@dataclass(frozen=True)
class SineFitResult:
    """Outcome of a sine-fit calibration.

    ``parameters`` are the nine parameters; ``standard_errors`` maps ``PARAMETER_NAMES`` to standard
    errors (NaN where the method gives none); ``curves`` maps ``"xy"``/``"xz"`` to per-axis
    ``SineCurve``; ``residual_rms_nt`` is the RMS of the model residual over all samples used.
    """

    parameters: SineFitParameters
    standard_errors: dict
    curves: dict
    method: str
    field_nt: float
    inclination_deg: float
    residual_rms_nt: float = float("nan")
    extras: dict = field(default_factory=dict)

    @property
    def R(self) -> np.ndarray:
        return self.parameters.matrix()

    @property
    def b(self) -> np.ndarray:
        return np.array(self.parameters.b)

    def to_calibration(self, source: str | None = None) -> Calibration:
        p = self.parameters.as_dict()
        p["phi_deg"] = self.parameters.phi_deg
        return Calibration(
            R=self.R,
            b=self.b,
            method=f"sinefit-{self.method}",
            parameters=p,
            standard_errors=self.standard_errors,
            quality={
                "residual_rms_nt": self.residual_rms_nt,
                "field_nt": self.field_nt,
                "inclination_deg": self.inclination_deg,
                **self.extras,
            },
            source=source,
        )

    def summary(self) -> dict:
        """JSON-ready result: the nine parameters, phi, R, b, standard errors, fit quality."""
        out = self.parameters.as_dict()
        out.update(
            phi_deg=self.parameters.phi_deg,
            R=self.R.tolist(),
            b=self.b.tolist(),
            standard_errors=self.standard_errors,
            method=self.method,
            residual_rms_nt=self.residual_rms_nt,
            field_nt=self.field_nt,
            inclination_deg=self.inclination_deg,
            curves={plane: {axis: vars(c) for axis, c in axes.items()} for plane, axes in self.curves.items()},
        )
        out.update(self.extras)
        return out


# ---------------------------------------------------------------- the paper's closed form
def paper_equations(
    curves_xy: dict, curves_xz: dict, field_nt: float, sample_xy=None, vertical_leak_nt: float = 0.0
) -> SineFitParameters:
    """The paper's eq. (5)-(16) from fitted curves.

    ``curves_xy`` maps ``x, y, z`` to the curves of rotation 1; ``curves_xz`` maps ``x, z`` to those of
    rotation 2. ``sample_xy`` is the raw reading (3,) used by eq. (15)-(16); by default the curves at
    table angle 0. ``vertical_leak_nt`` is subtracted from ``D'_z`` (0 reproduces eq. 11).
    """
    cx, cy, cz = (curves_xy[a] for a in "xyz")
    cx2, cz2 = curves_xz["x"], curves_xz["z"]
    if not (cx.amplitude > 0 and cy.amplitude > 0 and cx2.amplitude > 0):
        raise InputError(
            "degenerate: the x or y axis shows no sine over the table's turn (a sensor that does not follow the field)"
        )
    alpha = abs(float(wrap_deg(cy.phase_deg - cx.phase_deg - 90.0)))
    bx0, by0 = cx.offset, cy.offset
    kyx = cy.amplitude / cx.amplitude  # ky/kx; eq. (7) prints the inverse ratio, its own number is this one
    if cz.amplitude <= 3.0 * max(cz.amplitude_se, 1e-12 * cx.amplitude):
        beta = gamma = 0.0  # Zm perpendicular to the XmYm plane
    else:
        beta = abs(float(wrap_deg(cz.phase_deg - cx.phase_deg)))
        phi = abs(float(wrap_deg(cx2.phase_deg - cz2.phase_deg)))
        ratio = np.cos(np.radians(phi)) / np.cos(np.radians(beta))
        gamma = float(np.degrees(np.arcsin(np.clip(ratio, -1.0, 1.0))))
    bz0 = cz2.offset - vertical_leak_nt
    kzx = cz2.amplitude / cx2.amplitude
    if sample_xy is None:
        sample_xy = [cx(0.0), cy(0.0), cz(0.0)]
    mx, my, mz = np.asarray(sample_xy, float)
    a, be, g = np.radians([alpha, beta, gamma])
    kxbx = mx - bx0
    kyby = (my - by0 - kyx * kxbx * np.sin(a)) / np.cos(a)
    kzbz = (mz - bz0 - kzx * kxbx * np.cos(be) * np.sin(g) - (kzx / kyx) * kyby * np.sin(be) * np.sin(g)) / np.cos(g)
    kx = float(np.sqrt(kxbx**2 + (kyby / kyx) ** 2 + (kzbz / kzx) ** 2) / field_nt)
    return SineFitParameters(alpha, beta, gamma, kx, kyx * kx, kzx * kx, (bx0, by0, bz0))


def paper_from_curves(curves_xy: dict, curves_xz: dict, field_nt: float, inclination_deg: float) -> SineFitResult:
    """The paper's method applied to printed curves (no samples); standard errors are not available."""
    params = paper_equations(curves_xy, curves_xz, field_nt)
    return SineFitResult(
        params,
        {k: float("nan") for k in PARAMETER_NAMES},
        {"xy": dict(curves_xy), "xz": dict(curves_xz)},
        "paper",
        field_nt,
        inclination_deg,
    )


# ---------------------------------------------------------------- the calibrator
class SineFitCalibrator(Calibrator):
    """Sine-fit calibration from a two-plane turntable run.

    ``fit(table)`` takes the columns ``plane, angle_deg, mag_x, mag_y, mag_z`` (nT) as a DataFrame or anything
    ``pandas.DataFrame`` accepts (a dict of arrays, a structured array) and returns ``self``; the result is
    ``result_`` (and ``R_``, ``b_``, ``calibration_``). The scikit-learn contract of ``magkf.offline.base``:
    the settings are stored as given and checked by ``fit``.

    Parameters
    ----------
    field_nt : float
        The field magnitude, nT.
    inclination_deg : float
        Its inclination, degrees.
    method : str, optional
        ``exact`` (the corrected method, the default) or ``paper`` (the published equations).

    Attributes
    ----------
    result_ : SineFitResult
        The fit: the nine parameters, their standard errors (NaN for ``paper``), the sine curves, the
        residual.
    R_ : numpy.ndarray
        (3, 3) fitted ``R`` of ``m = R B + b``.
    b_ : numpy.ndarray
        (3,) fitted offsets, nT.
    calibration_ : Calibration
        The fitted calibration.

    Examples
    --------
    >>> cal = SineFitCalibrator(field_nt=50_000, inclination_deg=43).fit(table).calibration_  # doctest: +SKIP
    """

    def __init__(self, field_nt: float, inclination_deg: float, method: str = "exact"):
        self.field_nt, self.inclination_deg, self.method = field_nt, inclination_deg, method

    def fit(self, table, source: str = "turntable data") -> SineFitCalibrator:
        """Fit a turntable table with columns ``plane, angle_deg, mag_x, mag_y, mag_z`` (nT).

        A sine ``A sin(theta + C) + D`` is fitted to each axis in each plane (``xy``, ``xz``); the published
        equations give the parameters from the curves (``paper``), and the exact method refines them by
        least squares on every sample, with standard errors (``exact``).

        Parameters
        ----------
        table : pandas.DataFrame or mapping
            The turntable run: ``plane`` (``xy`` or ``xz``), ``angle_deg`` (table angle, degrees) and
            ``mag_x, mag_y, mag_z`` (nT); anything ``pandas.DataFrame`` accepts. At least 8 samples per plane,
            spanning at least 180 deg of table angle.
        source : str, optional
            What the table was read from, named in errors.

        Returns
        -------
        SineFitCalibrator
            ``self``, fitted: ``result_``, ``R_``, ``b_``, ``calibration_``.

        Raises
        ------
        ValueError
            An unknown ``method``, or a field magnitude that is not positive.
        InputError
            A required column missing, too few samples in a plane, or a plane spanning less than 180 deg of
            table angle (degenerate geometry).
        """
        if self.method not in ("paper", "exact"):
            raise ValueError(f"unknown method {self.method!r}; use 'paper' or 'exact'")
        if not float(self.field_nt) > 0:
            raise ValueError("the field magnitude must be positive")
        table = table if isinstance(table, pd.DataFrame) else pd.DataFrame(table)
        missing = [c for c in (PLANE, ANGLE, *MAG) if c not in table.columns]
        if missing:
            raise InputError("required column missing", source, column=missing[0])
        field_nt, inclination_deg = float(self.field_nt), float(self.inclination_deg)
        planes = {p: table[table[PLANE] == p] for p in PLANES}
        for p, rows in planes.items():
            require_rows(rows, MIN_SAMPLES_PER_PLANE, source, f"plane {p!r}")
        for p, rows in planes.items():
            span = arc_span_deg(rows[ANGLE].to_numpy())
            if span < MIN_ARC_DEG:
                raise InputError(
                    f"degenerate geometry: plane {p!r} spans only {span:.0f} deg of table angle; "
                    f"turn the table through at least {MIN_ARC_DEG:.0f} deg",
                    source,
                    column=ANGLE,
                )
        curves = {p: {a: fit_sine(rows[ANGLE], rows[f"mag_{a}"]) for a in "xyz"} for p, rows in planes.items()}
        first = planes["xy"][list(MAG)].to_numpy()[0]
        paper = paper_equations(curves["xy"], curves["xz"], field_nt, sample_xy=first)
        data = [(p, planes[p][ANGLE].to_numpy(), planes[p][list(MAG)].to_numpy()) for p in PLANES]
        if self.method == "paper":
            resid = model_residuals(paper, data, field_nt, inclination_deg, _heading_offsets(curves), 1)
            self._result = SineFitResult(
                paper,
                {k: float("nan") for k in PARAMETER_NAMES},
                curves,
                "paper",
                field_nt,
                inclination_deg,
                residual_rms_nt=float(np.sqrt(np.mean(resid**2))),
            )
        else:
            self._result = self._exact(data, curves, paper, field_nt, inclination_deg)
        return self

    def _exact(self, data, curves, paper: SineFitParameters, field_nt: float, inclination_deg: float) -> SineFitResult:
        # Turning the sensor 180 deg about z (kx, ky -> -kx, -ky) with both table headings + 180 deg and
        # the opposite roll in plane xz fits the data equally well; positive sensitivities pick the branch.
        fits = [(_solve_exact(data, curves, paper, field_nt, inclination_deg, sign), sign) for sign in (1, -1)]
        fit, sign = min(fits, key=lambda f: (not np.all(f[0].x[3:6] > 0), f[0].cost))
        n, p = fit.fun.size, fit.x.size
        s2 = 2 * fit.cost / max(n - p, 1)
        J = fit.jac
        try:
            cov = s2 * np.linalg.inv(J.T @ J)
            se = np.sqrt(np.clip(np.diag(cov), 0, None))
        except np.linalg.LinAlgError:
            se = np.full(p, np.nan)
        params = _unpack(fit.x)
        scale = np.array([np.degrees(1)] * 3 + [1.0] * 6)
        standard_errors = dict(zip(PARAMETER_NAMES, (se[:9] * scale).tolist()))
        return SineFitResult(
            params,
            standard_errors,
            curves,
            "exact",
            field_nt,
            inclination_deg,
            residual_rms_nt=float(np.sqrt(2 * fit.cost / n)),
            extras={
                "xz_roll_deg": 90.0 * sign,
                "heading_offsets_deg": {k: float(wrap_deg(np.degrees(fit.x[i]))) for k, i in (("xy", 9), ("xz", 10))},
            },
        )


def _heading_offsets(curves) -> tuple[float, float]:
    """Table heading offsets of the two planes from the X-axis phases (X reads ``A cos(psi)``)."""
    return curves["xy"]["x"].phase_deg - 90.0, curves["xz"]["x"].phase_deg - 90.0


def _unpack(x) -> SineFitParameters:
    """The parameters of the solver's vector, angles wrapped to (-180, 180] deg (they enter as angles only)."""
    return SineFitParameters(*(float(a) for a in wrap_deg(np.degrees(x[:3]))), *x[3:6], b=tuple(x[6:9]))


def model_residuals(params: SineFitParameters, data, field_nt, inclination_deg, offsets_deg, sign) -> np.ndarray:
    """Residuals ``m - (K B(psi) + b0)`` (nT, flattened per sample and axis) of both planes.

    ``data`` lists ``(plane, angle_deg (N,), m (N, 3))``; ``offsets_deg`` are the planes' heading offsets.
    """
    K, b = params.matrix(), np.array(params.b)
    out = []
    for (plane, angle, m), offset in zip(data, offsets_deg):
        B = turntable_field(plane, angle, field_nt, inclination_deg, offset, sign)
        out.append((m - (B @ K.T + b)).ravel())
    return np.concatenate(out)


def _solve_exact(data, curves, paper: SineFitParameters, field_nt, inclination_deg, sign):
    """Nonlinear least squares over all samples, started from the closed form with the leak removed."""
    a, be, g = np.radians([paper.alpha_deg, paper.beta_deg, paper.gamma_deg])
    v = field_nt * np.sin(np.radians(inclination_deg))
    # Plane xz: D'_z = Bz0 + kz sin(b) sin(g) * (sign * V); remove that leak from the start value.
    leak = paper.kz * np.sin(be) * np.sin(g) * sign * v
    # The paper's angles are absolute values; the signed ones follow from the phases.
    cxy = curves["xy"]
    a_signed = np.radians(wrap_deg(180.0 - (cxy["y"].phase_deg - cxy["x"].phase_deg + 90.0)))
    b_signed = np.radians(wrap_deg(cxy["z"].phase_deg - cxy["x"].phase_deg))
    offsets = np.radians(_heading_offsets(curves))
    x0 = np.array(
        [a_signed, b_signed, g, paper.kx, paper.ky, paper.kz, paper.b[0], paper.b[1], paper.b[2] - leak, *offsets]
    )
    if not np.isfinite(x0).all():
        raise InputError("degenerate geometry: the fitted curves do not determine the parameters")

    def residuals(x):
        return model_residuals(_unpack(x), data, field_nt, inclination_deg, np.degrees(x[9:11]), sign)

    def jacobian(x):
        return exact_jacobian(x, data, field_nt, inclination_deg, sign)

    scale = np.array([1e-2] * 3 + [1e-2] * 3 + [1.0] * 3 + [1e-2] * 2)
    return least_squares(
        residuals, x0, jac=jacobian, method="lm", x_scale=scale, xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000
    )


def exact_jacobian(x, data, field_nt, inclination_deg, sign) -> np.ndarray:
    """Analytic Jacobian (n_residuals, 11) of the exact method's residual ``m - (K B(psi) + b0)``.

    ``x`` = (alpha, beta, gamma in radians, kx, ky, kz, b0 (3), heading offsets of the two planes in
    radians); ``data`` lists ``(plane, angle_deg, m)`` per plane.
    """
    a, be, g, kx, ky, kz = x[:6]
    sa, ca, sb, cb, sg, cg = np.sin(a), np.cos(a), np.sin(be), np.cos(be), np.sin(g), np.cos(g)
    dK = np.zeros((6, 3, 3))  # dK / d(alpha, beta, gamma, kx, ky, kz)
    dK[0, 1] = ky * np.array([ca, -sa, 0.0])
    dK[1, 2] = kz * np.array([-sb * sg, cb * sg, 0.0])
    dK[2, 2] = kz * np.array([cb * cg, sb * cg, -sg])
    dK[3, 0] = [1.0, 0.0, 0.0]
    dK[4, 1] = [sa, ca, 0.0]
    dK[5, 2] = [cb * sg, sb * sg, cg]
    K = _unpack(x).matrix()
    h = field_nt * np.cos(np.radians(inclination_deg))
    blocks = []
    for i, (plane, angle, _) in enumerate(data):
        psi = np.radians(angle) + x[9 + i]
        B = turntable_field(plane, angle, field_nt, inclination_deg, np.degrees(x[9 + i]), sign)
        if plane == "xy":
            dB = np.column_stack([-h * np.sin(psi), -h * np.cos(psi), np.zeros_like(psi)])
        else:
            dB = np.column_stack([-h * np.sin(psi), np.zeros_like(psi), sign * h * np.cos(psi)])
        J = np.zeros((len(angle), 3, 11))
        J[:, :, :6] = -np.einsum("pij,nj->nip", dK, B)
        J[:, :, 6:9] = -np.eye(3)
        J[:, :, 9 + i] = -dB @ K.T
        blocks.append(J.reshape(-1, 11))
    return np.vstack(blocks)


# ---------------------------------------------------------------- files
def read_turntable(path, mag_unit: str = "nT", column_map=None) -> pd.DataFrame:
    """Read a turntable table (``plane, angle_deg, mag_x, mag_y, mag_z``), the field converted to nT.

    Parameters
    ----------
    path : str or Path
        magkf's CSV (or Parquet) turntable table or, with ``column_map``, any table the map describes.
    mag_unit : str
        Unit of the magnetometer columns of magkf's CSV; with a map, its ``[units] mag`` says it.
    column_map : str, Path or ColumnMap, optional
        A column map (``docs/column-maps.md``) whose ``[columns]`` give ``plane`` (text), ``angle_deg`` and
        ``mag_x, mag_y, mag_z``.

    Returns
    -------
    pandas.DataFrame
        ``plane`` (``xy`` or ``xz``), ``angle_deg`` (deg) and ``mag_x, mag_y, mag_z`` (nT), one row per sample.

    Raises
    ------
    InputError
        One line naming the file, row and column (rows as the file counts them).
    """
    from ..conventions import to_nanotesla
    from ..io.drivelog import MAG_MAX_NT
    from .reading import read_offline_table

    name = str(path)
    given_unit = mag_unit if column_map is None else None
    table, row_of = read_offline_table(path, (PLANE, ANGLE, *MAG), column_map, (PLANE,), mag_unit=mag_unit)
    planes = table[PLANE].astype(str).str.strip().str.lower()
    bad = ~planes.isin(PLANES)
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        raise InputError(f"plane must be 'xy' or 'xz', got {table[PLANE].iloc[i]!r}", name, row_of(i), PLANE)
    table[PLANE] = planes
    for c in MAG:
        table[c] = to_nanotesla(table[c].to_numpy(), given_unit or "nT")
        far = np.flatnonzero(np.abs(table[c].to_numpy()) > MAG_MAX_NT)
        if far.size:
            raise InputError(f"value beyond +-{MAG_MAX_NT:g} nT once in nT", name, row_of(int(far[0])), c)
    angle = table[ANGLE].to_numpy()
    far = np.flatnonzero(np.abs(angle) > 3600)
    if far.size:
        raise InputError("angle beyond +-3600 deg", name, row_of(int(far[0])), ANGLE)
    return table


def read_curves(path) -> tuple[dict, dict]:
    """Fitted curves from JSON ``{"xy": {"x": [A, C_deg, D], "y": ..., "z": ...}, "xz": {"x": ..., "z": ...}}``."""
    from ..calibration import read_json

    name = str(path)
    data = read_json(path, "curves file")
    out = []
    for plane, axes in (("xy", "xyz"), ("xz", "xz")):
        curves = {}
        for a in axes:
            try:
                amplitude, phase, offset = (float(v) for v in data[plane][a])
            except (KeyError, TypeError, ValueError):
                raise InputError(f"key {plane}.{a} must be a list [amplitude, phase_deg, offset]", name) from None
            if not (np.all(np.isfinite([amplitude, phase, offset])) and 0 < amplitude <= 1e7 and abs(offset) <= 1e8):
                raise InputError(
                    f"key {plane}.{a}: the amplitude must lie in (0, 1e7] nT and every value be finite", name
                )
            curves[a] = SineCurve(amplitude, phase, offset)
        out.append(curves)
    return out[0], out[1]
