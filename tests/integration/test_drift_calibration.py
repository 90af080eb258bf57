"""A wandering offset (``bias_drift``) calibrated, written and applied, judged against the simulator's truth.

The logs have no disturbance events (their thousands of nT on epochs ``apply`` calls ok would swamp the
comparison) and white noise of 30 nT per axis, so the truth-judged residual's floor is about 52 nT (the norm of
three axes). Comparisons between two calibrations of one log are paired: each epoch's squared error under one
minus under the other, its mean with a standard error from batch means of ``BATCH_S`` seconds (the drift makes
the differences correlated over seconds, not over a minute), bounded by the one-sided 99.9 % quantile of
Student's t for the batches.
"""

import numpy as np
import pytest
from scipy import stats

from magkf.apply import apply_calibration
from magkf.calibration import Calibration
from magkf.effects import BUILTIN
from magkf.io.drivelog import from_table
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import cli_json

WALK = 2.0
BATCH_S = 30.0


def _flight(seed: int, duration_s: float = 600.0, rate_hz: float = 10.0):
    sim = simulate_drive(
        DriveConfig(duration_s=duration_s, rate_hz=rate_hz, noise_nt=30, seed=seed, disturbances=0),
        effects=[(BUILTIN["bias_drift"](), [WALK])],
    )
    return sim, from_table(sim.table.reset_index(), f"flight {seed}")


def _errors(sim, log, cal: Calibration) -> tuple[np.ndarray, np.ndarray, object]:
    """The calibrated body field minus the true one (N, 3) nT as ``apply`` gives it, the epochs with status ok
    (N,), and ``apply``'s table."""
    out = apply_calibration(log, cal)
    field = out[["field_x", "field_y", "field_z"]].to_numpy()
    return field - sim.field_body, (out["status"] == "ok").to_numpy(), out


def _last_value_errors(sim, log, run) -> np.ndarray:
    """What the files written before gave: the filter's last state, the drift's last value taken as a constant
    offset on every epoch (N, 3) nT."""
    x = run.filter_x
    R, b, d = x[:9].reshape(3, 3), x[9:12], x[12:15]
    return np.linalg.solve(R, (log.mag - b - d).T).T - sim.field_body


def _paired(errors_a, errors_b, ok, time) -> tuple[float, float]:
    """``(mean, bound)``: the mean over the ok epochs of ``|e_a|^2 - |e_b|^2`` (nT^2) and the one-sided 99.9 %
    bound of its chance part (batch means of ``BATCH_S``)."""
    d = (np.sum(errors_a**2, axis=1) - np.sum(errors_b**2, axis=1))[ok]
    batch = np.floor((time[ok] - time[0]) / BATCH_S).astype(int)
    means = np.array([d[batch == k].mean() for k in np.unique(batch)])
    k = len(means)
    return float(d.mean()), float(stats.t.ppf(0.999, k - 1) * means.std(ddof=1) / np.sqrt(k))


def _rms(errors, ok) -> float:
    return float(np.sqrt(np.mean(np.sum(errors[ok] ** 2, axis=1))))


@pytest.fixture(scope="module")
def flights():
    """One flight calibrated without and with the drift, and a second flight of the same vehicle (another seed:
    another realisation of the drift)."""
    sim, log = _flight(1, rate_hz=5.0)
    without = calibrate_log(log)
    with_drift = calibrate_log(log, effects=[BUILTIN["bias_drift"]()])
    return sim, log, without, with_drift, _flight(1001, rate_hz=5.0)


def test_on_its_own_log_the_path_brings_the_residual_to_the_noise(flights):
    """The file with the drift, applied to the log it was learned on, is no worse than the file without it and
    better than the drift's last value taken as a constant (measured on these 600 s at 5 Hz: 50.8, 60.2 and
    73.9 nT), and
    within 5 % of the noise floor (sqrt(3) * 30 nT)."""
    sim, log, without, with_drift, _ = flights
    new, ok, _ = _errors(sim, log, with_drift.calibration)
    none, _, _ = _errors(sim, log, without.calibration)
    old = _last_value_errors(sim, log, with_drift)
    mean, bound = _paired(new, none, ok, log.time)
    assert mean <= bound, f"path {_rms(new, ok):.1f} nT against {_rms(none, ok):.1f} without the drift"
    mean, bound = _paired(new, old, ok, log.time)
    assert mean + bound < 0, f"path {_rms(new, ok):.1f} nT against {_rms(old, ok):.1f} with the last value"
    assert _rms(new, ok) < 1.05 * np.sqrt(3) * 30.0


def test_on_another_flight_the_mean_is_no_worse_than_no_drift(flights):
    """On a second flight (the same start time, another drift) the file is told from its own log by its
    fingerprint: it takes b (the offset's mean over the first flight) and is no worse than the file without the
    drift; its uncertainty column holds the spread about b grown by the walk."""
    _, _, without, with_drift, (sim2, log2) = flights
    new, ok, out = _errors(sim2, log2, with_drift.calibration)
    none, _, _ = _errors(sim2, log2, without.calibration)
    mean, bound = _paired(new, none, ok, log2.time)
    assert mean <= bound, f"mean {_rms(new, ok):.1f} nT against {_rms(none, ok):.1f} without the drift"
    spread = np.mean(np.square(with_drift.calibration.effects[0].wander["departure"]["rms"]))
    assert np.all(out["drift_std_nt"] ** 2 >= spread)


def test_the_file_keeps_the_rate_and_the_path_not_the_last_value(flights):
    """The stored departure is zero (its constant is b), the rate is learned with an interval holding the
    truth (one seeded draw of a 95 % interval; the slow test counts many), and the path spans the log."""
    _, log, _, with_drift, _ = flights
    stored = with_drift.calibration.effects[0]
    assert stored.values == (0.0, 0.0, 0.0)
    walk = stored.wander["walk"]
    assert walk["learned"] and walk["interval_95"][0] < WALK < walk["interval_95"][1]
    assert stored.wander["span"] == [log.time[0], log.time[-1]]
    assert with_drift.summary.model["wandering"]["bias_drift"]["walk"] == walk
    again = Calibration.from_dict(with_drift.calibration.to_dict(), "cal.json")
    assert again.to_dict() == with_drift.calibration.to_dict()


@pytest.mark.slow
def test_the_rate_interval_covers_the_truth_over_seeds():
    """Over 12 flights the 95 % interval of the learned walk holds the true 2 nT/sqrt(s) at least as often as
    the binomial(12, 0.95) bound that fails by chance one time in a thousand allows."""
    n = 12
    covered = 0
    for seed in range(200, 200 + n):
        _, log = _flight(seed)
        run = calibrate_log(log, effects=[BUILTIN["bias_drift"]()])
        low, high = run.calibration.effects[0].wander["walk"]["interval_95"]
        covered += low < WALK < high
    least = int(stats.binom.ppf(0.001, n, 0.95))
    assert covered >= least, f"{covered} of {n} intervals hold the truth; at least {least} expected"


@pytest.mark.slow
def test_calibrate_and_apply_commands_with_a_wandering_effect(tmp):
    """``calibrate --effect bias_drift`` reports the learned rate in its JSON and writes the path; ``apply``
    writes the drift's standard deviation per epoch."""
    sim, _ = _flight(7, duration_s=300.0)
    sim.write(tmp / "log.csv")
    summary = cli_json("calibrate", tmp / "log.csv", "--effect", "bias_drift", "-o", tmp / "cal.json")
    walk = summary["model"]["wandering"]["bias_drift"]["walk"]
    assert walk["learned"] and walk["unit"] == "nT/sqrt(s)"
    assert Calibration.load(tmp / "cal.json").effects[0].wander["walk"] == walk
    cli_json("apply", tmp / "log.csv", "--cal", tmp / "cal.json", "-o", tmp / "out.csv")
    import pandas as pd

    out = pd.read_csv(tmp / "out.csv")
    assert out["drift_std_nt"].notna().all() and (out["drift_std_nt"] < 30.0).all()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_coloured_noise_and_a_wandering_heading(seed):
    """Noise correlated over 3 s and a logged heading wandering by 0.3 deg over 60 s: the file with the drift is
    no worse than the file without it on its own log and on a second flight (paired, as above), and the rate's
    interval reaches the truth within the noise correlation's bias (at most twice its width above it)."""
    realism = dict(noise_correlation_s=3.0, attitude_wander_deg=(0.0, 0.0, 0.3))
    runs = []
    for s in (seed, seed + 1000):
        sim = simulate_drive(
            DriveConfig(duration_s=600.0, rate_hz=10, noise_nt=30, seed=s, disturbances=0, **realism),
            effects=[(BUILTIN["bias_drift"](), [WALK])],
        )
        runs.append((sim, from_table(sim.table.reset_index(), f"flight {s}")))
    (sim, log), (sim2, log2) = runs
    without = calibrate_log(log).calibration
    with_drift = calibrate_log(log, effects=[BUILTIN["bias_drift"]()]).calibration
    for truth, flight in ((sim, log), (sim2, log2)):
        new, ok, _ = _errors(truth, flight, with_drift)
        none, _, _ = _errors(truth, flight, without)
        mean, bound = _paired(new, none, ok, flight.time)
        assert mean <= bound, f"{flight.source}: {_rms(new, ok):.1f} nT against {_rms(none, ok):.1f} without the drift"
    low, high = with_drift.effects[0].wander["walk"]["interval_95"]
    assert low < WALK + 2.0 * (high - low)


def test_the_magnitude_alone_keeps_the_filter_state():
    """The magnitude alone cannot follow a path on each axis: the file is the filter's state, and says so."""
    from magkf.config import FilterConfig
    from magkf.online.results import FILTER_STATE

    _, log = _flight(3, duration_s=120.0, rate_hz=5.0)
    run = calibrate_log(log, FilterConfig(measure="magnitude"), effects=[BUILTIN["bias_drift"]()])
    assert run.calibration.model["estimated"] == FILTER_STATE
    assert run.calibration.effects[0].wander is None


def test_a_drift_beside_an_effect_with_held_directions():
    """Beside a field anomaly, one of whose directions the run holds at its prior (the diagnosis's rule), the
    drift's whole-log estimate holds it too and keeps its path; the anomaly's held direction is said."""
    _, log = _flight(4, duration_s=300.0, rate_hz=5.0)
    run = calibrate_log(log, effects=[BUILTIN["field_anomaly"](), BUILTIN["bias_drift"]()])
    anomaly, drift = run.calibration.effects
    assert drift.wander is not None and drift.values == (0.0, 0.0, 0.0)
    assert "field_anomaly" in run.calibration.model.get("effects_held", "")
