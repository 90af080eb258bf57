"""A log that no calibration of the core fits is refused by ``calibrate`` (nothing written), but ``diagnose`` still
runs on it, finds what is missing, and with it added ``calibrate`` writes a calibration that fits.

A load current of tens of amperes through 400 nT/A puts several thousand nT into the readings, more than
``RESIDUAL_REFUSED`` (5 %) of a 49 000 nT field: refused without the effect, found by the diagnosis, fitted with it
to the noise's level (30 nT per axis; the whole-log residual is within 2 noise levels of it).
"""

import json

import numpy as np
import pytest

from magkf.effects import BUILTIN
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import run_cli


@pytest.mark.slow
def test_refused_for_a_missing_load_effect_then_diagnosed_and_calibrated_with_it(tmp_path):
    sim = simulate_drive(
        DriveConfig(duration_s=300, rate_hz=10, noise_nt=30.0, seed=21, disturbances=0),
        effects=[(BUILTIN["current_field"](), [400.0, -300.0, 250.0])],
    )
    assert np.sqrt(np.mean(np.sum(sim.contributions[0] ** 2, axis=1))) > 0.05 * 49_000  # beyond the rule
    log = tmp_path / "log.csv"
    sim.table.to_csv(log)
    refused = run_cli("calibrate", log, "-o", tmp_path / "cal.json", "--quiet")
    assert refused.returncode == 2 and "no calibration fits" in refused.stderr and refused.stderr.count("\n") == 1
    assert not (tmp_path / "cal.json").exists()
    diagnosed = run_cli("diagnose", log, "--json", "--quiet")
    assert diagnosed.returncode == 0, diagnosed.stderr
    assert json.loads(diagnosed.stdout)["recommended"][0] == "--effect current_field:current_a"
    assert "calibrate would not write it" in diagnosed.stderr
    written = run_cli("calibrate", log, "--effect", "current_field", "-o", tmp_path / "cal.json", "--json")
    assert written.returncode == 0, written.stderr
    assert json.loads(written.stdout)["residual_rms_nt"] < 2 * 30.0 * np.sqrt(3)
