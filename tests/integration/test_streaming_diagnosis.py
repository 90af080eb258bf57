"""The diagnosis and the validation made in passes over small chunks give the whole-log results.

``diagnose`` and ``validate`` make the whitened rows of a model a chunk of ``CHUNK`` epochs at a time and
reduce them there (normal equations per held-out block, residuals to their sums of squares). Here a seeded
simulated log of 3 000 epochs, shorter than the default chunk (one pass over the whole log), is diagnosed again
with chunks of a prime number of epochs: with the heading's wander taken out the chunks are cut at its stretches
(each chunk one stretch of 10 s, so that the chunk edges fall inside the held-out folds), and with the logged
heading taken as exact the edges fall anywhere (inside the folds and the 10 s stretches alike). The ranking, the
decisions and every statistic must agree to the issue's 1e-6 relative; the chunked diagnosis also prepares its
epochs again from the log for each chunk it reads, where the whole one holds them prepared. Chunked sums differ
from whole ones only in the order in which the same products are added (about 1e-16 relative each); the normal
equations' condition (nested candidates, a heading wander that mimics part of an effect) amplifies that, and on
this log the largest difference seen is 1e-7 relative (a held-out residual), ten times inside the bound. A
parameter's estimate near zero is compared to 1e-6 of its standard deviation instead (a relative figure of a value
that is noise about zero says nothing).
"""

import math

import numpy as np
import pytest

import magkf.diagnostics.diagnose as diagnose_module
import magkf.diagnostics.inference as inference
import magkf.online.determined as determined
import magkf.online.prepare as prepare_module
import magkf.online.prepared_rows as prepared_rows
from magkf import Calibration, reference
from magkf.diagnostics.diagnose import diagnose
from magkf.diagnostics.validate import validate
from magkf.effects import BUILTIN, stored_effect
from magkf.io.drivelog import DriveLog
from magkf.sim import DriveConfig, simulate_drive

#: The issue's agreement of the chunked diagnosis with the whole-log one.
RELATIVE = 1e-6
#: A prime number of epochs per chunk: its edges fall at no round count of epochs.
SMALL_CHUNK = 97
#: Temperature coefficients (nT per degree) of the hidden effect.
TEMPERATURE = np.array([24.0, -15.0, 18.0])


@pytest.fixture(scope="module")
def hidden():
    """A 5-minute 10 Hz log (3 000 epochs, below ``CHUNK``) with a temperature effect no model has, coloured
    noise and a wandering heading."""
    config = DriveConfig(
        duration_s=300, rate_hz=10, noise_nt=30.0, seed=7, noise_correlation_s=2.0, attitude_wander_deg=(0.0, 0.0, 0.2)
    )
    sim = simulate_drive(config, effects=[(BUILTIN["temperature_bias"](), TEMPERATURE)])
    assert len(sim.table) < determined.CHUNK  # the default is one pass over the whole log
    return sim


def _chunked(monkeypatch, size):
    """Passes over ``size`` epochs at a time in the diagnosis (the whitened rows, the gate and the residuals), its
    epochs prepared again from the log for each chunk read rather than held (``prepared_rows.HELD_BYTES``), their
    reference field made for the rows read (``prepare.REFERENCE_HELD_EPOCHS``, in pieces of ``size``) as a long log's
    is; each candidate's scores and the tests' residual kept in a file and read back ``size`` rows at a time
    (``diagnose.ROWS_IN_MEMORY_BYTES``, ``inference.READ_ROWS``)."""
    monkeypatch.setattr(diagnose_module, "ROWS_IN_MEMORY_BYTES", 0)
    monkeypatch.setattr(inference, "READ_ROWS", size)
    monkeypatch.setattr(inference, "_COSINE_ROWS", size)
    monkeypatch.setattr(determined, "CHUNK", size)
    monkeypatch.setattr(diagnose_module, "CHUNK", size)
    monkeypatch.setattr(prepared_rows, "CHUNK", size)
    monkeypatch.setattr(prepared_rows, "HELD_BYTES", 0)
    monkeypatch.setattr(prepare_module, "REFERENCE_HELD_EPOCHS", 0)
    monkeypatch.setattr(reference, "INTERPOLATION_CHUNK", size)


def _agree(whole, chunked, path=""):
    """Assert that two summaries (nested dicts and lists) agree: the same keys, texts, flags and order, numbers to
    ``RELATIVE`` (an estimate's value to ``RELATIVE`` of its standard deviation)."""
    if isinstance(whole, dict):
        assert set(whole) == set(chunked), path
        if set(whole) == {"value", "std"}:
            scale = max(abs(whole["value"]), whole["std"])
            assert abs(whole["value"] - chunked["value"]) <= RELATIVE * scale, path
            assert chunked["std"] == pytest.approx(whole["std"], rel=RELATIVE), path
            return
        for key in whole:
            _agree(whole[key], chunked[key], f"{path}/{key}")
    elif isinstance(whole, (list, tuple)):
        assert len(whole) == len(chunked), path
        for i, (a, b) in enumerate(zip(whole, chunked)):
            _agree(a, b, f"{path}[{i}]")
    elif isinstance(whole, float) and not isinstance(whole, bool):
        if math.isnan(whole):
            assert math.isnan(chunked), path
        else:
            assert chunked == pytest.approx(whole, rel=RELATIVE, abs=1e-300), path
    elif path.endswith("/text"):
        return  # the advice in words prints the same figures rounded; compared through them
    else:
        assert whole == chunked, path


@pytest.mark.slow
@pytest.mark.parametrize("wander_s", [10.0, None])
def test_diagnose_in_small_chunks_gives_the_whole_log_results(hidden, monkeypatch, wander_s):
    """The hidden effect found and every candidate ranked, decided and measured as in one pass."""
    log = DriveLog(hidden.table)
    whole, run = diagnose(log, wander_s=wander_s)
    assert whole.recommended[0].effect == "temperature_bias:temp_c"  # the chunked run has something to find
    _chunked(monkeypatch, SMALL_CHUNK)
    chunked, _ = diagnose(log, wander_s=wander_s, run=run)
    _agree(whole.summary(), chunked.summary())
    _agree(whole.binned, chunked.binned)
    for key, values in whole.residuals.items():
        np.testing.assert_allclose(chunked.residuals[key], values, rtol=RELATIVE, atol=0)


@pytest.mark.slow
def test_validate_in_small_chunks_gives_the_whole_log_results(hidden, monkeypatch):
    """A stored temperature effect checked on the log: the held-out figures, the paired test and the verdict as in
    one pass."""
    effect = BUILTIN["temperature_bias"]()
    cal = Calibration(hidden.R, hidden.b, effects=(stored_effect(effect, TEMPERATURE, np.zeros(3)),))
    log = DriveLog(hidden.table)
    whole = validate(log, cal)
    assert whole.effects[0].verdict == "helps beyond chance"
    _chunked(monkeypatch, SMALL_CHUNK)
    _agree(whole.summary(), validate(log, cal).summary())


def test_long_log_diagnosed_from_the_run_calibrate_makes_in_chunks(tmp_path, monkeypatch):
    """``magkf diagnose`` of a canonical log that ``calibrate`` takes in chunks (``CHUNKED_EPOCHS`` lowered) starts
    from the chunked run, made before the log is read whole, not from a whole-log run. With the log's own reference
    field both runs do the same arithmetic (``tests/integration/test_chunked.py``), so the diagnosis is the one
    made from the whole-log run: every figure to ``RELATIVE`` (the NIS is read back from the states file as
    float32: 6e-8 relative)."""
    import json

    import magkf.online.chunked as chunked
    from magkf.cli import main

    path = tmp_path / "log.csv"
    simulate_drive(DriveConfig(duration_s=120, rate_hz=50, seed=3, write_reference=True)).write(path)

    def diagnosed():  # written to a file: within the command's outputs' commit (``magkf.files.committed``)
        out = tmp_path / "diagnosis.json"
        assert main(["diagnose", str(path), "--quiet", "--json", "-o", str(out)]) == 0
        return json.loads(out.read_text())

    whole = diagnosed()

    def refused(*args, **kwargs):
        raise AssertionError("a long log's diagnosis made a whole-log run")

    monkeypatch.setattr(chunked, "CHUNKED_EPOCHS", 1_000)
    monkeypatch.setattr(diagnose_module, "calibrate_log", refused)
    _agree(whole, diagnosed())
