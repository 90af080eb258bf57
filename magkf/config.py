"""Settings of the online calibration, with their units and defaults."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

__all__ = ["FilterConfig"]


@dataclass(frozen=True)
class FilterConfig:
    """Settings of ``magkf calibrate`` and ``OnlineCalibrator``.

    Measurement noise (from which every measurement covariance follows)
        ``sensor_noise_nt``: white noise of each magnetometer axis, nT.
        ``attitude_deg``: attitude uncertainty of the INS, degrees (1 sigma, each axis).
        ``reference_nt``: uncertainty of each reference-field component, nT (crustal anomalies,
        model error, diurnal variation).
    Process noise (random walk)
        ``r_walk``: of each element of ``R``, per sqrt(s); ``b_walk``: of each offset, nT per sqrt(s).
    Gates
        ``dop_max``: no update where ``dop > dop_max``.
        ``gate_nt``: no update where ``| |calibrated m| - |B_ref| | > gate_nt + 3 sigma`` (sigma: the
        calibrated magnitude's standard deviation implied by the estimate's covariance).
        ``innovation_prob``: no update where the normalised innovation squared exceeds the chi-square
        quantile of this probability (degrees of freedom = measurement size).
        ``max_gated_s``: after this many seconds of consecutive innovation gating with good DOP and
        magnitude, the covariance is inflated so that the filter can re-acquire (0 disables).
    Initialisation
        ``bootstrap_s``: length of the first stretch used by the batch bootstrap when no calibration is
        given, s. ``init_r_std`` and ``init_b_std``: standard deviations given to an offline calibration
        that carries no covariance.
    Other
        ``filter``: ``ekf`` or ``ukf`` (``magkf.online.filters``). ``measure``: ``magnitude``, ``vector``,
        ``both`` or a registered model's name (``magkf.online.measurements``).
        ``reference_refresh_m``: distance after which the real-time path re-evaluates IGRF, m.
        ``block_s``: duration of the blocks of epochs that update the filter together when
        post-processing a log, s (each epoch is still gated on its own; see ``magkf.online.estimator``).
        0 updates epoch by epoch, as the real-time path does.
    """

    filter: str = "ekf"
    measure: str = "both"
    sensor_noise_nt: float = 30.0
    attitude_deg: float = 0.1
    reference_nt: float = 10.0
    r_walk: float = 1e-7
    b_walk: float = 0.01
    dop_max: float = 5.0
    gate_nt: float = 1000.0
    innovation_prob: float = 0.999
    max_gated_s: float = 30.0
    bootstrap_s: float = 120.0
    init_r_std: float = 0.02
    init_b_std: float = 300.0
    reference_refresh_m: float = 2000.0
    block_s: float = 0.25

    def __post_init__(self):
        from .online.filters import FILTERS
        from .online.measurements import MEASUREMENTS

        for name, known in (("filter", FILTERS), ("measure", MEASUREMENTS)):
            if getattr(self, name) not in known:
                raise ValueError(f"{name} must be one of {', '.join(known)}, got {getattr(self, name)!r}")
        for name in ("sensor_noise_nt", "bootstrap_s", "gate_nt", "dop_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.block_s < 0:
            raise ValueError("block_s must not be negative")
        if not 0 < self.innovation_prob < 1:
            raise ValueError("innovation_prob must lie between 0 and 1")

    def replace(self, **changes) -> FilterConfig:
        return replace(self, **changes)

    def as_dict(self) -> dict:
        return asdict(self)
