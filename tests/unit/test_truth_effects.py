"""The independent effect generator of the truth study (``tests/truth_effects.py``): its effects follow their
physics and its true attitude reproduces the simulator's true body field."""

import numpy as np
from scipy import stats

from magkf.sim import DriveConfig, simulate_drive
from tests.truth_effects import DISTURBANCE_MARGIN_S, TruthInputs, contribution, early_disturbance, hidden_log, true_dcm

RATE_HZ = 10.0


def _inputs(field_body, time_s=None, R=None, columns=None, seed=0) -> TruthInputs:
    n = len(field_body)
    t = np.arange(n) / RATE_HZ if time_s is None else time_s
    return TruthInputs(
        t, field_body, np.tile(np.eye(3), (n, 1, 1)), np.eye(3) if R is None else R, np.zeros(3), columns or {}, seed
    )


def _turning_field(t, amplitude=20_000.0, omega=0.5):
    """A body field turning at ``omega`` rad/s, its first and second time derivatives (N, 3) each."""
    phase = omega * t
    B = amplitude * np.column_stack([np.cos(phase), np.sin(phase), 0.5 * np.cos(2 * phase)])
    dB = amplitude * omega * np.column_stack([-np.sin(phase), np.cos(phase), -np.sin(2 * phase)])
    d2B = amplitude * omega**2 * np.column_stack([-np.cos(phase), -np.sin(phase), -2.0 * np.cos(2 * phase)])
    return B, dB, d2B


def test_small_time_lag_is_minus_tau_times_the_field_rate():
    """For a small lag the delayed field is ``B - tau dB/dt``, up to the Taylor remainder ``tau^2 |B''| / 2``
    and the cubic spline's interpolation error, below ``h^4 |B''''| / 16`` (at most ``5/384`` inside, the
    not-a-knot ends within a small factor of it; the three epochs at each end are left out)."""
    t = np.arange(600) / RATE_HZ
    amplitude, omega, tau = 20_000.0, 0.5, 5e-3
    B, dB, d2B = _turning_field(t, amplitude, omega)
    R = np.array([[1.05, 0.03, -0.02], [0.01, 0.97, 0.04], [-0.03, 0.02, 1.02]])
    lagged = contribution("time_lag", [tau], _inputs(B, R=R))
    first_order = -tau * dB @ R.T
    h = 1.0 / RATE_HZ
    fourth = amplitude * (2 * omega) ** 4  # the largest |B''''|, of the 2 omega component
    bound = np.linalg.norm(R, 2) * (0.5 * tau**2 * np.abs(d2B).max() * np.sqrt(3) + fourth * h**4 / 16 * np.sqrt(3))
    gap = np.linalg.norm(lagged - first_order, axis=1)[3:-3]
    assert gap.max() < bound
    assert np.abs(first_order).max() > 50 * bound  # the check has teeth: the term itself is far larger


def test_eddy_term_vanishes_on_a_constant_field_and_follows_a_linear_one():
    """``E dB/dt``: zero where the field is constant, ``E v`` where it changes at a constant rate ``v``
    (central differences are exact on a straight line)."""
    n = 50
    E = np.arange(9, dtype=float).reshape(3, 3) * 1e-3
    constant = np.tile([20_000.0, 1_000.0, 43_000.0], (n, 1))
    assert np.allclose(contribution("eddy_current", E.ravel(), _inputs(constant)), 0.0, atol=1e-9)
    v = np.array([300.0, -150.0, 40.0])
    ramp = constant + np.outer(np.arange(n) / RATE_HZ, v)
    assert np.allclose(contribution("eddy_current", E.ravel(), _inputs(ramp)), E @ v, rtol=1e-9)


def test_temperature_and_current_effects_are_their_formulas():
    """``k (T - 20)``, ``s (T - 20) (R B + b)`` and ``c I`` per sensor axis."""
    T = np.array([15.0, 20.0, 30.0])
    current = np.array([0.0, 2.0, 27.0])
    B = np.tile([20_000.0, 0.0, 40_000.0], (3, 1))
    x = _inputs(B, columns={"temp_c": T, "current_a": current})
    k, s, c = np.array([8.0, -5.0, 6.0]), np.array([3e-4, -2e-4, 2e-4]), np.array([12.0, -8.0, 5.0])
    assert np.allclose(contribution("temperature_bias", k, x), np.outer(T - 20.0, k))
    assert np.allclose(contribution("temperature_scale", s, x), (T - 20.0)[:, None] * s * B)
    assert np.allclose(contribution("current_field", c, x), np.outer(current, c))


def test_bias_drift_steps_have_the_walk_variance():
    """Increments of a walk of ``W`` nT/sqrt(s) over ``dt`` are N(0, W^2 dt): their sum of squares over
    ``W^2 dt`` lies in the two-sided 99.9 % chi-square band of their count."""
    n, walk = 3001, 2.0
    drift = contribution("bias_drift", [walk], _inputs(np.zeros((n, 3)), seed=7))
    assert np.allclose(drift[0], 0.0)
    steps = np.diff(drift, axis=0).ravel() / (walk * np.sqrt(1.0 / RATE_HZ))
    dof = steps.size
    assert stats.chi2.ppf(0.0005, dof) < np.sum(steps**2) < stats.chi2.ppf(0.9995, dof)


def test_true_attitude_and_anomaly_follow_the_simulators_truth():
    """The true attitude (logged less the simulator's wander) turns the true reference into the simulator's true
    body field, and the anomaly ``R C_nb^T d``, taken back through ``R`` and the true attitude, is ``d``."""
    config = DriveConfig(duration_s=60.0, rate_hz=RATE_HZ, attitude_wander_deg=(0.0, 0.0, 0.5), seed=3)
    sim = simulate_drive(config)
    c_nb = true_dcm(sim)
    assert np.allclose(np.einsum("nji,nj->ni", c_nb, sim.reference_ned), sim.field_body, atol=1e-6)
    d = np.array([150.0, -80.0, 120.0])
    log = hidden_log(sim, ("field_anomaly",), thetas=(d,))
    anomaly_ned = np.einsum("nij,nj->ni", c_nb, log.contributions @ np.linalg.inv(sim.R).T)  # back to NED
    assert np.allclose(anomaly_ned, d)


def test_early_disturbance_lies_in_the_first_two_minutes_and_is_left_out():
    """A bump of 200 to 500 nT, 10 to 30 s long, within the first 120 s; the clean epochs keep a margin from it."""
    sim = simulate_drive(DriveConfig(duration_s=300.0, rate_hz=RATE_HZ, disturbances=0, seed=5))
    t = sim.table.index.to_numpy()
    bump = early_disturbance(t, seed=5)
    size = np.linalg.norm(bump, axis=1)
    on = t[size > 0] - t[0]
    assert 200.0 * 0.99 < size.max() <= 500.0 and on.max() < 120.0 and 9.9 < on.max() - on.min() < 30.0
    log = hidden_log(sim, (), seed=5, early=True)
    assert not log.clean[size > 0].any()
    near = np.abs(t - (t[0] + on.max())) <= DISTURBANCE_MARGIN_S
    assert not log.clean[near].any() and log.clean[t - t[0] > 121.0 + DISTURBANCE_MARGIN_S].all()
