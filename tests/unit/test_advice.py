"""Advice that fits the command and the data: the verdict's words on a log that does not determine the
calibration, the next step each command gives, the judgement of a calibration ``calibrate`` would not write,
the fleet's disagreement test against the logs whose model fits only, and a validation test without power."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from magkf.calibration import Calibration
from magkf.config import FilterConfig
from magkf.diagnostics.judgement import judge, next_step
from magkf.diagnostics.validate import _verdict as validation_verdict
from magkf.fleet import COMPARED, disagreements
from magkf.io.drivelog import DriveLog
from magkf.online.run import calibrate_log
from magkf.online.verdict import DIAGNOSE, MISSES, fits, retold, verdict
from magkf.sim import DriveConfig, simulate_drive

#: A learned noise five times the configured one: a verdict that finds fault.
NOISY = {
    "adapted": True,
    "configured": {"sensor_nt": 30.0, "attitude_deg": 0.1},
    "learned": {"sensor_median_nt": 150.0},
    "inflation": 1.0,
    "correlation_s": 0.1,
}
NIS = {"mean": 1.0, "band": (0.9, 1.1)}
R_UNDETERMINED = {"undetermined": [{"groups": ["the third column of R"]}, {"groups": ["the first column of R", "b"]}]}


def test_a_misfit_on_a_log_that_does_not_determine_r_blames_the_turning_not_an_effect():
    text = verdict(NOISY, NIS, 0.9, R_UNDETERMINED)
    assert MISSES not in text and DIAGNOSE not in text, text
    assert "does not determine the first column of R, the third column of R and the offsets b" in text
    assert "lack turning" in text and not fits(text)


def test_a_misfit_on_a_determined_log_says_the_model_misses_something_and_each_command_gives_its_own_step():
    text = verdict(NOISY, NIS, 0.9, {"undetermined": [{"groups": ["the current_field parameters"]}]})
    assert text.endswith(f"{MISSES}; {DIAGNOSE}") and not fits(text)  # what calibrate says
    assert retold(text, "add it").endswith(f"{MISSES}; add it")
    assert retold(text, None).endswith(MISSES)
    quiet = verdict({**NOISY, "learned": {"sensor_median_nt": 29.0}}, NIS, 0.9, {})
    assert fits(quiet) and retold(quiet, "add it") == quiet


def test_the_next_step_names_the_effects_taken_the_refusal_or_what_the_log_lacks():
    taken = [SimpleNamespace(option="--effect time_lag")]
    assert "magkf calibrate --effect time_lag" in next_step(taken)
    refused = SimpleNamespace(refusal="R is singular")
    assert "refuse" in next_step([], refused)
    assert "turns through more headings" in next_step([], None, "the first column of R")
    assert "diagnose" not in next_step([]) and "diagnose" not in next_step(taken)


@pytest.fixture(scope="module")
def sim_run():
    """A 2-minute simulated flight (10 Hz, seeded) and the filter's run over it: a calibration calibrate writes."""
    log = DriveLog(simulate_drive(DriveConfig(duration_s=120, rate_hz=10, seed=3)).table, "sim.csv")
    return log, calibrate_log(log, FilterConfig())


def _with(run, **summary):
    return replace(run, summary=replace(run.summary, **summary))


def test_a_calibration_refused_by_its_own_r_has_its_figures_withheld_and_one_that_passes_has_none(sim_run):
    log, run = sim_run
    fine = judge(run, log)
    assert fine.refusal is None and fine.withheld is None
    absurd = judge(_with(run, R=(6.0 * np.eye(3)).tolist()), log)  # sensitivities of 6: beyond any magnetometer
    assert "sensitivities" in absurd.refusal and absurd.withheld and "not what the model misses" in absurd.withheld
    unused = judge(_with(run, used_share=0.0), log)
    assert "no epoch was used" in unused.refusal and unused.withheld
    as_given = judge(None, log, cal=Calibration(R=6.0 * np.eye(3), b=np.zeros(3), method="ellipsoid"))
    assert as_given.withheld and as_given.warnings == ()


def _vehicle(verdicts, b_x, vehicle="v"):
    """One vehicle's logs: every parameter 0 with standard deviation 1, but ``b_x`` (one per log)."""
    rows = []
    for k, (text, value) in enumerate(zip(verdicts, b_x)):
        row = {name: 0.0 for name in COMPARED} | {f"std_{name}": 1.0 for name in COMPARED}
        rows.append(row | {"b_x": value, "verdict": text, "vehicle": vehicle, "log": f"{vehicle}/{k}", "error": ""})
    return pd.DataFrame(rows)


GOOD = "the model fits the data at the level of the noise (residuals white)"
BAD = f"Residuals are 5 times the stated sensor noise: {MISSES}; {DIAGNOSE}"


def test_the_one_correct_log_of_four_is_not_flagged_against_three_that_miss_something():
    """Three logs whose model misses something agree with one another 20 standard deviations away from the one
    log whose model fits: judged against them it was flagged (z = 20 / sqrt(1 + 1/3), about 17, against the
    limit 3.7, the normal quantile of 0.01 / (2 x 4 logs x 12 parameters)); with one log whose model fits there is
    nothing to judge against."""
    out = disagreements(_vehicle([GOOD, BAD, BAD, BAD], [0.0, 20.0, 20.0, 20.0]), 0.01)
    assert not out["disagrees"].any()
    assert out["disagreement"].str.startswith("not compared: 1 of the 4 calibrated logs of v").all()


def test_a_log_that_misses_something_is_judged_against_the_logs_whose_model_fits():
    """Three logs that fit agree within their standard deviations; the fourth, whose model misses something,
    is 20 of them off (z about 17 against the limit 3.7 at alpha 0.01 over 4 logs and 12 parameters): flagged, and
    only it; the three are within 0.8 of one another (z below 1)."""
    out = disagreements(_vehicle([GOOD, GOOD, BAD, GOOD], [0.3, -0.5, 20.0, 0.1]), 0.01)
    assert out["disagrees"].tolist() == [False, False, True, False]
    assert "judged against the 3 logs whose model fits" in out.loc[2, "disagreement"]


def test_a_validation_test_without_power_says_so_instead_of_no_difference():
    score = {"dof": 4, "p_helps": 0.3, "p_hurts": 0.7, "detectable": 0.25, "predicted": 0.04}
    assert validation_verdict(score, 0.01).startswith("no power on this log")
    powered = {**score, "detectable": 0.01}
    assert validation_verdict(powered, 0.01).startswith("no difference beyond chance")


def test_validate_as_stored_has_nothing_fitted_on_the_log_checked():
    """The true calibration checked on a log whose logged heading wanders (0.5 deg over a minute, seeded): the
    figure as stored is the plain residual of that calibration, computed here from the readings, the logged
    attitude and the reference (every epoch kept: no disturbance, no bad DOP); with the heading's error fitted
    on the log itself (the in-sample figure) most of it disappears. The two computations differ only in
    rounding, and in the few epochs the gross-outlier rule may leave out (at most 1 %: the figure within 1 %)."""
    from magkf.conventions import body_to_ned, euler_to_dcm
    from magkf.diagnostics.validate import validate

    config = DriveConfig(duration_s=300, rate_hz=10, seed=7, disturbances=0, dop_bad_stretches=0)
    sim = simulate_drive(replace(config, attitude_wander_deg=(0.0, 0.0, 0.5)))
    log = DriveLog(sim.table, "b.csv")
    cal = Calibration(R=sim.R, b=sim.b, method="truth")
    body = (log.mag - sim.b) @ np.linalg.inv(sim.R).T
    roll, pitch, yaw = log.attitude.T
    ned = body_to_ned(euler_to_dcm(yaw, pitch, roll), body)
    plain = float(np.sqrt(np.mean(np.sum((ned - log.reference_ned()) ** 2, axis=1))))
    v = validate(log, cal)
    assert abs(v.as_stored_nt - plain) < 0.01 * plain, (v.as_stored_nt, plain)
    assert v.with_effects_in_sample_nt < 0.5 * plain  # the heading's error fitted here: labelled in sample


def test_the_report_of_a_calibration_refused_by_its_own_r_shows_no_figure_of_it(sim_run, monkeypatch):
    """The report judges the run it makes; judged as refused by its own R (as a calibration of sensitivities 6
    is), the page says so in its box and shows neither plots nor residual figures nor a diagnosis."""
    import magkf.diagnostics.report as report

    log, _ = sim_run
    reason = "sensitivities 6 to 6 of the field, outside [0.2, 5]"
    refused = report.Judgement(reason, (), f"the calibration itself is refused ({reason})")
    monkeypatch.setattr(report, "judge", lambda *args: refused)
    page = report.build_report(log)
    assert "Refused: <code>magkf calibrate</code> would not write this calibration" in page and reason in page
    assert "<img" not in page and "residual RMS" not in page and "Which effect is missing" not in page


def test_nothing_to_add_when_the_model_fits():
    """No candidate taken and a verdict that finds the model fitting at the noise's level: the next step says there
    is nothing to add, not that the residual follows signals or the sensor is noisier than stated."""
    from magkf.diagnostics.judgement import next_step

    step = next_step([], None, "", fitting=True)
    assert step.startswith("nothing to add") and "noisier" not in step
    assert "noisier" in next_step([], None, "")
