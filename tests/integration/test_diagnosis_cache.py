"""The diagnosis with its chunk cache full, partly full or empty (``determined.CACHE_BYTES``), or its set taken as
long (``CACHED_EPOCHS``: only the whitenings kept, within ``WHITENING_CACHE_BYTES``), gives the same result.

A cached chunk is the array the pass made for it, read again; a chunk beyond the budget is made again by the same
code from the same inputs. So the ranking, the decisions and every number of the diagnosis must agree exactly
(bit for bit) whatever the budget. A seeded 3 000-epoch log is cut into chunks of a prime number of epochs (many
chunks, so that a small budget keeps some and makes the others again) and diagnosed at three budgets.
"""

import numpy as np
import pytest

import magkf.diagnostics.diagnose as diagnose_module
import magkf.online.determined as determined
from magkf.diagnostics.diagnose import diagnose
from magkf.effects import BUILTIN
from magkf.io.drivelog import DriveLog
from magkf.sim import DriveConfig, simulate_drive

#: A prime number of epochs per chunk: 31 chunks over the log.
SMALL_CHUNK = 97


@pytest.fixture(scope="module")
def log():
    """A 5-minute 10 Hz log with a temperature effect no model has and a wandering heading."""
    config = DriveConfig(duration_s=300, rate_hz=10, noise_nt=30.0, seed=7, attitude_wander_deg=(0.0, 0.0, 0.2))
    sim = simulate_drive(config, effects=[(BUILTIN["temperature_bias"](), np.array([24.0, -15.0, 18.0]))])
    return DriveLog(sim.table, "cache")


def _numbers(result) -> tuple[list, list]:
    """The candidates' names and decisions in ranked order, and every number of theirs."""
    names, values = [], []
    for c in result.candidates:
        names.append((c.effect, c.significant, c.note))
        values += [c.statistic, c.p_value, c.residual_rms_after_nt, c.residual_rms_fit_nt]
        values += [v[k] for v in c.estimate.values() for k in ("value", "std")]
    return names, values


@pytest.mark.slow
def test_same_diagnosis_whatever_the_budget(log, monkeypatch):
    """Budget 0 (every pass makes its rows again), 100 kB (a few chunks kept) and the default, and a set taken as long
    with some or none of its whitenings kept, give the same result bit for bit (NaN where a candidate was not
    testable, at the same places)."""
    monkeypatch.setattr(determined, "CHUNK", SMALL_CHUNK)
    monkeypatch.setattr(diagnose_module, "CHUNK", SMALL_CHUNK)
    results = []
    for budget in (0, 100_000, determined.CACHE_BYTES):
        monkeypatch.setattr(determined, "CACHE_BYTES", budget)
        results.append(_numbers(diagnose(log)[0]))
    monkeypatch.setattr(determined, "CACHED_EPOCHS", 100)  # a long set: its whitenings kept, the rest made again
    for whitenings in (20_000, 0):  # some of the whitenings kept, then none
        monkeypatch.setattr(determined, "WHITENING_CACHE_BYTES", whitenings)
        results.append(_numbers(diagnose(log)[0]))
    for names, values in results[1:]:
        assert names == results[0][0]
        np.testing.assert_array_equal(values, results[0][1])
