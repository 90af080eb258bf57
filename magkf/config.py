"""Settings of the online calibration, with their units and defaults."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

__all__ = ["FilterConfig", "NOISE_METHODS"]

#: How the noise is learned from the innovations (``magkf.online.noise``).
NOISE_METHODS = ("matching", "variational")


@dataclass(frozen=True)
class FilterConfig:
    """Settings of ``magkf calibrate`` and ``OnlineCalibrator``, with their units and defaults.

    Measurement noise, from which every measurement covariance follows: ``sensor_noise_nt``,
    ``attitude_deg`` and ``reference_nt``. With ``adapt_noise`` (the default) the first two are only the
    prior: the noise is learned from the log (``magkf.online.noise``), starting from a robust scale of a first
    whole-log fit, forgetting over ``noise_window_s`` seconds, by ``noise_method``, never below
    ``noise_floor_nt``; tilt and heading errors apart; the correlation of the residuals in time is measured
    and each epoch counts accordingly. Process noise (random walk): ``r_walk``, ``b_walk``. Gates:
    ``dop_max``, the magnitude gate (``gate_sigma``, ``gate_nt``), ``innovation_prob``, ``huber_prob``,
    ``max_gated_s``. Initialisation: ``bootstrap_s``, ``init_r_std``, ``init_b_std``.

    Parameters
    ----------
    filter : str, default "ekf"
        ``ekf``, ``ukf`` or a registered filter's name (``magkf.plugins.FILTERS``).
    measure : str, default "both"
        ``magnitude``, ``vector``, ``both`` or a registered model's name (``magkf.plugins.MEASUREMENTS``).
    sensor_noise_nt : float, default 30.0
        Noise of each magnetometer axis, nT.
    attitude_deg : float, default 0.1
        Attitude uncertainty of the INS, degrees (1 sigma, each axis).
    reference_nt : float, default 10.0
        Uncertainty of each reference-field component, nT (crustal anomalies, model error, diurnal
        variation); not learned.
    r_walk : float, default 1e-7
        Random walk of each element of ``R``, per sqrt(s).
    b_walk : float, default 0.01
        Random walk of each offset, nT per sqrt(s).
    dop_max : float, default 5.0
        No update where ``dop > dop_max``.
    gate_nt : float, default 0.0
        Magnitude gate: no update where ``| |calibrated m| - |B_ref| |`` exceeds ``gate_sigma`` standard
        deviations of the (learned) total-field noise, or ``gate_nt`` nT if that is wider, plus 3 sigma of
        the calibrated magnitude implied by the estimate's covariance.
    gate_sigma : float, default 5.0
        The magnitude gate's width in standard deviations of the (learned) total-field noise (``gate_nt``).
    innovation_prob : float, default 0.999
        No update where the normalised innovation squared (in units of the learned noise) exceeds the
        chi-square quantile of this probability (degrees of freedom = measurement size).
    huber_prob : float, default 0.99
        Beyond this quantile and up to the gate, an epoch is down-weighted (Huber weight ``sqrt(q / NIS)``)
        instead of refused, so that heavy tails do not starve the filter.
    adapt_noise : bool, default True
        Learn the sensor and attitude noise from the log; else keep them as configured.
    noise_method : str, default "variational"
        How the noise is learned: ``variational``, or ``matching`` (innovation covariance matching);
        compared in ``scripts/noise_study.py``.
    noise_window_s : float, default 60.0
        The noise learner forgets over this many seconds.
    noise_floor_nt : float, default 1.0
        The learned noise is never below this, nT.
    max_gated_s : float, default 30.0
        After this many seconds of consecutive innovation gating with good DOP and magnitude, the covariance
        is inflated so that the filter can re-acquire (0 disables).
    bootstrap_s : float, default 120.0
        Length of the first stretch used by the batch bootstrap when no calibration is given, s.
    init_r_std : float, default 0.02
        Standard deviation given to each element of ``R`` of an offline calibration that carries no
        covariance.
    init_b_std : float, default 300.0
        Standard deviation given to each offset of an offline calibration that carries no covariance, nT.
    reference_refresh_m : float, default 2000.0
        Distance after which the real-time path re-evaluates IGRF, m.
    block_s : float, default 1.0
        Duration of the blocks of epochs that update the filter together when post-processing a log, s (each
        epoch is still gated on its own; see ``magkf.online.estimator``). 0 updates epoch by epoch, as the
        real-time path does.
    model : str, default "auto"
        The model family a post-processing run writes (``magkf.families``): ``offsets``, ``scale``,
        ``soft-iron``, ``full``, or ``auto``, the richest the log determines.

    Raises
    ------
    ValueError
        A setting out of its range (not finite, negative, not positive where it must be, beyond its largest
        value) or an unknown filter, measurement model or noise method.
    """

    filter: str = "ekf"
    measure: str = "both"
    sensor_noise_nt: float = 30.0
    attitude_deg: float = 0.1
    reference_nt: float = 10.0
    r_walk: float = 1e-7
    b_walk: float = 0.01
    dop_max: float = 5.0
    gate_nt: float = 0.0
    gate_sigma: float = 5.0
    innovation_prob: float = 0.999
    huber_prob: float = 0.99
    adapt_noise: bool = True
    noise_method: str = "variational"
    noise_window_s: float = 60.0
    noise_floor_nt: float = 1.0
    max_gated_s: float = 30.0
    bootstrap_s: float = 120.0
    init_r_std: float = 0.02
    init_b_std: float = 300.0
    reference_refresh_m: float = 2000.0
    block_s: float = 1.0
    model: str = "auto"

    def __post_init__(self):
        from .plugins import FILTERS, MEASUREMENTS

        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float | int) and not isinstance(value, bool) and not math.isfinite(value):
                raise ValueError(f"{f.name} must be a finite number, got {value!r}")
        for name in ("attitude_deg", "reference_nt", "r_walk", "b_walk", "max_gated_s", "init_r_std", "init_b_std"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must not be negative")
        for name, most in (("r_walk", 1.0), ("b_walk", 1e5), ("sensor_noise_nt", 1e6), ("attitude_deg", 90.0)):
            if getattr(self, name) > most:
                raise ValueError(f"{name} must not exceed {most:g}")
        if not self.reference_refresh_m > 0:
            raise ValueError("reference_refresh_m must be positive")
        for name, known in (("filter", FILTERS), ("measure", MEASUREMENTS)):
            if getattr(self, name) not in known:
                raise ValueError(f"{name} must be one of {', '.join(known)}, got {getattr(self, name)!r}")
        for name in ("sensor_noise_nt", "bootstrap_s", "dop_max", "gate_sigma", "noise_window_s", "noise_floor_nt"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if not self.gate_nt >= 0:
            raise ValueError("gate_nt must not be negative")
        if not 0 < self.huber_prob < 1:
            raise ValueError("huber_prob must lie between 0 and 1")
        if self.noise_method not in NOISE_METHODS:
            raise ValueError(f"noise_method must be one of {', '.join(NOISE_METHODS)}, got {self.noise_method!r}")
        from .families import MODEL_CHOICES

        if self.model not in MODEL_CHOICES:
            raise ValueError(f"model must be one of {', '.join(MODEL_CHOICES)}, got {self.model!r}")
        if self.block_s < 0:
            raise ValueError("block_s must not be negative")
        if not 0 < self.innovation_prob < 1:
            raise ValueError("innovation_prob must lie between 0 and 1")

    def replace(self, **changes) -> FilterConfig:
        """A copy with some settings changed.

        Parameters
        ----------
        **changes
            Settings by name, as the constructor takes them.

        Returns
        -------
        FilterConfig
            The new settings, checked as the constructor checks them.
        """
        return replace(self, **changes)

    def as_dict(self) -> dict:
        """The settings as a dictionary.

        Returns
        -------
        dict
            Setting name -> value, in the order of the fields.
        """
        return asdict(self)
