"""Measurement models of the online calibration, one class each: ``magnitude``, ``vector`` and ``both``.

A model knows which epochs it can use (``needs_attitude``, and ``fallback``: the model for the epochs it
cannot use), its noise, its linearisation of a block of epochs for the EKF (whitened innovation and
Jacobian), its prediction at sigma points for the UKF, and its normalised residuals for the batch
solver. The filters, the estimator, the batch solver and the real-time path call these methods and never
look at a model's name; ``MEASUREMENTS`` maps a name to its class, and ``register_measurement`` adds one.

**Vector** (``vector``, ``both``). The NED components of the calibrated field, ``C_nb R^-1 (m - b - e)``,
against the reference ``B_ref``. The same equation, multiplied through by ``R C_nb^T``, reads
``m = R C_nb^T B_ref + b + e``: in the sensor frame it is *linear* in ``R``, ``b`` and every linear effect,
so magkf processes it there (the Kalman update is then exact, and its Jacobian is the effects' Jacobians
evaluated once for each epoch, not at every update). Residuals are reported in NED. Noise covariance in
the sensor frame:

    sensor_noise^2 I + R (reference^2 I + A) R^T

with the attitude term ``A = tilt^2 (|B|^2 I - B B^T) + (heading^2 - tilt^2) h h^T`` for ``both``, where
``h = B x down`` (body frame; its length is the horizontal field): an attitude error turns the field but
does not change its length, so the along-field (total-field) component keeps sensor-level noise and only
the two cross-field (inter-axis) components carry the attitude noise; this is the patent's total-field
plus inter-axis residual pair without counting the magnitude twice. A heading error (about the vertical,
usually an INS's worst angle) turns the field along ``h`` only; tilt errors (about the horizontal axes)
along both cross directions. For ``vector``, ``A = tilt^2 |B|^2 I + (heading^2 - tilt^2) h h^T``.
``both`` falls back to the magnitude for epochs without attitude.

**Magnitude.** ``|R^-1 (m - b - e)|`` against ``|B_ref|``; needs no attitude. Variance
``sensor_noise^2 u^T R^-1 R^-T u + reference^2`` with ``u`` the unit calibrated field. As the only
measurement of a run, it cannot see a rotation ``R -> R Q``: its Jacobian is projected off those
directions (an observability-constrained EKF), so the filter gains no spurious information there.

Shapes: a block of k epochs; ``r`` rows per epoch (``Model.rows``); n states; S sigma points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import FilterConfig
from ..conventions import body_to_ned, calibrated_field, inverse3, ned_to_body
from ..effects.base import EpochData
from ..plugins import MEASUREMENTS
from .noise import NoiseLevels
from .state import StateLayout

__all__ = [
    "Block",
    "MeasurementModel",
    "Magnitude",
    "Vector",
    "Both",
    "MEASUREMENTS",
    "register_measurement",
    "measurement_model",
    "nis_rows",
    "vector_noise",
    "attitude_structure",
    "heading_axis",
    "heading_axis_ned",
    "heading_structure",
    "compose_noise",
    "cross_basis",
    "field_frame",
    "sensor_frame",
    "whitening",
    "magnitude_jacobian",
    "rotation_directions",
]

_EYE = np.eye(3)


@dataclass
class Block:
    """k consecutive epochs as the models see them.

    ``m`` (k, 3) raw nT; ``ref_mag`` (k,) reference magnitude nT; ``H`` (k, 3, n) Jacobian of the linear
    blocks (``StateLayout.linear_jacobian``); ``B`` (k, 3) the reference field in the body frame and ``R``
    (3, 3) the calibration at which the vector noise is evaluated; ``heading`` (k, 3) nT the heading axis
    ``B x down`` in the body frame (``heading_axis``); ``G`` (k, 3, 3) the tilt part of the vector noise
    per unit variance, ``Gh`` (k, 3, 3) the heading part and ``RRt`` (3, 3) the reference part,
    precomputed (``Vector.structure``; None to compute them from ``B``, ``heading`` and ``R``), ``frame``
    (k, 3, 3) the unit field in the sensor frame, the horizontal direction across it and the third, as
    rows (``field_frame``; None for a model that needs no attitude); ``data`` the epochs' ``EpochData``
    (needed by nonlinear effects); ``e`` (k, 3) raw-field terms of the added effects at the current
    estimate; ``W`` (k, 3, 3) the whitening at the current noise, set by the model (``Vector.whiten``) and
    then by the estimator, which folds the residuals' correlation in time into it; ``N`` (k, 3, 3) the
    covariance of the noise whitened by ``W`` as the gates see it (None: the identity); ``whitened_with`` the
    ``NoiseLevels`` that ``W`` and ``N`` were computed at (None: not yet whitened).
    """

    m: np.ndarray
    ref_mag: np.ndarray
    H: np.ndarray
    B: np.ndarray | None = None
    R: np.ndarray | None = None
    heading: np.ndarray | None = None
    G: np.ndarray | None = None
    Gh: np.ndarray | None = None
    RRt: np.ndarray | None = None
    frame: np.ndarray | None = None
    data: EpochData | None = None
    e: np.ndarray | float = 0.0
    W: np.ndarray | None = None
    N: np.ndarray | None = None
    whitened_with: NoiseLevels | None = None

    def take(self, index) -> Block:
        """The same block at the epochs ``index`` (integer array or boolean mask)."""

        def cut(a):
            return a[index] if isinstance(a, np.ndarray) else a

        return Block(
            self.m[index],
            self.ref_mag[index],
            self.H[index],
            cut(self.B),
            self.R,
            cut(self.heading),
            cut(self.G),
            cut(self.Gh),
            self.RRt,
            cut(self.frame),
            None if self.data is None else self.data.take(index),
            cut(self.e),
            cut(self.W),
            cut(self.N),
            self.whitened_with,
        )


class MeasurementModel:
    """Base class of a measurement model (subclass it and ``register_measurement`` it).

    Class attributes: ``name``; ``rows`` per epoch; ``needs_attitude``. Constructed with the run's
    ``config``, ``layout`` and initial state ``x0``; ``fallback`` is the model for the epochs this one
    cannot use (epochs without attitude), or None.
    """

    name: str = "measurement"
    rows: int = 1
    needs_attitude: bool = False
    #: The rows are linear in the state; a model says so only where it holds for every state. The UKF then
    #: takes them at the estimate through ``linearise`` (which such a model must implement), as the EKF does:
    #: the unscented transform of a linear function is exact, so its sigma points would give the same.
    linear: bool = False

    def __init__(self, config: FilterConfig, layout: StateLayout, x0):
        self.config, self.layout = config, layout
        self.fallback: MeasurementModel | None = None
        self.noise = NoiseLevels(config.sensor_noise_nt, np.radians(config.attitude_deg), config.reference_nt)

    def set_noise(self, noise: NoiseLevels) -> None:
        """Use ``noise`` from now on (and in the fallback model)."""
        self.noise = noise
        if self.fallback is not None:
            self.fallback.set_noise(noise)

    def structure(self, field_body, R, heading=None):
        """What the noise of epochs with body field ``field_body`` (N, 3) and heading axis ``heading`` (N, 3)
        at ``R`` (3, 3) is made of, computed once for each epoch: ``(G, Gh, RRt, frame)`` with ``frame`` (N, 3, 3) the
        field's frame in the sensor axes (``field_frame``: what the noise learner splits the innovations
        along) and ``G``, ``Gh``, ``RRt`` what ``whiten`` may use (None here); None for a model that needs no
        attitude."""
        if not self.needs_attitude:
            return None
        return None, None, None, sensor_frame(field_body, heading, R)

    def whitening(self, field_body, R) -> np.ndarray | None:
        """Whitening (k, 3, 3) of the epochs' vector noise at calibration ``R`` (None: not needed)."""
        return None

    def whiten(self, blk: Block) -> None:
        """Set ``blk.W``, the whitening at the current noise, for the block's epochs (by default
        ``whitening(blk.B, blk.R)``; nothing for a model that needs none)."""
        if self.needs_attitude:
            blk.W = self.whitening(blk.B, blk.R)

    def covariance(self, blk: Block) -> np.ndarray | None:
        """The noise covariance (k, r, r) of the block's epochs at the current noise, nT^2; None when the model
        whitens its rows itself. By default ``W^-1 W^-T`` of ``whiten``'s ``W`` (which it sets on ``blk``)."""
        self.whiten(blk)
        if blk.W is None:
            return None
        L = np.linalg.inv(blk.W)
        return L @ np.swapaxes(L, 1, 2)

    def linearise(self, x, blk: Block) -> tuple[np.ndarray, np.ndarray]:
        """Whitened innovation ``y`` (k, r) and Jacobian ``H`` (k, r, n) at state ``x`` (n,)."""
        raise NotImplementedError

    def sigma_predict(self, sigmas, x, blk: Block) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whitened predictions ``h`` (S, k, r) at ``sigmas`` (S, n), the whitened measurement ``z`` (k, r),
        and the whitened Jacobian (k, r, n) at ``x`` (for the information the update carries)."""
        raise NotImplementedError

    def batch_residuals(self, ref, c_nb, ref_mag):
        """A function ``f(c) -> (k, q)``: residuals in units of their standard deviations of calibrated
        fields ``c`` (k, 3) nT at epochs with reference ``ref`` (k, 3), attitude ``c_nb`` (k, 3, 3), nT."""
        raise NotImplementedError

    # Noise of the batch solver's residuals: the same as the filter's.
    def _sigma_total(self) -> float:
        return float(np.sqrt(self.noise.along_var))

    def _sigma_cross(self, ref_mag) -> np.ndarray:
        attitude = max(self.noise.attitude_rad, self.noise.heading)
        return np.sqrt(self.noise.along_var + (attitude * ref_mag) ** 2)


# ---------------------------------------------------------------- vector
def attitude_structure(field_body: np.ndarray, R: np.ndarray, field_aligned: bool) -> np.ndarray:
    """The attitude part (N, 3, 3) of the sensor-frame vector noise per unit attitude variance (rad^2):
    ``R (|B|^2 I - B B^T) R^T`` across the field (``field_aligned``), else ``|B|^2 R R^T``."""
    B = np.asarray(field_body, float)
    R = np.asarray(R, float)
    out = np.einsum("ni,ni->n", B, B)[:, None, None] * (R @ R.T)
    if field_aligned:  # R B B^T R^T = (R B)(R B)^T
        RB = B @ R.T
        out -= RB[:, :, None] * RB[:, None, :]
    return out


def heading_axis(c_nb: np.ndarray, field_ned: np.ndarray) -> np.ndarray:
    """The heading axis ``B x down`` (N, 3) in the body frame, nT, at attitudes ``c_nb`` (N, 3, 3) for the
    reference ``field_ned`` (N, 3): a heading error ``e`` (rad) moves the body-frame field by ``e`` times it.
    Its length is the horizontal field."""
    return ned_to_body(c_nb, heading_axis_ned(field_ned))


def heading_axis_ned(field_ned: np.ndarray) -> np.ndarray:
    """``B x down`` (N, 3) in NED, nT: ``(B_e, -B_n, 0)``, horizontal and across the field."""
    f = np.asarray(field_ned, float)
    return np.column_stack([f[:, 1], -f[:, 0], np.zeros(len(f))])


def heading_structure(heading: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The heading part (N, 3, 3) of the sensor-frame vector noise per unit heading variance (rad^2):
    ``R h h^T R^T`` with ``h`` the heading axis (N, 3) nT."""
    Rh = np.asarray(heading, float) @ np.asarray(R).T
    return Rh[:, :, None] * Rh[:, None, :]


def vector_noise(field_body, R, noise: NoiseLevels, field_aligned: bool, heading=None) -> np.ndarray:
    """Sensor-frame noise covariance (N, 3, 3) of the vector measurement at N epochs (body field in nT):
    ``sensor^2 I + reference^2 R R^T + tilt^2 G + (heading^2 - tilt^2) Gh`` (``attitude_structure``,
    ``heading_structure``; without ``heading`` axes the heading error is taken as a tilt)."""
    Gh = None if heading is None else heading_structure(heading, R)
    return compose_noise(noise, attitude_structure(field_body, R, field_aligned), Gh, R @ R.T)


def compose_noise(noise: NoiseLevels, G, Gh, RRt) -> np.ndarray:
    """``sensor^2 I + reference^2 RRt + tilt^2 G + (heading^2 - tilt^2) Gh`` (N, 3, 3) from the noise levels
    and the parts of the noise per unit variance (``Vector.structure``; ``Gh`` None: no heading term)."""
    out = noise.sensor_nt**2 * _EYE + noise.reference_nt**2 * RRt + noise.attitude_rad**2 * G
    if Gh is not None:
        out = out + (noise.heading**2 - noise.attitude_rad**2) * Gh
    return out


def whitening(noise: np.ndarray) -> np.ndarray:
    """``W = L^-1`` (N, 3, 3) with ``noise = L L^T``: ``W y`` has unit, uncorrelated noise."""
    if len(noise) == 1:  # one epoch (real time): the 3x3 algebra written out beats numpy's call overhead
        return _whitening3(noise[0])[None]
    if noise.shape[1:] == (3, 3):
        W = _whitening_stack(noise)
        if W is not None:
            return W
    return np.linalg.inv(np.linalg.cholesky(noise))


def _whitening_stack(N: np.ndarray) -> np.ndarray | None:
    """``whitening`` of a stack (k, 3, 3), the Cholesky factor and its inverse written out over the stack (a
    stacked ``inv`` costs several times more); None when a pivot is not positive (the caller's LAPACK path
    then reports it)."""
    a, b, c, d, e, f = N[:, 0, 0], N[:, 0, 1], N[:, 0, 2], N[:, 1, 1], N[:, 1, 2], N[:, 2, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        l11 = np.sqrt(a)
        l21, l31 = b / l11, c / l11
        l22 = np.sqrt(d - l21 * l21)
        l32 = (e - l31 * l21) / l22
        l33 = np.sqrt(f - l31 * l31 - l32 * l32)
    if not (np.minimum(np.minimum(l11, l22), l33) > 0).all():  # also false for NaN
        return None
    W = np.zeros_like(N)
    W[:, 0, 0], W[:, 1, 1], W[:, 2, 2] = i11, i22, i33 = 1.0 / l11, 1.0 / l22, 1.0 / l33
    W[:, 1, 0] = i21 = -l21 * i11 * i22
    W[:, 2, 1] = -l32 * i22 * i33
    W[:, 2, 0] = -(l31 * i11 + l32 * i21) * i33
    return W


def _whitening3(N: np.ndarray) -> np.ndarray:
    """Inverse Cholesky factor of one symmetric positive-definite 3x3 matrix."""
    (a, b, c), (_, d, e), (_, _, f) = N.tolist()
    l11 = a**0.5
    l21, l31 = b / l11, c / l11
    l22 = (d - l21 * l21) ** 0.5
    l32 = (e - l31 * l21) / l22
    l33 = (f - l31 * l31 - l32 * l32) ** 0.5
    i11, i22, i33 = 1 / l11, 1 / l22, 1 / l33
    i21 = -l21 * i11 * i22
    i32 = -l32 * i22 * i33
    i31 = -(l31 * i11 + l32 * i21) * i33
    return np.array([[i11, 0.0, 0.0], [i21, i22, 0.0], [i31, i32, i33]])


class Vector(MeasurementModel):
    """The NED field vector, processed in the sensor frame where it is linear; attitude noise on every
    component. Epochs without attitude are not used."""

    name = "vector"
    rows = 3
    needs_attitude = True
    field_aligned = False

    @property
    def linear(self) -> bool:
        """Linear in the state unless the layout holds a nonlinear effect (a time lag), or a subclass predicts
        its rows in its own way."""
        own = type(self).sigma_predict is Vector.sigma_predict and type(self).linearise is Vector.linearise
        return own and not self.layout.nonlinear

    def structure(self, field_body, R, heading=None):
        B = np.asarray(field_body, float)
        if len(B) == 1:  # one epoch (real time): the same products on vectors, and the frame in plain floats
            return _structure1(B[0], np.asarray(R, float), None if heading is None else heading[0], self.field_aligned)
        Gh = None if heading is None else heading_structure(heading, R)
        return attitude_structure(B, R, self.field_aligned), Gh, R @ R.T, sensor_frame(B, heading, R)

    def whitening(self, field_body, R, heading=None):
        return whitening(vector_noise(field_body, R, self.noise, self.field_aligned, heading))

    def whiten(self, blk):
        blk.W = whitening(self.covariance(blk))

    def covariance(self, blk):
        if blk.G is None:
            return vector_noise(blk.B, blk.R, self.noise, self.field_aligned, blk.heading)
        return compose_noise(self.noise, blk.G, blk.Gh, blk.RRt)

    def _jacobian(self, x, blk: Block) -> np.ndarray:
        """(k, 3, n) Jacobian of ``m``: the linear blocks' with the nonlinear effects' filled in."""
        return self.layout.jacobian(x, blk.data, blk.H)

    def linearise(self, x, blk):
        h = blk.H @ x
        if self.layout.nonlinear:
            h = h + self.layout.nonlinear_terms(x, blk.data)
        y = (blk.W @ (blk.m - h)[:, :, None])[:, :, 0]
        return y, blk.W @ self._jacobian(x, blk)

    def sigma_predict(self, sigmas, x, blk):
        WH = blk.W @ blk.H
        h = np.tensordot(sigmas, WH, axes=([1], [2]))  # (S, k, 3)
        if self.layout.nonlinear:
            h = h + np.einsum("kij,skj->ski", blk.W, self.layout.nonlinear_terms(sigmas, blk.data))
        z = np.einsum("kij,kj->ki", blk.W, blk.m)
        return h, z, blk.W @ self._jacobian(x, blk)

    def batch_residuals(self, ref, c_nb, ref_mag):
        sigma = self._sigma_cross(ref_mag)[:, None]
        return lambda c: (body_to_ned(c_nb, c) - ref) / sigma


def _structure1(B, R, heading, field_aligned: bool) -> tuple:
    """``Vector.structure`` of one epoch: body field ``B`` (3,) and heading axis ``heading`` (3, or None) nT at
    calibration ``R`` (3, 3)."""
    RB, RRt = R @ B, R @ R.T
    G = (B @ B) * RRt
    if field_aligned:
        G = G - RB[:, None] * RB[None, :]
    Rh = None if heading is None else R @ np.asarray(heading, float)
    Gh = None if Rh is None else (Rh[:, None] * Rh[None, :])[None]
    return G[None], Gh, RRt, _field_frame1(RB, Rh)[None]


class Both(Vector):
    """The total field and the two inter-axis components across it (``vector`` with field-aligned noise);
    epochs without attitude fall back to the magnitude."""

    name = "both"
    field_aligned = True

    def __init__(self, config, layout, x0):
        super().__init__(config, layout, x0)
        self.fallback = Magnitude(config, layout, x0, primary=False)

    def batch_residuals(self, ref, c_nb, ref_mag):
        total = self.fallback.batch_residuals(ref, c_nb, ref_mag)
        basis = field_frame(ref, heading_axis_ned(ref))[:, 1:]
        var_h, var_v = self.noise.across_vars(ref_mag**2, ref[:, 0] ** 2 + ref[:, 1] ** 2)
        sigma = np.sqrt(np.column_stack([var_h, var_v]))

        def residuals(c):
            cross = np.einsum("nki,ni->nk", basis, body_to_ned(c_nb, c) - ref) / sigma
            return np.concatenate([total(c), cross], axis=1)

        return residuals


def cross_basis(ref: np.ndarray) -> np.ndarray:
    """Two unit vectors (N, 2, 3) spanning the plane across each reference field (N, 3)."""
    u = ref / np.linalg.norm(ref, axis=1)[:, None]
    helper = np.where(np.abs(u[:, [0]]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = _cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    return np.stack([e1, _cross(u, e1)], axis=1)


def field_frame(field: np.ndarray, heading=None) -> np.ndarray:
    """Orthonormal frames (N, 3, 3) whose rows are the unit field (N, 3), the unit ``heading`` axis (N, 3)
    made orthogonal to it, and the third direction, across both; without ``heading`` (or where it vanishes,
    a vertical field) two unit vectors across the field (``cross_basis``). Missing fields give a frame
    about the z axis."""
    if len(field) == 1:  # one epoch (real time): plain floats beat numpy's per-call cost
        return _field_frame1(field[0], None if heading is None else heading[0])[None]
    field = np.nan_to_num(np.asarray(field, float))
    norm = np.sqrt(np.einsum("ni,ni->n", field, field))
    present = norm > 0
    out = np.empty((len(field), 3, 3))
    u = out[:, 0]
    np.divide(field, np.where(present, norm, 1.0)[:, None], out=u)
    u[~present] = (0.0, 0.0, 1.0)
    second = out[:, 1]
    ok = np.zeros(len(field), bool)
    if heading is not None:
        h = np.nan_to_num(np.asarray(heading, float))
        h = h - np.einsum("ni,ni->n", h, u)[:, None] * u
        length = np.sqrt(np.einsum("ni,ni->n", h, h))
        ok = length > 1e-6 * np.where(present, norm, 1.0)
        np.divide(h, np.where(ok, length, 1.0)[:, None], out=second)
    if not ok.all():
        second[~ok] = cross_basis(u[~ok])[:, 0]
    out[:, 2] = _cross(u, second)
    return out


def _field_frame1(field, heading) -> np.ndarray:
    """``field_frame`` (3, 3) of one epoch's field (3,) and heading axis (3, or None)."""
    f = [v if math.isfinite(v) else 0.0 for v in np.asarray(field, float).tolist()]
    norm = math.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)
    u = [v / norm for v in f] if norm > 0 else [0.0, 0.0, 1.0]
    second = None
    if heading is not None:
        h = [v if math.isfinite(v) else 0.0 for v in np.asarray(heading, float).tolist()]
        along = h[0] * u[0] + h[1] * u[1] + h[2] * u[2]
        h = [a - along * b for a, b in zip(h, u)]
        length = math.sqrt(h[0] ** 2 + h[1] ** 2 + h[2] ** 2)
        if length > 1e-6 * max(norm, 1.0 if norm == 0 else norm):
            second = [v / length for v in h]
    if second is None:  # as cross_basis: across the field, from the x axis (or y near x)
        helper = [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]
        e = _cross3(u, helper)
        length = math.sqrt(e[0] ** 2 + e[1] ** 2 + e[2] ** 2)
        second = [v / length for v in e]
    return np.array([u, second, _cross3(u, second)])


def _cross3(a, b) -> list:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def sensor_frame(field_body, heading, R) -> np.ndarray:
    """``field_frame`` (N, 3, 3) in the sensor axes at calibration ``R`` (3, 3) of the body field (N, 3) and
    the heading axis (N, 3, or None)."""
    R = np.asarray(R)
    return field_frame(np.asarray(field_body, float) @ R.T, None if heading is None else np.asarray(heading) @ R.T)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products (N, 3), written out: ``np.cross`` pays a generic axis handling per call."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.column_stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


# ---------------------------------------------------------------- magnitude
def magnitude_jacobian(x_core: np.ndarray, m_minus_e: np.ndarray):
    """Magnitude model at k epochs: ``h`` (k,), ``H`` (k, 12) and ``w = u^T R^-1`` (k, 3).

    ``x_core`` (12,) is ``R`` row-major and ``b``; ``m_minus_e`` (k, 3) the raw readings less the other
    effects. ``h = |c|`` with ``c = R^-1 (m - e - b)``; ``dh/db = -w`` and ``dh/dR_ij = -w_i c_j``.
    """
    R, b = StateLayout.R_b(x_core)
    Rinv = inverse3(R)
    if len(m_minus_e) == 1:  # one epoch (real time, and the gate's variance per block): plain floats
        one = _magnitude_jacobian1(Rinv.tolist(), (np.asarray(m_minus_e, float)[0] - b).tolist())
        if one is not None:
            return one
    c = (m_minus_e - b) @ Rinv.T
    h = np.linalg.norm(c, axis=1)
    w = (c / h[:, None]) @ Rinv
    H = np.concatenate([-(w[:, :, None] * c[:, None, :]).reshape(-1, 9), -w], axis=1)
    return h, H, w


def _magnitude_jacobian1(Rinv: list, d: list):
    """``magnitude_jacobian`` of one epoch from ``R^-1`` (rows, floats) and ``m - e - b`` (3 floats); None for
    a zero field (left to numpy's handling of 0 / 0)."""
    c = [row[0] * d[0] + row[1] * d[1] + row[2] * d[2] for row in Rinv]
    h = math.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    if h == 0.0:
        return None
    u = [v / h for v in c]
    w = [u[0] * Rinv[0][j] + u[1] * Rinv[1][j] + u[2] * Rinv[2][j] for j in range(3)]
    H = [-wi * cj for wi in w for cj in c] + [-wi for wi in w]
    return np.array([h]), np.array([H]), np.array([w])


def rotation_directions(R: np.ndarray, size: int) -> np.ndarray:
    """State directions (size, 3) of ``R -> R (I + Omega)`` for the three infinitesimal rotations Omega."""
    out = np.zeros((size, 3))
    for k in range(3):
        omega = np.zeros((3, 3))
        i, j = [(1, 2), (2, 0), (0, 1)][k]
        omega[i, j], omega[j, i] = -1.0, 1.0
        out[StateLayout.R_INDEX, k] = (R @ omega).ravel()
    return out


class Magnitude(MeasurementModel):
    """The calibrated field magnitude against the reference's; needs no attitude.

    ``primary``: the run's only measurement, whose Jacobian is then projected off the rotations of the
    initial ``R`` (no magnitude can see them); False when it serves as another model's fallback.
    """

    name = "magnitude"
    rows = 1
    needs_attitude = False

    def __init__(self, config, layout, x0, primary: bool = True):
        super().__init__(config, layout, x0)
        self._projector = None
        if primary:
            N = rotation_directions(layout.R(x0), layout.size)
            self._projector = np.eye(layout.size) - N @ np.linalg.solve(N.T @ N, N.T)

    def _noise_sd(self, w) -> np.ndarray:
        """Standard deviation (k,) of the magnitude: ``sqrt(sensor^2 |w|^2 + reference^2)``, nT."""
        n = self.noise
        return np.sqrt(n.sensor_nt**2 * np.einsum("ki,ki->k", w, w) + n.reference_nt**2)

    def _linear(self, x, blk):
        """Magnitude ``h`` (k,), Jacobian (k, n) and noise sd (k,) at ``x``."""
        layout = self.layout
        h, H_core, w = magnitude_jacobian(layout.core_of(x), blk.m - blk.e)
        H = np.zeros((len(h), layout.size))
        H[:, layout.CORE] = H_core
        if layout.has_extra:
            H[:, layout.EXTRA] = -np.einsum("ki,kij->kj", w, blk.H[:, :, layout.EXTRA])
        return h, H, self._noise_sd(w)

    def linearise(self, x, blk):
        h, H, sd = self._linear(x, blk)
        if self._projector is not None:
            H = H @ self._projector
        return ((blk.ref_mag - h) / sd)[:, None], (H / sd[:, None])[:, None, :]

    def sigma_predict(self, sigmas, x, blk):
        """The whitened magnitude at each sigma point (S, k, 1). As the run's only measurement, a sigma point
        is taken less its step along the rotations of ``R`` (the projector of ``linearise``): a magnitude cannot
        see them, but a sigma point's step along one (a fraction of a radian while ``R``'s orientation is
        open) is no rotation to second order and shrinks the magnitude by about half its square (a percent of
        the field), which biased the predicted magnitude by hundreds of nT and taught the noise learner that
        much noise. The cross covariance still takes the whole step, as the EKF's gain does."""
        layout = self.layout
        if self._projector is not None:
            x = np.asarray(x, float)
            sigmas = x + (sigmas - x) @ self._projector  # the projector is symmetric
        mc = blk.m - blk.e
        if layout.has_extra:  # the other effects' terms move with the sigma points too
            mc = mc[None] - np.einsum(
                "kij,sj->ski", blk.H[:, :, layout.EXTRA], sigmas[:, layout.EXTRA] - np.asarray(x)[layout.EXTRA]
            )
        R, b = layout.R_b(sigmas)
        c = calibrated_field(R[:, None], b[:, None, :], mc)  # (S, k, 3): every sigma point's calibration
        _, H, sd = self._linear(x, blk)
        if self._projector is not None:  # the information it carries, as ``linearise`` gives it
            H = H @ self._projector
        h = np.linalg.norm(c, axis=2) / sd  # (S, k), whitened
        return h[..., None], (blk.ref_mag / sd)[:, None], (H / sd[:, None])[:, None, :]

    def batch_residuals(self, ref, c_nb, ref_mag):
        sigma = self._sigma_total()
        return lambda c: ((np.linalg.norm(c, axis=1) - ref_mag) / sigma)[:, None]


def nis_rows(model) -> tuple[int, int]:
    """The rows ``model`` (a ``MeasurementModel``, or its class) gives an epoch with attitude and one without
    (its fallback's, 1 when it has none, as a class has not; the model's own when it needs no attitude): the
    degrees of freedom of those epochs' NIS."""
    if not model.needs_attitude:
        return model.rows, model.rows
    fallback = getattr(model, "fallback", None)
    return model.rows, fallback.rows if fallback is not None else 1


# ---------------------------------------------------------------- registry
def register_measurement(cls: type[MeasurementModel]) -> type[MeasurementModel]:
    """Make a measurement model available by its ``name``; a decorator.

    The name is then known to ``FilterConfig(measure=...)`` and ``--measure``. The same as
    ``magkf.plugins.MEASUREMENTS.register(cls)``.

    Parameters
    ----------
    cls : type
        A subclass of ``MeasurementModel`` with a ``name``.

    Returns
    -------
    type
        ``cls``.

    Raises
    ------
    TypeError
        ``cls`` is not a ``MeasurementModel`` subclass.
    magkf.plugins.PluginError
        Its name is one of magkf's own models' or another's already registered.
    """
    if not (isinstance(cls, type) and issubclass(cls, MeasurementModel)):
        raise TypeError("a measurement model is a subclass of MeasurementModel")
    return MEASUREMENTS.register(cls, replace=True)


def measurement_model(config: FilterConfig, layout: StateLayout, x0) -> MeasurementModel:
    """The model ``config.measure`` names, for this layout and initial state."""
    try:
        cls = MEASUREMENTS[config.measure]
    except KeyError:
        raise ValueError(f"unknown measurement model {config.measure!r}; known: {', '.join(MEASUREMENTS)}") from None
    return cls(config, layout, x0)
