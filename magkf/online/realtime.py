"""Real-time calibration: a sample at a time (or a burst of them), constant memory.

    cal = OnlineCalibrator.from_file("cal.json", FilterConfig(sensor_noise_nt=40))
    for sample in stream:                     # a dict (or pandas row) with the log's column names
        result = cal.step(sample)
        use(result.field_body, result.heading_true_deg, result.status)
    results = cal.step_block(burst)           # consecutive samples read together: one update

A sample carries ``time`` (UNIX s), ``mag_x, mag_y, mag_z`` (nT), and when available ``roll, pitch,
yaw`` (deg), ``lat, lon, alt`` (or ``ref_n, ref_e, ref_d``), ``dop`` and the auxiliary columns the
effects need: a dict, or a pandas row (whose name is its time, as in ``log.table.iterrows()``). Missing
keys, None or NaN values mean missing, and the epoch is prepared by the rules that prepare a whole log
(``prepare.prepare_epoch``: the status of ``magkf.status.epoch_status``, the body-frame reference, the
heading axis; ``prepare.prepare_samples`` for a burst, by the same rules). The reference field is evaluated
lazily and cached (``ReferenceFieldCache``): again only after the vehicle has moved ``reference_refresh_m`` or
the UTC date has changed. Each step is the same gated update as post-processing, with a block of one epoch;
``step_block`` updates once for its samples, as post-processing updates a block of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..calibration import Calibration
from ..config import FilterConfig
from ..conventions import (
    ALT,
    ATTITUDE,
    DOP,
    HDOP,
    LAT,
    LON,
    MAG,
    PDOP,
    PITCH,
    REF,
    ROLL,
    TIME,
    declination_deg,
    magnetic_heading_deg,
)
from ..effects import restore_effects, stored_effect
from ..errors import InputError
from ..io.drivelog import read_sample, read_samples
from ..reference import ReferenceFieldCache
from ..status import STATUS_NAMES
from .estimator import Estimator
from .prepare import PreparedEpoch, PreparedLog, calibration_start, prepare_epoch, prepare_samples

__all__ = ["OnlineCalibrator", "EpochResult"]

_SAMPLE_COLUMNS = (*MAG, *ATTITUDE, *REF, LAT, LON, ALT, DOP, PDOP, HDOP)


@dataclass(frozen=True)
class EpochResult:
    """What ``OnlineCalibrator.step`` returns for one sample (and ``step_block`` for each of its samples).

    The field and headings are computed with the estimate after this step (after the block). Its arrays are the
    result's own.

    Parameters
    ----------
    time : float
        The sample's time, UNIX s.
    field_body : numpy.ndarray
        (3,) calibrated body field, nT (with the estimate after this step).
    magnitude_nt : float
        Its magnitude, nT.
    heading_mag_deg : float
        Magnetic heading, deg (NaN without attitude or position).
    heading_true_deg : float
        True heading, deg (NaN without attitude or position).
    status : str
        The epoch's status, a name of ``magkf.status``.
    updated : bool
        Whether the sample updated the filter.
    nis : float
        Its normalised innovation squared.
    R : numpy.ndarray
        (3, 3) the current estimate of ``R``.
    b : numpy.ndarray
        (3,) the current estimate of the offsets, nT.
    std : numpy.ndarray
        (n,) the current estimate's standard deviations in state order.
    x : numpy.ndarray
        (n,) the whole state.
    noise_sensor_nt : float
        Sensor noise the estimator uses after this step, nT per axis (1 sigma; learned from the
        innovations, ``magkf.online.noise``).
    noise_attitude_deg : float
        Tilt noise the estimator uses after this step, deg (1 sigma, learned likewise).
    noise_heading_deg : float
        Heading noise the estimator uses after this step, deg (1 sigma, learned likewise).
    reference_body_nt : numpy.ndarray
        (3,) the reference field in the body frame, nT (NaN without attitude or reference): ``field_body`` less
        it is the vector residual.
    """

    time: float
    field_body: np.ndarray
    magnitude_nt: float
    heading_mag_deg: float
    heading_true_deg: float
    status: str
    updated: bool
    nis: float
    R: np.ndarray
    b: np.ndarray
    std: np.ndarray
    x: np.ndarray
    noise_sensor_nt: float
    noise_attitude_deg: float
    noise_heading_deg: float
    reference_body_nt: np.ndarray


class OnlineCalibrator:
    """Streaming calibration from an initial calibration (``init``) with its covariance.

    Memory does not grow with the number of steps.

    Parameters
    ----------
    init : Calibration
        The calibration to start from, with its covariance.
    config : FilterConfig, optional
        The noise, gates and random walks.
    effects : sequence of Effect or None, optional
        Extra ``Effect`` blocks with their own priors; None: the effects ``init`` stores, at their stored
        values.

    Attributes
    ----------
    calibration : Calibration
        The current estimate.
    config : FilterConfig
        The settings given.

    Examples
    --------
    >>> cal = OnlineCalibrator.from_file("cal.json")  # doctest: +SKIP
    >>> result = cal.step({"time": 1.7e9, "mag_x": 21000.0, ...})  # doctest: +SKIP
    >>> result.field_body, result.status  # doctest: +SKIP
    """

    def __init__(self, init: Calibration, config: FilterConfig = FilterConfig(), effects=None):
        self.config = config
        effects = restore_effects(init) if effects is None else tuple(effects)
        self.layout, x0, P0 = calibration_start(init, config, effects)
        self.estimator = Estimator(self.layout, config, x0, P0)
        # What the filter needs for these models (the UKF's sigma points and FilterPy, where a model is not
        # linear) made now, not at the first epoch that needs it (one without attitude), where loading it
        # would hold that step for a few hundred milliseconds.
        model = self.estimator.model
        self.estimator.filter.prepare((model, model.fallback))
        self.reference = ReferenceFieldCache(config.reference_refresh_m)
        self._effect_columns = tuple(c for e in self.layout.extra() for c in e.columns)
        self._columns = _SAMPLE_COLUMNS + self._effect_columns
        self._last_time = None
        self._last_field_body = None

    @classmethod
    def from_file(cls, path, config: FilterConfig = FilterConfig(), effects=None) -> OnlineCalibrator:
        """Start from a calibration file (JSON).

        The effects the file stores start at their stored values and covariance, unless ``effects`` is given.

        Parameters
        ----------
        path : str or path-like
            The calibration file (JSON).
        config : FilterConfig, optional
            The noise, gates and random walks.
        effects : sequence of Effect or None, optional
            The effects to estimate instead of the file's (those the file stores start from it, the others
            from their priors); None: the file's own (a user effect's class must be registered, e.g. by
            ``load_effect_file``).

        Returns
        -------
        OnlineCalibrator
            Started from the file's calibration.

        Raises
        ------
        InputError
            The file cannot be read or is not a valid calibration.
        """
        init = Calibration.load(path)
        return cls(init, config, restore_effects(init) if effects is None else effects)

    @property
    def calibration(self) -> Calibration:
        """The current estimate as a calibration with its 12x12 covariance, and its effects.

        Returns
        -------
        Calibration
            ``R``, ``b``, their (12, 12) covariance and the effects' estimates.
        """
        x, P, core = self.estimator.x, self.estimator.P, self.layout.CORE
        R, b = self.layout.R_b(x)
        std = np.sqrt(np.diag(P))
        return Calibration(
            R=R,
            b=b,
            method=f"{self.config.filter}-online",
            covariance=P[core, core],
            effects=tuple(stored_effect(e, x[sl], std[sl]) for e, sl in self.layout.blocks()),
            state_covariance=P if self.layout.has_extra else None,
        )

    def step(self, sample, time: float | None = None) -> EpochResult:
        """Process one sample.

        Parameters
        ----------
        sample : mapping or pandas.Series
            Column names to values (canonical names, nT and degrees), or a pandas row. Its time is its
            ``time`` entry, else a pandas row's name.
        time : float or None, optional
            UNIX s; overrides the sample's own.

        Returns
        -------
        EpochResult
            The calibrated field, headings, status and the estimate after this step.

        Raises
        ------
        InputError
            The sample is not a mapping, holds a number beyond the range a log may hold, has no time, or its
            time is not after the previous sample's.
        """
        v = read_sample(sample, self._columns, time)
        t = _checked_time(v["time"], self._last_time)
        est, layout = self.estimator, self.layout
        R = layout.R(est.x)
        previous = None if self._last_time is None else (self._last_time, self._last_field_body)
        epoch = prepare_epoch(v, self._reference(t, v), self.config, self._effect_columns, previous, R)
        dt = 0.0 if self._last_time is None else t - self._last_time
        self._last_time, self._last_field_body = t, epoch.field_body
        block = epoch.block(layout, est.model, R)
        status, updated, nis = est.process_block(np.array([t]), dt, block, epoch.base)
        return self._result(epoch, v, block.H, int(status[0]), bool(updated[0]), float(nis[0]))

    def step_block(self, samples) -> list[EpochResult]:
        """Process consecutive samples as one block.

        Each sample is prepared by the rules of ``step``; the block is then gated and the filter updated once
        with its accepted epochs, as post-processing filters a block of ``FilterConfig.block_s`` seconds
        (``Estimator.process_block``, the prediction over the time since the previous sample). For a stream
        read in bursts (a telemetry link polled ten times a second) this costs a fraction of a ``step`` per
        sample: the update's fixed cost is paid once a block. A block of one sample is a ``step``.

        Parameters
        ----------
        samples : sequence of mapping or pandas.Series
            The samples, in time order, each as ``step`` takes one.

        Returns
        -------
        list of EpochResult
            One per sample, in order; the estimate in each (``R``, ``b``, ``std``, ``x``, the noise and the
            calibrated field) is the one after the block.

        Raises
        ------
        InputError
            As ``step``, for a sample that is not valid, naming it (counted from 0); nothing is processed then.
        """
        if len(samples) <= 1:  # a block of one is a step, whose scalar path costs half
            return [self.step(sample) for sample in samples]
        values = read_samples(samples, self._columns)
        columns = dict(zip((*self._columns, TIME), values.T))
        last = self._last_time
        for i, t in enumerate(columns[TIME].tolist()):
            last = _checked_time(t, last, f"sample {i}: ")
        est, layout = self.estimator, self.layout
        R = layout.R(est.x)
        previous = None if self._last_time is None else (self._last_time, self._last_field_body)
        prep = prepare_samples(columns, self._references(columns), self.config, self._effect_columns, previous, R)
        t = prep.time
        dt = 0.0 if self._last_time is None else float(t[-1] - self._last_time)
        self._last_time, self._last_field_body = float(t[-1]), prep.data.field_body[-1].copy()
        block = prep.block(slice(None), layout, est.model, R, with_data=True)
        status, updated, nis = est.process_block(t, dt, block, prep.base)
        return self._results(prep, columns, block.H, status, updated, nis)

    def _result(self, epoch: PreparedEpoch, v, H, status: int, updated: bool, nis: float) -> EpochResult:
        """The ``EpochResult`` of the sample ``epoch`` (its values ``v`` by column name, its linear Jacobian ``H``
        (1, 3, n)) with the estimate after its update, which gave it ``status`` (a code of ``magkf.status``),
        ``updated`` and ``nis``."""
        est, layout = self.estimator, self.layout
        x = est.x
        R, b = layout.R_b(x)
        e = layout.extra_terms(x, H, epoch.data) if layout.has_extra else 0.0
        field = layout.calibrated(x, epoch.m[None], e)[0]
        heading = magnetic_heading_deg(field, v[ROLL], v[PITCH]) if epoch.has_attitude else math.nan
        return EpochResult(
            time=epoch.time,
            field_body=field,
            magnitude_nt=math.hypot(*field.tolist()),
            heading_mag_deg=heading,
            heading_true_deg=(heading + declination_deg(epoch.ref)) % 360.0,
            status=STATUS_NAMES[status],
            updated=updated,
            nis=nis,
            R=R.copy(),
            b=b.copy(),
            std=np.sqrt(est.P.diagonal()),
            x=x.copy(),
            noise_sensor_nt=float(est.noise.sensor_nt),
            noise_attitude_deg=float(est.noise.attitude_deg),
            noise_heading_deg=float(est.noise.heading_deg),
            reference_body_nt=epoch.field_body.copy(),
        )

    def _results(self, prep: PreparedLog, columns, H, status, updated, nis) -> list[EpochResult]:
        """The ``EpochResult`` s of a block's samples ``prep`` (their ``columns`` (k,) by name, their linear
        Jacobian ``H`` (k, 3, n)), with the estimate after the block's update, which gave them ``status`` (codes of
        ``magkf.status``), ``updated`` and ``nis`` (k,)."""
        est, layout = self.estimator, self.layout
        x = est.x
        R, b = layout.R_b(x)
        e = layout.extra_terms(x, H, prep.data) if layout.has_extra else 0.0
        field = layout.calibrated(x, prep.m, e)
        with np.errstate(invalid="ignore"):
            heading = np.where(prep.has_attitude, magnetic_heading_deg(field, columns[ROLL], columns[PITCH]), np.nan)
            true = (heading + declination_deg(prep.ref)) % 360.0
        magnitude = np.linalg.norm(field, axis=1)
        std = np.sqrt(est.P.diagonal())
        noise = {
            "noise_sensor_nt": float(est.noise.sensor_nt),
            "noise_attitude_deg": float(est.noise.attitude_deg),
            "noise_heading_deg": float(est.noise.heading_deg),
        }
        return [
            EpochResult(
                time=float(prep.time[i]),
                field_body=field[i].copy(),
                magnitude_nt=float(magnitude[i]),
                heading_mag_deg=float(heading[i]),
                heading_true_deg=float(true[i]),
                status=STATUS_NAMES[int(status[i])],
                updated=bool(updated[i]),
                nis=float(nis[i]),
                reference_body_nt=prep.data.field_body[i].copy(),
                R=R.copy(),
                b=b.copy(),
                std=std.copy(),
                x=x.copy(),
                **noise,
            )
            for i in range(len(prep))
        ]

    def _references(self, columns: dict) -> np.ndarray:
        """(k, 3) NED nT the reference field of a block's samples (``columns`` (k,) by name): their ``ref_*`` where
        given, else the cached IGRF at their position, else NaN (``_reference`` of each)."""
        given = np.column_stack([columns[c] for c in REF])
        out = np.where(np.isfinite(given).all(axis=1, keepdims=True), given, np.nan)
        placed = np.isnan(out[:, 0]) & np.isfinite(columns[LAT]) & np.isfinite(columns[LON])
        if placed.any():
            alt = np.nan_to_num(columns[ALT][placed], nan=0.0, posinf=0.0, neginf=0.0)
            out[placed] = self.reference.ned_many(
                columns[TIME][placed], columns[LAT][placed], columns[LON][placed], alt
            )
        return out

    def _reference(self, t, v) -> np.ndarray:
        ref = [v[c] for c in REF]
        if all(map(math.isfinite, ref)):
            return np.array(ref)
        lat, lon, alt = v[LAT], v[LON], v[ALT]
        if not (math.isfinite(lat) and math.isfinite(lon)):
            return np.full(3, np.nan)
        return self.reference.ned(t, lat, lon, alt if math.isfinite(alt) else 0.0)


def _checked_time(t: float, last: float | None, which: str = "") -> float:
    """The sample's time ``t`` (UNIX s), or InputError when it is missing or not after ``last`` (the previous
    sample's, None for the first); ``which`` starts the message (a block's ``"sample 3: "``)."""
    if not math.isfinite(t):
        how = "" if which else ", or time=..."  # step_block takes no time argument
        raise InputError(f"{which}the sample has no time (give a 'time' entry, a row named by its time{how})")
    if last is not None and not t > last:
        raise InputError(f"{which}time {t!r} s is not after the previous sample's {last!r} s", column="time")
    return t
