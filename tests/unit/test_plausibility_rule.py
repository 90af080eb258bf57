"""The one write rule of magkf.plausibility: a mirrored R, the offsets' standard deviations against the field,
offsets the data carried nothing about, a batch estimate far from the log's own start, a --init calibration
and a calibration that is used (apply, export), with refusals that say what the data lack."""

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from magkf.calibration import Calibration
from magkf.errors import InputError
from magkf.plausibility import (
    OFFSET_STD_REFUSED,
    OFFSET_STD_WARNED,
    check_calibration,
    check_loaded,
    check_offset_std,
    check_run,
    check_start,
    turning_text,
    unit_option,
)

FIELD = 49_000.0
MIRROR = np.diag([1.0, 1.0, -1.0])


def test_a_mirrored_r_is_refused_and_a_rotation_is_not():
    with pytest.raises(InputError, match=r"R is mirrored \(determinant -1, not positive\)"):
        check_calibration(MIRROR, np.zeros(3), "cal")
    c, s = np.cos(0.3), np.sin(0.3)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    assert check_calibration(rotation, np.zeros(3), "cal") == []


def test_the_offsets_standard_deviations_are_judged_against_the_field():
    """Below 1 % nothing is said, 1 to 3 % is warned, above 3 % refused; an unknown field says nothing."""
    assert check_offset_std([2.0, 2.0, 9.5], FIELD, "log") == []
    (warning,) = check_offset_std([976.0] * 3, FIELD, "log", "turn it")
    assert "976 (1.99 % of the field 49000)" in warning and warning.endswith("turn it")
    with pytest.raises(InputError, match=r"more than 3 %: the data do not determine them; turn it \(nothing written"):
        check_offset_std([3500.0, 10.0, 10.0], FIELD, "log", "turn it")
    assert check_offset_std([1e9] * 3, float("nan"), "log") == []
    assert OFFSET_STD_WARNED < OFFSET_STD_REFUSED < 0.10  # the acceptance: never above 10 % of the field


def test_mag_unit_is_suggested_only_where_it_applies():
    R = np.eye(3) * 7.0
    for source, suggested in (("flight.bin", False), ("flight.ulg", False), ("log.csv", True)):
        assert unit_option(source) is suggested
        with pytest.raises(InputError) as caught:
            check_calibration(R, np.zeros(3), source, unit_option=unit_option(source))
        assert ("--mag-unit" in str(caught.value)) is suggested


def test_a_mirrored_start_is_refused_as_the_start_itself():
    start = Calibration(R=MIRROR, b=np.zeros(3), covariance=np.eye(12) * 1e-12)
    with pytest.raises(InputError, match="mirror.json: the start calibration itself is mirrored"):
        check_start(start, "mirror.json")
    check_start(None, "none")  # no --init: nothing to judge
    check_start(Calibration(R=np.eye(3) * 1.02, b=[300.0, -200.0, 100.0]), "good.json")


def test_an_absurd_calibration_is_not_used():
    """R = 1e-3 I and b = 1e7 nT: calibrated magnitudes of 1e10 nT; refused naming the file, nothing used."""
    absurd = Calibration(R=np.eye(3) * 1e-3, b=np.full(3, 1e7))
    with pytest.raises(InputError, match=r"absurd.json: the calibration is not used: sensitivities 0.001"):
        check_loaded(absurd, "absurd.json", FIELD)
    with pytest.raises(InputError, match="nothing used"):
        check_loaded(absurd, "absurd.json")  # no log: against the Earth's largest field
    assert check_loaded(Calibration(R=np.eye(3), b=[400.0, -300.0, 200.0]), "good.json", FIELD) == []


def _run(b_std=10.0, undetermined=(), model=None, start=None, method="ekf", R=None, b=(100.0, 0.0, 0.0)):
    """A stand-in for a CalibrationRun with what check_run reads."""
    summary = SimpleNamespace(
        used_share=1.0,
        n_epochs=1000,
        model=model,
        R=(np.eye(3) if R is None else np.asarray(R)).tolist(),
        b=list(b),
        std={k: b_std for k in ("b_x", "b_y", "b_z")},
        observability={"undetermined": list(undetermined), "text": "; ".join(u["text"] for u in undetermined)},
        filter=method,
    )
    covariance = np.diag([1e-4] * 9 + [b_std**2] * 3)
    calibration = SimpleNamespace(covariance=covariance)
    return SimpleNamespace(summary=summary, calibration=calibration, start=start, states=None)


def test_a_run_whose_offsets_remain_at_their_prior_is_refused():
    """A direction of b alone that the data carried a thousandth of the prior's information about: b is where it
    started, refused; at 0.89 of the prior's information (the PX4 sample flight) it is written."""
    at_prior = {"ratio": 1e-3, "groups": ["b"], "text": "b remains at its prior (data carried 0.001 of ...)"}
    with pytest.raises(InputError, match=r"the data do not determine the offsets; b remains at its prior"):
        check_run(_run(undetermined=[at_prior]), "flight.bin", FIELD)
    partly = dict(at_prior, ratio=0.89)
    assert check_run(_run(undetermined=[partly]), "flight.bin", FIELD) == []


def test_a_whole_log_estimate_whose_offsets_are_known_no_better_than_its_start_is_refused():
    """R held by the family: the offsets' standard deviations given R (the whole-log fit's) against the start's
    300 nT; 330 nT (as over ``ardupilot_box_center_0003.bin --init logged``) refused, 10 nT written."""
    start = Calibration(R=np.eye(3), b=np.zeros(3), covariance=np.diag([1e-4] * 9 + [300.0**2] * 3))

    def held(std):
        return {"family": "offsets", "std_given_held": {k: std for k in ("b_x", "b_y", "b_z")}}

    with pytest.raises(InputError, match="the data do not determine the offsets"):
        check_run(_run(model=held(330.0), start=start), "flight.bin", FIELD, init=start)
    assert check_run(_run(model=held(10.0), start=start), "flight.bin", FIELD, init=start) == []


def test_a_batch_estimate_far_from_the_logs_own_start_is_refused():
    """No --init and no whole-log family: 10 of the start's standard deviations away is refused; a whole-log
    family's estimate (which may hold R at another calibration) is not judged so."""
    start = Calibration(R=np.eye(3), b=np.zeros(3), covariance=np.diag([1e-4] * 9 + [100.0**2] * 3))
    run = _run(start=start, method="batch", b=(1000.0, 0.0, 0.0))
    with pytest.raises(InputError, match=r"left the log's own starting fit by 10 of its standard deviations.*--batch"):
        check_run(run, "log.csv", FIELD)
    held = _run(start=start, model={"family": "offsets"}, b=(1000.0, 0.0, 0.0))
    assert check_run(held, "log.csv", FIELD) == []


def test_a_run_with_a_mirrored_estimate_or_start_is_refused():
    with pytest.raises(InputError, match="R is mirrored"):
        check_run(_run(R=MIRROR), "log.csv", FIELD)
    start = Calibration(R=MIRROR, b=np.zeros(3))
    with pytest.raises(InputError, match="the start calibration itself is mirrored"):
        check_run(_run(), "log.csv", FIELD, init=start)


def test_the_turning_is_said_over_the_epochs_used():
    table = pd.DataFrame({"yaw": [10.0, 10.5, 11.0, 200.0], "pitch": [1.0, 2.0, 3.0, 40.0], "roll": [0.0] * 4})
    log = SimpleNamespace(table=table)
    used = np.array([True, True, True, False])
    assert turning_text(log, used).startswith("the 3 epochs used turn through 1 deg of heading, pitch 1 to 3 deg")
    assert turning_text(SimpleNamespace(table=table[["pitch"]])) == ""


def test_a_batch_estimate_over_a_log_that_hardly_turns_is_refused():
    """All 12 parameters over 6 degrees of heading: refused; over a full circle, or as a whole-log family's
    estimate (which holds what the log does not determine), written."""
    turning = np.linspace(0.0, 6.0, 50)
    narrow = SimpleNamespace(table=pd.DataFrame({"yaw": turning, "pitch": 0.0, "roll": 0.0}))
    with pytest.raises(InputError, match=r"fewer than 90 deg of heading, which do not determine R: the log turns"):
        check_run(_run(method="batch"), "log.csv", FIELD, log=narrow)
    circle = SimpleNamespace(table=narrow.table.assign(yaw=turning * 60.0))
    assert check_run(_run(method="batch"), "log.csv", FIELD, log=circle) == []
    assert check_run(_run(model={"family": "offsets"}), "log.csv", FIELD, log=narrow) == []


def test_magnitudes_of_readings_in_another_unit_are_refused_once_applied():
    """Calibrated magnitudes of a log read ten times too large (another unit) are refused naming the log; within
    5 % of the field they pass; 19 % above it (an offset off) they are warned."""
    from magkf.plausibility import check_applied

    field = 48_000.0
    rng = np.random.default_rng(1)
    around = field * (1 + 0.01 * rng.standard_normal(500))
    assert check_applied(around, field, "log.csv") == []
    (warning,) = check_applied(1.19 * around, field, "log.csv")  # an offset of 35 000 nT edited in by hand
    assert "1.19 times the field" in warning
    with pytest.raises(InputError, match="10 times the field") as err:
        check_applied(10 * around, field, "log.csv")
    assert err.value.source == "log.csv"


def test_an_estimate_worse_than_its_start_on_its_own_epochs_is_refused():
    """Written figures as ``baseline.written_figures`` gives them: 1.4 times the start's residual passes (the
    warning is the run's), 2.3 times is refused naming the log; without a start, or for a family that holds what
    its start fitted, nothing is judged."""
    from magkf.plausibility import WORSE_REFUSED, check_against_start

    def figures(ours, theirs):
        return {"written": {"vector_rms_nt": ours}, "start": {"vector_rms_nt": theirs}, "n_used": 200}

    check_against_start(figures(0.95 * WORSE_REFUSED * 390.0, 390.0), "log.bin")
    check_against_start({"written": {"vector_rms_nt": 886.9}, "start": None, "n_used": 200}, "log.bin")
    check_against_start(figures(886.9, 390.0), "log.bin", family="offsets")  # R held: not as free as its start
    with pytest.raises(InputError, match=r"886.9 nT against 390.0 nT") as err:
        check_against_start(figures(886.9, 390.0), "log.bin")
    assert err.value.source == "log.bin"


def test_a_start_in_the_readings_own_units_is_not_judged_by_a_field_it_does_not_have():
    """An ellipsoid fitted without --field (``counts``: R scaled to determinant 1, b in the readings' units, here
    thousands of counts) is a valid --init; the same offsets in nT against a unit sphere are refused."""
    from magkf.plausibility import check_start

    counts = Calibration(R=np.eye(3), b=np.array([350.0, -220.0, 480.0]) * 30, field_unit="counts")
    check_start(counts, "e.json")
    with pytest.raises(InputError, match="times the field"):
        check_start(Calibration(R=np.eye(3), b=counts.b, field_unit="unit-sphere"), "e.json")
