"""Real-time calibration: one sample at a time, constant memory.

    cal = OnlineCalibrator.from_file("cal.json", FilterConfig(sensor_noise_nt=40))
    for sample in stream:                     # a dict (or pandas row) with the log's column names
        result = cal.step(sample)
        use(result.field_body, result.heading_true_deg, result.status)

A sample carries ``time`` (UNIX s), ``mag_x, mag_y, mag_z`` (nT), and when available ``roll, pitch,
yaw`` (deg), ``lat, lon, alt`` (or ``ref_n, ref_e, ref_d``), ``dop`` and the auxiliary columns the
effects need. Missing keys or NaN values mean missing. The reference field is evaluated lazily and
cached (``ReferenceFieldCache``): again only after the vehicle has moved ``reference_refresh_m`` or the
UTC date has changed. Each step is the same gated update as post-processing, with a block of one epoch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import FilterConfig
from ..conventions import (
    ATTITUDE,
    MAG,
    REF,
    declination_deg,
    euler_to_dcm,
    magnetic_heading_deg,
    ned_to_body,
)
from ..effects.base import EpochData
from ..effects.core import SoftHardIron
from ..io.calibration import Calibration
from ..reference import ReferenceFieldCache
from .estimator import STATUSES, USED, Estimator
from .filters import inv_small
from .measurements import vector_noise, whitening
from .run import sample_status
from .state import StateLayout

_IDENTITY = np.eye(3)[None]
_NAN33 = np.full((3, 3), np.nan)


@dataclass(frozen=True)
class EpochResult:
    """What ``OnlineCalibrator.step`` returns for one sample.

    ``field_body`` (3,) calibrated body field, nT (with the estimate after this step); ``magnitude_nt``;
    ``heading_mag_deg`` and ``heading_true_deg`` (NaN without attitude or position); ``status`` (one of
    ``magkf.estimator.STATUSES``), ``updated``, ``nis``; ``R`` (3, 3), ``b`` (3,), ``std`` (n,) the
    current estimate's standard deviations in state order, ``x`` (n,) the whole state.
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


class OnlineCalibrator:
    """Streaming calibration from an initial calibration (``init``) with its covariance.

    ``config`` gives the noise, gates and random walks; ``effects`` extra ``Effect`` blocks with their
    own priors. Memory does not grow with the number of steps.
    """

    def __init__(self, init: Calibration, config: FilterConfig = FilterConfig(), effects=()):
        self.config = config
        if init.covariance is not None:
            P_core = np.array(init.covariance)
        else:
            P_core = np.diag(np.concatenate([np.full(9, config.init_r_std**2), np.full(3, config.init_b_std**2)]))
        core = SoftHardIron(init.state, np.sqrt(np.diag(P_core)), config.r_walk, config.b_walk)
        self.layout = StateLayout((core, *effects))
        x0, P0 = self.layout.prior()
        P0[:12, :12] = P_core
        self.estimator = Estimator(self.layout, config, x0, P0)
        self.reference = ReferenceFieldCache(config.reference_refresh_m)
        self._last_time = None

    @classmethod
    def from_file(cls, path, config: FilterConfig = FilterConfig(), effects=()) -> "OnlineCalibrator":
        """Start from a calibration file (JSON)."""
        return cls(Calibration.load(path), config, effects)

    @property
    def calibration(self) -> Calibration:
        """The current estimate as a calibration with its 12x12 covariance."""
        x, P = self.estimator.x, self.estimator.P
        return Calibration(R=x[:9].reshape(3, 3), b=x[9:12], method=f"{self.config.filter}-online",
                           covariance=P[:12, :12])

    def step(self, sample) -> EpochResult:
        """Process one sample (a mapping of column names to values); returns an ``EpochResult``."""
        get = _getter(sample)
        t = get("time")
        m = np.array([get(c) for c in MAG])
        roll, pitch, yaw = (get(c) for c in ATTITUDE)
        ref = self._reference(t, get)
        has_att = bool(np.isfinite(roll) and np.isfinite(pitch) and np.isfinite(yaw))
        c_nb = euler_to_dcm(yaw, pitch, roll) if has_att else _NAN33
        field_body = ned_to_body(c_nb, ref)
        dop = get("dop")
        if not np.isfinite(dop):
            dop = get("pdop") if np.isfinite(get("pdop")) else get("hdop")
        base = np.array([sample_status(m, ref, has_att, dop, self.config.dop_max)], dtype=np.int8)
        columns = {c: np.array([get(c)]) for e in self.layout.extra() for c in e.columns}
        data = EpochData(np.array([t]), field_body[None], ref[None], columns)
        H = np.concatenate([e.jacobian(self.estimator.x[sl], data) if e.linear else np.zeros((1, 3, e.size))
                            for e, sl in zip(self.layout.effects, self.layout.slices.values())], axis=2)
        x = self.estimator.x
        if base[0] == USED and self.config.measure != "magnitude":
            W = whitening(vector_noise(field_body[None], x[:9].reshape(3, 3), self.config, self.config.measure))
        else:
            W = _IDENTITY  # not used: the sample has no vector update
        dt = 0.0 if self._last_time is None else t - self._last_time
        self._last_time = t
        status, updated, nis = self.estimator.process_block(
            np.array([t]), dt, m[None], np.array([np.linalg.norm(ref)]), H, W, base,
            data if self.estimator.nonlinear else None)
        x = self.estimator.x
        R, b = x[:9].reshape(3, 3), x[9:12]
        e = np.einsum("kij,j->ki", H[:, :, 12:], x[12:])[0] if self.layout.size > 12 else 0.0
        field = inv_small(R) @ (m - b - e)
        heading = float(magnetic_heading_deg(field, roll, pitch)) if has_att else float("nan")
        return EpochResult(time=t, field_body=field, magnitude_nt=float(np.linalg.norm(field)),
                           heading_mag_deg=heading,
                           heading_true_deg=float((heading + declination_deg(ref)) % 360.0),
                           status=STATUSES[int(status[0])], updated=bool(updated[0]), nis=float(nis[0]),
                           R=R.copy(), b=b.copy(), std=np.sqrt(np.diag(self.estimator.P)), x=x.copy())

    def _reference(self, t, get) -> np.ndarray:
        ref = np.array([get(c) for c in REF])
        if np.all(np.isfinite(ref)):
            return ref
        lat, lon, alt = get("lat"), get("lon"), get("alt")
        if not (np.isfinite(lat) and np.isfinite(lon)):
            return np.full(3, np.nan)
        return self.reference.ned(t, lat, lon, alt if np.isfinite(alt) else 0.0)


def _getter(sample):
    """A function name -> float (NaN when absent, empty or None) over a mapping or pandas row."""
    def get(name: str) -> float:
        try:
            v = sample[name]
        except (KeyError, IndexError):
            return float("nan")
        try:
            return float(v)
        except (TypeError, ValueError):
            return float("nan")
    return get
