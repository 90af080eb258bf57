"""The truth-judged effect study (``scripts/effect_truth_study.py``) on a few logs: the acceptance of "add it and
watch the error fall", judged against the simulator's truth with an effect generator independent of magkf's
effect classes (``tests/truth_effects.py``).

Each case is one seeded 10-minute log at 10 Hz with the simulator's six disturbances and one more in its first
two minutes. The bounds:

* "not worse": the file written with the recommended effects leaves a truth-judged RMS at most that of the
  file written without effects plus ``tolerance_nt``, the one-sided 99 % bound of the difference of two RMS
  figures of this noise over this many (effective) epochs (``rms_tolerance``: standard error
  ``s / sqrt(6 N_eff)`` each);
* "reaches the noise level within 5 %": the file written with the true effect leaves at most 1.05 times what
  the same log with the effect taken out leaves when calibrated without effects, plus the same tolerance. A
  field anomaly's horizontal component across the field is a heading offset: with the logged heading wandering,
  no calibration can tell it from the heading's own error, and magkf holds it at the prior (as the diagnosis
  does), so it stays in the truth-judged residual as a constant body-frame vector of its size; the floor is
  then ``sqrt(free^2 + d_h^2)``, the two adding in quadrature (the noise has zero mean);
* "recommended": the hidden effect is ranked first and recommended; the acceptance asks 95 % of logs, so the
  misses over the cases are at most the 99 % binomial bound of 5 % over their count;
* null logs: false alarms at most the 99 % binomial bound of ``alpha`` over their count.
"""

import importlib.util
import sys
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from magkf.config import FilterConfig
from magkf.io.drivelog import DriveLog
from magkf.online.prepare import prepare

ROOT = Path(__file__).resolve().parents[2]
MINUTES, RATE_HZ, ALPHA = 10.0, 10.0, 0.01


def _study():
    spec = importlib.util.spec_from_file_location("effect_truth_study", ROOT / "scripts" / "effect_truth_study.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, module)
    spec.loader.exec_module(module)
    return module


study = _study()

#: One log each: drone and car, white and coloured noise; bias_drift and field_anomaly with coloured noise are
#: the cases the issue found written worse than without.
CASES = [
    study.Case(("temperature_bias",), "3d", "coloured", 1000, True),
    study.Case(("current_field",), "planar", "white", 1001, True),
    study.Case(("eddy_current",), "3d", "white", 1002, True),
    study.Case(("time_lag",), "planar", "coloured", 1000, True),
    study.Case(("bias_drift",), "3d", "white", 1000, True),
    study.Case(("field_anomaly",), "3d", "coloured", 1001, True),
]
NULL_CASES = [
    study.Case((), motion, noise, 5000, True) for motion in ("3d", "planar") for noise in ("white", "coloured")
]


@cache
def judged(case):
    return study.run_case(case, MINUTES, RATE_HZ, ALPHA)


def _heading_offset_part(case) -> float:
    """The size (nT) of a hidden field anomaly's component along the horizontal direction across the field (east
    of magnetic north: ``(-B_e, B_n, 0) / |B_h|``, the mean reference field of the log), the part a heading offset
    makes; 0 for any other effect."""
    if "field_anomaly" not in case.hidden:
        return 0.0
    tlog = study.case_log(case, MINUTES, RATE_HZ)
    ref = np.mean(prepare(DriveLog(tlog.table), FilterConfig()).ref, axis=0)
    across = np.array([-ref[1], ref[0], 0.0]) / np.hypot(ref[0], ref[1])
    return float(abs(across @ np.asarray(tlog.thetas[case.hidden.index("field_anomaly")], float)))


def _id(case) -> str:
    return f"{case.name}-{case.motion}-{case.noise}"


@pytest.mark.slow
def test_hidden_effect_is_ranked_first_and_recommended():
    rows = [judged(case) for case in CASES]
    assert not [r["error"] for r in rows if "error" in r]
    missed = [f"{r['hidden']}-{r['motion']}-{r['noise']}: top {r['top_candidate']}, took {r['recommended']}" for r in
              rows if not (r["ranked_first"] and r["recommended_hidden"])]  # fmt: skip
    assert len(missed) <= int(stats.binom.ppf(0.99, len(rows), 0.05)), missed


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=_id)
def test_file_written_with_recommended_effect_is_not_worse_against_truth(case):
    row = judged(case)
    assert not row["refused"], row["refused"]
    assert row["rms_rec"] <= row["rms_none"] + row["tolerance_nt"], (
        f"with [{row['recommended']}] {row['rms_rec']:.1f} nT, without {row['rms_none']:.1f} nT "
        f"(tolerance {row['tolerance_nt']:.2f} nT)"
    )


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=_id)
def test_true_effect_reaches_the_noise_level_within_5_percent(case):
    row = judged(case)
    free = np.hypot(row["rms_free"], _heading_offset_part(case)) if case.noise == "coloured" else row["rms_free"]
    bound = study.FLOOR_FACTOR * free + row["tolerance_nt"]
    assert row["rms_true"] <= bound, (
        f"with the true effect {row['rms_true']:.1f} nT; the effect-free log {row['rms_free']:.1f} nT, "
        f"noise {row['floor_nt']:.1f} nT"
    )


@pytest.mark.slow
def test_null_logs_false_alarms_within_binomial_bound():
    rows = [judged(case) for case in NULL_CASES]
    alarms = sum(r["false_alarm"] for r in rows)
    bound = int(stats.binom.ppf(0.99, len(rows), ALPHA))
    assert alarms <= bound, [r["recommended"] for r in rows]
    assert not any(r["worse"] for r in rows)


def test_rms_tolerance_follows_the_standard_error_of_an_rms():
    """White noise: ``N`` independent epochs; Gauss-Markov noise of 2 s at 10 Hz: ``rho^2 = exp(-0.1)``, so
    ``N (1 - rho^2) / (1 + rho^2)``, about N / 20. The tolerance is ``2.326 sqrt(2) s / sqrt(6 N_eff)``."""
    assert study.effective_epochs(6000, 10.0, 0.0) == 6000.0
    assert study.effective_epochs(6000, 10.0, 2.0) == pytest.approx(6000 * 0.0499584, rel=1e-4)
    assert study.rms_tolerance(52.0, 6000.0) == pytest.approx(2.3263 * 2**0.5 * 52.0 / 36000**0.5, rel=1e-4)
