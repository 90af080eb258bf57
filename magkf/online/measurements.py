"""Measurement models of the online calibration, one class each: ``magnitude``, ``vector`` and ``both``.

A model is filter-neutral, as navlie's and Stone Soup's are: for a block of epochs it gives what it measures
(``measure``), what a state or a stack of states predicts (``predict``), the prediction's Jacobian
(``jacobian``) and the noise (``covariance``), and which epochs it can use (``needs_attitude``, and
``fallback``: the model for the epochs it cannot use). ``MeasurementModel`` declares these four as abstract
methods and gives every estimator its rows from them alone: the EKF's whitened innovation and Jacobian
(``linearise``), the UKF's whitened predictions at sigma points (``sigma_predict``), the batch solver's
normalised residuals (``batch_residuals``), the noise learner's innovations (``innovation``, split along the
field by ``along_across``) and the estimator's whitening (``whiten``). The built-in models override these
with faster forms of the same numbers (``tests/unit/test_model_equivalence.py`` compares them). The filters,
the estimator, the batch solver and the real-time path call these methods and never look at a model's name
or its number of rows; ``MEASUREMENTS`` maps a name to its class, and ``register_measurement`` adds one.

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

**Batch residuals of the built-in models.** The batch solver's objective for them is the patent's, in
terms of the calibrated field ``c``: the total-field residual ``|c| - |B_ref|`` and the NED residual
``C_nb c - B_ref`` (``vector``: all three components; ``both``: the two across the reference field), each
divided by a standard deviation of the same noise levels (``_sigma_total``, ``_sigma_cross``). These are
not the filter's rows whitened (another frame, and a diagonal noise), so ``batch_residuals`` of these models
is their own; a model that does not override it gets its filter rows whitened (``field_residuals`` is the
calibrated-field form's machinery).

Shapes: a block of k epochs; ``r`` rows per epoch (``Model.rows``); n states; S sigma points.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, replace

import numpy as np

from ..config import FilterConfig
from ..conventions import body_to_ned, calibrated_field, inverse3, ned_to_body
from ..effects.base import EpochData
from ..effects.core import core_jacobian
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
    "correlated_whitening",
    "field_residuals",
    "FIELD_STEP",
    "magnitude_jacobian",
    "rotation_directions",
]

_EYE = np.eye(3)


@dataclass
class Block:
    """k consecutive epochs as the models see them.

    ``m`` (k, 3) raw nT; ``ref_mag`` (k,) reference magnitude nT; ``H`` (k, 3, n) Jacobian of the linear
    blocks (``StateLayout.linear_jacobian``; None in the batch solver's blocks, made by the models that need
    it); ``B`` (k, 3) the reference field in the body frame and ``R`` (3, 3) the calibration at which the
    vector noise is evaluated; ``heading`` (k, 3) nT the heading axis ``B x down`` in the body frame
    (``heading_axis``); ``G`` (k, 3, 3) the tilt part of the vector noise per unit variance, ``Gh`` (k, 3, 3)
    the heading part and ``RRt`` (3, 3) the reference part, precomputed (``Vector.structure``; None to compute
    them from ``B``, ``heading`` and ``R``), ``frame`` (k, 3, r) the unit field in the sensor frame, the
    horizontal direction across it and the third, as rows in the model's r rows (``structure``; None for a
    model that needs no attitude); ``data`` the epochs' ``EpochData`` (needed by nonlinear effects); ``e``
    (k, 3) raw-field terms of the added effects at the current estimate (set by the estimator); ``W`` (k, r,
    r) the whitening of the model's rows at the current noise, with the residuals' correlation in time folded
    in (``MeasurementModel.whiten``, which the estimator calls; None: the model whitens its rows at the
    estimate); ``N`` (k, r, r) the covariance of the noise whitened by ``W`` as the gates see it (None: the
    identity); ``whitened_with`` the ``NoiseLevels`` that ``W`` and ``N`` were computed at (None: not yet
    whitened); ``magnitude`` (k,) the calibrated field's magnitude at the estimate, nT (set by the estimator
    with ``e``, for its magnitude gate; None: not known). ``G``, ``Gh``, ``RRt``, ``frame``, ``W`` and ``N``
    belong to the model the block was made for (``for_fallback`` clears them for its fallback).
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
    magnitude: np.ndarray | None = None

    def take(self, index) -> Block:
        """The same block at the epochs ``index`` (integer array or boolean mask)."""

        def cut(a):
            return a[index] if isinstance(a, np.ndarray) else a

        return Block(
            self.m[index],
            self.ref_mag[index],
            cut(self.H),
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
            cut(self.magnitude),
        )

    def for_fallback(self) -> Block:
        """The same epochs for the fallback model: without the noise structure and the whitening, which are the
        model's the block was made for."""
        return replace(self, G=None, Gh=None, RRt=None, frame=None, W=None, N=None)


#: The methods every measurement model implements (``MeasurementModel``'s abstract methods).
REQUIRED = ("measure", "predict", "jacobian", "covariance")


class MeasurementModel(abc.ABC):
    """Base class of a measurement model: subclass it, implement ``measure``, ``predict``, ``jacobian`` and
    ``covariance``, and ``register_measurement`` it.

    A model compares ``rows`` rows per epoch of what it measures with what a state predicts. From its four
    methods the base class gives every estimator its rows: ``linearise`` (EKF), ``sigma_predict`` (UKF),
    ``batch_residuals`` (batch solver), ``innovation`` and ``along_across`` (noise learner), ``whiten`` (the
    estimator's whitening of a span of blocks). Rows are whitened by the inverse Cholesky factor ``W = L^-1``
    of the covariance ``L L^T`` (``whitening``). A subclass may override any of these with a faster form of
    the same numbers, as the built-in models do.

    Parameters
    ----------
    config : FilterConfig
        The run's settings (the configured noise is the start of ``noise``).
    layout : StateLayout
        The state's blocks: ``R`` row-major and ``b`` (nT) first, then each effect's parameters.
    x0 : ndarray, shape (n,)
        The initial state.

    Attributes
    ----------
    name : str
        The name ``FilterConfig(measure=...)`` and ``--measure`` take.
    rows : int
        Rows per epoch, ``r``: the degrees of freedom of an epoch's NIS.
    needs_attitude : bool
        The model takes epochs with attitude only; ``fallback`` takes the others.
    needs_data : bool
        The model reads its blocks' ``EpochData`` (``Block.data``: attitude, the reference in NED, auxiliary
        channels), which the filters' blocks then carry (they carry it anyway for a nonlinear effect).
    linear : bool
        The rows are linear in the state, for every state; the UKF then takes them at the estimate through
        ``linearise``, as the EKF does (the unscented transform of a linear function is exact, so its sigma
        points would give the same).
    noise_depends_on_state : bool
        ``covariance`` changes with the state: the rows are then whitened at the estimate in every update
        (``whiten`` leaves ``Block.W`` None), and the residuals' correlation in time counts as the along-field
        inflation. False: the noise is whitened once for a span of blocks, the correlation folded in.
    fallback : MeasurementModel or None
        The model for the epochs this one cannot use (epochs without attitude).
    projector : ndarray, shape (n, n), or None
        The rows are taken blind to the state directions the (symmetric) projector removes: ``linearise``'s
        and ``sigma_predict``'s Jacobian is projected by it and sigma points move along them no more (an
        observability-constrained filter). None: every direction is seen.
    noise : NoiseLevels
        The noise levels ``covariance`` is evaluated at (``set_noise``).
    """

    name: str = "measurement"
    rows: int = 1
    needs_attitude: bool = False
    needs_data: bool = False
    linear: bool = False
    noise_depends_on_state: bool = False

    def __init__(self, config: FilterConfig, layout: StateLayout, x0):
        self.config, self.layout = config, layout
        self.fallback: MeasurementModel | None = None
        self.projector: np.ndarray | None = None
        self.noise = NoiseLevels(config.sensor_noise_nt, np.radians(config.attitude_deg), config.reference_nt)

    def set_noise(self, noise: NoiseLevels) -> None:
        """Use ``noise`` from now on (and in the fallback model)."""
        self.noise = noise
        if self.fallback is not None:
            self.fallback.set_noise(noise)

    # ------------------------------------------------------------ the model: implement these four
    @abc.abstractmethod
    def measure(self, blk: Block) -> np.ndarray:
        """What the model measures at the block's epochs.

        Parameters
        ----------
        blk : Block
            k epochs.

        Returns
        -------
        ndarray, shape (k, r)
            The measured rows, nT.
        """

    @abc.abstractmethod
    def predict(self, x, blk: Block) -> np.ndarray:
        """What a state, or each state of a stack, predicts of the measured rows.

        Parameters
        ----------
        x : ndarray, shape (n,) or (S, n)
            One state, or a stack of states (the UKF's sigma points).
        blk : Block
            k epochs.

        Returns
        -------
        ndarray, shape (k, r) or (S, k, r)
            The predicted rows, nT: (k, r) for one state, (S, k, r) for a stack.
        """

    @abc.abstractmethod
    def jacobian(self, x, blk: Block) -> np.ndarray:
        """The derivative of ``predict`` with respect to the state.

        Parameters
        ----------
        x : ndarray, shape (n,)
            The state.
        blk : Block
            k epochs.

        Returns
        -------
        ndarray, shape (k, r, n)
            ``d predict / d x`` at ``x``: nT per unit of each state.
        """

    @abc.abstractmethod
    def covariance(self, x, blk: Block) -> np.ndarray:
        """The noise covariance of the measured rows at the current noise levels (``noise``).

        Parameters
        ----------
        x : ndarray, shape (n,)
            The estimate. A model whose ``noise_depends_on_state`` is False may ignore it (the built-in vector
            models evaluate their noise at ``blk.R``, the calibration the block was prepared at).
        blk : Block
            k epochs.

        Returns
        -------
        ndarray, shape (k, r, r)
            Symmetric positive definite, nT^2.
        """

    # ------------------------------------------------------------ what the estimators use, from those four
    def structure(self, field_body, R, heading=None):
        """What the noise of epochs with body field ``field_body`` (N, 3) and heading axis ``heading`` (N, 3)
        at ``R`` (3, 3) is made of, computed once for each epoch: ``(G, Gh, RRt, frame)`` with ``frame`` (N, 3, r)
        the field's frame in the model's rows (``field_frame``: what the noise learner splits the innovations
        along, and the correlation in time is folded in along) and ``G``, ``Gh``, ``RRt`` what ``covariance``
        may use (None here); None for a model that needs no attitude. By default the rows are taken to be
        the field vector in the sensor axes (``sensor_frame``)."""
        if not self.needs_attitude:
            return None
        return None, None, None, sensor_frame(field_body, heading, R)

    def whitening(self, field_body, R) -> np.ndarray | None:
        """Whitening (k, 3, 3) of the epochs' vector noise at calibration ``R`` for the diagnostics (None: the
        model has none)."""
        return None

    def whiten(self, x, blk: Block, inflations=(1.0, 1.0, 1.0)) -> None:
        """Set ``blk.W``, the whitening of the block's rows at the current noise, and ``blk.N``, the covariance
        of the un-inflated noise in the whitened rows (None: the identity).

        Where the block has the field's frame (``structure``) and it spans the rows, the noise is inflated by
        ``inflations`` (along the field, ``h``, ``v``: the residuals' correlation in time, in epochs) along
        its rows (``correlated_whitening``); otherwise ``W`` is the plain whitening of ``covariance`` and
        ``N`` None. A model whose ``noise_depends_on_state`` leaves both None: ``linearise`` whitens its rows
        at the estimate.

        Parameters
        ----------
        x : ndarray, shape (n,)
            The estimate.
        blk : Block
            k epochs (a span of blocks), changed in place.
        inflations : tuple of 3 float
            Along the field, along ``h``, along ``v``; at least 1.
        """
        if self.noise_depends_on_state:
            blk.W = blk.N = None
            return
        cov = self.covariance(x, blk)
        if blk.frame is not None and blk.frame.shape[1:] == cov.shape[1:]:
            blk.W, blk.N = correlated_whitening(cov, blk.frame, inflations)
        else:
            blk.W, blk.N = whitening(cov), None

    def _whitening_at(self, x, blk: Block) -> np.ndarray:
        """The whitening (k, r, r) of the block's rows: ``blk.W`` where ``whiten`` set it, else the inverse
        Cholesky factor of ``covariance`` at ``x``."""
        return blk.W if blk.W is not None else whitening(self.covariance(x, blk))

    def linearise(self, x, blk: Block) -> tuple[np.ndarray, np.ndarray]:
        """The EKF's rows at state ``x`` (n,): the whitened innovation ``y = W (measure - predict)`` (k, r) and
        the whitened Jacobian ``W jacobian`` (k, r, n), projected by ``projector``."""
        W = self._whitening_at(x, blk)
        y = np.einsum("kij,kj->ki", W, self.measure(blk) - self.predict(x, blk))
        return y, self._seen_jacobian(x, blk, W)

    def sigma_predict(self, sigmas, x, blk: Block) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The UKF's rows: whitened predictions ``h`` (S, k, r) at ``sigmas`` (S, n), the whitened measurement
        ``z`` (k, r), and the whitened Jacobian (k, r, n) at the estimate ``x`` (n,) (the information the update
        carries), all whitened as ``linearise``'s. With a ``projector``, a sigma point is taken less its step
        along the directions the model cannot see."""
        x = np.asarray(x, float)
        W = self._whitening_at(x, blk)
        if self.projector is not None:
            sigmas = x + (sigmas - x) @ self.projector  # the projector is symmetric
        h = np.einsum("kij,skj->ski", W, self.predict(sigmas, blk))
        z = np.einsum("kij,kj->ki", W, self.measure(blk))
        return h, z, self._seen_jacobian(x, blk, W)

    def _seen_jacobian(self, x, blk: Block, W) -> np.ndarray:
        """The whitened Jacobian ``W jacobian`` (k, r, n) at ``x``, projected by ``projector``."""
        H = W @ self.jacobian(x, blk)
        return H if self.projector is None else H @ self.projector

    def batch_residuals(self, x, blk: Block, jacobian: bool = False, noise_at=None):
        """The batch solver's residuals: ``W (predict - measure)`` (k, q) at state ``x`` (n,), in units of their
        standard deviations, with ``W`` the whitening of ``covariance`` at ``noise_at`` (n,; default ``x``),
        held fixed; with ``jacobian``, ``(r, J)`` with ``J = W jacobian`` (k, q, n). Here ``q = r``; a model
        may give other residuals of the same epochs (the built-in ones do, ``field_residuals``). A block
        without the linear Jacobian (``blk.H`` None) has it made here."""
        if blk.H is None:
            blk = replace(blk, H=self.layout.linear_jacobian(blk.data))
        W = whitening(self.covariance(x if noise_at is None else noise_at, blk))
        r = np.einsum("kij,kj->ki", W, self.predict(x, blk) - self.measure(blk))
        return (r, W @ self.jacobian(x, blk)) if jacobian else r

    def innovation(self, x, blk: Block) -> np.ndarray:
        """``measure - predict`` (k, r) at the estimate ``x`` (n,), nT, as the noise learner takes it (before
        whitening). The estimator has put the effects' terms at ``x`` in ``blk.e``, which an override may
        use instead of computing them again."""
        return self.measure(blk) - self.predict(x, blk)

    def along_across(self, innovation, frame=None) -> tuple[np.ndarray, np.ndarray | None]:
        """The innovations split as the noise learner takes them.

        Parameters
        ----------
        innovation : ndarray, shape (k, r)
            ``innovation``'s, nT.
        frame : ndarray, shape (k, 3, r), or None
            The field's frame in the rows (``structure``'s; None where the model has none).

        Returns
        -------
        along : ndarray, shape (k,)
            Along the field, nT.
        across : ndarray, shape (k, 2), or None
            Along ``h`` and ``v``, nT; None where the rows do not see across the field.

        Raises
        ------
        NotImplementedError
            A model of several rows without a frame in them (``structure``'s default frame is of the three rows
            of the sensor-frame vector): override this, or ``structure``, to say how its rows split.
        """
        rows = innovation.shape[1]
        if frame is not None and frame.shape[2] == rows:
            parts = (frame @ innovation[:, :, None])[:, :, 0]
            return parts[:, 0], parts[:, 1:]
        if rows != 1:
            raise NotImplementedError(
                f"measurement model {self.name!r}: {rows} rows without the field's frame in them "
                "(give structure a frame of its rows, or override along_across)"
            )
        return innovation[:, 0], None

    # Noise of the built-in models' batch residuals: the filter's levels.
    def _sigma_total(self) -> float:
        return float(np.sqrt(self.noise.along_var))

    def _sigma_cross(self, ref_mag) -> np.ndarray:
        attitude = max(self.noise.attitude_rad, self.noise.heading)
        return np.sqrt(self.noise.along_var + (attitude * ref_mag) ** 2)


def correlated_whitening(cov, frame, inflations) -> tuple[np.ndarray, np.ndarray]:
    """The whitening ``W`` (k, 3, 3) of noise of covariance ``cov`` (k, 3, 3) inflated by ``inflations``
    (along the field, ``h``, ``v``) along the rows of ``frame`` (k, 3, 3: the field's direction, the heading
    axis and the third, in the model's rows; ``field_frame``), and ``N = W cov W^T`` (k, 3, 3), the covariance
    of the un-inflated noise in the whitened rows.

    With ``M = frame cov frame^T`` the noise in the field's frame and ``D`` the inflations' square roots:
    ``W = chol(D M D)^-1 frame`` (``whitening``).
    """
    d = np.sqrt(np.asarray(inflations, float))
    if len(cov) == 1:  # one epoch (real time): plain 3x3 products cost less than stacked ones
        c, f = cov[0], frame[0]
        W = whitening(((f @ c @ f.T) * d[:, None] * d[None, :])[None])[0] @ f
        return W[None], (W @ c @ W.T)[None]
    M = frame @ cov @ np.swapaxes(frame, 1, 2)
    W = whitening(M * d[:, None] * d[None, :]) @ frame
    return W, W @ cov @ np.swapaxes(W, 1, 2)


#: Central-difference step of ``field_residuals``' functions in the calibrated field, relative to its length.
FIELD_STEP = 1e-4


def field_residuals(layout: StateLayout, x, blk: Block, f, jacobian: bool = False):
    """Residuals given as a function of each epoch's calibrated field, and their Jacobian in the state.

    Parameters
    ----------
    layout : StateLayout
        The state's blocks.
    x : ndarray, shape (n,)
        The state.
    blk : Block
        k epochs, with their ``EpochData`` (``blk.data``: the effects' inputs).
    f : callable
        ``f(c) -> (k, q)``: the residuals, in units of their standard deviations, of calibrated fields ``c``
        (k, 3) nT, each epoch's from its own field.
    jacobian : bool
        Also give the Jacobian.

    Returns
    -------
    r : ndarray, shape (k, q)
        ``f(c)`` at ``c = R^-1 (m - b - e)`` of ``x`` (missing effect inputs count as 0).
    J : ndarray, shape (k, q, n)
        With ``jacobian``: ``dr/dx = dr/dc dc/dx``, with ``dr/dc`` three central differences of ``f`` (step
        ``FIELD_STEP`` of the field's length) and ``dc/dx = -R^-1 dm/dx`` analytic (``core_jacobian(c)`` for
        ``R`` and ``b``, the effects' own ``jacobian`` for theirs).
    """
    data = blk.data if layout.has_extra else None
    terms = 0.0 if data is None else layout.effect_terms(x, data)
    c = layout.calibrated(x, blk.m, terms)
    r = f(c)
    if not jacobian:
        return r
    # dr/dc (k, q, 3): each epoch's residuals are a function of its own calibrated field
    h = FIELD_STEP * np.maximum(np.linalg.norm(c, axis=1), 1.0)
    drdc = np.empty(r.shape + (3,))
    for a in range(3):
        shifted = c.copy()
        shifted[:, a] += h
        up = f(shifted)
        shifted[:, a] -= 2 * h
        drdc[:, :, a] = (up - f(shifted)) / (2 * h[:, None])
    # dc/dx = -R^-1 dm/dx with m = R c + b + e(x): the core's Jacobian at c, the effects' their own
    if data is None:
        dmdx = core_jacobian(c)
    else:
        dmdx = np.nan_to_num(layout.jacobian(x, data))  # missing inputs count as 0, as in effect_terms
        dmdx[:, :, layout.CORE] = core_jacobian(c)
    dcdx = -(inverse3(layout.R(x)) @ dmdx)
    return r, drdc @ dcdx


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
    """``W = L^-1`` (N, r, r) with ``noise = L L^T`` (N, r, r), nT^-1 for noise in nT^2: ``W y`` has unit,
    uncorrelated noise. Raises ``numpy.linalg.LinAlgError`` where a covariance is not positive definite."""
    if noise.shape[1:] == (3, 3):
        if len(noise) == 1:  # one epoch (real time): the 3x3 algebra written out beats numpy's call overhead
            return _whitening3(noise[0])[None]
        W = _whitening_stack(noise)
        if W is not None:
            return W
    elif noise.shape[1:] == (1, 1) and (noise > 0).all():
        return 1.0 / np.sqrt(noise)
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

    def __init__(self, config, layout, x0):
        super().__init__(config, layout, x0)
        self._fast = _keeps_model(self, Vector)

    @property
    def linear(self) -> bool:
        """Linear in the state unless the layout holds a nonlinear effect (a time lag), or a subclass predicts
        its rows in its own way."""
        own = type(self).sigma_predict is Vector.sigma_predict and type(self).linearise is Vector.linearise
        return own and self._fast and not self.layout.nonlinear

    # ------------------------------------------------------------ the model
    def measure(self, blk):
        """The raw reading ``m`` (k, 3), nT in the sensor axes."""
        return blk.m

    def predict(self, x, blk):
        """``R C_nb^T B_ref + b + e`` (k, 3), or (S, k, 3) for a stack of states (S, n): the linear blocks'
        Jacobian times the state, and the nonlinear effects' terms, nT."""
        x = np.asarray(x, float)
        h = blk.H @ x if x.ndim == 1 else np.tensordot(x, blk.H, axes=([1], [2]))
        if self.layout.nonlinear:
            h = h + self.layout.nonlinear_terms(x, blk.data)
        return h

    def jacobian(self, x, blk):
        """(k, 3, n): the linear blocks' Jacobian with the nonlinear effects' filled in at ``x``."""
        return self.layout.jacobian(x, blk.data, blk.H)

    def covariance(self, x, blk):
        """The sensor-frame noise (k, 3, 3) at ``blk.R`` (``compose_noise`` of the block's structure, or
        ``vector_noise``), nT^2; the same for every state."""
        if blk.G is None:
            return vector_noise(blk.B, blk.R, self.noise, self.field_aligned, blk.heading)
        return compose_noise(self.noise, blk.G, blk.Gh, blk.RRt)

    # ------------------------------------------------------------ the same numbers, faster
    def structure(self, field_body, R, heading=None):
        B = np.asarray(field_body, float)
        if len(B) == 1:  # one epoch (real time): the same products on vectors, and the frame in plain floats
            return _structure1(B[0], np.asarray(R, float), None if heading is None else heading[0], self.field_aligned)
        Gh = None if heading is None else heading_structure(heading, R)
        return attitude_structure(B, R, self.field_aligned), Gh, R @ R.T, sensor_frame(B, heading, R)

    def whitening(self, field_body, R, heading=None):
        return whitening(vector_noise(field_body, R, self.noise, self.field_aligned, heading))

    def linearise(self, x, blk):
        if not self._fast:
            return super().linearise(x, blk)
        h = blk.H @ x
        if self.layout.nonlinear:
            h = h + self.layout.nonlinear_terms(x, blk.data)
        y = (blk.W @ (blk.m - h)[:, :, None])[:, :, 0]
        return y, blk.W @ self.jacobian(x, blk)

    def sigma_predict(self, sigmas, x, blk):
        if not self._fast:
            return super().sigma_predict(sigmas, x, blk)
        WH = blk.W @ blk.H
        h = np.tensordot(sigmas, WH, axes=([1], [2]))  # (S, k, 3)
        if self.layout.nonlinear:
            h = h + np.einsum("kij,skj->ski", blk.W, self.layout.nonlinear_terms(sigmas, blk.data))
        z = np.einsum("kij,kj->ki", blk.W, blk.m)
        return h, z, blk.W @ self.jacobian(x, blk)

    def innovation(self, x, blk):
        if not self._fast:
            return super().innovation(x, blk)
        e = blk.m - blk.H @ x
        if self.layout.nonlinear:  # their terms (in ``blk.e``), which the linear Jacobian's zero columns leave out
            extra = self.layout.EXTRA
            e = e - (blk.e - blk.H[:, :, extra] @ x[extra])
        return e

    # ------------------------------------------------------------ the batch solver's own residuals
    def batch_residuals(self, x, blk, jacobian=False, noise_at=None):
        """The NED residuals ``(C_nb c - B_ref) / sigma`` (k, 3) of the calibrated field ``c`` at ``x``, with
        ``sigma`` the cross-field standard deviation (``_sigma_cross``), and their Jacobian (``field_residuals``).
        ``noise_at`` is not used: the noise does not depend on the state."""
        return field_residuals(self.layout, x, blk, self.field_function(blk), jacobian)

    def field_function(self, blk):
        """``f(c) -> (k, q)``: the batch residuals of calibrated fields ``c`` (k, 3) nT at the block's epochs."""
        ref, c_nb = blk.data.field_ned, np.asarray(blk.data.c_nb)  # made once: f is called several times
        sigma = self._sigma_cross(blk.ref_mag)[:, None]
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

    def field_function(self, blk):
        """The total-field residual (``Magnitude.field_function``) and the NED residual's two components across
        the reference field, along ``h`` and ``v`` (``field_frame``), each over its standard deviation."""
        total = self.fallback.field_function(blk)
        ref, c_nb, ref_mag = blk.data.field_ned, np.asarray(blk.data.c_nb), blk.ref_mag  # made once
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
    initial ``R`` (``projector``: no magnitude can see them); False when it serves as another model's fallback.
    """

    name = "magnitude"
    rows = 1
    needs_attitude = False
    noise_depends_on_state = True

    def __init__(self, config, layout, x0, primary: bool = True):
        super().__init__(config, layout, x0)
        if primary:
            N = rotation_directions(layout.R(x0), layout.size)
            self.projector = np.eye(layout.size) - N @ np.linalg.solve(N.T @ N, N.T)
        self._fast = _keeps_model(self, Magnitude)

    # ------------------------------------------------------------ the model
    def measure(self, blk):
        """The reference's magnitude ``|B_ref|`` (k, 1), nT."""
        return blk.ref_mag[:, None]

    def predict(self, x, blk):
        """The calibrated magnitude ``|R^-1 (m - b - e)|`` (k, 1), or (S, k, 1) for a stack of states (S, n), nT;
        the effects' terms ``e`` at each state (``_terms``)."""
        x = np.asarray(x, float)
        R, b = self.layout.R_b(x)
        e = self._terms(x, blk)
        if x.ndim == 1:
            return np.linalg.norm(calibrated_field(R, b, blk.m, e), axis=1)[:, None]
        c = calibrated_field(R[:, None], b[:, None, :], blk.m - e)  # (S, k, 3): every state's calibration
        return np.linalg.norm(c, axis=2)[..., None]

    def jacobian(self, x, blk):
        """(k, 1, n): ``-w_i c_j`` for ``R_ij``, ``-w`` for ``b`` and ``-w^T de/dtheta`` for an effect's
        parameters, with ``c`` the calibrated field and ``w = u^T R^-1`` (``magnitude_jacobian``)."""
        layout = self.layout
        h, H_core, w = magnitude_jacobian(layout.core_of(x), blk.m - self._terms(x, blk))
        H = np.zeros((len(h), layout.size))
        H[:, layout.CORE] = H_core
        if layout.has_extra:
            H[:, layout.EXTRA] = -np.einsum("ki,kij->kj", w, self._terms_jacobian(x, blk))
        return H[:, None, :]

    def covariance(self, x, blk):
        """``sensor^2 |w|^2 + reference^2`` (k, 1, 1) at ``x``, nT^2: the sensor's noise through ``R^-1`` along
        the calibrated field."""
        _, _, w = magnitude_jacobian(self.layout.core_of(x), blk.m - self._terms(x, blk))
        return self._noise_var(w)[:, None, None]

    def _terms(self, x, blk):
        """The effects' raw-field terms (k, 3), or (S, k, 3) for a stack of states, nT; 0 without effects.
        Missing inputs count as 0, as in the estimator's ``blk.e``."""
        layout = self.layout
        if not layout.has_extra:
            return 0.0
        if np.ndim(x) == 1:
            return np.nan_to_num(layout.extra_terms(x, blk.H, blk.data))
        e = np.einsum("kij,sj->ski", blk.H[:, :, layout.EXTRA], x[:, layout.EXTRA])
        if layout.nonlinear:
            e = e + layout.nonlinear_terms(x, blk.data)
        return np.nan_to_num(e)

    def _terms_jacobian(self, x, blk) -> np.ndarray:
        """``de/dtheta`` (k, 3, n - 12) of the effects after the core at ``x`` (missing inputs: 0)."""
        layout = self.layout
        if not layout.nonlinear:
            return blk.H[:, :, layout.EXTRA]
        return np.nan_to_num(layout.jacobian(x, blk.data, blk.H)[:, :, layout.EXTRA])

    def _noise_var(self, w) -> np.ndarray:
        """Variance (k,) of the magnitude: ``sensor^2 |w|^2 + reference^2``, nT^2."""
        n = self.noise
        return n.sensor_nt**2 * np.einsum("ki,ki->k", w, w) + n.reference_nt**2

    # ------------------------------------------------------------ the same numbers, faster
    def _linear(self, x, blk):
        """Magnitude ``h`` (k,), Jacobian (k, n) and noise sd (k,) at the estimate ``x`` (the effects' terms
        from ``blk.e``)."""
        layout = self.layout
        h, H_core, w = magnitude_jacobian(layout.core_of(x), blk.m - blk.e)
        H = np.zeros((len(h), layout.size))
        H[:, layout.CORE] = H_core
        if layout.has_extra:
            H[:, layout.EXTRA] = -np.einsum("ki,kij->kj", w, self._terms_jacobian(x, blk))
        return h, H, np.sqrt(self._noise_var(w))

    def linearise(self, x, blk):
        if not self._fast:
            return super().linearise(x, blk)
        h, H, sd = self._linear(x, blk)
        if self.projector is not None:
            H = H @ self.projector
        return ((blk.ref_mag - h) / sd)[:, None], (H / sd[:, None])[:, None, :]

    def sigma_predict(self, sigmas, x, blk):
        """The whitened magnitude at each sigma point (S, k, 1). As the run's only measurement, a sigma point
        is taken less its step along the rotations of ``R`` (the projector of ``linearise``): a magnitude cannot
        see them, but a sigma point's step along one (a fraction of a radian while ``R``'s orientation is
        open) is no rotation to second order and shrinks the magnitude by about half its square (a percent of
        the field), which biased the predicted magnitude by hundreds of nT and taught the noise learner that
        much noise. The cross covariance still takes the whole step, as the EKF's gain does."""
        if not self._fast:
            return super().sigma_predict(sigmas, x, blk)
        layout = self.layout
        if self.projector is not None:
            x = np.asarray(x, float)
            sigmas = x + (sigmas - x) @ self.projector  # the projector is symmetric
        mc = blk.m - blk.e
        if layout.nonlinear:  # every effect's terms at each sigma point
            mc = blk.m - self._terms(sigmas, blk)
        elif layout.has_extra:  # the other effects' terms move with the sigma points too
            mc = mc[None] - np.einsum(
                "kij,sj->ski", blk.H[:, :, layout.EXTRA], sigmas[:, layout.EXTRA] - np.asarray(x)[layout.EXTRA]
            )
        R, b = layout.R_b(sigmas)
        c = calibrated_field(R[:, None], b[:, None, :], mc)  # (S, k, 3): every sigma point's calibration
        _, H, sd = self._linear(x, blk)
        if self.projector is not None:  # the information it carries, as ``linearise`` gives it
            H = H @ self.projector
        h = np.linalg.norm(c, axis=2) / sd  # (S, k), whitened
        return h[..., None], (blk.ref_mag / sd)[:, None], (H / sd[:, None])[:, None, :]

    def innovation(self, x, blk):
        if not self._fast:
            return super().innovation(x, blk)
        h = blk.magnitude  # the estimator's, at x
        if h is None:
            h = np.linalg.norm(self.layout.calibrated(x, blk.m, blk.e), axis=1)
        return (blk.ref_mag - h)[:, None]

    # ------------------------------------------------------------ the batch solver's own residuals
    def batch_residuals(self, x, blk, jacobian=False, noise_at=None):
        """The total-field residual ``(|c| - |B_ref|) / sigma`` (k, 1) of the calibrated field ``c`` at ``x``,
        with ``sigma`` the along-field standard deviation (``_sigma_total``), and its Jacobian
        (``field_residuals``). ``noise_at`` is not used."""
        return field_residuals(self.layout, x, blk, self.field_function(blk), jacobian)

    def field_function(self, blk):
        """``f(c) -> (k, 1)``: the batch residual of calibrated fields ``c`` (k, 3) nT at the block's epochs."""
        sigma, ref_mag = self._sigma_total(), blk.ref_mag
        return lambda c: ((np.linalg.norm(c, axis=1) - ref_mag) / sigma)[:, None]


def _keeps_model(model: MeasurementModel, cls: type) -> bool:
    """Whether ``model``'s class keeps ``cls``'s four model methods (``REQUIRED``): ``cls``'s faster forms of the
    estimators' rows hold only then, and a subclass that predicts in its own way gets the generic ones."""
    own = type(model)
    return all(getattr(own, name) is getattr(cls, name) for name in REQUIRED)


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
    ``magkf.plugins.MEASUREMENTS.register(cls, replace=True)``: it takes the place of an earlier
    registration of that name (a model being redefined), never of magkf's own.

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
        Its name is one of magkf's own models'.
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
