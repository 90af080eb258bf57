"""Whole runs with the compiled kernel (``magkf.online.kernel``, numba) against the numpy path, over the
filters, measurement models and effects the filter loop supports, and a log with a stretch without attitude
(blocks of two models, which the numpy path takes).

The kernel is made to take every block it can from the first (``WORTH_AFTER_EPOCHS = 0``); the numpy run has
no kernel at all. Tolerances: the two paths compute the same sums in another order, so each update differs by
rounding (about 1e-16 relative) and the filter carries it on; measured, the filter's final state differs by
under 1e-13 of its standard deviations. Any difference in logic, one epoch gated or weighted otherwise among
the N = 30 000 of these logs, moves the state by about one N-th of that epoch's innovation in standard
deviations, over 1e-6: 1e-9 of the standard deviations tells the two apart with margins of a thousand either
way; the whole-log estimate's covariance is compared more loosely, for the reason given at
``WHOLE_LOG_COVARIANCE``. The statuses must be equal. The per-epoch states table is stored in float32, whose
rounding turns a difference of 1e-15 into one unit in the last place of a value now and then: its columns are
compared to two units of float32 (2 x 2^-23 relative) of each value, and the NIS likewise.
"""

import numpy as np
import pytest

from magkf.config import FilterConfig
from magkf.effects import BUILTIN
from magkf.io.drivelog import DriveLog
from magkf.online import kernel
from magkf.online.estimator import Estimator
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive

pytestmark = pytest.mark.slow

FLOAT32_UNITS = 2 * 2.0**-23
#: The whole-log estimate's covariance sums the gradient over batches of a width proportional to the learned
#: correlation time (``whole_log._Problem.model_meat``), so a change of 1e-12 in it can move an epoch into the
#: next batch: measured, 1.3e-6 of the variances on this log (2.6e-6 between the two paths, whose learned noise
#: differs by 1e-13 to 1e-12). One epoch moved changes the sum by about one N-th of it (N = 30 000 epochs,
#: 3e-5): 1e-4 of the variances allows a few, and is far below the covariance's own sampling error.
WHOLE_LOG_COVARIANCE = 1e-4


@pytest.fixture(scope="module")
def sim():
    effects = [(BUILTIN["current_field"](), [12.0, -8.0, 5.0]), (BUILTIN["time_lag"](), [0.02])]
    return simulate_drive(DriveConfig(duration_s=600, rate_hz=50, seed=11), effects=effects)


def _run(log, config, effects, use_kernel, monkeypatch):
    """The run with the kernel from the first block, or without it; and the blocks the kernel took."""
    taken = []
    original = Estimator._kernel_update

    def counted(self, *args):
        done = original(self, *args)
        taken.append(done)
        return done

    with monkeypatch.context() as patch:
        patch.setattr(kernel, "WORTH_AFTER_EPOCHS", 0)
        patch.setattr(Estimator, "_kernel_update", counted)
        if not use_kernel:
            patch.setattr(kernel, "available", lambda: False)
        run = calibrate_log(log, config, effects=[BUILTIN[name]() for name in effects])
    return run, sum(taken)


def _assert_same(a, b):
    assert a.states["status"].equals(b.states["status"])
    for x, P, x_ref, P_ref, tolerance in (
        (a.filter_x, a.filter_P, b.filter_x, b.filter_P, 1e-9),
        (a.x, a.P, b.x, b.P, WHOLE_LOG_COVARIANCE),
    ):
        std = np.sqrt(np.diag(P_ref))
        np.testing.assert_allclose((x - x_ref) / std, 0.0, atol=1e-9)
        np.testing.assert_allclose(P / np.outer(std, std), P_ref / np.outer(std, std), rtol=0, atol=tolerance)
    for column in a.states.columns:
        if a.states[column].dtype.kind == "f":
            ref = b.states[column].to_numpy(float)
            np.testing.assert_allclose(a.states[column].to_numpy(float), ref, rtol=FLOAT32_UNITS, atol=0)


@pytest.mark.parametrize(
    "filter_name, measure, effects, adapt",
    [
        ("ekf", "both", (), True),
        ("ukf", "both", (), True),
        ("ekf", "vector", (), True),
        ("ekf", "magnitude", (), True),
        ("ekf", "both", (), False),
        ("ekf", "both", ("current_field",), True),
        ("ekf", "both", ("time_lag",), True),
    ],
)
def test_the_kernel_gives_the_numpy_paths_run(sim, monkeypatch, filter_name, measure, effects, adapt):
    log = DriveLog(sim.table, "kernel")
    config = FilterConfig(filter=filter_name, measure=measure, adapt_noise=adapt)
    with_kernel, taken = _run(log, config, effects, True, monkeypatch)
    without, none = _run(log, config, effects, False, monkeypatch)
    assert none == 0 and taken > 400  # of 600 blocks: the kernel took most (not those it leaves to numpy)
    _assert_same(with_kernel, without)


def test_blocks_without_attitude_are_left_to_numpy_and_the_run_is_the_same(sim, monkeypatch):
    table = sim.table.copy()
    gap = (table.index - table.index[0]).to_series(index=table.index).between(200.0, 260.0)
    table.loc[gap, ["roll", "pitch", "yaw"]] = np.nan
    log = DriveLog(table, "gap")
    with_kernel, taken = _run(log, FilterConfig(), (), True, monkeypatch)
    without, _ = _run(log, FilterConfig(), (), False, monkeypatch)
    assert 400 < taken < 560  # the 60 s without attitude (and their edges) went to numpy
    _assert_same(with_kernel, without)


def test_the_kernel_is_loaded_only_once_a_run_has_filtered_enough_epochs(monkeypatch):
    """A short log never loads it (nor numba); past ``WORTH_AFTER_EPOCHS`` it is loaded once, and the blocks after
    that are its."""
    sim = simulate_drive(DriveConfig(duration_s=60, rate_hz=20, seed=2, dop_bad_stretches=0))
    loads = []
    monkeypatch.setattr(kernel, "load", lambda: loads.append(1) or kernel.gate_and_fold)  # the plain-Python kernel
    calibrate_log(DriveLog(sim.table, "short"), FilterConfig())
    assert loads == []
    monkeypatch.setattr(kernel, "WORTH_AFTER_EPOCHS", 600)  # 30 s of the 60
    calibrate_log(DriveLog(sim.table, "short"), FilterConfig())
    assert loads == [1]
