"""The noise learner against innovations of known spread and correlation (seeded)."""

import numpy as np
import pytest

from magkf.online.noise import CORRELATION_WINDOWS, RHO_STOP, NoiseLearner, NoiseLevels, robust_start
from magkf.sim.realism import coloured

RATE = 50.0
FIELD2 = (50_000.0) ** 2


START = NoiseLevels(1000.0, 0.0, 10.0)


def _learn(along, cross, start=START, block=12, **options):
    learner = NoiseLearner(start, **options)
    for i in range(0, len(along), block):
        t = np.arange(i, min(i + block, len(along))) / RATE
        rows = slice(i, i + len(t))
        learner.observe(t, along[rows], None if cross is None else cross[rows], np.full(len(t), FIELD2))
    return learner


@pytest.mark.parametrize("tau", [0.0, 0.2, 2.0])
def test_the_integrated_correlation_time_of_a_gauss_markov_process(tau):
    rng = np.random.default_rng(7)
    e = 30.0 * coloured(rng.normal(size=(120_000, 3)), RATE, tau)
    learner = _learn(e[:, 0], e[:, 1:])
    phi = np.exp(-1.0 / (RATE * tau)) if tau else 0.0
    expected = (1 + phi) / (1 - phi)  # the integrated autocorrelation time of an AR(1) process, epochs
    # Its estimate from N epochs summed up to lag M has a relative standard deviation of about
    # sqrt(2 (2 M + 1) / N) (Sokal, "Monte Carlo methods in statistical mechanics", 1997, eq. 3.19); N is
    # the learner's memory, M the lag where the correlation falls below RHO_STOP.
    memory = CORRELATION_WINDOWS * 60.0 * RATE
    lag = RATE * tau * np.log(1 / RHO_STOP)
    tolerance = 3 * np.sqrt(2 * (2 * lag + 1) / memory)
    for inflation in learner.inflations():  # along the field, along h, along v: each measured apart
        assert inflation == pytest.approx(expected, rel=max(tolerance, 1e-9))


@pytest.mark.parametrize("start", [1.0, 30.0, 900.0])
def test_the_sensor_noise_is_learned_whatever_it_started_from(start):
    """30 nT of white noise along and across the field, 3 % of the epochs disturbed by 3 000 nT: the
    learned sensor part is sqrt(30^2 - reference^2) within the robust scale's error over a 60 s window."""
    rng = np.random.default_rng(11)
    n = 60_000
    e = rng.normal(scale=30.0, size=(n, 3))
    disturbed = rng.random(n) < 0.03
    e[disturbed] += 3000.0
    learner = _learn(e[:, 0], e[:, 1:], NoiseLevels(start, 0.0, 10.0))
    # The median absolute value of 3000 samples has a relative standard error of about 1.4 / sqrt(3000).
    assert learner.levels.sensor_nt == pytest.approx(np.sqrt(30.0**2 - 10.0**2), rel=4 * 1.4 / np.sqrt(3000))
    assert learner.levels.attitude_deg < 0.01


def test_an_attitude_error_shows_across_the_field_only():
    rng = np.random.default_rng(12)
    n = 60_000
    att = np.radians(0.2)
    along = rng.normal(scale=30.0, size=n)
    cross = rng.normal(size=(n, 2)) * np.sqrt(30.0**2 + (att * 50_000.0) ** 2)
    learner = _learn(along, cross, NoiseLevels(30.0, 0.0, 0.0))
    assert learner.levels.attitude_deg == pytest.approx(0.2, rel=0.1)
    assert learner.levels.sensor_nt == pytest.approx(30.0, rel=0.1)


def test_the_floor_keeps_a_quiet_sensor_from_collapsing():
    learner = _learn(np.zeros(5000), np.zeros((5000, 2)), NoiseLevels(30.0, 0.0, 0.0), floor_nt=2.0)
    assert learner.levels.sensor_nt == 2.0


def test_robust_start_ignores_a_minority_of_disturbances():
    rng = np.random.default_rng(13)
    along = rng.normal(scale=40.0, size=6000)
    along[:300] += 5000.0
    levels = robust_start(along, None, np.full(6000, FIELD2), 0.0, 1.0, 0.0)
    assert levels.sensor_nt == pytest.approx(40.0, rel=0.1)
    assert levels.inflation < 2.0


def test_a_heading_error_is_told_from_a_tilt():
    """A heading error moves the field along h only (by the horizontal field), a tilt along h by the
    vertical field and along v by the whole field: 0.3 deg of heading and 0.05 deg of tilt are learned apart.
    Tolerances: the median absolute deviation of N = 3000 samples (one window) estimates a variance with a
    relative standard deviation of about 1 / sqrt(0.37 N / 2) = 4 %; carried through the differences below
    that is 2.6 % on the heading and 3.4 % on the tilt, checked at 3 sigma (and a little more)."""
    rng = np.random.default_rng(14)
    n, horizontal, vertical = 60_000, 20_000.0, 44_000.0
    field2, horizontal2 = horizontal**2 + vertical**2, horizontal**2
    heading, tilt = np.radians(0.3), np.radians(0.05)
    var_h = 30.0**2 + tilt**2 * vertical**2 + heading**2 * horizontal2
    var_v = 30.0**2 + tilt**2 * field2
    along = rng.normal(scale=30.0, size=n)
    cross = rng.normal(size=(n, 2)) * np.sqrt([var_h, var_v])
    learner = NoiseLearner(NoiseLevels(30.0, 0.0, 0.0))
    for i in range(0, n, 12):
        rows = slice(i, i + 12)
        learner.observe(
            np.arange(i, i + 12) / RATE, along[rows], cross[rows], np.full(12, field2), 0.0, np.full(12, horizontal2)
        )
    assert learner.levels.heading_deg == pytest.approx(0.3, rel=0.1)
    assert learner.levels.attitude_deg == pytest.approx(0.05, rel=0.12)


def test_correlation_in_pieces_is_the_correlation_of_all(monkeypatch):
    """The lagged products are summed piece by piece as the pending innovations come, each piece let go once
    counted: observed at one instant (as ``robust_start`` gives a whole log's residuals) in 9 bursts (pending in 9
    pieces, their products cut at 4 099 epochs) or in one, the correlation is the same to rounding."""
    from magkf.online import noise

    rng = np.random.default_rng(11)
    n = 9 * 9000  # each burst beyond the ring (BUFFER), so each goes to the pending list as it comes
    along = coloured(rng.normal(size=(n, 1)), RATE, 0.8)[:, 0] * 30.0
    cross = coloured(rng.normal(size=(n, 2)), RATE, 0.5) * 40.0
    field2 = np.full(n, FIELD2)

    def learned(bursts: int) -> np.ndarray:
        learner = NoiseLearner(START, adapt=False)
        for part in np.array_split(np.arange(n), bursts):
            learner.observe(np.zeros(len(part)), along[part], cross[part], field2[part])
        assert len(learner._pending) == bursts
        return learner.correlation()

    whole = learned(1)
    assert np.abs(whole[0, 1:4]).min() > 0.3  # the coloured noise's correlation is there to be measured
    monkeypatch.setattr(noise, "_CHUNK", 4099)
    np.testing.assert_allclose(learned(9), whole, rtol=1e-12, atol=1e-15)
