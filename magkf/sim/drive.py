"""Simulated drive and flight logs with known truth.

``simulate_drive(DriveConfig(...), truth)`` returns a ``SimulatedDrive``: the canonical log table and
the truth behind it. The raw field is

    m = R (C_nb^T B_ref + d) + b + sum(effect contributions) + noise

with ``B_ref`` the IGRF field along the track, ``d`` the body-frame disturbances, and ``R`` the sensor
matrix times the mounting. Physical effects plug in through ``effects``: pairs ``(effect, theta)`` of an
``Effect`` (the same class the filter, batch solver and diagnostics use) and its true parameters; the
effect's ``simulate`` adds its contribution, evaluated on the reading without effects.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime

import numpy as np
import pandas as pd

from ..calibration import Calibration
from ..conventions import ATTITUDE, MAG, REF, TIME, euler_to_dcm, ned_to_body
from ..effects.base import EpochData, rate_of_change
from ..files import output_text
from ..io.drivelog import write_drive_log
from ..offline.sinefit import SineFitParameters
from ..reference import igrf_ned
from .disturbance import simulate_disturbances
from .gnss import simulate_dop
from .motion import simulate_motion, smooth_noise
from .mounting import mounting_matrix
from .realism import coloured, gauss_markov, realism_rng

__all__ = ["DEFAULT_START", "DriveConfig", "SimulatedDrive", "true_matrix", "simulate_drive"]

DEFAULT_START = datetime(2026, 6, 1, 10, 0, tzinfo=UTC).timestamp()


@dataclass(frozen=True)
class DriveConfig:
    """Settings of a simulated log. Durations in seconds, rates in Hz, fields in nT, angles in degrees.

    ``motion`` is ``"3d"`` or ``"planar"``; ``mounting`` a signed permutation such as ``"-y,x,z"``
    (sensor axis i along the named body axis); ``disturbances`` the number of disturbance events and
    ``disturbance_peak_nt`` their peak range; ``dop_bad_stretches`` the number of bad-DOP stretches;
    ``write_reference`` adds the ``ref_n, ref_e, ref_d`` columns; ``tilt_deg`` is the roll and pitch
    standard deviation of planar motion.

    Realism (``magkf.sim.realism``; all off by default): ``noise_correlation_s`` makes the sensor noise a
    first-order Gauss-Markov process of that correlation time (standard deviation still ``noise_nt``);
    ``attitude_wander_deg`` (roll, pitch, yaw) is the standard deviation of the logged attitude's error, a
    Gauss-Markov process of correlation time ``attitude_wander_s`` (a bounded random walk); ``interference_nt``
    is the standard deviation per body axis of a slowly varying field nobody modelled, correlation time
    ``interference_s``.
    """

    duration_s: float = 600.0
    rate_hz: float = 50.0
    motion: str = "3d"
    noise_nt: float = 30.0
    seed: int = 0
    start_time: float = DEFAULT_START
    lat0: float = 48.1
    lon0: float = 11.6
    alt0: float = 500.0
    mounting: str = "x,y,z"
    disturbances: int = 6
    disturbance_peak_nt: tuple = (1000.0, 5000.0)
    disturbance_duration_s: tuple = (2.0, 8.0)
    dop_bad_stretches: int = 3
    write_reference: bool = False
    tilt_deg: float = 0.8
    noise_correlation_s: float = 0.0
    attitude_wander_deg: tuple = (0.0, 0.0, 0.0)
    attitude_wander_s: float = 60.0
    interference_nt: float = 0.0
    interference_s: float = 30.0


@dataclass(frozen=True)
class SimulatedDrive:
    """A simulated log and its truth.

    ``table`` is the canonical log indexed by time; ``R`` (3, 3) and ``b`` (3,) the true calibration
    (mounting included); ``reference_ned`` (N, 3) the true field; ``field_body`` (N, 3) the true body
    field without disturbances; ``disturbance`` (N, 3) the body-frame disturbance; ``dop_bad`` (N,)
    marks the bad-DOP stretches; ``events`` lists the disturbance events; ``effects`` the simulated
    ``(effect, theta)`` pairs and ``contributions`` their raw-field contributions (N, 3);
    ``sensor_noise`` (N, 3) nT the noise added to the reading, ``attitude_error`` (N, 3) deg the logged
    roll, pitch and yaw less the true ones, ``interference`` (N, 3) nT the unmodelled body-frame field.
    """

    table: pd.DataFrame
    R: np.ndarray
    b: np.ndarray
    config: DriveConfig
    reference_ned: np.ndarray
    field_body: np.ndarray
    disturbance: np.ndarray
    dop_bad: np.ndarray
    events: list = field(default_factory=list)
    dop_stretches: list = field(default_factory=list)
    effects: list = field(default_factory=list)
    contributions: list = field(default_factory=list)
    sensor_noise: np.ndarray | None = None
    attitude_error: np.ndarray | None = None
    interference: np.ndarray | None = None

    @property
    def calibration(self) -> Calibration:
        return Calibration(R=self.R, b=self.b, method="truth")

    def truth(self) -> dict:
        """JSON-ready truth: ``R``, ``b``, settings, and the disturbance and bad-DOP stretches (times in s)."""
        t = self.table.index.to_numpy()

        def span(a, z):
            return {"start": float(t[a]), "stop": float(t[min(z, len(t)) - 1])}

        return {
            "format": "magkf-truth",
            "version": 1,
            "R": self.R.tolist(),
            "b": self.b.tolist(),
            "config": asdict(self.config),
            "disturbances": [{**span(e["start"], e["stop"]), "peak_nt": e["peak_nt"]} for e in self.events],
            "dop_bad": [span(a, z) for a, z in self.dop_stretches],
            "effects": [{**e.describe(), "truth": np.asarray(theta, float).tolist()} for e, theta in self.effects],
        }

    def write(self, csv_path, truth_path=None) -> None:
        """Write the canonical CSV and, if ``truth_path`` is given, the truth JSON."""
        write_drive_log(self.table, csv_path)
        if truth_path is not None:
            output_text(truth_path, json.dumps(self.truth(), indent=2) + "\n")


def true_matrix(truth) -> tuple[np.ndarray, np.ndarray]:
    """``(R, b)`` from a Calibration, SineFitParameters, or a pair ``(R, b)``."""
    if isinstance(truth, Calibration):
        return np.array(truth.R), np.array(truth.b)
    if isinstance(truth, SineFitParameters):
        return truth.matrix(), np.array(truth.b, float)
    R, b = truth
    return np.asarray(R, float), np.asarray(b, float)


def simulate_drive(config: DriveConfig = DriveConfig(), truth=None, effects=()) -> SimulatedDrive:
    """Simulate a log. ``truth`` is a Calibration, SineFitParameters or ``(R, b)``; by default a
    realistic soft- and hard-iron calibration. The mounting of ``config`` is applied after it.
    ``effects`` are ``(Effect, theta)`` pairs added to the raw field."""
    rng = np.random.default_rng(config.seed)
    n = int(round(config.duration_s * config.rate_hz))
    K, b = true_matrix(_default_truth() if truth is None else truth)
    R = K @ mounting_matrix(config.mounting)
    t = config.start_time + np.arange(n) / config.rate_hz
    motion = simulate_motion(
        config.motion, n, config.rate_hz, rng, config.lat0, config.lon0, config.alt0, config.tilt_deg
    )
    dop, stretches = simulate_dop(n, config.rate_hz, rng, config.dop_bad_stretches)
    disturbance, events = simulate_disturbances(
        n,
        config.rate_hz,
        rng,
        config.disturbances,
        config.disturbance_peak_nt,
        config.disturbance_duration_s,
        inside=stretches,
    )
    ref = igrf_ned(t, motion["lat"], motion["lon"], motion["alt"])
    c_nb = euler_to_dcm(motion["yaw"], motion["pitch"], motion["roll"])
    field_body = ned_to_body(c_nb, ref)
    extra = realism_rng(config.seed)
    attitude_error = gauss_markov(n, config.rate_hz, config.attitude_wander_deg, config.attitude_wander_s, extra)
    interference = gauss_markov(n, config.rate_hz, config.interference_nt, config.interference_s, extra)
    table = _log_table(config, t, motion, attitude_error, dop, ref, rng)
    sensor_noise = config.noise_nt * coloured(rng.normal(size=(n, 3)), config.rate_hz, config.noise_correlation_s)
    mag = (field_body + disturbance + interference) @ R.T + b + sensor_noise
    contributions = _contributions(effects, table, field_body, ref, mag, c_nb, R, rng)
    for c in contributions:
        mag = mag + c
    for i, name in enumerate(MAG):
        table.insert(1 + i, name, mag[:, i])
    return SimulatedDrive(
        table=table.set_index(TIME),
        R=R,
        b=b,
        config=config,
        reference_ned=ref,
        field_body=field_body,
        disturbance=disturbance,
        dop_bad=_marked(n, stretches),
        events=events,
        dop_stretches=stretches,
        effects=list(effects),
        contributions=contributions,
        sensor_noise=sensor_noise,
        attitude_error=attitude_error,
        interference=interference,
    )


def _default_truth() -> tuple[np.ndarray, np.ndarray]:
    """The default true calibration ``(R, b)``: a realistic soft iron (3, 3) and hard iron (3,) nT."""
    return (np.array([[1.05, 0.03, -0.02], [0.01, 0.97, 0.04], [-0.03, 0.02, 1.02]]), np.array([350.0, -220.0, 480.0]))


def _log_table(config: DriveConfig, t, motion: dict, attitude_error, dop, ref, rng) -> pd.DataFrame:
    """The log without its magnetometer columns: time (s), position, the logged attitude (the truth plus
    ``attitude_error`` (N, 3) deg), DOP, speed, temperature, current and, with ``write_reference``, the
    reference field ``ref`` (N, 3) nT. Draws the temperature's and current's noise from ``rng``."""
    table = pd.DataFrame({TIME: t})
    for name in ("lat", "lon", "alt"):
        table[name] = motion[name]
    for k, name in enumerate(ATTITUDE):  # the logged attitude: the truth and its error
        table.insert(1 + k, name, motion[name] + attitude_error[:, k])
    if any(config.attitude_wander_deg):
        table["yaw"] %= 360.0
    table["dop"] = dop
    table["speed_mps"] = motion["speed_mps"]
    table["temp_c"] = _temperature(t, config.rate_hz, rng)
    table["current_a"] = _current(len(t), config.rate_hz, rng)
    if config.write_reference:
        for i, name in enumerate(REF):
            table[name] = ref[:, i]
    return table


def _temperature(t, rate_hz: float, rng) -> np.ndarray:
    """The sensor temperature (N,) degC at times ``t`` (N,) s: a warm-up, a slow wander (sun and shade,
    heater cycles) and sensor noise."""
    n = len(t)
    return (
        20.0
        + 10.0 * (1 - np.exp(-(t - t[0]) / 900.0))
        + 3.0 * smooth_noise(n, rate_hz, 120.0, rng)
        + 0.1 * rng.normal(size=n)
    )


def _current(n: int, rate_hz: float, rng) -> np.ndarray:
    """A load current (n,) A switching between about 2 and 27 A, on average every 20 s, with noise."""
    load = (np.cumsum(rng.random(n) < 1.0 / (20.0 * rate_hz)) % 2).astype(float)
    return 2.0 + 25.0 * load + 0.3 * rng.normal(size=n)


def _contributions(effects, table: pd.DataFrame, field_body, ref, mag, c_nb, R, rng) -> list:
    """Each effect's raw-field contribution (N, 3) nT for its true ``theta``, evaluated on the reading
    without effects ``mag`` (N, 3) nT and the log's columns other than the attitude (``table``, time first)."""
    t = table[TIME].to_numpy()
    data = EpochData(
        t,
        field_body,
        ref,
        {c: table[c].to_numpy() for c in table.columns if c not in ATTITUDE},
        mag=mag.copy(),
        c_nb=c_nb,
        field_body_rate=rate_of_change(t, field_body),
        R0=R,
    )
    return [effect.simulate(np.asarray(theta, float), data, rng) for effect, theta in effects]


def _marked(n: int, stretches) -> np.ndarray:
    """A mask (n,) true inside the ``(start, stop)`` epoch stretches."""
    mask = np.zeros(n, bool)
    for a, z in stretches:
        mask[a:z] = True
    return mask
