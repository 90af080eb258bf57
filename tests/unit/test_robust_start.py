"""The start of a bootstrapped run is the robust fit over the whole log: a disturbance in the bootstrap's first
stretch does not pull it off.

A simulated log (white noise of ``NOISE_NT`` per axis, the exact logged attitude and reference field, no other
disturbance) gets a 5 000 nT bump for 30 s inside the bootstrap's first 120 s. The start's offsets are compared
with the truth in units of their least-squares standard error over the log's usable epochs (``NOISE_NT`` times
the square root of the diagonal of ``(H^T H)^-1``, H the core's Jacobian): within ``SIGMAS`` of them. The
first stretch's fit alone is far outside: the case the whole-log start is for.
"""

import numpy as np
import pytest

from magkf.config import FilterConfig
from magkf.conventions import MAG
from magkf.effects.core import core_jacobian
from magkf.io.drivelog import DriveLog
from magkf.online.bootstrap import bootstrap_vector
from magkf.online.prepare import prepare, prepare_run
from magkf.sim import DriveConfig, simulate_drive
from magkf.status import Status

NOISE_NT = 30.0
#: Two-sided normal tail of 6e-7 per axis: the estimate is a linear function of thousands of Gaussian readings.
SIGMAS = 5.0


@pytest.fixture(scope="module")
def disturbed():
    config = DriveConfig(
        duration_s=600, rate_hz=10, noise_nt=NOISE_NT, seed=5, disturbances=0, dop_bad_stretches=0, write_reference=True
    )
    sim = simulate_drive(config)
    table = sim.table.copy()
    first, length = 400, 300  # 40 s in, 30 s long: inside the first 120 s
    bump = 5000.0 * np.hanning(length)[:, None] * np.array([0.6, -0.64, 0.48])
    table.iloc[first : first + length, [table.columns.get_loc(c) for c in MAG]] += bump
    return sim, prepare(DriveLog(table), FilterConfig())


def _offset_standard_error(prep) -> np.ndarray:
    used = prep.base == Status.USED
    H = core_jacobian(prep.data.field_body[used]).reshape(-1, 12)
    return NOISE_NT * np.sqrt(np.diag(np.linalg.inv(H.T @ H)))[9:]


def test_a_disturbance_in_the_first_minutes_does_not_pull_the_start_off(disturbed):
    sim, prep = disturbed
    setup = prepare_run(prep, FilterConfig())
    se = _offset_standard_error(prep)
    z = (setup.x0[9:12] - sim.b) / se
    assert np.all(np.abs(z) < SIGMAS), f"start offsets {setup.x0[9:12]} against {sim.b}: z = {z}"
    assert "whole log" in setup.how
    used = prep.base == Status.USED
    first = bootstrap_vector(
        prep.m[used], prep.data.field_body[used], prep.time[used], NOISE_NT, FilterConfig().bootstrap_s
    )
    assert np.max(np.abs(first.x[9:12] - sim.b) / se) > SIGMAS  # the first stretch alone is pulled off
