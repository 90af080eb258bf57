"""Real-time calibration: one sample at a time, constant memory.

    cal = OnlineCalibrator.from_file("cal.json", FilterConfig(sensor_noise_nt=40))
    for sample in stream:                     # a dict (or pandas row) with the log's column names
        result = cal.step(sample)
        use(result.field_body, result.heading_true_deg, result.status)

A sample carries ``time`` (UNIX s), ``mag_x, mag_y, mag_z`` (nT), and when available ``roll, pitch,
yaw`` (deg), ``lat, lon, alt`` (or ``ref_n, ref_e, ref_d``), ``dop`` and the auxiliary columns the
effects need: a dict, or a pandas row (whose name is its time, as in ``log.table.iterrows()``). Missing
keys, None or NaN values mean missing, and the epoch gets the status the same rules give a whole log
(``magkf.status.epoch_status``). The reference field is evaluated lazily and
cached (``ReferenceFieldCache``): again only after the vehicle has moved ``reference_refresh_m`` or the
UTC date has changed. Each step is the same gated update as post-processing, with a block of one epoch.
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
    REF,
    declination_deg,
    euler_to_dcm,
    magnetic_heading_deg,
)
from ..effects import restore_effects, stored_effect
from ..effects.base import EpochData
from ..errors import InputError
from ..io.drivelog import read_sample
from ..reference import ReferenceFieldCache
from ..status import MISSING_ATTITUDE, MISSING_COLUMN, STATUS_NAMES, USED, epoch_status, first_dop
from .estimator import Estimator
from .measurements import Block
from .prepare import calibration_start

__all__ = ["OnlineCalibrator", "EpochResult"]

_NAN33 = np.full((3, 3), np.nan)
_SAMPLE_COLUMNS = (*MAG, *ATTITUDE, *REF, LAT, LON, ALT, DOP, PDOP, HDOP)


@dataclass(frozen=True)
class EpochResult:
    """What ``OnlineCalibrator.step`` returns for one sample.

    The field and headings are computed with the estimate after this step.

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
    def from_file(cls, path, config: FilterConfig = FilterConfig(), effects=None, registry=None) -> OnlineCalibrator:
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
            from their priors); None: the file's own.
        registry : dict or None, optional
            Classes of user effects, from ``load_effect_file``, which the file's user effects need.

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
        return cls(init, config, restore_effects(init, registry) if effects is None else effects)

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
        t = v["time"]
        if not math.isfinite(t):
            raise InputError("the sample has no time (give a 'time' entry, a row named by its time, or time=...)")
        if self._last_time is not None and not t > self._last_time:
            raise InputError(f"time {t!r} s is not after the previous sample's {self._last_time!r} s", column="time")
        m = np.array([v[c] for c in MAG])
        roll, pitch, yaw = (v[c] for c in ATTITUDE)
        ref = self._reference(t, v)
        has_att = math.isfinite(roll) and math.isfinite(pitch) and math.isfinite(yaw)
        c_nb = euler_to_dcm(yaw, pitch, roll) if has_att else _NAN33
        # the reference field and the heading axis B x down (``measurements.heading_axis``) in the body frame
        field_body, axis = np.array([ref, (ref[1], -ref[0], 0.0)]) @ c_nb
        dop = first_dop(v)
        base = epoch_status(m[None], ref[None], [has_att], [dop], self.config.dop_max)
        updating = base[0] == USED or base[0] == MISSING_ATTITUDE  # the latter by its magnitude
        if updating and not all(math.isfinite(v[c]) for c in self._effect_columns):
            base[0] = MISSING_COLUMN  # an added effect lacks its channel: no update, as post-processing
        dt = 0.0 if self._last_time is None else t - self._last_time
        rate = (field_body - self._last_field_body) / dt if dt > 0 else np.zeros(3)
        if not np.isfinite(rate).all():
            rate = np.zeros(3)
        self._last_time, self._last_field_body = t, field_body
        est, layout = self.estimator, self.layout
        R = layout.R(est.x)
        data = EpochData(
            np.array([t]),
            field_body[None],
            ref[None],
            {c: np.array([v[c]]) for c in self._effect_columns},
            mag=m[None],
            c_nb=c_nb[None],
            field_body_rate=rate[None],
            R0=R,
        )
        H = layout.linear_jacobian(data)
        axis = axis[None] if all(map(math.isfinite, axis.tolist())) else np.nan_to_num(axis[None])
        structure = est.structure(field_body[None], R, axis) if base[0] == USED else None
        G, Gh, RRt, frame = structure if structure is not None else (None, None, None, None)
        blk = Block(m[None], np.array([math.hypot(*ref)]), H, field_body[None], R, axis, G, Gh, RRt, frame, data)
        status, updated, nis = est.process_block(np.array([t]), dt, blk, base)
        x = est.x
        R, b = layout.R_b(x)
        e = layout.extra_terms(x, H, data) if layout.has_extra else 0.0
        field = layout.calibrated(x, m[None], e)[0]
        heading = magnetic_heading_deg(field, roll, pitch) if has_att else math.nan
        return EpochResult(
            time=t,
            field_body=field,
            magnitude_nt=math.hypot(*field.tolist()),
            heading_mag_deg=heading,
            heading_true_deg=(heading + declination_deg(ref)) % 360.0,
            status=STATUS_NAMES[int(status[0])],
            updated=bool(updated[0]),
            nis=float(nis[0]),
            R=R.copy(),
            b=b.copy(),
            std=np.sqrt(est.P.diagonal()),
            x=x.copy(),
            noise_sensor_nt=float(est.noise.sensor_nt),
            noise_attitude_deg=float(est.noise.attitude_deg),
            noise_heading_deg=float(est.noise.heading_deg),
        )

    def _reference(self, t, v) -> np.ndarray:
        ref = [v[c] for c in REF]
        if all(map(math.isfinite, ref)):
            return np.array(ref)
        lat, lon, alt = v[LAT], v[LON], v[ALT]
        if not (math.isfinite(lat) and math.isfinite(lon)):
            return np.full(3, np.nan)
        return self.reference.ned(t, lat, lon, alt if math.isfinite(alt) else 0.0)
