"""What a live calibration shows its operator, once a second: one ``LiveStatus`` (numbers in SI-like units as
named; nothing here is computed, ``session.LiveSession.status`` fills it)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

__all__ = ["LiveStatus"]


@dataclass
class LiveStatus:
    """One snapshot of a live calibration.

    Parameters
    ----------
    elapsed_s : float
        Seconds of the vehicle's clock since the first sample.
    utc : float
        UNIX s of the last sample (NaN before the first).
    counts : dict of str to int
        Epochs by status name (``magkf.status``): ``used``, ``gated_dop``, ...; ``waiting`` the epochs held for
        the start (``bootstrap``) before the filter runs.
    link : dict
        The link's figures: ``packets``, ``lost`` (by sequence numbers), ``lost_share``, ``reordered``,
        ``reboots``, ``link_drops``, ``rates_hz`` (message name -> measured Hz) and ``asked_hz`` (message name ->
        Hz asked).
    residual_rms_nt : float
        RMS of the vector residual over the recent used epochs, nT.
    noise : dict
        Learned noise: ``sensor_nt``, ``attitude_deg``, ``heading_deg``.
    b_nt, b_std_nt : list of float
        (3,) the offsets and their standard deviations, nT.
    r_diag, r_diag_std : list of float
        (3,) the diagonal of ``R`` and its standard deviations.
    undetermined : list of str
        What the data do not determine yet, in words (``"turn through 90 more degrees of heading"``).
    verdict : str
        The fit in words.
    diagnosis : dict or None
        The running diagnosis over a sliding window: ``window_s``, ``candidates`` (list of ``{"effect", "p_value",
        "significant"}``), ``text``; None before the first.
    converged : bool
        Whether every parameter's standard deviation is below the target (``--until-converged``).
    target : float or None
        That target (a fraction: of 1 for ``R``, of the field for ``b``); None: none set.
    events : list of str
        The link's and the session's recent events, newest last.
    step_ms : dict
        The filter step's time over the recent steps, ms: ``median`` and ``p99``; and ``samples``, the median
        number of samples a step filtered (one step a poll: its samples filtered as one block).
    """

    elapsed_s: float = 0.0
    utc: float = float("nan")
    counts: dict = field(default_factory=dict)
    link: dict = field(default_factory=dict)
    residual_rms_nt: float = float("nan")
    noise: dict = field(default_factory=dict)
    b_nt: list = field(default_factory=lambda: [float("nan")] * 3)
    b_std_nt: list = field(default_factory=lambda: [float("nan")] * 3)
    r_diag: list = field(default_factory=lambda: [float("nan")] * 3)
    r_diag_std: list = field(default_factory=lambda: [float("nan")] * 3)
    undetermined: list = field(default_factory=list)
    verdict: str = "waiting for the first samples"
    diagnosis: dict | None = None
    converged: bool = False
    target: float | None = None
    events: list = field(default_factory=list)
    step_ms: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """The snapshot as plain JSON-ready values."""
        return asdict(self)
