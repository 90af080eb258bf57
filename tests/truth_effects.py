"""Physical effects written from their physics, independently of magkf's effect classes, for judging magkf
against the truth.

magkf's simulator (``magkf.sim.simulate_drive``) makes a clean log (no effect) and keeps its truth: the true
body-frame field, the disturbances, the sensor noise, the attitude error, the true calibration ``R, b``.
``hidden_log`` adds to the log's reading, in sensor axes and nT, the contribution of each hidden effect,
computed here from those true quantities (the true attitude, the true field, the log's auxiliary channels),
with the parameter conventions docs/effects.md states (units, ``T0 = 20 degC``, signs):

* ``temperature_bias``: an offset ``k (T - T0)`` per sensor axis, ``k`` in nT/degC;
* ``temperature_scale``: each axis's sensitivity changes by ``s (T - T0)`` (``s`` in 1/degC), scaling the whole
  reading the sensor would give at ``T0`` (field and hard iron alike);
* ``current_field``: ``c I`` per sensor axis, ``c`` in nT/A;
* ``time_lag``: the sensor reads the field of ``tau`` seconds earlier: ``R B(t - tau)`` in place of
  ``R B(t)``, with ``B(t - tau)`` interpolated in time through the true body field (a cubic spline);
* ``field_anomaly``: a constant NED offset ``d`` (nT) of the true field, turned into body axes by the true
  attitude and seen through ``R``: ``R C_nb^T d``;
* ``bias_drift``: an offset wandering as a random walk of ``W`` nT/sqrt(s) on each axis, from zero;
* ``eddy_current``: ``E dB/dt`` with ``E`` (3x3, s, row-major) in sensor axes and ``dB/dt`` the time
  derivative of the true body field.

The body field the sensor sees is the whole physical field: the Earth's (``field_body``), the simulator's
disturbances and interference, and the early disturbance this module can add. Only the epochs away from any
disturbance are judged (``TruthLog.clean``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

__all__ = [
    "TRUE_PARAMETERS",
    "EFFECT_NAMES",
    "MAG_COLUMNS",
    "NOISES",
    "TruthInputs",
    "TruthLog",
    "contribution",
    "true_dcm",
    "hidden_log",
    "early_disturbance",
]

T0_DEGC = 20.0  # the reference temperature of the temperature effects (magkf's default)
MAG_COLUMNS = ("mag_x", "mag_y", "mag_z")
#: Seconds on each side of a disturbance left out of the judgement (the lag and the derivative reach a few
#: epochs beyond it; a second is ample at 10 Hz and more).
DISTURBANCE_MARGIN_S = 1.0

#: Hidden effects of realistic size: tens to hundreds of nT on a 10-minute log against 30 nT of noise.
TRUE_PARAMETERS = {
    "temperature_bias": (8.0, -5.0, 6.0),  # nT/degC
    "temperature_scale": (3e-4, -2e-4, 2e-4),  # 1/degC
    "current_field": (12.0, -8.0, 5.0),  # nT/A
    "time_lag": (0.05,),  # s (hundreds of nT on a drone turning at tens of deg/s)
    "field_anomaly": (150.0, -80.0, 120.0),  # nT north, east, down
    "bias_drift": (2.0,),  # nT/sqrt(s)
    "eddy_current": (1e-2, 0.0, 0.0, 0.0, -8e-3, 0.0, 0.0, 0.0, 8e-3),  # s, row-major
}
EFFECT_NAMES = tuple(TRUE_PARAMETERS)

#: Sensor noise and logged-attitude settings of ``magkf.sim.DriveConfig``: white noise with an exact attitude,
#: or Gauss-Markov noise (2 s) with the logged yaw wandering by 0.2 deg.
NOISES = {"white": {}, "coloured": {"noise_correlation_s": 2.0, "attitude_wander_deg": (0.0, 0.0, 0.2)}}


@dataclass(frozen=True)
class TruthInputs:
    """The true quantities an effect is computed from, N epochs.

    ``time`` (N,) s; ``field_body`` (N, 3) nT the whole physical field in body axes; ``c_nb`` (N, 3, 3) the true
    body-to-NED rotation; ``R`` (3, 3) and ``b`` (3,) nT the true sensor calibration; ``columns`` the log's
    auxiliary channels (``temp_c`` degC, ``current_a`` A) as arrays (N,); ``seed`` for a random effect.
    """

    time: np.ndarray
    field_body: np.ndarray
    c_nb: np.ndarray
    R: np.ndarray
    b: np.ndarray
    columns: dict
    seed: int


def _temperature_bias(theta, x: TruthInputs) -> np.ndarray:
    return np.outer(x.columns["temp_c"] - T0_DEGC, theta)


def _temperature_scale(theta, x: TruthInputs) -> np.ndarray:
    reading_at_t0 = x.field_body @ x.R.T + x.b
    return reading_at_t0 * np.outer(x.columns["temp_c"] - T0_DEGC, theta)


def _current_field(theta, x: TruthInputs) -> np.ndarray:
    return np.outer(x.columns["current_a"], theta)


def _time_lag(theta, x: TruthInputs) -> np.ndarray:
    earlier = CubicSpline(x.time - x.time[0], x.field_body, axis=0)(x.time - x.time[0] - theta[0])
    return (earlier - x.field_body) @ x.R.T


def _field_anomaly(theta, x: TruthInputs) -> np.ndarray:
    anomaly_body = np.einsum("nji,j->ni", x.c_nb, np.asarray(theta, float))  # C_nb^T d
    return anomaly_body @ x.R.T


def _bias_drift(theta, x: TruthInputs) -> np.ndarray:
    rng = np.random.default_rng([x.seed, 2029])
    dt = np.diff(x.time, prepend=x.time[0])
    steps = rng.normal(size=(len(x.time), 3)) * theta[0] * np.sqrt(dt)[:, None]
    return np.cumsum(steps, axis=0)


def _eddy_current(theta, x: TruthInputs) -> np.ndarray:
    rate = np.gradient(x.field_body, x.time - x.time[0], axis=0)  # nT/s, second-order central differences
    return rate @ np.reshape(theta, (3, 3)).T


GENERATORS = {
    "temperature_bias": _temperature_bias,
    "temperature_scale": _temperature_scale,
    "current_field": _current_field,
    "time_lag": _time_lag,
    "field_anomaly": _field_anomaly,
    "bias_drift": _bias_drift,
    "eddy_current": _eddy_current,
}


def contribution(name: str, theta, inputs: TruthInputs) -> np.ndarray:
    """The raw-field contribution (N, 3) nT, in sensor axes, of the effect ``name`` with parameters ``theta``
    (``TRUE_PARAMETERS``' units) on the true quantities ``inputs``."""
    return GENERATORS[name](np.asarray(theta, float), inputs)


def true_dcm(sim) -> np.ndarray:
    """The true body-to-NED rotations (N, 3, 3) of a ``SimulatedDrive``: the logged roll, pitch and yaw less the
    simulator's attitude error, as ZYX Euler angles (``C_nb = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    logged = sim.table[["yaw", "pitch", "roll"]].to_numpy()
    error = sim.attitude_error[:, ::-1]  # (roll, pitch, yaw) -> (yaw, pitch, roll)
    return Rotation.from_euler("ZYX", logged - error, degrees=True).as_matrix()


def early_disturbance(time_s: np.ndarray, seed: int) -> np.ndarray:
    """A body-frame disturbance (N, 3) nT within the first two minutes of ``time_s`` (N,) s: a Hann-shaped
    bump of 200 to 500 nT peak, lasting 10 to 30 s, in a random direction (seeded by ``seed``)."""
    rng = np.random.default_rng([seed, 1129])
    elapsed = time_s - time_s[0]
    duration = rng.uniform(10.0, 30.0)
    start = rng.uniform(0.0, min(120.0, elapsed[-1]) - duration)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    phase = (elapsed - start) / duration
    shape = np.where((phase > 0.0) & (phase < 1.0), np.sin(np.pi * phase) ** 2, 0.0)  # the peak at its middle
    return rng.uniform(200.0, 500.0) * shape[:, None] * direction


@dataclass(frozen=True)
class TruthLog:
    """A log with hidden effects and its truth.

    ``table`` the canonical log (time index) whose reading holds the hidden effects; ``hidden`` their names and
    ``thetas`` their parameters; ``contributions`` (N, 3) nT their summed contribution; ``field_body`` (N, 3) nT
    the true Earth field in body axes (true attitude, true reference); ``R`` (3, 3), ``b`` (3,) the true
    calibration; ``sensor_noise`` (N, 3) nT the noise in the reading; ``clean`` (N,) the epochs at least
    ``DISTURBANCE_MARGIN_S`` away from any disturbance; ``noise_correlation_s`` the noise's correlation time.
    """

    table: pd.DataFrame
    hidden: tuple
    thetas: tuple
    contributions: np.ndarray
    field_body: np.ndarray
    R: np.ndarray
    b: np.ndarray
    sensor_noise: np.ndarray
    clean: np.ndarray
    noise_correlation_s: float


def _clean_epochs(time_s: np.ndarray, disturbance: np.ndarray) -> np.ndarray:
    """Epochs (N,) at least ``DISTURBANCE_MARGIN_S`` from any epoch with a nonzero ``disturbance`` (N, 3)."""
    disturbed_t = time_s[np.any(disturbance != 0.0, axis=1)]
    if disturbed_t.size == 0:
        return np.ones(len(time_s), bool)
    i = np.clip(np.searchsorted(disturbed_t, time_s), 1, len(disturbed_t)) - 1
    j = np.clip(i + 1, 0, len(disturbed_t) - 1)
    nearest = np.minimum(np.abs(time_s - disturbed_t[i]), np.abs(time_s - disturbed_t[j]))
    return nearest > DISTURBANCE_MARGIN_S


def hidden_log(sim, hidden=(), seed: int = 0, early: bool = False, thetas=None) -> TruthLog:
    """``sim`` (a ``SimulatedDrive`` made without effects) with the effects ``hidden`` (names) added to its
    reading at ``thetas`` (default ``TRUE_PARAMETERS``), and with ``early`` a disturbance in its first two
    minutes (``early_disturbance``); ``seed`` seeds the random ones."""
    hidden = tuple(hidden)
    thetas = tuple(TRUE_PARAMETERS[h] for h in hidden) if thetas is None else tuple(thetas)
    table = sim.table.copy()
    time_s = table.index.to_numpy(float)
    extra = early_disturbance(time_s, seed) if early else np.zeros_like(sim.field_body)
    disturbance = sim.disturbance + extra
    physical = sim.field_body + disturbance + (0.0 if sim.interference is None else sim.interference)
    inputs = TruthInputs(
        time_s,
        physical,
        true_dcm(sim),
        sim.R,
        sim.b,
        {c: table[c].to_numpy(float) for c in ("temp_c", "current_a")},
        seed,
    )
    added = sum((contribution(h, th, inputs) for h, th in zip(hidden, thetas)), np.zeros_like(physical))
    table[list(MAG_COLUMNS)] = table[list(MAG_COLUMNS)].to_numpy() + extra @ sim.R.T + added
    return TruthLog(
        table=table,
        hidden=hidden,
        thetas=thetas,
        contributions=added,
        field_body=sim.field_body,
        R=sim.R,
        b=sim.b,
        sensor_noise=sim.sensor_noise,
        clean=_clean_epochs(time_s, disturbance),
        noise_correlation_s=sim.config.noise_correlation_s,
    )
