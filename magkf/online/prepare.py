"""Per-log work done once and vectorised, per-epoch work of a stream, and the start of a run.

``prepare`` evaluates, for every epoch of a ``DriveLog``, the reference field (IGRF or ``ref_*``), the attitude
matrices, the body-frame reference and its rate, and the statuses known before filtering (the epoch rules of
``magkf.status.epoch_status``; ``prepare_arrays``, the same from the epochs' arrays); ``prepare_epoch`` does the
same for one sample of a stream (the real-time step), ``prepare_samples`` for a burst of them
(``OnlineCalibrator.step_block``). ``prepare_run`` gives the start of a run over a log, for the whole-log filter,
the chunked filter and the batch solver alike: the statuses with the effects' missing channels
(``mark_missing_columns``), the state layout and the initial estimate (``initial_state``: from an offline
calibration, or bootstrapped from the log itself), the measurement model and the starting noise (``start_noise``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from ..calibration import Calibration
from ..config import FilterConfig
from ..conventions import ATTITUDE, MAG, TIME, AttitudeMatrices, calibrated_field, epochs_of, euler_to_dcm, ned_to_body
from ..effects.base import EpochData, rate_of_change
from ..effects.core import SoftHardIron
from ..errors import InputError
from ..io.drivelog import DriveLog
from ..status import MISSING_ATTITUDE, MISSING_COLUMN, USED, Status, epoch_status, first_dop, select_dop
from .bootstrap import PRIOR_B_STD, PRIOR_R_STD, bootstrap_magnitude, bootstrap_vector
from .determined import WANDER_BLOCK_S, held_directions, whitened_gram
from .estimator import Estimator, run_model
from .measurements import MEASUREMENTS, Block, MeasurementModel, heading_axis, sensor_frame
from .noise import NoiseLevels, robust_start
from .state import CORE_SIZE, StateLayout

__all__ = [
    "PreparedLog",
    "prepare",
    "prepare_arrays",
    "body_arrays",
    "field_rates",
    "prepare_samples",
    "PreparedEpoch",
    "prepare_epoch",
    "concat_prepared",
    "RunSetup",
    "prepare_run",
    "initial_state",
    "initial_covariance",
    "with_initial_R",
    "without_rates",
    "calibration_start",
    "start_noise",
    "deflate_bootstrap",
    "robust_linear_fit",
]


@dataclass(frozen=True)
class PreparedLog:
    """Per-epoch arrays of a log, computed once: ``m`` (N, 3) nT, ``ref`` (N, 3) NED nT, ``ref_mag`` (N,),
    ``c_nb`` (N, 3, 3) (``prepare``'s an ``AttitudeMatrices``: made from the attitude when read),
    ``has_attitude`` (N,), ``dop`` (N,), ``base`` (N,) status before filtering (codes of ``magkf.status.Status``),
    ``data`` (``EpochData`` for the effects and the models) and ``heading`` (N, 3) nT the heading axis in the
    body frame (``measurements.heading_axis``; zero without attitude; None once a run no longer needs it)."""

    m: np.ndarray
    ref: np.ndarray
    ref_mag: np.ndarray
    c_nb: np.ndarray
    has_attitude: np.ndarray
    dop: np.ndarray
    base: np.ndarray
    data: EpochData
    heading: np.ndarray

    def __len__(self) -> int:
        return len(self.m)

    @property
    def time(self) -> np.ndarray:
        """(N,) UNIX seconds."""
        return self.data.time

    def take(self, index) -> PreparedLog:
        """The same arrays at the epochs ``index`` (a slice gives views; attitude matrices made when read stay so)."""
        return PreparedLog(
            self.m[index],
            self.ref[index],
            self.ref_mag[index],
            epochs_of(self.c_nb, index),
            self.has_attitude[index],
            self.dop[index],
            self.base[index],
            self.data.take(index, lazy=True),
            None if self.heading is None else self.heading[index],
        )

    def block(self, index, layout: StateLayout, model, R, with_data: bool = False) -> Block:
        """The epochs ``index`` (slice, integer array or mask) as a ``Block`` for the measurement ``model``: their
        linear Jacobian (``layout.linear_jacobian``) and noise structure (``model.structure``) at the
        calibration ``R`` (3, 3), computed for these epochs only (a long log is never held whole in them);
        ``with_data`` keeps the epochs' ``EpochData`` (for nonlinear effects). Needs the heading axis (a
        ``PreparedLog`` whose ``heading`` was let go cannot make blocks)."""
        # the matrices made once for the block where the model or the effects read them
        data = self.data.take(index, lazy=not (with_data or layout.has_extra))
        heading = self.heading[index]
        structure = model.structure(np.nan_to_num(data.field_body), R, heading)
        G, Gh, RRt, frame = structure if structure is not None else (None, None, None, None)
        return Block(
            self.m[index],
            self.ref_mag[index],
            layout.linear_jacobian(data),
            data.field_body,
            R,
            heading,
            G,
            Gh,
            RRt,
            frame,
            data if with_data else None,
        )

    def frame(self, index, R) -> np.ndarray:
        """The field's frame (k, 3, 3) in the sensor axes at the epochs ``index`` at calibration ``R``
        (``measurements.sensor_frame``); needs the heading axis, as ``block`` does."""
        return sensor_frame(np.nan_to_num(self.data.field_body[index]), self.heading[index], R)


def _joined(values):
    """The arrays ``values`` (one per piece) end to end, or None when the pieces hold none (the first says);
    attitude matrices made when read stay so."""
    values = list(values)
    if values[0] is None:
        return None
    if all(isinstance(v, AttitudeMatrices) for v in values):
        return AttitudeMatrices(np.concatenate([v.attitude for v in values]))
    return np.concatenate(values)


def concat_prepared(parts) -> PreparedLog:
    """The epochs of the ``PreparedLog`` s ``parts`` (consecutive pieces of one log, with the same columns and
    ``R0``) as one."""
    parts = list(parts)
    d = [p.data for p in parts]
    data = EpochData(
        *(_joined(getattr(x, f) for x in d) for f in ("time", "field_body", "field_ned")),
        {c: np.concatenate([x.columns[c] for x in d]) for c in d[0].columns},
        *(_joined(getattr(x, f) for x in d) for f in ("mag", "c_nb", "field_body_rate")),
        d[0].R0,
        _joined(x.field_body_accel for x in d),
    )
    fields = ("m", "ref", "ref_mag", "c_nb", "has_attitude", "dop", "base")
    return PreparedLog(
        *(_joined(getattr(p, f) for p in parts) for f in fields), data, _joined(p.heading for p in parts)
    )


def prepare(log: DriveLog, config: FilterConfig, rates: bool = True) -> PreparedLog:
    """Reference field, attitude and the statuses known before filtering, for every epoch; without ``rates``, not
    the field's rates (``EpochData.field_body_rate`` and ``field_body_accel`` None: 48 bytes an epoch that only
    added effects read)."""
    ref = reference_field(log, config)
    columns = {c: log.column(c) for c in log.auxiliary}
    return prepare_arrays(log.time, log.mag, ref, log.attitude_columns, log.dop, columns, config, rates=rates)


def prepare_arrays(
    t, m, ref, attitude, dop, columns: dict, config: FilterConfig, previous=None, R0=None, rates: bool = True
) -> PreparedLog:
    """The epochs given as arrays, prepared by the epoch rules (``prepare`` of a log, ``prepare_samples`` of a
    stream's samples).

    Parameters
    ----------
    t : ndarray
        (N,) UNIX s.
    m : ndarray
        (N, 3) raw magnetometer, nT.
    ref : ndarray
        (N, 3) the reference field, NED nT (NaN where unknown).
    attitude : ndarray or ColumnStack
        (N, 3) roll, pitch, yaw, deg (NaN where missing); a ``conventions.ColumnStack`` of a log's columns is held as
        it is (``AttitudeMatrices``) and read a chunk at a time.
    dop : ndarray
        (N,) the dilution of precision gated (NaN where not logged).
    columns : dict
        The auxiliary channels by name, (N,) each.
    config : FilterConfig
        Gives ``dop_max``.
    previous : tuple or None
        None: a whole log, the body-frame field's rate and acceleration by central differences
        (``rate_of_change``). ``(time, field_body)`` of a stream's epoch before these (UNIX s, (3,) nT, or None
        for the stream's first): the rate by backward differences from it, as a stream knows it (no
        acceleration), zero where it cannot be taken.
    R0 : ndarray or None
        (3, 3) the calibration the effects' data carry (``EpochData.R0``; None: the identity).
    rates : bool
        Whether to compute the field's rates (False: None, for a run without added effects).

    Returns
    -------
    PreparedLog
    """
    has_att = attitude_known(attitude)
    c_nb = AttitudeMatrices(attitude)
    field_body, heading = body_fields(attitude, ref)
    base = epoch_status(m, ref, has_att, dop, config.dop_max)
    ref_mag = np.linalg.norm(ref, axis=1)
    if not rates:
        rate, accel = None, None
    elif previous is None:
        rate, accel = field_rates(t, field_body)
    else:
        rate, accel = _backward_rates(t, field_body, previous), None
    data = EpochData(
        t, field_body, ref, columns, mag=m, c_nb=c_nb, field_body_rate=rate, field_body_accel=accel,
        R0=np.eye(3) if R0 is None else R0,
    )  # fmt: skip
    return PreparedLog(m, ref, ref_mag, c_nb, has_att, dop, base, data, heading)


def attitude_known(attitude) -> np.ndarray:
    """Mask (N,) of the epochs whose ``attitude`` (N, 3) roll, pitch, yaw (an array or a ``ColumnStack``) is known
    (every angle finite), read a chunk at a time (a ``ColumnStack`` is not copied whole)."""
    known = np.empty(len(attitude), bool)
    for a in range(0, len(attitude), CHUNK):
        known[a : a + CHUNK] = np.all(np.isfinite(attitude[a : a + CHUNK]), axis=1)
    return known


def reference_field(log: DriveLog, config: FilterConfig) -> np.ndarray:
    """The reference field (N, 3) NED nT of every epoch of ``log``, as ``prepare`` takes it: the log's own, else
    IGRF refreshed every ``config.reference_refresh_m``."""
    return log.reference_ned(knot_spacing_m=config.reference_refresh_m)


#: Epochs up to which a diagnosis holds the log's reference field as an array (24 bytes an epoch); a longer log's is
#: made for the rows each pass reads (``reference_track``). On the 1-hour 100 Hz log (360 000 epochs) making it so on
#: each of the diagnosis's 40-odd passes took a fifth more time (8.6 s of 41.5 s) and did not lower its peak, which
#: lies in the run it starts from; on four hours it saves 33 MB of the candidates' tests' peak, which is then the
#: highest.
REFERENCE_HELD_EPOCHS = 1_000_000


def reference_track(log: DriveLog, config: FilterConfig, prep: PreparedLog | None = None):
    """``reference_field(log, config)`` as a diagnosis reads it, ``track[rows]`` (k, 3) NED nT: for a log of up to
    ``REFERENCE_HELD_EPOCHS`` epochs an array (that of its prepared arrays ``prep``, ``prep.ref`` itself, or made
    here without ``prep``), else made for the epochs asked when read (``DriveLog.reference_track``)."""
    if len(log.table) <= REFERENCE_HELD_EPOCHS:
        return reference_field(log, config) if prep is None else prep.ref
    return log.reference_track(knot_spacing_m=config.reference_refresh_m)


def attitude_matrices(attitude: np.ndarray) -> np.ndarray:
    """The attitude matrices ``C_nb`` (N, 3, 3), body FRD to NED, of ``attitude`` (N, 3) roll, pitch, yaw deg (NaN
    where it is missing)."""
    return euler_to_dcm(attitude[:, 2], attitude[:, 1], attitude[:, 0])


def body_arrays(attitude: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(c_nb, field_body, heading)`` of epochs with ``attitude`` (N, 3) roll, pitch, yaw deg and reference field
    ``ref`` (N, 3) NED nT: the attitude matrices (N, 3, 3), the reference field in the body frame (N, 3) nT and the
    heading axis in the body frame (N, 3) (``measurements.heading_axis``; zero without attitude)."""
    c_nb = attitude_matrices(attitude)
    return c_nb, ned_to_body(c_nb, ref), np.nan_to_num(heading_axis(c_nb, ref))


def body_fields(attitude: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(field_body, heading)`` (N, 3) nT each of ``body_arrays``, made ``CHUNK`` epochs at a time: the attitude
    matrices and the working arrays are a chunk's, not the log's."""
    n = len(ref)
    field_body, heading = np.empty((n, 3)), np.empty((n, 3))
    for a in range(0, n, CHUNK):
        at = slice(a, a + CHUNK)
        _, field_body[at], heading[at] = body_arrays(attitude[at], ref[at])
    return field_body, heading


def field_rates(t: np.ndarray, field_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rate, accel)`` (N, 3) nT/s and nT/s^2 of the body-frame field (N, 3) nT at ``t`` (N,) s, by central
    differences over a whole log (``effects.base.rate_of_change``)."""
    rate = rate_of_change(t, field_body)
    return rate, rate_of_change(t, rate)


def prepare_samples(columns: dict, refs, config: FilterConfig, channels=(), previous=None, R0=None) -> PreparedLog:
    """A stream's consecutive samples prepared together, by the rules ``prepare_epoch`` applies to each (and
    ``missing_column`` where an effect's channel is empty).

    Parameters
    ----------
    columns : dict
        The samples' values by column name, (N,) each (``io.drivelog.read_samples``): ``time`` (UNIX s, in
        order), ``mag_*`` (nT), ``roll, pitch, yaw`` (deg), ``dop``, ``pdop``, ``hdop`` and ``channels``.
    refs : ndarray
        (N, 3) NED nT the reference field at the samples (NaN where unknown).
    config : FilterConfig
        Gives ``dop_max``.
    channels : tuple of str
        The auxiliary channels the effects need.
    previous : tuple or None
        ``(time, field_body)`` of the stream's epoch before these (see ``prepare_arrays``), or None for the
        stream's first.
    R0 : ndarray or None
        (3, 3) the calibration the effects' data carry.

    Returns
    -------
    PreparedLog
    """
    m = np.column_stack([columns[c] for c in MAG])
    attitude = np.column_stack([columns[c] for c in ATTITUDE])
    attitude[~np.isfinite(attitude).all(axis=1)] = np.nan  # a partial attitude is none (as ``prepare_epoch``)
    aux = {c: columns[c] for c in channels}
    dop = select_dop(columns)
    prep = prepare_arrays(
        columns[TIME], m, np.asarray(refs, float), attitude, np.full(len(m), np.nan) if dop is None else dop, aux,
        config, previous or (math.nan, None), R0,
    )  # fmt: skip
    if aux:
        updating = (prep.base == USED) | (prep.base == MISSING_ATTITUDE)
        missing = ~np.all([np.isfinite(a) for a in aux.values()], axis=0)
        prep.base[updating & missing] = MISSING_COLUMN
    return prep


def _backward_rates(t, field_body, previous) -> np.ndarray:
    """(N, 3) nT/s the rate of ``field_body`` (N, 3) at ``t`` (N,) s by backward differences, the first from
    ``previous`` (``(time, field_body)``; its field None for none): zero where it cannot be taken."""
    before_t, before = previous
    t0 = np.concatenate([[before_t], t[:-1]])
    f0 = np.concatenate(
        [np.full((1, 3), np.nan) if before is None else np.asarray(before, float)[None], field_body[:-1]]
    )
    dt = (t - t0)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(dt > 0, (field_body - f0) / np.where(dt > 0, dt, 1.0), 0.0)
    rate[~np.isfinite(rate).all(axis=1)] = 0.0
    return rate


_NAN33 = np.full((3, 3), np.nan)


@dataclass(frozen=True)
class PreparedEpoch:
    """One sample of a stream, prepared as ``prepare`` prepares a log's epochs (``prepare_epoch``).

    ``time`` UNIX s; ``m`` (3,) nT; ``ref`` (3,) NED nT (NaN where unknown); ``has_attitude``; ``c_nb`` (3, 3)
    (NaN without attitude); ``field_body`` (3,) nT the reference in the body frame; ``heading`` (1, 3) nT the
    heading axis in the body frame (``measurements.heading_axis``; zero where not finite); ``base`` (1,) int8 the
    status before filtering (a code of ``magkf.status.Status``); ``data`` the epoch's ``EpochData`` (one epoch).
    """

    time: float
    m: np.ndarray
    ref: np.ndarray
    has_attitude: bool
    c_nb: np.ndarray
    field_body: np.ndarray
    heading: np.ndarray
    base: np.ndarray
    data: EpochData

    def block(self, layout: StateLayout, model: MeasurementModel, R) -> Block:
        """The epoch as a ``Block`` of one for the measurement ``model``, as ``PreparedLog.block`` makes one, with
        its data: the linear Jacobian (``layout.linear_jacobian``) and, for an epoch the vector model may use
        (status used), the noise structure (``model.structure``) at the calibration ``R`` (3, 3)."""
        body = self.field_body[None]
        structure = model.structure(body, R, self.heading) if self.base[0] == USED else None
        G, Gh, RRt, frame = structure if structure is not None else (None, None, None, None)
        ref_mag = np.array([math.hypot(*self.ref)])
        H = layout.linear_jacobian(self.data)
        return Block(self.m[None], ref_mag, H, body, R, self.heading, G, Gh, RRt, frame, self.data)


def prepare_epoch(
    values: Mapping[str, float], ref, config: FilterConfig, columns=(), previous=None, R0=None
) -> PreparedEpoch:
    """One sample prepared as ``prepare`` prepares the epochs of a log, by the same epoch rules: the attitude
    matrix, the reference in the body frame and its rate, the heading axis and the status before filtering
    (``magkf.status.epoch_status``, and ``missing_column`` where an effect's channel is empty, as
    ``mark_missing_columns`` marks a log).

    Parameters
    ----------
    values : mapping
        The sample's values by column name (``io.drivelog.read_sample``: floats, NaN where missing): ``time``
        (UNIX s), ``mag_*`` (nT), ``roll, pitch, yaw`` (deg), ``dop``, ``pdop``, ``hdop`` and ``columns``.
    ref : array_like
        (3,) NED nT the reference field at the sample (NaN where unknown).
    config : FilterConfig
        Gives ``dop_max``.
    columns : tuple of str
        The auxiliary channels the effects need (the epoch's ``EpochData.columns``).
    previous : tuple or None
        ``(time, field_body)`` of the stream's previous epoch (UNIX s, (3,) nT), for the rate of change of the
        body-frame field: a backward difference here (``prepare`` takes a central one, which needs the next
        epoch), zero for the first epoch or where it is not finite.
    R0 : ndarray or None
        (3, 3) the calibration the effects' data carry (``EpochData.R0``; None: the identity).

    Returns
    -------
    PreparedEpoch
    """
    t = values[TIME]
    m = np.array([values[c] for c in MAG])
    roll, pitch, yaw = (values[c] for c in ATTITUDE)
    ref = np.asarray(ref, float)
    has_att = math.isfinite(roll) and math.isfinite(pitch) and math.isfinite(yaw)
    c_nb = euler_to_dcm(yaw, pitch, roll) if has_att else _NAN33
    # the reference field and the heading axis B x down (``measurements.heading_axis``) in the body frame
    field_body, axis = np.array([ref, (ref[1], -ref[0], 0.0)]) @ c_nb
    base = epoch_status(m[None], ref[None], [has_att], [first_dop(values)], config.dop_max)
    if (base[0] == USED or base[0] == MISSING_ATTITUDE) and not all(math.isfinite(values[c]) for c in columns):
        base[0] = MISSING_COLUMN  # an added effect lacks its channel: no update (the latter by its magnitude)
    data = EpochData(
        np.array([t]),
        field_body[None],
        ref[None],
        {c: np.array([values[c]]) for c in columns},
        mag=m[None],
        c_nb=c_nb[None],
        field_body_rate=_backward_rate(t, field_body, previous)[None],
        R0=np.eye(3) if R0 is None else R0,
    )
    heading = axis[None] if all(map(math.isfinite, axis.tolist())) else np.nan_to_num(axis[None])
    return PreparedEpoch(t, m, ref, has_att, c_nb, field_body, heading, base, data)


def _backward_rate(t: float, field_body, previous) -> np.ndarray:
    """(3,) nT/s the rate of ``field_body`` (3,) nT at ``t`` (UNIX s) from the epoch ``previous``
    (``(time, field_body)``, or None); zero where it cannot be taken."""
    dt = 0.0 if previous is None else t - previous[0]
    rate = (field_body - previous[1]) / dt if dt > 0 else np.zeros(3)
    return rate if np.isfinite(rate).all() else np.zeros(3)


def without_rates(prep: PreparedLog, layout: StateLayout) -> PreparedLog:
    """``prep`` without the field's rates (``EpochData.field_body_rate``, ``field_body_accel``) when ``layout``
    holds no effect beyond the core: effects alone read them, and a long log need not keep them."""
    if layout.has_extra:
        return prep
    return replace(prep, data=replace(prep.data, field_body_rate=None, field_body_accel=None))


def with_initial_R(prep: PreparedLog, x) -> PreparedLog:
    """``prep`` whose effect data carry the calibration ``R`` of state ``x`` (see ``EpochData.R0``)."""
    return replace(prep, data=replace(prep.data, R0=StateLayout.R(np.asarray(x, float)[:CORE_SIZE])))


def mark_missing_columns(prep: PreparedLog, effects, source: str) -> np.ndarray:
    """The base statuses with ``missing_column`` where an added effect's channel is empty, or where a linear
    effect's Jacobian is not finite for want of an input it derives (the field's rate where the attitude is
    missing on both sides); raises InputError when the log lacks a channel an effect needs altogether."""
    from ..effects import check_columns

    base = prep.base.copy()
    check_columns(effects, prep.data.columns, source)  # naming the calibration file an effect came from
    for effect in effects:
        for c in effect.columns:
            updating = (base == Status.USED) | (base == Status.MISSING_ATTITUDE)  # the latter by its magnitude
            base[updating & ~np.isfinite(prep.data.columns[c])] = Status.MISSING_COLUMN
        if effect.linear:
            theta = effect.prior()[0]
            for i in range(0, len(base), CHUNK):
                epochs = slice(i, i + CHUNK)
                J = effect.jacobian(theta, prep.data.take(epochs))
                updating = (base[epochs] == Status.USED) | (base[epochs] == Status.MISSING_ATTITUDE)
                base[epochs][updating & ~np.isfinite(J).all(axis=(1, 2))] = Status.MISSING_COLUMN
    return base


def initial_covariance(init: Calibration, config: FilterConfig) -> np.ndarray:
    """Covariance (12, 12) of an offline calibration: its own, or ``init_r_std`` and ``init_b_std``."""
    if init.covariance is not None:
        return np.array(init.covariance)
    return np.diag(np.concatenate([np.full(9, config.init_r_std**2), np.full(3, config.init_b_std**2)]))


def initial_core(prep: PreparedLog, config: FilterConfig, effects=()):
    """Initial ``(x, P, how)`` of the core block bootstrapped from the log (and of ``effects``, when the
    bootstrap fitted them with it: then ``x`` and ``P`` cover 12 + their parameters).

    With attitude (a model that uses it, and at least 50 epochs used whose linear effects have their channels):
    ``bootstrap.bootstrap_vector``, jointly with ``effects`` when all of them are linear; else
    ``bootstrap.bootstrap_magnitude`` over the epochs used or without attitude (at least 200).
    """
    good = prep.base == Status.USED
    linear = [e for e in effects if e.linear]
    if linear:
        good &= np.all([np.isfinite(prep.data.columns[c]) for e in linear for c in e.columns] or [True], axis=0)
    if good.sum() >= 50 and MEASUREMENTS[config.measure].needs_attitude:
        boot = _vector_bootstrap(prep, good, config, effects if linear and len(linear) == len(effects) else ())
    else:
        cand = (prep.base == Status.USED) | (prep.base == Status.MISSING_ATTITUDE)
        if cand.sum() < 200:
            raise InputError(f"too few usable epochs ({int(cand.sum())}) to bootstrap a calibration; give --init")
        boot = bootstrap_magnitude(prep.m[cand], prep.ref_mag[cand], prep.time[cand], config.bootstrap_s)
    return boot.x, boot.P, f"{boot.method} ({boot.n_epochs} epochs, {boot.span_s:.0f} s)"


def _vector_bootstrap(prep: PreparedLog, good, config: FilterConfig, effects=()):
    """``bootstrap.bootstrap_vector`` over the epochs ``good`` (N,) bool of ``prep``, with the linear ``effects``
    fitted jointly with the core (none: the core alone)."""
    m, B, t = prep.m[good], prep.data.field_body[good], prep.time[good]
    boot = bootstrap_vector(m, B, t, config.sensor_noise_nt, config.bootstrap_s)
    if not effects:
        return boot
    # Effects whose regressors use the calibration (a field anomaly is seen through R) fitted with the core,
    # their regressors made at the R of the fit before: twice, so that they are made at the R the filter then
    # runs at (``with_initial_R``) to within the second fit's change. Made at the core-only fit's R alone, 3 %
    # off the joint fit's, the anomaly's prior along the direction the data cannot see was 102 nT instead of
    # 1 618, and R's scale came out 4 standard deviations off.
    d = prep.data.take(good)
    extra_prior = tuple(np.concatenate(v) for v in zip(*(e.prior() for e in effects)))
    for _ in range(2):
        d = replace(d, R0=StateLayout.R(boot.x))
        extra = np.concatenate([e.jacobian(e.prior()[0], d) for e in effects], axis=2)
        boot = bootstrap_vector(m, B, t, config.sensor_noise_nt, config.bootstrap_s, extra, extra_prior)
    return boot


def initial_state(prep: PreparedLog, config: FilterConfig, init: Calibration | None, effects=()):
    """The start of a run: ``(prep, layout, x0, P0, how)``.

    From the calibration ``init`` (``calibration_start``), else the core block (and the effects, when the
    bootstrap fitted them jointly) from ``initial_core`` and the other effects from their priors; ``prep``
    with the initial ``R`` for the effects that use it.
    """
    if init is not None:
        layout, x0, P0 = calibration_start(init, config, effects)
        return with_initial_R(prep, x0), layout, x0, P0, f"file ({init.method})"
    x_init, P_init, how = initial_core(prep, config, effects)
    core = SoftHardIron(x_init[:CORE_SIZE], np.sqrt(np.diag(P_init)[:CORE_SIZE]), config.r_walk, config.b_walk)
    layout = StateLayout((core, *effects))
    x0, P0 = layout.prior()
    x0[: len(x_init)] = x_init
    P0[: len(x_init), : len(x_init)] = P_init
    return with_initial_R(prep, x_init), layout, x0, P0, how


@dataclass(frozen=True)
class RunSetup:
    """The start of a run over a log (``prepare_run``), the same for the whole-log filter
    (``run.calibrate_log``), the chunked filter (``chunked.calibrate_file``) and the batch solver
    (``batch.batch_problem``).

    ``prep`` the prepared epochs the start was found from, their effects' data at the initial ``R``
    (``with_initial_R``) and without the field's rates when no effect is added (``without_rates``; None where
    the run reads its epochs again piece by piece, as a chunked log's does); ``base`` (N,) int8 their statuses
    before filtering, with the effects' missing channels (``mark_missing_columns``);
    ``layout`` the state layout; ``x0`` (n,) and ``P0`` (n, n) the initial estimate and its covariance (a
    bootstrap's deflated by the starting noise's correlation, ``deflate_bootstrap``); ``how`` where the start
    came from, in words; ``model`` the measurement model of the run; ``noise`` the starting ``NoiseLevels``
    (None: the model's configured noise; so with ``init``, or with ``config.adapt_noise`` False).
    """

    prep: PreparedLog | None
    base: np.ndarray
    layout: StateLayout
    x0: np.ndarray
    P0: np.ndarray
    how: str
    model: MeasurementModel
    noise: NoiseLevels | None
    held: object = None

    @property
    def R0(self) -> np.ndarray:
        """(3, 3) the initial calibration, at which the Jacobians and the noise structure are computed."""
        return self.layout.R(self.x0)

    def estimator(self, config: FilterConfig) -> Estimator:
        """A filter (``Estimator``) starting from this setup, with the gates and noise of ``config``."""
        return Estimator(self.layout, config, self.x0, self.P0, self.noise, self.model)


#: ``(layout, x0, attitude) -> (NoiseLevels, x)``: the starting noise of a run from the start ``x0`` (n,) of state
#: ``layout`` and the robust whole-log start ``x``, for a model that uses the attitude or not (``start_noise``'s
#: arguments beside the log's).
NoiseStart = Callable[[StateLayout, np.ndarray, bool], NoiseLevels]


def prepare_run(
    prep: PreparedLog,
    config: FilterConfig,
    init: Calibration | None = None,
    effects=(),
    source: str | None = None,
    *,
    any_attitude: bool | None = None,
    noise_start: NoiseStart | None = None,
    batch: bool = False,
) -> RunSetup:
    """The start of a run over the epochs ``prep``: the one sequence of the whole-log, chunked and batch paths.

    1. the statuses before filtering: ``prep.base`` with the effects' missing channels (``mark_missing_columns``);
    2. the layout and initial estimate (``initial_state``): from ``init``, else bootstrapped from ``prep``;
       ``prep`` without the field's rates when no effect is added (``without_rates``);
    3. the measurement model (``estimator.run_model``): the magnitude alone when no epoch has attitude; with the
       magnitude alone and linear effects, their starting spread checked (``check_magnitude_start``);
    4. bootstrapped (no ``init``): the start moved to the robust (Huber-weighted) fit over the whole log, and the
       starting noise its residuals' scale (``start_noise``, or ``noise_start``), by whose correlation the
       bootstrap's information is deflated (``deflate_bootstrap``); kept when ``config.adapt_noise``. A
       disturbance in the bootstrap's first stretch then does not pull the start off.

    Parameters
    ----------
    prep : PreparedLog
        The prepared epochs (``prepare``): the whole log, or (chunked) its first stretch, which the bootstrap
        and the checks see.
    config : FilterConfig
        The run's settings.
    init : Calibration or None
        An offline calibration to start from (None: a bootstrap from ``prep``).
    effects : sequence of Effect
        The effect blocks added to the core.
    source : str or None
        The log's name, which InputErrors are located at.
    any_attitude : bool or None
        Whether any epoch of the log has attitude (None: any of ``prep``'s; a chunked log's scan knows).
    noise_start : callable or None
        ``(layout, x0, attitude) -> (NoiseLevels, x)`` the starting noise and the robust whole-log start (None:
        ``start_noise`` over ``prep``); a chunked log's is computed in passes over the file.
    batch : bool
        For the batch solver: the model ``config.measure`` names whatever the attitude (the epochs without
        it go to its fallback), no check of the magnitude's starting spread (the batch solver is what its
        refusal recommends), and the bootstrap sees the statuses of step 1 rather than ``prep.base``.

    Returns
    -------
    RunSetup

    Raises
    ------
    InputError
        When the log lacks an effect's channel, is too short to bootstrap from, or (the magnitude alone) the
        effects' starting uncertainty is beyond the filter's linearisation; located at ``source``.
    """
    base = mark_missing_columns(prep, effects, source)
    try:
        prep, layout, x0, P0, how = initial_state(replace(prep, base=base) if batch else prep, config, init, effects)
        prep = without_rates(prep, layout)
        attitude = bool(prep.has_attitude.any()) if any_attitude is None else any_attitude
        model = run_model(config, layout, x0, magnitude_only=not (batch or attitude))
        if not (batch or model.needs_attitude):
            check_magnitude_start(prep, layout, P0, base)
    except InputError as exc:
        raise exc.located(source) from None
    noise = None
    if init is None:  # bootstrapped: the start moves to the robust whole-log fit, the noise starts from its scale
        if noise_start is None:
            start, x_fit = start_noise(prep, config, x0, layout, model.needs_attitude, base)
        else:
            start, x_fit = noise_start(layout, x0, model.needs_attitude)
        if x_fit is not x0:
            x0 = np.asarray(x_fit, float)
            prep = with_initial_R(prep, x0) if prep is not None else None
            how += "; moved to the robust fit over the whole log"
        P0 = deflate_bootstrap(P0, layout, start.inflation)
        noise = start if config.adapt_noise else None
    held = None
    if layout.has_extra and model.needs_attitude and prep is not None:
        x0, P0, held = hold_undetermined(prep, config, layout, x0, P0, base, noise)
    return RunSetup(prep, base, layout, x0, P0, how, model, noise, held)


#: Held directions get this share of their prior variance in the filter's start (zero would make the
#: covariance singular, which the unscented filter's square root cannot take): held for good, as no process
#: noise reaches them.
HELD_VARIANCE_SHARE = 1e-8


def hold_undetermined(prep: PreparedLog, config: FilterConfig, layout: StateLayout, x0, P0, base, noise):
    """The start ``(x0, P0, held)`` with the directions of the added effects' parameters that the log does not
    determine beside the rest of the model and the heading's wander (``determined.held_directions``, the
    diagnosis's rule, over the epochs used with attitude at ``x0``) held at their prior mean: ``x0``'s part along
    them set to it, ``P0``'s variance along them nearly zero, so that the filter, the whole-log estimate and the
    diagnosis agree on what is determined and an effect cannot absorb what the data do not determine (a field
    anomaly across the horizontal field is a heading offset). The heading's wander is a nuisance there unless the
    starting noise ``noise`` found the logged heading exact (``heading_rad`` 0): then a heading-like direction is
    determined. ``held`` is None when none is held or too few epochs say."""
    used = (base == Status.USED) & prep.has_attitude
    if used.sum() < 10 * layout.size:
        return x0, P0, None
    wander_s = None if noise is not None and noise.heading_rad == 0.0 else WANDER_BLOCK_S
    gram = whitened_gram(prep.data.take(used), prep.heading[used], config, noise, wander_s, layout, x0)
    held = held_directions(gram, layout)
    if held is None or not held.count:
        return x0, P0, None
    core = layout.CORE.stop
    mean = layout.prior()[0][core:]
    x0 = np.array(x0, float)
    moved = held.hold(x0[core:], mean) - x0[core:]
    # the core follows the effects' held part as the start's covariance ties them (the conditional mean): a field
    # anomaly along the field set back to 0 takes R's scale with it
    P0 = np.asarray(P0, float)
    x0[:core] += P0[:core, core:] @ np.linalg.pinv(P0[core:, core:], rcond=1e-12, hermitian=True) @ moved
    x0[core:] += moved
    K = np.eye(layout.size)
    K[core:, core:] = held.projector
    P0 = K @ np.asarray(P0, float) @ K.T
    P0[core:, core:] += HELD_VARIANCE_SHARE * held.held_cov
    return x0, 0.5 * (P0 + P0.T), held


#: The largest spread (one standard deviation, at the 95th percentile of the epochs) that the start's uncertainty
#: may give the effects' terms, as a share of the field, when the magnitude alone is measured: the filter
#: linearises the magnitude about its estimate. With a load effect's default prior (1 000 nT/A at 27 A, about
#: the whole field) the UKF's predicted magnitude was hundreds of nT off and the EKF's standard deviations 12
#: times too wide; with 30 nT/A (1.6 %) both agreed with the batch solution.
MAGNITUDE_EFFECT_SPREAD = 0.05


def check_magnitude_start(prep: PreparedLog, layout: StateLayout, P0, base) -> None:
    """Raise InputError when the magnitude alone is to be filtered with linear effects whose starting uncertainty
    ``P0`` spreads their terms over more than ``MAGNITUDE_EFFECT_SPREAD`` of the field at the usable epochs
    (statuses ``base``), saying what to do instead."""
    usable = np.flatnonzero((base == Status.USED) | (base == Status.MISSING_ATTITUDE))
    if not layout.has_extra or not len(usable):
        return
    usable = usable[fit_positions(len(usable))]
    data = prep.data.take(usable)
    field = float(np.median(prep.ref_mag[usable]))
    std = np.sqrt(np.diag(P0))
    for effect, sl in layout.blocks():
        if not effect.linear:
            continue
        G = np.nan_to_num(effect.jacobian(np.zeros(effect.size), data))  # (k, 3, p)
        spread = float(np.percentile(np.linalg.norm(G * std[sl], axis=(1, 2)), 95))
        if spread > MAGNITUDE_EFFECT_SPREAD * field:
            raise InputError(
                f"with the magnitude alone, {effect.label}'s starting uncertainty spreads its terms over "
                f"{spread:.3g} nT, {100 * spread / field:.0f} % of the field: more than the filter's linearisation "
                f"of the magnitude holds ({100 * MAGNITUDE_EFFECT_SPREAD:g} %); calibrate with the batch solver "
                "(magkf calibrate --batch), measure the vector too (--measure both, with attitude), or start from a "
                "calibration that stores the effect (--init, --cal)"
            )


def calibration_start(
    init: Calibration, config: FilterConfig, effects=()
) -> tuple[StateLayout, np.ndarray, np.ndarray]:
    """``(layout, x0, P0)`` starting from a calibration: its core with its covariance (``initial_covariance``),
    and each of ``effects`` that the calibration stores (same ``label``) at its stored values and covariance
    (with the cross terms to the core and to the other stored effects); the others from their priors."""
    P_core = initial_covariance(init, config)
    core = SoftHardIron(init.state, np.sqrt(np.diag(P_core)), config.r_walk, config.b_walk)
    layout = StateLayout((core, *effects))
    x0, P0 = layout.prior()
    P0[:CORE_SIZE, :CORE_SIZE] = P_core
    x0[:CORE_SIZE] = init.state
    # the stored state's index of each stored effect, and of the core
    stored_at, start = {"core": np.arange(CORE_SIZE)}, CORE_SIZE
    for e in init.effects:
        stored_at[e.label] = np.arange(start, start + len(e.values))
        start += len(e.values)
    ours, theirs = [np.arange(CORE_SIZE)], [stored_at["core"]]
    for effect, sl in layout.blocks():
        if effect.label in stored_at:
            x0[sl] = init.full_state[stored_at[effect.label]]
            ours.append(np.arange(sl.start, sl.stop))
            theirs.append(stored_at[effect.label])
    if init.state_covariance is not None and len(ours) > 1:
        a, b = np.concatenate(ours), np.concatenate(theirs)
        P0[np.ix_(a, a)] = init.state_covariance[np.ix_(b, b)]
    return layout, x0, P0


def start_noise(
    prep: PreparedLog, config: FilterConfig, x0, layout: StateLayout, attitude: bool, base
) -> tuple[NoiseLevels, np.ndarray]:
    """The noise to start from and the robust whole-log start: ``(NoiseLevels, x)``, the noise a robust scale of the
    residuals of a whole-log fit ``x`` (n,) (fitted to at most ``FIT_EPOCHS`` epochs spread evenly over the log;
    the scale over every usable epoch).

    With ``attitude`` (a model that uses it), the fit is a robust (Huber-weighted) linear least squares of
    ``m = H x`` (``H`` the layout's linear Jacobian) over the usable epochs, starting from ``x0``: over the
    bootstrap's short stretch alone, a slowly wandering attitude error is absorbed into ``R`` and ``b`` and
    its residuals understate the noise (and its correlation), which lets the filter trust its first
    minutes far too much, and a disturbance in that stretch pulls the start off. Without attitude, the residual
    magnitudes at ``x0``, and ``x`` is ``x0``. ``base`` (N,) the statuses before filtering. The log is gone
    through in pieces of ``CHUNK`` epochs."""
    start = configured_noise(config)
    if attitude:
        usable = np.flatnonzero(base == Status.USED)
        if len(usable) < 50:
            return start, x0
        # The fit needs far fewer epochs than a long log has: its error is then still far below the noise
        # whose scale it is for. Every epoch's residual counts in the scale.
        fit = usable[fit_positions(len(usable))]
        x = robust_linear_fit(
            *start_rows(layout, x0, prep.data, prep.m[fit], fit), x0, start.along_var, prior_std=effect_spread(layout)
        )
        R = StateLayout.R(np.asarray(x0, float))
        parts_of_e = np.empty((len(usable), 3))
        for i in range(0, len(usable), CHUNK):
            parts_of_e[i : i + CHUNK] = residual_parts(prep, layout, x, R, usable[i : i + CHUNK])
        along, cross = parts_of_e[:, 0], parts_of_e[:, 1:]  # along the field, the heading axis, the third
    else:
        usable = (base == Status.USED) | (base == Status.MISSING_ATTITUDE)
        if usable.sum() < 10:
            return start, x0
        along, cross, x = magnitude_residuals(prep.take(usable), x0), None, x0
    return start_levels(along, cross, prep.ref_mag[usable], horizontal_squared(prep.ref, usable), config), x


def effect_spread(layout: StateLayout) -> np.ndarray:
    """(n,) the added effects' prior standard deviations, infinite for the core: the prior of the start's robust fit
    (``robust_linear_fit``)."""
    spread = np.sqrt(np.diag(layout.prior()[1]))
    spread[layout.CORE] = np.inf
    return spread


def configured_noise(config: FilterConfig) -> NoiseLevels:
    """The noise ``config`` states (sensor, attitude, reference)."""
    return NoiseLevels(config.sensor_noise_nt, np.radians(config.attitude_deg), config.reference_nt)


def fit_positions(n_usable: int) -> np.ndarray:
    """Which of ``n_usable`` usable epochs (their positions among them) go into a whole-log start's fit (the
    starting noise's, the batch solver's linear start): every ``ceil(n_usable / FIT_EPOCHS)``-th."""
    return np.arange(0, n_usable, max(-(-n_usable // FIT_EPOCHS), 1))


def start_rows(layout: StateLayout, x0, data, m, rows) -> tuple[np.ndarray, np.ndarray]:
    """The readings ``m`` (k, 3) nT and Jacobian (k, 3, n) of the start's linear fit at the epochs ``rows`` (k,)
    of ``data``: the layout's linear Jacobian with the nonlinear effects (a time lag) linearised at ``x0`` (left
    out, their terms would read as noise), and the readings less what that linearisation leaves at ``x0``.
    ``data`` holds the epochs around ``rows`` too, which a time lag interpolates between."""
    linear = layout.linear_jacobian(data, rows=rows)
    if not layout.nonlinear:
        return m, linear
    x0 = np.asarray(x0, float)
    H = linear.copy()
    for effect, sl in layout.nonlinear:
        H[:, :, sl] = effect.jacobian(x0[sl], data, rows=rows)
    offset = layout.nonlinear_terms(x0, data, rows=rows) - (H - linear) @ x0
    return m - np.nan_to_num(offset), np.nan_to_num(H)


def residual_parts(prep: PreparedLog, layout: StateLayout, x, R, rows=None) -> np.ndarray:
    """The residuals ``m - H x`` (k, 3) nT at the epochs ``rows`` of ``prep`` (None: all) at state ``x`` (``H`` the
    layout's linear Jacobian, less the nonlinear effects' terms at ``x``, which ``prep``'s epochs around ``rows``
    serve; a missing input counts as 0) along the field, the heading axis and the third (the field's frame at
    calibration ``R``)."""
    index = slice(None) if rows is None else rows
    e = prep.m[index] - layout.linear_jacobian(prep.data, rows=rows) @ x
    if layout.nonlinear:
        e = e - np.nan_to_num(layout.nonlinear_terms(x, prep.data, rows=rows))
    return np.einsum("kji,ki->kj", prep.frame(index, R), e)


def magnitude_residuals(prep: PreparedLog, x0) -> np.ndarray:
    """The magnitude residuals (k,) nT of the epochs of ``prep`` at the calibration of state ``x0``."""
    c = StateLayout.R_b(x0)
    return prep.ref_mag - np.linalg.norm(calibrated_field(*c, prep.m), axis=1)


def start_levels(along, cross, ref_mag, horizontal2, config: FilterConfig) -> NoiseLevels:
    """The starting noise (``noise.robust_start``) from the residuals ``along`` (k,) the field and ``cross`` (k, 2)
    across it (None: without attitude) at epochs of reference field magnitude ``ref_mag`` (k,) nT and horizontal
    part squared ``horizontal2`` (k,) nT^2 (``horizontal_squared``). ``along`` and ``cross`` are the caller's
    working arrays: they are centred in place."""
    return robust_start(
        along,
        cross,
        np.asarray(ref_mag, float) ** 2,
        config.reference_nt,
        config.noise_floor_nt,
        configured_noise(config).attitude_rad,
        np.asarray(horizontal2, float),
    )


def horizontal_squared(ref, rows=None) -> np.ndarray:
    """The horizontal part squared (k,) nT^2 of the reference field ``ref`` (N, 3) NED nT at the epochs ``rows``
    (k,) (None: every epoch), ``CHUNK`` at a time: no copy of those epochs' field."""
    rows = np.arange(len(ref)) if rows is None else np.asarray(rows)
    if rows.dtype == bool:
        rows = np.flatnonzero(rows)
    out = np.empty(len(rows))
    for i in range(0, len(rows), CHUNK):
        out[i : i + CHUNK] = np.sum(ref[rows[i : i + CHUNK], :2] ** 2, axis=1)
    return out


#: Epochs taken at once where a whole log is gone through (the starting noise's Jacobians, the per-epoch table).
CHUNK = 8_192
#: At most about this many epochs (evenly spaced) go into the starting noise's whole-log fit.
FIT_EPOCHS = 50_000


#: Huber's threshold of the start's robust fit, in robust scales of the residual norm (1.4826 times its median:
#: about 2.3 noise standard deviations for Gaussian noise, so 3 of them are about 7 standard deviations); the
#: epochs beyond it are left out of the last ``REJECT_ITERATIONS`` iterations (a disturbance, not noise).
ROBUST_SCALES = 3.0
REJECT_ITERATIONS = 2


def robust_linear_fit(m, H, x0, noise_var: float, iterations: int = 6, prior_std=None) -> np.ndarray:
    """``x`` (n,) minimising Huber-weighted ``|m - H x|^2`` over epochs ``m`` (N, 3) nT, ``H`` (N, 3, n), with a
    weak pull towards ``x0`` that keeps directions the log does not determine where the start put them: where
    ``prior_std`` (n,) is finite, a prior of that standard deviation weighed as one epoch's (an effect's own, which
    keeps a direction it shares with the core, a field anomaly along the field with R's scale, near its mean).

    ``iterations`` of Huber weights (threshold ``ROBUST_SCALES`` robust scales of the residual norm), then
    ``REJECT_ITERATIONS`` with the epochs beyond it left out: a Huber weight bounds a disturbance's pull but
    keeps it (a 5 000 nT bump over 5 % of a log moved the offsets by 3 nT, six standard errors), a redescending
    step removes it."""
    x0 = np.asarray(x0, float)
    n = len(x0)
    rows, y = H.reshape(-1, n), m.reshape(-1)  # (3N, n) and (3N,): one row per component
    pull = noise_var / (1e6 * (np.abs(x0) * 1e-3 + 1e-3)) ** 2
    if prior_std is not None:
        std = np.asarray(prior_std, float)
        pull = np.where(np.isfinite(std), noise_var / std**2, pull)
    w = np.ones(len(m))
    x = x0
    pieces = [slice(a, a + 3 * CHUNK) for a in range(0, len(y), 3 * CHUNK)]  # whole epochs: CHUNK of them a piece
    for i in range(iterations + REJECT_ITERATIONS):
        normal, rhs = np.diag(pull), pull * x0
        for at in pieces:  # the normal equations summed a piece at a time: no weighted copy of the rows
            weighted = rows[at] * np.repeat(w[at.start // 3 : at.stop // 3], 3)[:, None]
            normal = normal + rows[at].T @ weighted
            rhs = rhs + weighted.T @ y[at]
        x = np.linalg.solve(normal, rhs)
        r = np.linalg.norm((y - rows @ x).reshape(-1, 3), axis=1)
        s = 1.4826 * np.median(r) + 1e-9
        w = np.minimum(1.0, ROBUST_SCALES * s / np.maximum(r, 1e-12))
        if i + 1 >= iterations:
            w = np.where(w < 1.0, 0.0, 1.0)
    return x


def deflate_bootstrap(P0, layout: StateLayout, inflation: float) -> np.ndarray:
    """``P0`` with the information the bootstrap's *data* gave the core block divided by ``inflation``: the
    bootstrap counted its stretch's epochs as independent, and residuals correlated over ``inflation``
    epochs carry that much less. Its weak prior (``bootstrap.PRIOR_R_STD``, ``PRIOR_B_STD``) is kept as
    it was, so that directions the stretch did not determine stay where the prior holds them."""
    if inflation <= 1.0:
        return P0
    P0 = np.array(P0, float)
    core = layout.CORE
    prior = np.diag(1.0 / np.concatenate([np.full(9, PRIOR_R_STD), np.full(3, PRIOR_B_STD)]) ** 2)
    data = np.linalg.inv(P0[core, core]) - prior
    values, vectors = np.linalg.eigh(0.5 * (data + data.T))
    data = (vectors * np.maximum(values, 0.0)) @ vectors.T  # what the data added, never less than nothing
    deflated = np.linalg.inv(data / inflation + prior)
    P0[core, core] = 0.5 * (deflated + deflated.T)
    return P0
