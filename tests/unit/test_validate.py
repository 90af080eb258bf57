"""``validate``: the held-out paired test of each stored effect, its power, and a wandering effect's rate, against
the statistical truth of seeded simulations.

Rates over seeds are bounded binomially: a rate claimed to be at most (or at least) ``p`` is checked against the
0.1 % (99.9 %) quantile of the binomial distribution of ``trials`` draws at ``p``, so that a correct method fails
one run in a thousand."""

import numpy as np
import pytest
from scipy import signal, stats

from magkf import Calibration
from magkf.blas import one_thread
from magkf.config import FilterConfig
from magkf.diagnostics.inference import walk_rate
from magkf.diagnostics.validate import MAX_BLOCKS, POWER, _share_test, _verdict, validate, validation_edges
from magkf.effects import BUILTIN, stored_effect
from magkf.io.drivelog import DriveLog
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive

COLOURED = {"noise_correlation_s": 2.0, "attitude_wander_deg": (0.0, 0.0, 0.2)}
#: Temperature coefficients (nT per degree) of the issue's realistic size: on 10-minute logs the learned effect
#: cuts the held-out residual by 10 to 30 %.
TEMPERATURE = np.array([8.0, -5.0, 6.0])


def _log(seed, minutes=10.0, rate=10.0, effects=(), **realism):
    config = DriveConfig(duration_s=60 * minutes, rate_hz=rate, noise_nt=30.0, seed=seed, **realism)
    return simulate_drive(config, effects=list(effects))


def _at_most(rate, trials):
    """The 99.9 % binomial quantile of ``trials`` draws at ``rate``: a count above it refutes 'at most rate'."""
    return int(stats.binom.ppf(0.999, trials, rate))


def _at_least(rate, trials):
    """The 0.1 % binomial quantile: a count below it refutes 'at least rate'."""
    return int(stats.binom.ppf(0.001, trials, rate))


def _shape(n):
    """A whitened predicted contribution (3n,) whose size varies over the log as a temperature's does: small at
    the start, large at the end (the heterogeneity that made a t test over blocks timid)."""
    ramp = np.linspace(0.0, 1.0, n) ** 2
    return (ramp[:, None] * np.array([0.3, -0.2, 0.25])).ravel()


def _ar1(rng, n, phi=0.9):
    """AR(1) noise (3n,), unit variance per component, correlated over about (1 + phi) / (1 - phi) epochs."""
    return (signal.lfilter([1.0], [1.0, -phi], rng.normal(size=(n, 3)), axis=0) * np.sqrt(1 - phi**2)).ravel()


def test_validation_edges_keep_blocks_long_and_at_most_max_blocks():
    """Blocks of at least 20 correlation times; at least 2 and at most ``MAX_BLOCKS``; edges from 0 to n."""
    for n, tau, blocks in ((100_000, 1.0, MAX_BLOCKS), (10_000, 25.0, 20), (1000, 100.0, 2)):
        edges = validation_edges(n, tau)
        assert edges[0] == 0 and edges[-1] == n and len(edges) - 1 == blocks
        assert np.min(np.diff(edges)) >= min(20 * tau, n / 2) - 1


@one_thread
def test_share_test_keeps_its_size_at_the_boundary_and_its_stated_power():
    """AR(1) noise (correlated over 19 epochs) and a contribution whose size grows over the log. At the boundary
    (B shows half the predicted contribution, where adding it neither helps nor hurts) p_helps < 0.05 in at most
    5 % of 300 trials (binomial bound); with the expected fall equal to the ``detectable`` figure the test
    stated, it detects in about ``POWER`` of the trials (binomial band; the normal approximation of the
    noncentral t errs by about 1 % at these degrees of freedom)."""
    rng = np.random.default_rng(11)
    n, trials = 2000, 300
    c = _shape(n)
    cc = float(c @ c)
    scale = 4.0  # noise large against the contribution: a fall of a few per cent
    hits, detectable = 0, []
    for _ in range(trials):
        r = 0.5 * c + scale * _ar1(rng, n)
        out = _share_test(r, c, 0.05)
        hits += out["p_helps"] < 0.05
        detectable.append(out["detectable"])
    assert hits <= _at_most(0.05, trials)
    # the expected sum of squares without the effect and the fall the test said it detects with POWER
    total = 3 * n * scale**2 + 0.25 * cc
    fall = total * (1.0 - (1.0 - np.median(detectable)) ** 2)
    gain = 0.5 + fall / (2.0 * cc)  # (2 g - 1) c.c is the fall
    found = sum(_share_test(gain * c + scale * _ar1(rng, n), c, 0.05)["p_helps"] < 0.05 for _ in range(trials))
    assert _at_least(POWER - 0.02, trials) <= found <= _at_most(POWER + 0.02, trials)


def test_a_test_without_power_says_so():
    """300 epochs correlated over about 40 (AR(1), phi 0.95): fewer than three independent stretches, so
    no test is made, and the verdict says it was not tested instead of "no difference"."""
    rng = np.random.default_rng(2)
    n = 300
    out = _share_test(_ar1(rng, n, phi=0.95), _shape(n), 0.01)
    assert out["dof"] == 0 and out["p_helps"] == 1.0 and out["detectable"] == 1.0
    assert _verdict(out, 0.01).startswith("not tested")


@one_thread  # small matrices: BLAS threads only contend (as in validate)
def test_walk_rate_interval_covers_the_true_rate():
    """Stretch means of a random walk (0.5 and 2 nT/sqrt(s)) plus noise of 15 nT, a direction per stretch left
    out: the 95 % interval covers the true rate in at least 95 % of 40 seeds each (binomial bound); with no walk
    its lower end is 0 as often."""
    rng = np.random.default_rng(7)
    K, L, trials = 60, 10.0, 40
    start = np.arange(K) * L
    for rate in (0.0, 0.5, 2.0):
        covered = 0
        for _ in range(trials):
            t = np.arange(0.0, K * L, 1.0)
            walk = np.cumsum(rng.normal(size=(len(t), 3)) * rate, axis=0) + 40.0
            means = walk.reshape(K, int(L), 3).mean(axis=1) + rng.normal(size=(K, 3)) * 15.0
            drop = rng.normal(size=(K, 3))
            drop /= np.linalg.norm(drop, axis=1, keepdims=True)
            found = walk_rate(means, start, start + L, np.full(K, L), drop)
            covered += found.low <= rate <= found.high
        assert covered >= _at_least(0.95, trials), (rate, covered)


def test_validate_reports_held_out_figures_and_calls_a_true_effect_helpful():
    """A temperature effect stored at its true values on a short log that has it: held out, the effect helps
    beyond chance, B shows about all of its predicted contribution (within 4 standard errors), the held-out
    residual is at least the in-sample one, and the JSON summary holds the power and the blocks."""
    effect = BUILTIN["temperature_bias"]()
    b = _log(3, minutes=5.0, rate=10.0, effects=[(effect, TEMPERATURE)])
    cal = Calibration(b.R, b.b, effects=(stored_effect(effect, TEMPERATURE, np.zeros(3)),))
    v = validate(DriveLog(b.table), cal)
    (check,) = v.effects
    assert check.verdict == "helps beyond chance"
    assert abs(check.gain - 1.0) < 4.0 * check.gain_se
    assert v.with_effects_nt >= v.with_effects_in_sample_nt and v.core_only_nt > v.with_effects_nt
    assert 0.0 < check.detectable < -check.change and check.blocks == v.blocks >= 2
    summary = v.summary()
    assert summary["effects"][0]["detectable"] == check.detectable and summary["wandering"] == []


def test_validate_says_what_it_cannot_test_for_a_wandering_effect():
    """A stored bias drift is not held at its values (they are another log's path): its check is the rate, and
    the words say the path cannot be tested."""
    drift = BUILTIN["bias_drift"](walk=2.0)
    b = _log(4, minutes=5.0, rate=10.0, effects=[(drift, [2.0])])
    cal = Calibration(b.R, b.b, effects=(stored_effect(drift, np.zeros(3), np.zeros(3)),))
    v = validate(DriveLog(b.table), cal)
    assert v.effects == [] and len(v.wandering) == 1
    (w,) = v.wandering
    assert w.stored_rate == 2.0 and w.low <= w.rate <= w.high
    assert "path cannot be tested" in w.verdict and "rate" in v.text


def _learned(seed, noise, hidden_on_a=True, on_b=1.0):
    """A calibration learned on log A (with a temperature effect when ``hidden_on_a``) and log B with ``on_b``
    times the true effect."""
    effect = BUILTIN["temperature_bias"]()
    a = _log(seed, effects=[(effect, TEMPERATURE)] if hidden_on_a else [], **noise)
    b = _log(seed + 1, effects=[(effect, on_b * TEMPERATURE)] if on_b else [], **noise)
    cal = calibrate_log(DriveLog(a.table), FilterConfig(), effects=[BUILTIN["temperature_bias"]()]).calibration
    return validate(DriveLog(b.table), cal).effects[0]


@pytest.mark.slow
def test_a_correctly_learned_temperature_effect_is_called_helpful():
    """The issue's case: temperature learned on A, checked on B, white and coloured noise (Gauss-Markov 2 s and
    a wandering heading), 10 seeds each (10-minute logs at 10 Hz). The held-out residual falls by 8 to 40 % and
    the effect is called helpful at alpha 0.01 in at least 95 % of the logs (binomial bound), never harmful."""
    changes, helps, hurts = [], 0, 0
    for noise in ({}, COLOURED):
        for seed in range(10):
            check = _learned(600 + 2 * seed, noise)
            changes.append(check.change)
            helps += check.verdict == "helps beyond chance"
            hurts += check.verdict.startswith("makes")
    assert -0.40 < np.median(changes) < -0.08, changes
    assert helps >= _at_least(0.95, len(changes)) and hurts == 0, (helps, changes)


@pytest.mark.slow
def test_an_effect_that_is_not_there_is_rarely_called_helpful():
    """Two nulls, coloured noise, alpha 0.05: (a) the effect learned on a log without it (stored at about 0) and
    checked on a log without it; (b) the boundary, B showing half the stored contribution, where adding it
    neither helps nor hurts. Called helpful in at most 5 % of 20 seeds each (binomial bound)."""
    effect = BUILTIN["temperature_bias"]()
    trials, alpha = 20, 0.05
    fitted_on_nothing = sum(
        _learned(700 + 2 * seed, COLOURED, hidden_on_a=False, on_b=0.0).p_helps < alpha for seed in range(trials)
    )
    at_boundary = 0
    for seed in range(trials):
        b = _log(800 + seed, effects=[(effect, 0.5 * TEMPERATURE)], **COLOURED)
        cal = Calibration(b.R, b.b, effects=(stored_effect(effect, TEMPERATURE, np.zeros(3)),))
        at_boundary += validate(DriveLog(b.table), cal, alpha=alpha).effects[0].p_helps < alpha
    assert fitted_on_nothing <= _at_most(alpha, trials)
    assert at_boundary <= _at_most(alpha, trials)


@pytest.mark.slow
def test_a_wandering_effects_rate_is_covered():
    """Bias drift of 2 nT/sqrt(s) learned on A and present on B (coloured noise and a wandering heading, 10-minute
    logs): the 95 % interval of B's rate covers the true 2 in at least 95 % of 12 seeds (binomial bound); on 6 logs
    without drift the rate the file stores (2, or the rate learned on A, near 2) is refuted in at least 95 % of
    them (on 10-minute logs the interval's upper end is below 1 nT/sqrt(s))."""
    drift = BUILTIN["bias_drift"]
    covered, refuted, trials = 0, 0, 12
    for seed in range(trials):
        a, b = (_log(900 + 2 * seed + k, effects=[(drift(), [2.0])], **COLOURED) for k in (0, 1))
        cal = calibrate_log(DriveLog(a.table), FilterConfig(), effects=[drift(walk=2.0)]).calibration
        (w,) = validate(DriveLog(b.table), cal).wandering
        assert w.stored_rate > 1.0, w
        covered += w.low <= 2.0 <= w.high
        if seed < trials // 2:
            still = _log(950 + seed, **COLOURED)
            refuted += not validate(DriveLog(still.table), cal).wandering[0].within
    assert covered >= _at_least(0.95, trials)
    assert refuted >= _at_least(0.95, trials // 2)
