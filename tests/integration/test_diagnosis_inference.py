"""The diagnosis on correlated residuals, nested effects, channel kinds, and effects that travel with the
calibration to the next log (seeded)."""

import json

import numpy as np
import pytest
from scipy import signal, stats

from magkf import Calibration
from magkf.conventions import MAG
from magkf.diagnostics.diagnose import diagnose
from magkf.diagnostics.fitting import HeadingWander
from magkf.diagnostics.inference import constancy_test, robust_test
from magkf.diagnostics.validate import validate
from magkf.effects import BUILTIN, candidates, restore_effects, stored_effect, untried_columns
from magkf.errors import InputError
from magkf.io.drivelog import DriveLog
from magkf.online.realtime import OnlineCalibrator
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import cli_json, run_cli

COLOURED = {"noise_correlation_s": 2.0, "attitude_wander_deg": (0.0, 0.0, 0.2)}


def _log(seed, minutes=5.0, rate=10.0, effects=(), **realism):
    config = DriveConfig(duration_s=60 * minutes, rate_hz=rate, noise_nt=30.0, seed=seed, **realism)
    return simulate_drive(config, effects=list(effects))


def test_robust_test_keeps_its_size_on_autocorrelated_residuals():
    """AR(1) residuals (phi 0.9) and autocorrelated regressors: the share of p < 0.05 over 300 seeded
    trials stays within the 99.9 % binomial band of 0.05."""
    rng = np.random.default_rng(5)
    n, q, trials = 3000, 3, 300
    hits = 0
    for _ in range(trials):
        e = signal.lfilter([1.0], [1.0, -0.9], rng.normal(size=(n, 3)), axis=0)
        G = signal.lfilter([1.0], [1.0, -0.8], rng.normal(size=(3 * n, q)), axis=0)
        u, _, _ = np.linalg.svd(G - G.mean(axis=0), full_matrices=False)
        result = robust_test(u.reshape(n, 3, q), e)
        hits += result is not None and result.p_value < 0.05
    lo, hi = stats.binom.ppf([0.0005, 0.9995], trials, 0.05)
    assert lo <= hits <= hi, hits


def _ar1(rng, n, k, phi):
    return signal.lfilter([1.0], [1.0, -phi], rng.normal(size=(n, k)), axis=0)


def test_constancy_test_keeps_its_size_on_autocorrelated_scores_and_finds_a_random_walk():
    """Scores AR(1) (phi 0.9) with no wander: the share of p < 0.05 over 300 seeded trials stays within the
    99.9 % binomial band of 0.05; a random walk added (ending at three times the scores' long-run standard
    deviation) is found at p < 0.01 in at least 90 % of 100 trials."""
    rng = np.random.default_rng(7)
    n, q, trials = 3000, 3, 300
    hits = 0
    for _ in range(trials):
        result = constancy_test(_ar1(rng, n, q, 0.9))
        hits += result is not None and result.p_value < 0.05
    lo, hi = stats.binom.ppf([0.0005, 0.9995], trials, 0.05)
    assert lo <= hits <= hi, hits
    found = 0
    for _ in range(100):
        # a walk ending at three times the scores' long-run standard deviation (1 / (1 - phi) = 10)
        walk = np.cumsum(rng.normal(size=(n, q)), axis=0) * 3 * 10 / np.sqrt(n)
        scores = _ar1(rng, n, q, 0.9) + walk
        result = constancy_test(scores - scores.mean(axis=0))
        found += result is not None and result.p_value < 0.01
    assert found >= 90, found


def test_heading_wander_takes_out_a_heading_error_straight_over_each_stretch():
    """A heading error that is a straight line over each 10 s stretch is removed to rounding; what is left
    is orthogonal to the heading directions; the projection is idempotent."""
    rng = np.random.default_rng(3)
    n = 2000
    t = np.arange(n) * 0.05
    Z = rng.normal(size=(n, 3))
    stretch = np.floor(t / 10.0).astype(int)
    error = rng.normal(size=stretch.max() + 1)[stretch] + rng.normal(size=stretch.max() + 1)[stretch] * (t % 10.0)
    noise = rng.normal(size=(n, 3))
    wander = HeadingWander(Z, t, 10.0)
    assert np.allclose(wander.remove((Z * error[:, None]).ravel()), 0.0, atol=1e-9)
    left = wander.remove((Z * error[:, None] + noise).ravel())
    assert np.allclose(wander.remove(left), left)
    assert np.allclose(left, wander.remove(noise.ravel()))


@pytest.mark.slow
def test_no_false_alarms_on_coloured_noise_with_a_wandering_yaw():
    """20 null logs, coloured sensor noise (2 s) and a logged yaw wandering by 0.2 deg: logs with any
    candidate taken stay within the 99.9 % binomial bound of alpha."""
    alpha, runs = 0.01, 20
    alarms = sum(
        bool(diagnose(DriveLog(_log(800 + s, **COLOURED).table), alpha=alpha)[0].recommended) for s in range(runs)
    )
    assert alarms <= stats.binom.ppf(0.999, runs, alpha), alarms


@pytest.mark.slow
@pytest.mark.parametrize("realism", [{}, COLOURED], ids=["white", "coloured"])
def test_an_exact_time_lag_is_named_time_lag_not_eddy_current(realism):
    """The log's sample stamped t is the field at t - 0.12 s (exact delay, not the first-order model)."""
    sim = _log(61, minutes=10.0, rate=20.0, effects=[(BUILTIN["time_lag"](), [0.12])], **realism)
    found, _ = diagnose(DriveLog(sim.table))
    assert [c.effect for c in found.recommended][:1] == ["time_lag"], found.text
    tau = found.recommended[0].estimate["tau"]
    assert abs(tau["value"] - 0.12) < 4 * tau["std"] + 1e-3, tau


@pytest.mark.slow
def test_a_field_anomaly_is_fitted_in_the_directions_the_drive_determines():
    """Of a field anomaly, the part along the field looks like a scale of R and the horizontal part across it
    like a heading offset, which the heading's wander takes out. Fitted anyway, on this seed (coloured noise,
    wandering yaw) it took 150 000 nT of noise and left a held-out residual 3 times the true model's."""
    truth = np.array([150.0, -80.0, 120.0])
    sim = _log(1008, minutes=10.0, rate=20.0, effects=[(BUILTIN["field_anomaly"](), truth)], **COLOURED)
    found, _ = diagnose(DriveLog(sim.table))
    oracle_log = sim.table.copy()
    oracle_log[list(MAG)] -= sim.contributions[0]
    oracle, _ = diagnose(DriveLog(oracle_log), candidates=[])
    assert [c.effect for c in found.recommended][:1] == ["field_anomaly"], found.text
    row = found.recommended[0]
    assert row.residual_rms_after_nt < 1.1 * oracle.residual_rms_held_out_nt
    assert "not determined" in row.note, row.note
    # the truth's part in the determined directions (an orthogonal projection: the three priors are equal)
    value = np.array([row.estimate[k]["value"] for k in ("d_n", "d_e", "d_d")])
    std = np.array([row.estimate[k]["std"] for k in ("d_n", "d_e", "d_d")])
    assert np.linalg.norm(value) < np.linalg.norm(truth) + 4 * np.linalg.norm(std), (value, std)


def test_alpha_outside_zero_one_is_refused(tmp):
    sim = _log(3, minutes=2.0)
    with pytest.raises(InputError, match="alpha"):
        diagnose(DriveLog(sim.table), alpha=1.5)
    sim.write(tmp / "log.csv")
    proc = run_cli("diagnose", tmp / "log.csv", "--alpha", "5")
    assert proc.returncode == 2 and "--alpha" in proc.stderr


def test_candidates_only_from_channels_of_their_kind():
    columns = ["temp_c", "current_a", "throttle", "speed_mps", "mag_health"]
    labels = {e.label for e in candidates(columns)}
    assert {"temperature_bias:temp_c", "current_field:current_a", "current_field:throttle"} <= labels
    assert not any(":speed_mps" in x or ":mag_health" in x or "current_field:temp_c" == x for x in labels)
    assert untried_columns(columns) == ["speed_mps", "mag_health"]


def _with_effect(effect, theta, cov_scale=1e-4):
    """A calibration storing ``effect`` at ``theta`` with a full state covariance."""
    theta = np.asarray(theta, float)
    n = 12 + len(theta)
    A = np.random.default_rng(2).normal(size=(n, n))
    cov = cov_scale * (A @ A.T + n * np.eye(n))
    R = np.array([[1.02, 0.01, 0.0], [0.0, 0.98, 0.02], [0.01, 0.0, 1.01]])
    std = np.sqrt(np.diag(cov))[12:]
    return Calibration(
        R,
        [120.0, -80.0, 40.0],
        effects=(stored_effect(effect, theta, std),),
        state_covariance=cov,
        covariance=cov[:12, :12],
    )


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_each_builtin_travels_with_the_calibration(name, tmp):
    """Saved and loaded bit for bit; restored with its settings; applied; and the real-time calibrator starts
    from its stored values and covariance."""
    effect = BUILTIN[name]()
    theta = {"time_lag": [0.05], "bias_drift": [3.0, -2.0, 1.0]}.get(name, np.linspace(0.5, 2.0, effect.size) * 1e-3)
    cal = _with_effect(effect, theta)
    cal.save(tmp / "cal.json")
    back = Calibration.load(tmp / "cal.json")
    assert back.to_dict() == json.loads(json.dumps(cal.to_dict()))
    (restored,) = restore_effects(back)
    assert restored.label == effect.label and restored.settings() == effect.settings()
    online = OnlineCalibrator.from_file(tmp / "cal.json")
    assert np.array_equal(online.estimator.x, back.full_state)
    assert np.allclose(online.estimator.P, back.state_covariance)
    assert online.calibration.effects[0].label == effect.label


@pytest.mark.slow
def test_apply_and_diagnose_use_the_stored_effects(tmp):
    effect, theta = BUILTIN["current_field"](), np.array([12.0, -8.0, 5.0])
    sim = _log(21, effects=[(effect, theta)])
    sim.write(tmp / "log.csv")
    with_it = Calibration(sim.R, sim.b, effects=(stored_effect(effect, theta, np.zeros(3)),))
    with_it.save(tmp / "cal.json")
    Calibration(sim.R, sim.b).save(tmp / "core.json")
    quiet = np.linalg.norm(sim.disturbance, axis=1) == 0
    for path, expect_small in (("cal.json", True), ("core.json", False)):
        cli_json("apply", tmp / "log.csv", "--cal", tmp / path, "-o", tmp / "out.csv")
        import pandas as pd

        out = pd.read_csv(tmp / "out.csv")
        err = np.linalg.norm(out[["field_x", "field_y", "field_z"]].to_numpy() - sim.field_body, axis=1)[quiet]
        assert (np.sqrt(np.mean(err**2)) < 1.1 * np.sqrt(3) * 30.0) == expect_small
    found = cli_json("diagnose", tmp / "log.csv", "--cal", tmp / "cal.json")
    assert found["model_effects"] == ["current_field:current_a"] and not found["recommended"]
    proc = run_cli("report", tmp / "log.csv", "--cal", tmp / "cal.json", "-o", tmp / "r.html")
    assert proc.returncode == 0, proc.stderr
    assert "Before and after adding current_field:current_a" in (tmp / "r.html").read_text()


@pytest.mark.slow
def test_learn_on_one_log_check_on_the_next(tmp):
    """A hidden current field in both logs: learned on A, it brings B's residual within 1.1 times the true
    model's and helps beyond chance; with nothing hidden, adding it never makes B worse beyond chance."""
    effect, theta = BUILTIN["current_field"](), [12.0, -8.0, 5.0]
    for hidden, seeds in ((True, (31, 32)), (False, (33, 34))):
        a, b = (
            _log(s, minutes=10.0, rate=20.0, effects=[(effect, theta)] if hidden else [], **COLOURED) for s in seeds
        )
        a.write(tmp / "a.csv")
        b.write(tmp / "b.csv")
        assert run_cli("calibrate", tmp / "a.csv", "--effect", "current_field", "-o", tmp / "a.json").returncode == 0
        checked = cli_json("validate", tmp / "b.csv", "--cal", tmp / "a.json")
        (check,) = checked["effects"]
        if hidden:
            truth = Calibration(b.R, b.b, effects=(stored_effect(effect, theta, np.zeros(3)),))
            true_model = validate(DriveLog(b.table), truth)
            assert checked["with_effects_nt"] <= 1.1 * true_model.with_effects_nt
            assert check["verdict"] == "helps beyond chance", check
        else:
            assert check["p_hurts"] >= 0.01, check
