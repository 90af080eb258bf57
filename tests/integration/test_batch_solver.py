"""The chunked batch solver against scipy's least_squares on the same objective (seeded).

The reference is how ``solve_batch`` solved the log before it went through it in chunks: the whole log's
residual vector (with the prior rows) handed to ``least_squares`` (trf, finite-difference Jacobian), the
robust pass under ``soft_l1``, then plain least squares without the outlying epochs, the covariance
``(J^T J)^-1`` of its Jacobian and the outliers found again at its solution.
"""

import numpy as np
import pytest
from scipy.optimize import least_squares

from magkf.config import FilterConfig
from magkf.effects import BUILTIN
from magkf.io.drivelog import DriveLog
from magkf.online import batch
from magkf.online.batch import LOSS_SCALE, batch_problem, solve_batch
from magkf.sim import DriveConfig, simulate_drive
from magkf.status import Status, status_names

NOISE = 30.0
MATCHED = FilterConfig(sensor_noise_nt=NOISE, attitude_deg=0.0, reference_nt=0.0, r_walk=0.0, b_walk=0.0)
#: Largest difference of the two solutions, in standard deviations: both stop far closer to the minimum
#: (least_squares at a relative change of 1e-8, the chunked solver at steps of 1e-6 sigma).
X_TOL = 1e-3
#: Largest difference of the covariances, relative to the product of the standard deviations: the
#: reference's Jacobian is a central difference (relative step about 6e-6, error of its square); with a forward
#: difference (relative step 1.5e-8) the magnitude model's covariance came within 1.25e-4 of this bound.
P_TOL = 1e-4


def _whole_log(problem):
    """``(x, P, status)`` of the log by least_squares over the whole log's residual vector."""

    def residuals(x, keep=None):
        parts = []
        for model, epochs in problem.chunks():
            r = problem.residuals(x, model, epochs)
            parts.append((r if keep is None else r * keep[epochs][:, None]).ravel())
        return np.concatenate(parts + [(x - problem.x0) / problem.prior_std])

    scale = np.maximum(np.abs(problem.prior_std), 1e-9)
    robust = least_squares(residuals, problem.x_start, loss="soft_l1", f_scale=LOSS_SCALE, x_scale=scale, method="trf")
    keep = {"keep": ~problem.outliers(robust.x)}
    fit = least_squares(residuals, robust.x, x_scale=scale, method="trf", jac="3-point", kwargs=keep)
    status = problem.status.copy()
    status[problem.outliers(fit.x)] = Status.GATED_INNOVATION
    return fit.x, np.linalg.inv(fit.jac.T @ fit.jac), status


def _drive(effects=()):
    """5 minutes at 10 Hz with ten disturbances (outlying epochs), seeded."""
    config = DriveConfig(duration_s=300, rate_hz=10, motion="3d", noise_nt=NOISE, seed=41, disturbances=10)
    return simulate_drive(config, effects=list(effects))


@pytest.fixture(scope="module")
def drive():
    return _drive()


@pytest.fixture(scope="module")
def loaded():
    """The same drive with a field proportional to an electrical load (``current_field``)."""
    return _drive([(BUILTIN["current_field"](), [40.0] * 3)])


@pytest.mark.parametrize(
    "measure,effects,outliers",
    # magnitude only: the magnitude gate and the residual are one quantity, so the gate takes the outliers
    [("both", (), True), ("vector", (), True), ("magnitude", (), False), ("both", ("current_field",), True)],
)
def test_chunked_solver_agrees_with_least_squares(drive, loaded, measure, effects, outliers, monkeypatch):
    log = DriveLog((loaded if effects else drive).table, "drive")
    config = MATCHED.replace(measure=measure)
    monkeypatch.setattr(batch, "CHUNK_EPOCHS", 500)  # several chunks per model on a short log
    run = solve_batch(log, config, effects=[BUILTIN[name]() for name in effects])
    x_ref, P_ref, status_ref = _whole_log(batch_problem(log, config, effects=[BUILTIN[name]() for name in effects]))
    std = np.sqrt(np.diag(P_ref))
    assert np.max(np.abs(run.x - x_ref) / std) < X_TOL
    assert np.max(np.abs(run.P - P_ref) / np.outer(std, std)) < P_TOL
    assert np.array_equal(run.states["status"].to_numpy(), status_names(status_ref))
    assert (status_ref == Status.GATED_INNOVATION).any() == outliers  # the robust pass had outliers to find


def test_a_pass_that_does_not_converge_says_so(drive, monkeypatch):
    monkeypatch.setattr(batch, "MAX_ITERATIONS", 1)
    with pytest.warns(UserWarning) as record:
        solve_batch(DriveLog(drive.table, "drive"), MATCHED)
    said = [str(w.message) for w in record]
    for name in ("robust pass", "least-squares fit"):
        assert any(m.startswith(f"drive: the batch solver's {name} did not converge") for m in said), said


def test_a_time_lag_is_estimated(recwarn):
    """A nonlinear effect (its model interpolates between epochs; the log is one chunk): the delay determined by
    the log (far from its prior's 0 +- 0.5 s), within three standard deviations of the truth, and both passes
    converged (no warning)."""
    lag = 0.05
    sim = simulate_drive(
        DriveConfig(duration_s=150, rate_hz=20, motion="3d", noise_nt=NOISE, seed=7),
        effects=[(BUILTIN["time_lag"](), [lag])],
    )
    run = solve_batch(DriveLog(sim.table, "lagged"), MATCHED, effects=[BUILTIN["time_lag"]()])
    assert run.std[12] < lag / 10
    assert abs(run.x[12] - lag) < 3 * run.std[12], (run.x[12], run.std[12])
    assert not [w for w in recwarn if "did not converge" in str(w.message)]
