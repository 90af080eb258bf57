"""The chunked batch solver against scipy's least_squares on the same objective (seeded).

The reference is how ``solve_batch`` solved the log before it went through it in chunks: the whole log's
residual vector (with the prior rows) handed to ``least_squares`` (trf, finite-difference Jacobian), the
robust pass under ``soft_l1``, then plain least squares without the outlying epochs, the covariance
``(J^T J)^-1`` of its Jacobian and the outliers found again at its solution. On the shipped example drive the
same reference, with the analytic Jacobian and tight tolerances, is matched to 1e-9 relative, whatever the chunks.
"""

from pathlib import Path

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


#: The example drive's solution by the chunked solver and by least_squares over the whole log's residual vector
#: with the same analytic Jacobian, both to their tightest tolerances: relative to each value, 1e-9 is the issue's
#: bound. Both minimise the same sums; what differs is the order of summation (1e-16 relative per term, about
#: ``sqrt(N) eps`` = 1e-14 over N = 36 000 residuals) and where each stops (the chunked solver's last step below
#: ``STEP_TOL`` = 1e-6 of a standard deviation, which the example drive determines to 1e-3 of each value or better).
SAME = 1e-9


@pytest.fixture(scope="module")
def example_drive():
    from magkf.io.readers import read_log

    return read_log(Path(__file__).parents[2] / "data" / "example_drive.csv")


def _least_squares_tight(problem):
    """``(x, P)`` by least_squares (trf, analytic Jacobian from ``problem``, tolerances 1e-15), robust pass then
    the plain fit without the robust pass's outliers, as ``solve_batch`` does."""

    def parts(x, keep, jacobian):
        out = []
        for model, epochs in problem.chunks():
            got = problem.residuals(x, model, epochs, jacobian=jacobian)
            weight = np.ones((len(epochs), 1)) if keep is None else keep[epochs][:, None]
            out.append((got[1] * weight[..., None]).reshape(-1, len(x)) if jacobian else (got * weight).ravel())
        return out

    def residuals(x, keep=None):
        return np.concatenate(parts(x, keep, False) + [(x - problem.x0) / problem.prior_std])

    def jacobian(x, keep=None):
        return np.vstack(parts(x, keep, True) + [np.diag(1.0 / problem.prior_std)])

    tight = {"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15, "method": "trf", "jac": jacobian}
    robust = least_squares(residuals, problem.x_start, loss="soft_l1", f_scale=LOSS_SCALE, **tight)
    fit = least_squares(residuals, robust.x, kwargs={"keep": ~problem.outliers(robust.x)}, **tight)
    return fit.x, np.linalg.inv(fit.jac.T @ fit.jac)


def test_the_example_drive_as_least_squares_over_the_whole_log(example_drive):
    """``calibrate --batch`` on the shipped example drive: the chunked normal equations give least_squares' answer
    on the whole log's Jacobian to ``SAME`` relative (state and covariance)."""
    run = solve_batch(example_drive, FilterConfig())
    x_ref, P_ref = _least_squares_tight(batch_problem(example_drive, FilterConfig()))
    assert np.max(np.abs(run.x - x_ref) / np.abs(x_ref)) < SAME
    assert np.max(np.abs(run.P - P_ref)) < SAME * np.max(np.abs(P_ref))


@pytest.mark.parametrize("chunk", [997, 100_000])
def test_the_answer_does_not_depend_on_the_chunks(example_drive, chunk, monkeypatch):
    """Chunks of a prime number of epochs (edges everywhere in the log) and one chunk for the whole log: the same
    state, covariance and statuses as the default chunks, to ``SAME`` relative (only the order of the sums
    differs)."""
    reference = solve_batch(example_drive, FilterConfig())
    monkeypatch.setattr(batch, "CHUNK_EPOCHS", chunk)
    run = solve_batch(example_drive, FilterConfig())
    assert np.max(np.abs(run.x - reference.x) / np.abs(reference.x)) < SAME
    assert np.max(np.abs(run.P - reference.P)) < SAME * np.max(np.abs(reference.P))
    assert run.states["status"].equals(reference.states["status"])
